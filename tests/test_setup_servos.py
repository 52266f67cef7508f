"""Setting up servos on a new arm, against the wire-level simulators.

First the simulators' EEPROM (what `crtk-bridge setup-servos` and `check --scan --all-bauds` meet on
a real bus): writes that persist for the simulator's life under each vendor's lock rule (Feetech:
Lock = 0; Dynamixel: torque off), a Baud_Rate write after which the servo answers only at the new
rate, factory-fresh servos added, detached and attached through the control socket, and the
`crtk-sim` options that build day-one buses."""

from __future__ import annotations

import subprocess
import sys

import dynamixel_sdk as dxl
import pytest
import scservo_sdk as scs

from crtk_bridge.backends.feetech.port import FastPortHandler
from crtk_bridge.sim.control import control_request
from crtk_bridge.sim.dynamixel import DynamixelSimulator
from crtk_bridge.sim.feetech import FeetechSimulator

from .conftest import ROOT, SO101, wait_until


def sdk_port(module, path: str, baud: int):
    # Feetech: the backend's port, which discards stale input (the status of an unacknowledged
    # write) before each request; the pip SDK's does not
    port = FastPortHandler(path) if module is scs else module.PortHandler(path)
    assert port.openPort() and port.setBaudRate(baud)
    return port


def write_unacknowledged(ph, port, sid: int, address: int, value: int) -> None:
    """A one-byte write whose status may come back under a new id or rate: sent without
    waiting for it, then that status read off the wire (so no later request takes it as its own)."""
    assert ph.write1ByteTxOnly(port, sid, address, value) == 0
    port.setPacketTimeout(12)
    ph.rxPacket(port, False) if isinstance(ph, dxl.Protocol2PacketHandler) else ph.rxPacket(port)
    port.is_using = False


def sts_ping(port, sid: int) -> bool:
    return scs.PacketHandler(0).ping(port, sid)[1] == scs.COMM_SUCCESS


# ---------------------------------------------------------------- simulators: EEPROM
def test_feetech_eeprom_persists_only_while_unlocked_and_baud_moves_the_servo():
    with FeetechSimulator(servo_ids=[1]) as sim:
        port = sdk_port(scs, sim.port, 1_000_000)
        ph = scs.PacketHandler(0)
        try:
            # Lock = 1 (power-on default): the new id takes effect, but a power cycle forgets it
            write_unacknowledged(ph, port, 1, 5, 7)
            assert sts_ping(port, 7) and not sts_ping(port, 1)
            sim.power_cycle()
            assert sim.ids == [1] and sts_ping(port, 1)
            # Lock = 0: id and Return_Delay_Time persist
            assert ph.write1ByteTxRx(port, 1, 55, 0)[0] == scs.COMM_SUCCESS
            write_unacknowledged(ph, port, 1, 5, 7)
            assert ph.write1ByteTxRx(port, 7, 7, 0)[0] == scs.COMM_SUCCESS
            # the new baud rate: deaf at 1 Mbps from now on, answering at 115200 only
            write_unacknowledged(ph, port, 7, 6, 4)
            assert not sts_ping(port, 7)
            assert port.setBaudRate(115_200) and sts_ping(port, 7)
            sim.power_cycle()
            assert sim.ids == [7] and sts_ping(port, 7)
            assert sim.servo(7).read("Lock") == 1 and sim.servo(7).read("Baud_Rate") == 4
            assert port.setBaudRate(1_000_000) and not sts_ping(port, 7)
        finally:
            port.closePort()


def test_dynamixel_eeprom_needs_torque_off_and_persists_across_a_power_cycle():
    with DynamixelSimulator({3: "xl430-w250"}) as sim:
        port = sdk_port(dxl, sim.port, 1_000_000)
        ph = dxl.PacketHandler(2.0)
        try:
            assert ph.write1ByteTxRx(port, 3, 64, 1)[0] == dxl.COMM_SUCCESS  # torque on
            result, error = ph.write4ByteTxRx(port, 3, 20, 300)  # Homing_Offset: EEPROM
            assert result == dxl.COMM_SUCCESS and error == 7  # access error: not written
            assert sim.servo(3).read("Homing_Offset") == 0
            assert ph.write1ByteTxRx(port, 3, 64, 0)[0] == dxl.COMM_SUCCESS
            assert ph.write4ByteTxRx(port, 3, 20, 300) == (dxl.COMM_SUCCESS, 0)
            write_unacknowledged(ph, port, 3, 8, 1)  # Baud_Rate 1: 57600
            assert ph.ping(port, 3)[1] != dxl.COMM_SUCCESS
            assert port.setBaudRate(57_600) and ph.ping(port, 3)[1] == dxl.COMM_SUCCESS
            sim.power_cycle()
            assert sim.servo(3).read("Homing_Offset") == 300 and sim.servo(3).read("Baud_Rate") == 1
            assert sim.servo(3).read("Torque_Enable") == 0
        finally:
            port.closePort()


def test_factory_servos_through_the_control_socket(short_tmp):
    ctl = short_tmp / "sim.ctl"
    with DynamixelSimulator({5: "xm430-w350"}, control=ctl):
        reply = control_request(ctl, {"cmd": "add_servo"})
        assert reply["ok"] and reply["serial"] == 2
        dump = control_request(ctl, {"cmd": "dump"})
        fresh = dump["servos"]["1"]
        assert (fresh["model"], fresh["baud_rate"], fresh["return_delay_time"], fresh["serial"]) == \
            ("xl430-w250", 1, 250, 2)  # id 1, 57600 baud, 500 us: as shipped
        taken = control_request(ctl, {"cmd": "add_servo", "model": "xl330-m288"})
        assert not taken["ok"] and "id 1 is taken on the bus" in taken["error"]
        assert control_request(ctl, {"cmd": "write", "id": 1, "register": "ID", "value": 9})["ok"]
        assert control_request(ctl, {"cmd": "detach", "serial": 2})["ok"]
        dump = control_request(ctl, {"cmd": "dump"})
        assert list(dump["servos"]) == ["5"] and dump["detached"]["2"]["id"] == 9  # keeps its EEPROM
        assert control_request(ctl, {"cmd": "attach", "serial": 2})["ok"]
        assert sorted(control_request(ctl, {"cmd": "dump"})["servos"]) == ["5", "9"]
        bad = control_request(ctl, {"cmd": "add_servo", "model": "ax-12"})
        assert not bad["ok"] and "unknown model 'ax-12'" in bad["error"]


def crtk_sim(short_tmp, *options) -> tuple[subprocess.Popen, str]:
    ctl = short_tmp / "sim.ctl"
    proc = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", "feetech", "--profile", str(SO101),
                             "--control", str(ctl), *options], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    assert "bus ready" in line, line
    return proc, str(ctl)


@pytest.mark.parametrize("options, expect", [
    (["--empty", "--factory-servo"], {"1": (0, 777, 250)}),
    (["--servo-baud", "115200", "--model", "3=sts3250"],
     {str(i): (4, 2825, 250) if i == 3 else (4, 777, 0) for i in range(1, 7)}),
], ids=["one-unconfigured-servo", "baud-mismatch-and-other-model"])
def test_crtk_sim_day_one_buses(short_tmp, options, expect):
    proc, ctl = crtk_sim(short_tmp, *options)
    try:
        servos = control_request(ctl, {"cmd": "dump"})["servos"]
        assert {sid: (s["baud_rate"], s["model_number"], s["return_delay_time"]) for sid, s in servos.items()} \
            == expect
    finally:
        proc.terminate()
        assert proc.wait(10) == 0

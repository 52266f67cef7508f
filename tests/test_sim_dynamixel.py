"""The Dynamixel Protocol 2.0 simulator driven by the real dynamixel_sdk on a pty.

Every wait is a poll with a deadline."""

from __future__ import annotations

import select
import signal
import subprocess
import sys

import pytest
from dynamixel_sdk import (
    COMM_SUCCESS,
    GroupBulkRead,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from crtk_bridge.backends.dynamixel import tables as T
from crtk_bridge.sim import SimulatorError
from crtk_bridge.sim.control import control_request
from crtk_bridge.sim.dynamixel import DynamixelSimulator, crc16, packet, stuff, unstuff

from .conftest import wait_until
from .sdk_patience import patient_port, silence_expected

PatientPort = patient_port(PortHandler)

SERVOS = {1: "xl430-w250", 2: "xl330-m288", 3: "xm430-w350"}


@pytest.fixture
def sim():
    s = DynamixelSimulator(SERVOS)
    s.start()
    yield s
    s.stop()


@pytest.fixture
def bus(sim):
    port = PatientPort(sim.port)
    assert port.openPort()
    yield port, PacketHandler(2.0)
    port.closePort()


def test_crc_and_packet_match_the_emanual_ping_example():
    # e-Manual Protocol 2.0, Ping example: ID 1 -> FF FF FD 00 01 03 00 01 19 4E
    assert packet(1, T.INST_PING) == bytes.fromhex("FFFFFD00010300 01 194E".replace(" ", ""))
    assert crc16(bytes.fromhex("FFFFFD0001030001")) == 0x4E19


def test_byte_stuffing_round_trip():
    data = bytes.fromhex("01FFFFFD02FFFFFDFD")
    s = stuff(data)
    assert s == bytes.fromhex("01FFFFFDFD02FFFFFDFDFD")
    assert unstuff(s) == data


def test_ping_reports_model_numbers_and_firmware(sim, bus):
    port, ph = bus
    for sid, model in SERVOS.items():
        number, result, error = ph.ping(port, sid)
        assert result == COMM_SUCCESS and error == 0
        assert number == T.MODEL_NUMBERS[model]
    with silence_expected(sim, port):
        _, result, _ = ph.ping(port, 9)
    assert result != COMM_SUCCESS  # unknown id: silence


def test_stuffed_values_survive_write_and_read(sim, bus):
    """-131073 is FF FF FD FF little-endian: instruction and status packets need stuffing."""
    port, ph = bus
    assert ph.write1ByteTxRx(port, 3, 11, int(T.OperatingMode.EXTENDED_POSITION))[0] == COMM_SUCCESS
    raw = T.to_raw(-131073, 4)
    assert raw.to_bytes(4, "little")[:3] == b"\xff\xff\xfd"
    assert ph.write4ByteTxRx(port, 3, 116, raw) == (COMM_SUCCESS, 0)
    assert sim.servo(3).read("Goal_Position") == -131073
    sim.servo(3).write("Present_Position", -131073)
    value, result, _ = ph.read4ByteTxRx(port, 3, 132)
    assert result == COMM_SUCCESS and T.to_signed(value, 4) == -131073
    # plain sync read: stuffed status packets, un-stuffed by the SDK
    group = GroupSyncRead(port, ph, 132, 4)
    group.addParam(3)
    assert group.txRxPacket() == COMM_SUCCESS
    assert T.to_signed(group.getData(3, 132, 4), 4) == -131073


def test_sync_read_and_fast_sync_read_agree(sim, bus):
    port, ph = bus
    for sid, pos in ((1, 1000), (2, 2000), (3, 3000)):
        sim.servo(sid).write("Present_Position", pos)
    plain = GroupSyncRead(port, ph, 126, 10)
    fast = GroupSyncRead(port, ph, 126, 10)
    for sid in SERVOS:
        plain.addParam(sid)
        fast.addParam(sid)
    assert plain.txRxPacket() == COMM_SUCCESS
    assert fast.fastSyncRead() == COMM_SUCCESS
    for sid, pos in ((1, 1000), (2, 2000), (3, 3000)):
        assert plain.getData(sid, 132, 4) == pos
        assert fast.getData(sid, 132, 4) == pos


def test_bulk_read_and_sync_write(sim, bus):
    port, ph = bus
    gsw = GroupSyncWrite(port, ph, 116, 4)
    for sid, goal in ((1, 1500), (2, 2500)):
        gsw.addParam(sid, list(goal.to_bytes(4, "little")))
    assert gsw.txPacket() == COMM_SUCCESS
    wait_until(lambda: sim.servo(1).read("Goal_Position") == 1500 and sim.servo(2).read("Goal_Position") == 2500,
               2.0, what="sync-written goals")
    bulk = GroupBulkRead(port, ph)
    assert bulk.addParam(1, 116, 4) and bulk.addParam(3, 0, 2)
    assert bulk.txRxPacket() == COMM_SUCCESS
    assert bulk.getData(1, 116, 4) == 1500 and bulk.getData(3, 0, 2) == 1020


def test_position_mode_converges_and_current_mode_spins(sim, bus):
    port, ph = bus
    assert ph.write4ByteTxRx(port, 3, 116, 2600)[0] == COMM_SUCCESS
    assert ph.write1ByteTxRx(port, 3, 64, 1)[0] == COMM_SUCCESS
    wait_until(lambda: abs(sim.servo(3).read("Present_Position") - 2600) <= 1, 5.0, what="servo 3 at its goal")
    # current mode on the XL330: an unloaded motor turns one way with a positive current
    assert ph.write1ByteTxRx(port, 2, 11, 0)[0] == COMM_SUCCESS
    assert ph.write2ByteTxRx(port, 2, 102, 50)[0] == COMM_SUCCESS
    assert ph.write1ByteTxRx(port, 2, 64, 1)[0] == COMM_SUCCESS
    start = sim.servo(2).read("Present_Position")
    wait_until(lambda: sim.servo(2).read("Present_Position") > start + 200, 5.0, what="current mode motion")
    assert sim.servo(2).read("Present_Current") == 50


def test_eeprom_locked_while_torque_on(sim, bus):
    port, ph = bus
    assert ph.write1ByteTxRx(port, 1, 64, 1)[0] == COMM_SUCCESS
    result, error = ph.write1ByteTxRx(port, 1, 11, 1)
    assert result == COMM_SUCCESS and error == T.ERRNUM_ACCESS
    assert sim.servo(1).read("Operating_Mode") == 3


def test_hardware_error_alert_and_reboot(sim, bus):
    port, ph = bus
    assert ph.write1ByteTxRx(port, 2, 64, 1)[0] == COMM_SUCCESS
    sim.set_fault(2, "error_bits", T.HW_OVERLOAD)
    assert sim.servo(2).read("Torque_Enable") == 0  # overload is in the Shutdown mask: torque off
    value, result, error = ph.read1ByteTxRx(port, 2, 70)
    assert result == COMM_SUCCESS and value == T.HW_OVERLOAD and error & T.ERR_ALERT
    result, error = ph.write1ByteTxRx(port, 2, 64, 1)
    assert sim.servo(2).read("Torque_Enable") == 0  # refused until rebooted
    sim.clear_faults()
    assert sim.servo(2).read("Hardware_Error_Status") == T.HW_OVERLOAD  # latched
    assert ph.reboot(port, 2)[0] == COMM_SUCCESS
    with silence_expected(sim, port):  # deaf for REBOOT_S: a ping meanwhile goes unanswered
        wait_until(lambda: ph.ping(port, 2)[1] == COMM_SUCCESS, 5.0, what="servo 2 back after reboot")
    value, result, error = ph.read1ByteTxRx(port, 2, 70)
    assert result == COMM_SUCCESS and value == 0 and error == 0


def test_silent_and_corrupt_faults(sim, bus):
    port, ph = bus
    sim.set_fault(1, "silent")
    with silence_expected(sim, port):
        assert ph.ping(port, 1)[1] != COMM_SUCCESS
    sim.clear_faults()
    sim.set_fault(2, "corrupt")
    assert ph.ping(port, 2)[1] != COMM_SUCCESS
    sim.clear_faults()
    assert ph.ping(port, 1)[1] == COMM_SUCCESS and ph.ping(port, 2)[1] == COMM_SUCCESS
    with pytest.raises(SimulatorError, match="unknown fault kind"):
        sim.set_fault(1, "melt")


def test_control_socket_dump_write_fault(tmp_path):
    ctl = tmp_path / "s.sock"
    with DynamixelSimulator(SERVOS, control=ctl) as s:
        dump = control_request(ctl, {"cmd": "dump"})
        assert dump["servos"]["2"]["model"] == "xl330-m288" and dump["servos"]["1"]["present_load"] == 0
        for sid, servo in dump["servos"].items():  # the horn's position, before the rounding to ticks
            assert round(servo["present_position_exact"]) == servo["present_position"], sid
        assert control_request(ctl, {"cmd": "write", "id": 3, "register": "goal_position", "value": 77})["ok"]
        assert s.servo(3).read("Goal_Position") == 77
        assert control_request(ctl, {"cmd": "fault", "id": 1, "kind": "error_bits", "bits": 4})["ok"]
        assert control_request(ctl, {"cmd": "dump"})["faults"] == {"1": ["error_bits"]}
        bad = control_request(ctl, {"cmd": "read", "id": 1, "register": "goal_current"})
        assert not bad["ok"] and "xl430-w250" in bad["error"]  # the XL430 has no current registers


def test_cli_serves_until_sigterm(tmp_path):
    link, ctl = tmp_path / "tty", tmp_path / "c.sock"
    proc = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", "dynamixel", "--profile",
                             "profiles/koch.yaml", "--link", str(link), "--control", str(ctl)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 20.0)
        assert ready, "crtk-sim printed nothing within 20 s"
        line = proc.stdout.readline()
        assert "dynamixel bus ready" in line and f"port={link}" in line, (line, proc.stderr.read())
        port = PatientPort(str(link))
        assert port.openPort()
        try:
            assert PacketHandler(2.0).ping(port, 1)[:2] == (1060, COMM_SUCCESS)
        finally:
            port.closePort()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        assert not link.exists() and not ctl.exists()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()

"""The Robotiq 2F simulator (crtk_bridge/sim/robotiq.py) checked against an independent Modbus
client: pymodbus's own sync clients used directly (not the backend), by the register map of
Robotiq's 2F-85 / 2F-140 manual (section 4: output words 0x03E8 written with function 16, input
words 0x07D0 read with function 4), on the pty and on the raw-RTU TCP socket."""

from __future__ import annotations

import time

import pytest
from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusIOException

from crtk_bridge.profile import load_profile
from crtk_bridge.sim.control import control_request
from crtk_bridge.sim.robotiq import CLOSED_COUNT, OPEN_COUNT, RobotiqSimulator

from .conftest import ROOT, wait_until

SLAVE = 9


def _status(client) -> dict:
    """Bytes 0-5 of the input registers, decoded by the manual's tables (4.4), here by hand."""
    rr = client.read_input_registers(0x07D0, count=3, device_id=SLAVE)
    assert not rr.isError(), rr
    w = rr.registers
    status, fault, echo, pos, cur = w[0] >> 8, w[1] >> 8, w[1] & 0xFF, w[2] >> 8, w[2] & 0xFF
    return {"gACT": status & 1, "gGTO": (status >> 3) & 1, "gSTA": (status >> 4) & 3, "gOBJ": status >> 6,
            "gFLT": fault & 0x0F, "gPR": echo, "gPO": pos, "gCU": cur}


def _request(client, action: int, position: int = 0, speed: int = 0, force: int = 0) -> None:
    """The manual's output words (4.3): ACTION REQUEST | 0, 0 | POSITION, SPEED | FORCE."""
    wr = client.write_registers(0x03E8, [action << 8, position, (speed << 8) | force], device_id=SLAVE)
    assert not wr.isError(), wr


def _activate_move_read(client, sim) -> None:
    _request(client, 0x00)  # reset (rACT 0)
    assert _status(client)["gSTA"] == 0
    _request(client, 0x01)  # rACT 1: activation
    assert _status(client)["gSTA"] == 1  # activation in progress
    wait_until(lambda: _status(client)["gSTA"] == 3, 5, what="activation completed (gSTA 3)")
    st = _status(client)
    assert st["gACT"] == 1 and st["gPO"] == OPEN_COUNT and st["gFLT"] == 0
    _request(client, 0x09, 0xFF, 0xFF, 0x80)  # rACT + rGTO: close at full speed, half force
    st = _status(client)
    assert st["gGTO"] == 1 and st["gPR"] == 0xFF and st["gOBJ"] == 0 and st["gCU"] > 0  # moving
    wait_until(lambda: _status(client)["gOBJ"] == 3, 5, what="fingers at the request (gOBJ 3)")
    assert _status(client)["gPO"] == CLOSED_COUNT  # clamped to its closed stroke end
    sim.set_object(0.04)  # an object at 40 mm: open, then close on it
    _request(client, 0x09, 0x00, 0xFF, 0x80)
    wait_until(lambda: _status(client)["gOBJ"] == 3, 5, what="open again")
    _request(client, 0x09, 0xFF, 0xFF, 0xFF)
    wait_until(lambda: _status(client)["gOBJ"] == 2, 5, what="stopped on the object while closing (gOBJ 2)")
    st = _status(client)
    expect = CLOSED_COUNT - 0.04 / 0.085 * (CLOSED_COUNT - OPEN_COUNT)
    assert abs(st["gPO"] - expect) <= 1 and st["gCU"] > 0  # current follows the force setting
    strong = st["gCU"]
    _request(client, 0x09, 0xFF, 0xFF, 0x00)  # the least force: less current
    assert _status(client)["gCU"] < strong


@pytest.fixture
def sim_pty(short_tmp):
    sim = RobotiqSimulator.from_profile(load_profile(ROOT / "profiles" / "robotiq_2f85.yaml"),
                                        link=short_tmp / "tty", control=short_tmp / "ctl", activation_s=0.3)
    sim.start()
    yield sim, short_tmp
    sim.stop()


def test_an_independent_modbus_client_activates_moves_and_reads_on_the_pty(sim_pty):
    sim, tmp = sim_pty
    client = ModbusSerialClient(str(tmp / "tty"), framer=FramerType.RTU, baudrate=115200, bytesize=8,
                                parity="N", stopbits=1, timeout=1, retries=0)
    assert client.connect()
    try:
        _activate_move_read(client, sim)
    finally:
        client.close()


def test_an_independent_modbus_client_on_the_tool_port_socket():
    """Raw RTU frames over TCP, as a UR tool flange's port 54321 carries them."""
    sim = RobotiqSimulator(tcp=("127.0.0.1", 0), activation_s=0.3)
    sim.start()
    client = ModbusTcpClient(sim.tcp_address[0], port=sim.tcp_address[1], framer=FramerType.RTU, timeout=1, retries=0)
    try:
        assert sim.port == f"socket://127.0.0.1:{sim.tcp_address[1]}" and client.connect()
        _activate_move_read(client, sim)
    finally:
        client.close()
        sim.stop()


def test_faults_on_the_control_socket(sim_pty):
    sim, tmp = sim_pty
    ctl = tmp / "ctl"
    client = ModbusSerialClient(str(tmp / "tty"), framer=FramerType.RTU, baudrate=115200, timeout=0.2, retries=0)
    assert client.connect()
    try:
        _request(client, 0x01)
        wait_until(lambda: _status(client)["gSTA"] == 3, 5, what="activated")
        assert control_request(ctl, {"cmd": "fault", "kind": "overcurrent"})["ok"]
        assert _status(client)["gFLT"] == 0x0E
        _request(client, 0x09, 0xFF, 0xFF, 0xFF)  # a major fault: no motion until a reset
        time.sleep(0.05)
        assert _status(client)["gPO"] == OPEN_COUNT
        _request(client, 0x00)  # the reset clears it
        assert _status(client)["gFLT"] == 0
        assert control_request(ctl, {"cmd": "fault", "kind": "under_voltage"})["ok"]
        assert _status(client)["gFLT"] == 0x0A
        assert control_request(ctl, {"cmd": "fault", "kind": "no_communication"})["ok"]
        with pytest.raises(ModbusIOException):  # silent
            client.read_input_registers(0x07D0, count=3, device_id=SLAVE)
        assert control_request(ctl, {"cmd": "clear_faults"})["ok"]
        assert _status(client)["gFLT"] == 0x0A  # heard again; the major fault waits for a reset
        # not this slave, another address: no reply (the gripper sends no exception responses)
        for device_id, address in ((3, 0x07D0), (SLAVE, 0x0100)):
            with pytest.raises(ModbusIOException):
                client.read_input_registers(address, count=3, device_id=device_id)
        dump = control_request(ctl, {"cmd": "dump"})
        assert dump["ok"] and dump["gFLT"] == 0x0A and dump["servos"]["9"]["gFLT"] == 0x0A
        bad = control_request(ctl, {"cmd": "fault", "kind": "lightning"})
        assert not bad["ok"] and "overcurrent" in bad["error"]
    finally:
        client.close()


def test_a_second_of_silence_is_reported_once_as_the_minor_fault_0x09(sim_pty):
    sim, tmp = sim_pty
    client = ModbusSerialClient(str(tmp / "tty"), framer=FramerType.RTU, baudrate=115200, timeout=0.5, retries=0)
    assert client.connect()
    try:
        _request(client, 0x01)
        wait_until(lambda: _status(client)["gSTA"] == 3, 5, what="activated")
        with sim.gripper.lock:
            sim.gripper._last_heard -= 1.5  # a second and a half without a request
        assert _status(client)["gFLT"] == 0x09
        assert _status(client)["gFLT"] == 0  # once
    finally:
        client.close()


def test_crtk_sim_robotiq_serves_the_profile(short_tmp):
    import subprocess
    import sys

    link, ctl = short_tmp / "tty", short_tmp / "ctl"
    proc = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", "robotiq", "--profile", "robotiq_2f85",
                             "--link", str(link), "--control", str(ctl)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        line = proc.stdout.readline()
        assert "robotiq ready: port=" in line and str(link) in line, line
        assert control_request(ctl, {"cmd": "activation", "seconds": 0.1})["ok"]
        client = ModbusSerialClient(str(link), framer=FramerType.RTU, baudrate=115200, timeout=1, retries=0)
        assert client.connect()
        _request(client, 0x01)
        wait_until(lambda: _status(client)["gSTA"] == 3, 5, what="activated")
        client.close()
    finally:
        proc.terminate()
        assert proc.wait(10) == 0


def test_plugging_in_a_plugged_link_changes_nothing(sim_pty):
    """``set_unplugged(False)`` on a link that is in (a test's recovery does it every time) is a
    no-op: it registered the pty a second time ('FD is already registered') and failed."""
    sim, tmp = sim_pty
    sim.set_unplugged(False)
    sim.set_unplugged(True)
    sim.set_unplugged(False)
    sim.set_unplugged(False)
    client = ModbusSerialClient(str(tmp / "tty"), framer=FramerType.RTU, baudrate=115200, bytesize=8,
                                parity="N", stopbits=1, timeout=1, retries=0)
    assert client.connect()
    try:
        assert _status(client)["gFLT"] == 0  # the gripper answers on the link
    finally:
        client.close()

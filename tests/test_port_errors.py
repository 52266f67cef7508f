"""A port that will not open, or a bus where nobody answers, is said with its likely cause and the
next thing to do (backends/port_errors.py), through the real backend and the real simulator."""

from __future__ import annotations

import copy
import errno
import subprocess
import sys

import pytest

from crtk_bridge.backends import port_errors
from crtk_bridge.backends.feetech.backend import FeetechBackend
from crtk_bridge.errors import BackendError
from crtk_bridge.profile import parse_profile

from .conftest import so101_data


def backend(port: str, data: dict | None = None, **keys) -> FeetechBackend:
    data = copy.deepcopy(data or so101_data())
    data["backend"].update(port=port, **keys)
    return FeetechBackend(parse_profile(data, "so101.yaml"), source="so101.yaml")


def open_error(b: FeetechBackend) -> str:
    with pytest.raises(BackendError) as info:
        b.open()
    b.close()
    msg = str(info.value)
    assert "\n" not in msg
    return msg


@pytest.fixture
def sim():
    from crtk_bridge.sim.feetech import FeetechSimulator

    s = FeetechSimulator.from_profile(parse_profile(so101_data()), link=None, control=None, emulate_baud=False)
    s.start()
    yield s
    s.stop()


def test_missing_port_points_at_serial_by_id(tmp_path, monkeypatch):
    by_id = tmp_path / "by-id"
    monkeypatch.setattr(port_errors, "BY_ID", str(by_id))
    msg = open_error(backend("/nonexistent/ttyACM9"))
    assert msg == ("so101: cannot open port /nonexistent/ttyACM9: no such device (is the adapter plugged in? "
                   f"no USB serial adapter found: {by_id} does not exist)")
    by_id.mkdir()
    (by_id / "usb-1a86_USB_Single_Serial_5A46083062-if00").symlink_to("/dev/null")
    msg = open_error(backend("/nonexistent/ttyACM9"))
    assert msg.endswith(f"(is the adapter plugged in? adapters plugged in (ls {by_id}): "
                        f"usb-1a86_USB_Single_Serial_5A46083062-if00; set backend.port to {by_id}/<one of these>)")


def test_locked_port_names_the_process_holding_it(sim):
    holder = subprocess.Popen(
        [sys.executable, "-c", "import serial, sys; p = serial.Serial(sys.argv[1], exclusive=True); "
                               "print('held', flush=True); sys.stdin.read()", sim.port],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"  # blocks until the lock is taken
        msg = open_error(backend(sim.port))
        assert msg.startswith(f"so101: cannot open port {sim.port}: the port is in use by pid {holder.pid} (")
        assert "serial.Serial" in msg  # its command line, cut short
    finally:
        holder.stdin.close()
        holder.wait(10)
    b = backend(sim.port)  # released: it opens
    b.open()
    b.close()


def test_no_servo_answering_names_power_baud_and_ids(sim):
    data = so101_data()
    for j in data["joints"]:
        j["id"] += 10  # the simulator has ids 1-6
    msg = open_error(backend(sim.port, data, timeout_ms=5, read_retries=0))
    assert msg.startswith("so101: joint 'shoulder_pan' (id 11) did not answer ping on ")
    assert msg.endswith("; no servo answered: check that the servos are powered (their own supply, not USB), "
                        "that backend.baudrate (1000000) is the servos' baud rate, and that the joints' ids "
                        "(11, 12, 13, 14, 15, 16) are the servos' ids")


def test_one_silent_servo_gets_no_bus_wide_hint(sim):
    data = so101_data()
    data["joints"][5]["id"] = 16
    msg = open_error(backend(sim.port, data, timeout_ms=5, read_retries=0))
    assert "joint 'gripper' (id 16) did not answer ping" in msg and "no servo answered" not in msg


def test_permission_denied_names_the_group():
    reason = port_errors.open_error_reason("/dev/ttyACM0", PermissionError(errno.EACCES, "Permission denied"))
    assert reason.startswith("permission denied (add the user to the port's group, usually dialout: ")


def test_unknown_cause_keeps_the_error_text():
    assert port_errors.open_error_reason("/dev/x", OSError(errno.EIO, "I/O error")) == "[Errno 5] I/O error"

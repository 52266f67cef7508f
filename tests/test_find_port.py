"""``crtk-bridge find-port`` and ``backend.port: {serial_number: ...}`` (backends/ports.py): the
port list from pyserial with by-id links, the unplug / replug dialogue, and a profile naming its
adapter by USB serial number, resolved at open on the real backend and simulator."""

from __future__ import annotations

import copy
import subprocess
import sys
import textwrap

import pytest
from serial.tools.list_ports_common import ListPortInfo

from crtk_bridge.backends import ports
from crtk_bridge.backends.feetech.backend import FeetechBackend
from crtk_bridge.backends.ports import SerialPort, find_replugged, list_serial_ports, resolve_port
from crtk_bridge.errors import BackendError, ProfileError
from crtk_bridge.profile import parse_profile

from .conftest import ROOT, so101_data

LEFT = SerialPort("/dev/ttyACM0", ("usb-1a86_USB_Single_Serial_5A46083062-if00",), 0x1A86, 0x55D3,
                  "5A46083062", "QinHeng", "USB Single Serial")
RIGHT = SerialPort("/dev/ttyACM1", ("usb-1a86_USB_Single_Serial_5A46083171-if00",), 0x1A86, 0x55D3,
                   "5A46083171", "QinHeng", "USB Single Serial")


def usb_info(device: str, vid: int, pid: int, serial_number: str, product: str) -> ListPortInfo:
    info = ListPortInfo(device, skip_link_detection=True)
    info.vid, info.pid, info.serial_number, info.product, info.manufacturer = vid, pid, serial_number, product, "QinHeng"
    return info


def test_list_serial_ports_adds_by_id_links_and_usb_fields(tmp_path):
    acm0, acm1 = tmp_path / "ttyACM0", tmp_path / "ttyACM1"
    acm0.touch()
    acm1.touch()
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    (by_id / "usb-1a86_USB_Single_Serial_5A46083062-if00").symlink_to(acm0)
    serial_port = ListPortInfo(str(tmp_path / "ttyS0"), skip_link_detection=True)  # not USB
    listed = [serial_port, usb_info(str(acm1), 0x1A86, 0x55D3, "5A46083171", "USB Single Serial"),
              usb_info(str(acm0), 0x1A86, 0x55D3, "5A46083062", "USB Single Serial")]
    found = list_serial_ports(lambda: listed, str(by_id))
    assert [p.device for p in found] == [str(acm0), str(acm1), str(tmp_path / "ttyS0")]  # USB first
    assert found[0].by_id == ("usb-1a86_USB_Single_Serial_5A46083062-if00",) and found[1].by_id == ()
    assert found[0].serial_number == "5A46083062" and (found[0].vid, found[0].pid) == (0x1A86, 0x55D3)
    line = found[0].describe()
    assert line == (f"{acm0}  {by_id.parent}/by-id/usb-1a86_USB_Single_Serial_5A46083062-if00".replace(
        f"{by_id.parent}/by-id", ports.BY_ID) + "  usb 1a86:55d3  serial_number '5A46083062'  "
        "(QinHeng USB Single Serial)")
    assert found[2].describe().endswith("no serial number")


def test_find_port_lists_what_pyserial_finds(monkeypatch, capsys):
    from crtk_bridge import cli

    monkeypatch.setattr(ports, "list_serial_ports", lambda: [LEFT, RIGHT])
    assert cli.main(["find-port"]) == 0
    assert capsys.readouterr().out.splitlines() == [LEFT.describe(), RIGHT.describe()]


def lists(*snapshots):
    it = iter(snapshots)
    return lambda: list(next(it))


def test_replug_names_the_port_that_went_away_and_came_back():
    asked, out = [], []

    class Out:
        def write(self, s):
            out.append(s)

    moved = SerialPort("/dev/ttyACM2", LEFT.by_id, LEFT.vid, LEFT.pid, LEFT.serial_number)
    port = find_replugged(lists([LEFT, RIGHT], [RIGHT], [RIGHT, moved]), asked.append, Out())
    assert port == moved
    assert [a.split(",")[0] for a in asked] == ["Unplug the arm's USB adapter", "Plug it back in"]
    text = "".join(out)
    assert "The arm's adapter is /dev/ttyACM2 (was /dev/ttyACM0)" in text
    assert f"port: {ports.BY_ID}/{LEFT.by_id[0]}" in text and "port: {serial_number: '5A46083062'}" in text


@pytest.mark.parametrize("snapshots, says", [
    (([LEFT, RIGHT], [LEFT, RIGHT]), "No port went away"),
    (([LEFT, RIGHT], []), "More than one port went away (/dev/ttyACM0, /dev/ttyACM1)"),
    (([LEFT, RIGHT], [RIGHT], [RIGHT]), "went away but did not come back"),
])
def test_replug_says_why_no_port_was_found(snapshots, says, capsys):
    assert find_replugged(lists(*snapshots), lambda prompt: "", sys.stdout) is None
    assert says in capsys.readouterr().out


def test_replug_reads_the_users_enter_from_stdin():
    """The real command in a process of its own, the user's Enter keys on its stdin; only the port
    lister is scripted (no adapter to unplug here)."""
    script = textwrap.dedent(f"""
        import sys
        from crtk_bridge import cli
        from crtk_bridge.backends import ports
        from crtk_bridge.backends.ports import SerialPort
        left = SerialPort("/dev/ttyACM0", serial_number="AAA")
        right = SerialPort("/dev/ttyACM1", serial_number="BBB")
        snapshots = iter([[left, right], [right], [right, SerialPort("/dev/ttyACM3", serial_number="AAA")]])
        ports.list_serial_ports = lambda: next(snapshots)
        sys.exit(cli.main(["find-port", "--replug"]))
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = proc.communicate("\n\n", timeout=30)
    assert proc.returncode == 0, err
    assert out.startswith("Unplug the arm's USB adapter, then press Enter. Plug it back in, then press Enter. ")
    assert "The arm's adapter is /dev/ttyACM3 (was /dev/ttyACM0)" in out
    # no Enter at all (stdin closed): input() fails, the command does not report a port
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, input="", capture_output=True, text=True,
                          timeout=30)
    assert proc.returncode != 0 and "The arm's adapter is" not in proc.stdout


def test_resolve_port_by_serial_number():
    from crtk_bridge.backends.servo_keys import PortMatch

    assert resolve_port("/dev/serial/by-id/x", "so101", "p.yaml", lambda: []) == "/dev/serial/by-id/x"
    assert resolve_port(PortMatch(serial_number="5A46083171"), "so101", "p.yaml", lambda: [LEFT, RIGHT]) == RIGHT.device
    with pytest.raises(BackendError) as info:
        resolve_port(PortMatch(serial_number="NOPE"), "so101", "p.yaml", lambda: [LEFT, RIGHT])
    msg = str(info.value)
    assert msg.startswith("so101: p.yaml: backend.port.serial_number: no USB serial adapter has serial "
                          "number 'NOPE'; plugged in: /dev/ttyACM0 ")
    assert "serial_number '5A46083062'" in msg and "serial_number '5A46083171'" in msg
    twin = SerialPort("/dev/ttyACM5", serial_number="5A46083062", vid=1, pid=2)
    with pytest.raises(BackendError, match=r"2 adapters \(/dev/ttyACM0, /dev/ttyACM5\) have serial number"):
        resolve_port(PortMatch(serial_number="5A46083062"), "so101", "p.yaml", lambda: [LEFT, twin])
    with pytest.raises(BackendError, match="no USB serial adapter has .*; no USB serial adapter is plugged in"):
        resolve_port(PortMatch(serial_number="X"), "so101", "p.yaml", lambda: [SerialPort("/dev/ttyS0")])


def backend(port) -> FeetechBackend:
    data = copy.deepcopy(so101_data())
    data["backend"]["port"] = port
    return FeetechBackend(parse_profile(data, "so101.yaml"), source="so101.yaml")


@pytest.mark.parametrize("port, says", [
    ({"serial": "x"}, "backend.port: Object contains unknown field `serial`"),
    ({"serial_number": 5}, "backend.port.serial_number: Expected `str`, got `int`"),
    ({}, "backend.port: Object missing required field `serial_number`"),
])
def test_port_schema_refuses_bad_selectors(port, says):
    with pytest.raises(ProfileError) as info:
        backend(port)
    assert str(info.value) == f"so101.yaml: {says}"


def test_backend_opens_the_adapter_with_that_serial_number(monkeypatch):
    from crtk_bridge.sim.feetech import FeetechSimulator

    sim = FeetechSimulator.from_profile(parse_profile(so101_data()))
    sim.start()
    try:
        plugged = [SerialPort("/dev/ttyACM7", serial_number="OTHER-ARM", vid=1, pid=1),
                   SerialPort(sim.port, serial_number="SIM-ARM", vid=1, pid=1)]
        monkeypatch.setattr(ports, "list_serial_ports", lambda: plugged)
        b = backend({"serial_number": "SIM-ARM"})
        b.open()
        try:
            assert b.info().details["port"] == sim.port
        finally:
            b.close()
        b = backend({"serial_number": "MISSING"})
        with pytest.raises(BackendError) as info:
            b.open()
        b.close()
        assert "backend.port.serial_number: no USB serial adapter has serial number 'MISSING'" in str(info.value)
        assert "/dev/ttyACM7" in str(info.value) and sim.port in str(info.value)
    finally:
        sim.stop()


def test_find_port_runs_on_this_machines_real_ports():
    """No injection: pyserial's own comports() and the real /dev/serial/by-id, as a user runs it."""
    from serial.tools.list_ports import comports

    proc = subprocess.run([sys.executable, "-m", "crtk_bridge.cli", "find-port"], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    devices = sorted(p.device for p in comports())
    lines = proc.stdout.splitlines()
    if devices:
        assert sorted(line.split()[0] for line in lines) == devices
    else:
        assert lines == ["no serial ports found"]


def test_two_bus_profile_names_the_bus_key_of_a_missing_serial_number(monkeypatch):
    from crtk_bridge.backends import create_backend
    from crtk_bridge.sim.feetech import FeetechSimulator

    from .conftest import profile_data

    data = profile_data(ROOT / "profiles" / "bimanual_so101.yaml")
    with FeetechSimulator(servo_ids=range(1, 7)) as left:
        monkeypatch.setattr(ports, "list_serial_ports", lambda: [SerialPort(left.port, serial_number="LEFT", vid=1, pid=1)])
        data["backends"]["left"]["port"] = {"serial_number": "LEFT"}
        data["backends"]["right"]["port"] = {"serial_number": "RIGHT"}
        robot = create_backend(parse_profile(data, "bimanual.yaml"), source="bimanual.yaml")
        with pytest.raises(BackendError) as info:
            robot.open()
        robot.close()
    assert str(info.value).startswith(f"{data['name']}: bus 'right': bimanual.yaml: backends.right.port.serial_number: "
                                      "no USB serial adapter has serial number 'RIGHT'; plugged in: ")
    assert left.port in str(info.value)

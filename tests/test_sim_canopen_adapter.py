"""The simulated USB-CAN adapter (crtk_bridge/sim/slcan.py) and ``crtk-sim canopen`` in its own
process: python-can's ``slcan`` interface (the client a real CANable needs) opens the pty link
another process made, canopen's RemoteNode configures and drives a simulated drive through it,
and the control socket injects faults. Plus the LAWICEL command set, bitrate mismatch, bus-off
and hostile lines, in-process against the adapter alone."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time

import can
import canopen
import pytest
import yaml

from crtk_bridge.sim.canopen402 import CanopenSimulator, make_object_dictionary
from crtk_bridge.sim.control import control_request
from crtk_bridge.sim.slcan import SlcanAdapter, format_frame, parse_frame

from .conftest import ROOT, wait_until
from .test_sim_canopen import _emcy  # one helper for both files


def _profile(path) -> None:
    """A two-drive robot (node ids 1, 2) at 500 kbit/s; the simulator reads only these keys."""
    limits = {"position_min": -3.0, "position_max": 3.0, "velocity_max": 2.0, "acceleration_max": 10.0,
              "jerk_max": 100.0}
    path.write_text(yaml.safe_dump({
        "name": "cansim_test", "description": "two simulated CiA 402 drives",
        "backend": {"type": "canopen402", "interface": "slcan", "channel": "/dev/ttyACM0", "bitrate": 500_000},
        "loop": {"rate_hz": 100},
        "joints": [{"name": f"axis{n}", "node_id": n, "limits": limits} for n in (1, 2)],
        "namespaces": [{"name": "cansim", "joints": ["axis1", "axis2"]}],
    }))


@pytest.fixture(scope="module")
def crtk_sim(tmp_path_factory):
    """``crtk-sim canopen`` as a child process, its link and control socket."""
    d = tmp_path_factory.mktemp("cansim")
    profile, link, control = d / "p.yaml", d / "ttyCAN", d / "sim.sock"
    _profile(profile)
    proc = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", "canopen", "--profile", str(profile),
                             "--link", str(link), "--control", str(control)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("crtk-sim: canopen bus ready: interface=slcan"), (line, proc.stderr.read())
        assert f"channel={link}" in line and "nodes=1,2" in line and "bitrate=500000" in line
        yield proc, str(link), str(control)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            assert proc.wait(5) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert not link.exists() and not control.exists()  # removed on exit


def test_a_remote_node_drives_the_simulator_process_through_the_adapter(crtk_sim):
    _, link, control = crtk_sim
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.02
    # exactly what a real CANable needs; sleep_after_open: the simulated adapter is ready at once
    net.connect(interface="slcan", channel=link, bitrate=500_000, sleep_after_open=0)
    try:
        node = canopen.RemoteNode(2, make_object_dictionary(2))
        net.add_node(node)
        assert node.sdo[0x1018][4].raw == 2  # serial number = node id
        node.tpdo.read()
        node.rpdo.read()
        node.tpdo[1].clear()
        for index in (0x6041, 0x6064):
            node.tpdo[1].add_variable(index)
        node.tpdo[1].trans_type = 1
        node.tpdo[1].enabled = True
        node.rpdo[1].clear()
        for index in (0x6040, 0x607A):
            node.rpdo[1].add_variable(index)
        node.rpdo[1].trans_type = 1
        node.rpdo[1].enabled = True
        node.pdo.save()
        node.nmt.state = "OPERATIONAL"
        node.sdo[0x6060].raw = 8  # CSP
        net.sync.transmit()
        assert node.tpdo[1].wait_for_reception(1) is not None
        assert node.tpdo[1][0x6041].raw & 0x4F == 0x40  # SWITCH ON DISABLED

        def cycle(cw: int, target: int) -> int:
            """One loop cycle as a master runs it: RPDO1, SYNC, the TPDO answering it."""
            node.rpdo[1][0x6040].raw = cw
            node.rpdo[1][0x607A].raw = target
            node.rpdo[1].transmit()
            net.sync.transmit()
            assert node.tpdo[1].wait_for_reception(1) is not None
            return node.tpdo[1][0x6041].raw

        for cw, state in ((0x06, 0x21), (0x07, 0x23), (0x0F, 0x27)):  # the 402 walk, a cycle each
            assert cycle(cw, 0) & 0x6F == state
        for _ in range(200):
            cycle(0x0F, 3000)
            if node.tpdo[1][0x6064].raw == 3000:
                break
            time.sleep(0.005)
        assert node.tpdo[1][0x6064].raw == 3000

        dump = control_request(control, {"cmd": "dump"})
        assert dump["ok"] and dump["drives"]["2"]["state"] == "OPERATION_ENABLED"
        assert dump["drives"]["2"]["position"] == 3000 and dump["drives"]["1"]["position"] == 0
        assert control_request(control, {"cmd": "fault", "node": 2, "kind": "emcy", "code": "0x3210"})["ok"]
        _emcy(node, 0x3210)  # over-voltage, through the adapter
        assert cycle(0x0F, 3000) & 0x4F in (0x08, 0x0F)  # fault reaction, then FAULT

        # heartbeats, then the control socket stops them
        beats = []
        node.nmt.add_heartbeat_callback(beats.append)
        node.sdo[0x1017].raw = 10
        assert node.nmt.wait_for_heartbeat(1) == "OPERATIONAL"
        assert control_request(control, {"cmd": "fault", "node": 2, "kind": "heartbeat_stop"})["ok"]
        n = len(beats)
        time.sleep(0.2)  # about 20 beats if it were still beating; one may have been in flight
        assert len(beats) - n <= 1
        # bus-off: nothing passes; cleared, everything does again
        assert control_request(control, {"cmd": "bus_off"})["ok"]
        net.sync.transmit()
        assert node.tpdo[1].wait_for_reception(0.1) is None
        assert control_request(control, {"cmd": "clear_faults"})["ok"]
        net.sync.transmit()
        assert node.tpdo[1].wait_for_reception(1) is not None
        assert node.nmt.wait_for_heartbeat(1) == "OPERATIONAL"
        bad = control_request(control, {"cmd": "fault", "node": 9, "kind": "emcy"})
        assert not bad["ok"] and "node id 9" in bad["error"]
    finally:
        net.disconnect()


@pytest.fixture
def adapter():
    """An adapter alone, a python-can peer on its bus side, the pty's raw file descriptor."""
    sim_side = f"adapter-test-{os.getpid()}-{time.monotonic_ns()}"
    a = SlcanAdapter("virtual", sim_side, bitrate=1_000_000)
    a.start()
    peer = can.Bus(interface="virtual", channel=sim_side, receive_own_messages=False)
    fd = os.open(a.port, os.O_RDWR | os.O_NOCTTY)
    yield a, peer, fd
    os.close(fd)
    peer.shutdown()
    a.stop()


def _ask(fd: int, line: bytes, reply_len: int = 1) -> bytes:
    """Send one command line; the adapter's reply (``reply_len`` bytes, or what came in 1 s)."""
    os.write(fd, line + b"\r")
    out = b""
    deadline = time.monotonic() + 1
    while len(out) < reply_len and time.monotonic() < deadline:
        if select.select([fd], [], [], max(0.0, deadline - time.monotonic()))[0]:
            out += os.read(fd, 64)
    return out


def test_lawicel_commands_and_hostile_lines(adapter):
    a, peer, fd = adapter
    assert _ask(fd, b"t12381122") == b"\a"  # closed: no transmit
    assert _ask(fd, b"S8") == b"\r" and _ask(fd, b"Z0") == b"\r" and _ask(fd, b"O") == b"\r"
    assert _ask(fd, b"S6") == b"\a"  # no bitrate change while open
    assert _ask(fd, b"V", 6) == b"V1013\r" and _ask(fd, b"F", 4) == b"F00\r"
    assert _ask(fd, b"t1232AABB", 2) == b"z\r"
    msg = peer.recv(1)
    assert msg.arbitration_id == 0x123 and msg.data == b"\xaa\xbb" and not msg.is_extended_id
    assert _ask(fd, b"T1ABCDEF00", 2) == b"Z\r"
    msg = peer.recv(1)
    assert msg.arbitration_id == 0x1ABCDEF0 and msg.is_extended_id and msg.data == b""
    for hostile in (b"t1239" + b"00" * 9, b"t123211223344", b"t8001", b"tXYZ0", b"t12", b"d1231AA",
                    b"T1ABCDEFG0", b"t1231ZZ", b"?", b"r1232FF"):
        assert _ask(fd, hostile) == b"\a", hostile
    assert peer.recv(0.05) is None  # none of them reached the bus
    os.write(fd, b"x" * 200)  # noise without a CR is dropped, the next command still works
    assert _ask(fd, b"\rt7000", 4).endswith(b"z\r")
    assert peer.recv(1).arbitration_id == 0x700
    # bus -> master
    peer.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x37\x02\x10\x27\x00\x00"))
    assert b"t1816370210270000\r" in _ask(fd, b"", 20)  # the frame and the empty line's OK
    assert parse_frame(format_frame(can.Message(arbitration_id=0x1FFFFFFF, is_extended_id=True,
                                                data=b"\x01"))).arbitration_id == 0x1FFFFFFF
    assert a.rx_frames == 3


def test_bus_off_and_a_wrong_bitrate_pass_nothing(adapter):
    a, peer, fd = adapter
    assert _ask(fd, b"S4") == b"\r" and _ask(fd, b"O") == b"\r"  # 125 kbit/s on a 1 Mbit/s bus
    assert _ask(fd, b"t7000") == b"\a" and _ask(fd, b"F", 4) == b"FA4\r"
    peer.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x01"))
    assert _ask(fd, b"C") == b"\r"  # nothing came in before the close's OK
    assert _ask(fd, b"S8") == b"\r" and _ask(fd, b"O") == b"\r"
    a.bus_off = True
    assert _ask(fd, b"t7000") == b"\a" and _ask(fd, b"F", 4) == b"FA4\r"
    a.bus_off = False
    assert _ask(fd, b"t7000", 2) == b"z\r" and peer.recv(1) is not None


def test_python_can_slcan_client_in_process():
    """python-can's slcan bus on the adapter of an in-process simulator (what the backend's
    conformance row uses): SDO round trips and a SYNC answered by the drive's TPDO."""
    with CanopenSimulator([3], interface="slcan") as sim:
        net = canopen.Network()
        net.NOTIFIER_CYCLE = 0.02
        net.connect(interface="slcan", channel=sim.port, bitrate=1_000_000, sleep_after_open=0)
        try:
            node = canopen.RemoteNode(3, make_object_dictionary(3))
            net.add_node(node)
            assert node.sdo[0x6502].raw == 0x3A0
            node.tpdo.read()
            node.tpdo[1].trans_type = 1
            node.tpdo[1].save()  # TPDO1 = statusword, SYNC type
            node.nmt.state = "OPERATIONAL"
            assert node.tpdo[1].timestamp is None  # nothing received before the SYNC
            # not wait_for_reception(): it waits for the NEXT TPDO, and the in-process drive's
            # answer can come before the call (it failed so once in a clean CI run)
            net.sync.transmit()
            wait_until(lambda: node.tpdo[1].timestamp is not None, 5, what="TPDO1 answering the SYNC")
            assert node.tpdo[1][0x6041].raw & 0x4F == 0x40
            assert sim.rx_bytes > 0
        finally:
            net.disconnect()
    assert not sim.running


def _opened_and_held(adapter, monkeypatch):
    """The adapter opened at 1 Mbit/s, its bus thread held inside its first write to the master
    until ``gate`` is set. Returns (adapter, bus peer, master fd, the writes, gate)."""
    import threading

    a, peer, fd = adapter
    assert _ask(fd, b"S8") == b"\r" and _ask(fd, b"O") == b"\r"
    writes, gate = [], threading.Event()
    real = a._write

    def held(data):
        writes.append(data)
        if len(writes) == 1:
            gate.wait(5)
        real(data)

    monkeypatch.setattr(a, "_write", held)
    return a, peer, fd, writes, gate


def test_the_frames_waiting_for_the_adapter_go_to_the_master_in_one_write(adapter, monkeypatch):
    """What the bus brought while the adapter was busy goes up in ONE write, in order, as a USB
    adapter's transfer carries several frames (a SYNC's TPDOs wake the master's reader once, not
    once per frame). The adapter is held inside its first write while four frames arrive."""
    a, peer, fd, writes, gate = _opened_and_held(adapter, monkeypatch)
    first = can.Message(arbitration_id=0x701, is_extended_id=False, data=b"\x05")
    peer.send(first)
    wait_until(lambda: writes, 5, what="the adapter writing the first frame")
    frames = [(0x181, b"\x37\x02"), (0x281, b"\x01"), (0x182, b"\x37\x02"), (0x282, b"")]
    for cob, data in frames:
        peer.send(can.Message(arbitration_id=cob, is_extended_id=False, data=data))
    gate.set()
    burst = b"".join(format_frame(can.Message(arbitration_id=c, is_extended_id=False, data=d)) + b"\r"
                     for c, d in frames)
    expected = format_frame(first) + b"\r" + burst
    out = b""
    deadline = time.monotonic() + 5
    while len(out) < len(expected) and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.1)[0]:
            out += os.read(fd, 256)
    assert out == expected
    assert writes == [format_frame(first) + b"\r", burst]  # the four in one write, in the order they came
    assert a.tx_frames == 5


def test_a_frames_acknowledgement_goes_up_with_the_frames_that_answer_it(adapter, monkeypatch):
    """A transmitted frame is acknowledged (``z``) once it is on the bus, in the adapter's stream
    to the master in bus order: a SYNC's acknowledgement and the TPDOs answering it within one
    USB frame go up in ONE write (one wake-up of the master's reader per SYNC, not two). The
    window is widened here so a loaded host cannot split them."""
    import crtk_bridge.sim.slcan as slcan_mod

    a, peer, fd = adapter
    assert _ask(fd, b"S8") == b"\r" and _ask(fd, b"O") == b"\r"
    monkeypatch.setattr(slcan_mod, "USB_FRAME_S", 0.5)
    writes = []
    real = a._write
    monkeypatch.setattr(a, "_write", lambda data: (writes.append(data), real(data)))
    os.write(fd, b"t0800\r")  # SYNC
    sync = peer.recv(5)
    assert sync is not None and sync.arbitration_id == 0x80
    answers = [(0x181, b"\x37\x02")]
    for cob, data in answers:
        peer.send(can.Message(arbitration_id=cob, is_extended_id=False, data=data))
    expected = b"z\r" + b"".join(format_frame(can.Message(arbitration_id=c, is_extended_id=False, data=d)) + b"\r"
                                 for c, d in answers)
    out = b""
    deadline = time.monotonic() + 5
    while len(out) < len(expected) and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.1)[0]:
            out += os.read(fd, 256)
    assert out == expected and writes == [expected]
    assert a.tx_frames == 1 and a.rx_frames == 1


def test_a_frame_from_while_the_adapter_was_closed_is_not_forwarded_after_it_reopens(adapter, monkeypatch):
    """Whether a frame passes is decided by when it was on the bus, not by when the adapter's
    bus thread gets to it: a frame sent while the channel was closed (or at the wrong bitrate,
    or bus-off) never reaches the master, even when the thread was busy until after the master
    opened the channel again (a race a loaded host hit in test_bus_off_and_a_wrong_bitrate_pass_nothing)."""
    a, peer, fd, writes, gate = _opened_and_held(adapter, monkeypatch)  # the bus thread, busy with frame A
    peer.send(can.Message(arbitration_id=0x701, is_extended_id=False, data=b"\x05"))  # A
    wait_until(lambda: writes, 5, what="the adapter writing frame A")
    os.write(fd, b"C\r")
    wait_until(lambda: not a.is_open, 5, what="the channel closed")
    peer.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x01"))  # B, while closed
    os.write(fd, b"O\r")
    wait_until(lambda: a.is_open, 5, what="the channel open again")
    gate.set()
    peer.send(can.Message(arbitration_id=0x182, is_extended_id=False, data=b"\x02"))  # C, open
    out = b""
    deadline = time.monotonic() + 5
    while b"t1821" not in out and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.1)[0]:
            out += os.read(fd, 256)
    assert b"t1821" in out and b"t7011" in out, out
    assert b"t181" not in out, out

"""Recording and the black box (docs/recording.md): every control cycle's sample, through the
shared ring, into rosbag2 MCAP read back with the independent ``mcap`` reader and with rosbags;
a killed daemon's recording; the black box on a FAULT and on request; a write error ends the
recording, never the robot."""

from __future__ import annotations

import os
import resource
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from rosbags.rosbag2 import Reader

from crtk_bridge.client import connect
from crtk_bridge.client.cli import main as ctl_main
from crtk_bridge.core.samples import MARKER, STAMP, SampleReader, SampleRing
from crtk_bridge.core.snapshot import Layout
from crtk_bridge.errors import CommandError
from crtk_bridge.transport.ros.types import TYPESTORE

from .conftest import DaemonProcess, RemoteSim, so101_data, wait_until

RATE_HZ = 1000.0
BLACKBOX_S = 2.0


# ---------------------------------------------------------------- the ring, alone
def test_ring_counts_overwritten_samples_and_never_returns_a_torn_one():
    ring = SampleRing(Layout(2, 1), 8, create=True)
    try:
        reader = SampleReader(ring)
        state = np.zeros(ring.state)
        for i in range(5):
            state[:] = i
            ring.push(i, 100.0 + i, state)
        rows, lost = reader.drain()
        assert rows[:, MARKER].tolist() == [0, 1, 2, 3, 4] and lost == 0
        assert (rows[:, 2:] == rows[:, [MARKER]]).all() and rows[:, STAMP].tolist() == [100, 101, 102, 103, 104]
        for i in range(5, 20):  # 15 cycles into 8 slots: 7 overwritten before the reader came back
            ring.push(i, 100.0 + i, state)
        rows, lost = reader.drain()
        assert lost == 7 and reader.lost == 7 and rows[:, MARKER].tolist() == list(range(12, 20))
        # a slot being rewritten (marker -1 while the writer copies) is lost, not returned
        ring.push(20, 120.0, state)
        ring.slots[20 % 8, MARKER] = -1.0
        rows, lost = reader.drain()
        assert lost == 1 and len(rows) == 0 and reader.next == 21
    finally:
        ring.close(unlink=True)


def test_overwritten_samples_are_said_and_counted_in_each_recording(tmp_path):
    """The drain thread (one pass, in-process): cycles the loop overwrote before the front read
    them become a samples_lost warning and each running recording's ``lost``; the black box
    keeps what was read."""
    from types import SimpleNamespace

    from crtk_bridge.profile import load_profile
    from crtk_bridge.recording.recorder import Recorder

    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(so101_data()))
    profile = load_profile(path)
    ring = SampleRing(Layout(len(profile.joints), len(profile.namespaces)), 16, create=True)
    try:
        link = SimpleNamespace(period_s=0.001, ns_index={"so101": 0, "so101/gripper": 1})
        server = SimpleNamespace(link=link, profile=profile, robot="so101", state={"state": "DISABLED"})
        rec = Recorder(server, ring)
        said = []
        rec.say = lambda kind, code, message, **extra: said.append((kind, code, message, extra))
        running = SimpleNamespace(lost=0, stopping=False, offered=[], offer=lambda item: running.offered.append(item))
        rec._active = (running,)
        state = np.zeros(ring.state)
        ring.push(0, 1.0, state)
        rec._drain_once()
        for i in range(1, 41):  # 40 cycles into 16 slots: 24 overwritten
            ring.push(i, 1.0 + i * 1e-3, state)
        rec._drain_once()
        assert running.lost == 24 and rec.lost == 24
        assert [(k, c, e) for k, c, _, e in said] == [("warning", "samples_lost", {"value": 24})]
        assert "24 cycles' samples were overwritten" in said[0][2]
        rows = np.concatenate([item[1] for item in running.offered])
        assert rows[:, MARKER].tolist() == [0] + list(range(25, 41))
        assert rec.blackbox.count == 17
    finally:
        ring.close(unlink=True)


def test_black_boxes_go_to_the_units_state_directory(monkeypatch, tmp_path):
    from crtk_bridge.recording.recorder import default_blackbox_dir

    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    assert default_blackbox_dir() == str(tmp_path / "crtk-bridge" / "blackbox")
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/crtk-bridge")  # systemd's StateDirectory=crtk-bridge
    assert default_blackbox_dir() == "/var/lib/crtk-bridge/blackbox"


@pytest.mark.parametrize("key, value", [("blackbox_s", -1.0), ("blackbox_s", 601.0), ("rotate_s", 0.5)])
def test_recording_keys_out_of_range_are_refused_naming_the_key(tmp_path, key, value):
    from crtk_bridge.errors import ProfileError
    from crtk_bridge.profile import load_profile

    data = so101_data()
    data["recording"] = {key: value}
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ProfileError, match=rf"recording\.{key}: {value} is not in"):
        load_profile(path)


# ---------------------------------------------------------------- a daemon at 1 kHz
def _profile(tmp: Path, **recording) -> Path:
    data = so101_data()
    data["loop"]["rate_hz"] = RATE_HZ
    data["recording"] = {"blackbox_s": BLACKBOX_S, "blackbox_dir": str(tmp / "blackbox"), **recording}
    path = tmp / "so101_1khz.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _start(tmp: Path) -> DaemonProcess:
    return DaemonProcess(["--profile", str(_profile(tmp)), "--sim"], tmp / "so101.sock", tmp / "daemon.log")


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    import tempfile
    tmp = Path(tempfile.mkdtemp(prefix="crtk-rec-"))  # short: the socket path
    d = _start(tmp)
    d.tmp = tmp
    try:
        yield d
    finally:
        d.print_tail()
        d.stop()


@pytest.fixture
def robot(daemon):
    r = connect(socket=str(daemon.socket_path), timeout=10.0)
    try:
        yield r
    finally:
        try:
            r.disable()
        except Exception:
            pass
        r.close()


def _messages(path: Path, topic: str) -> list[tuple[int, object]]:
    """(log_time, decoded) of ``topic``, read with the independent mcap reader (index and summary)."""
    out = []
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        for schema, channel, message in reader.iter_messages(topics=[topic]):
            assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
            out.append((message.log_time, TYPESTORE.deserialize_cdr(message.data, schema.name)))
    return out


def _stamp(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def test_a_recording_holds_every_cycle_of_a_move(robot, daemon):
    arm = robot.device("so101")
    robot.enable()
    goal = [0.2, -0.2, 0.2, 0.1, 0.1]
    c0 = robot.period_statistics()["cycles"]
    start = robot.record(str(daemon.tmp / "move.mcap"), duration_s=2.0)
    arm.move_jp(goal).wait(timeout=10)
    result = robot.record_stop(start["recording"], wait=True, timeout=20)
    c1 = robot.period_statistics()["cycles"]
    path = Path(result["path"])
    assert path == daemon.tmp / "move" / "move.mcap" and result["lost"] == 0

    # one measured_js per control cycle: the count equals the cycles the daemon ran in the window
    first, last = result["first_cycle"], result["last_cycle"]
    assert c0 <= first < last <= c1
    js = _messages(path, "/so101/measured_js")
    assert len(js) == result["samples"] == last - first + 1
    assert RATE_HZ / 4 < len(js) <= 2.0 * RATE_HZ + 1  # 2 s of cycles (fewer only by overruns)
    logs = np.array([t for t, _ in js])
    stamps = np.array([_stamp(m.header) for _, m in js])
    assert (np.diff(logs) > 0).all() and (np.diff(stamps) > 0).all()  # strictly increasing
    assert 1.0e9 < logs[-1] - logs[0] < 2.0e9  # the cycles of 2 s, on the loop's own clock
    assert js[0][1].name == ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]
    # the move is in it: the setpoint runs from where it was to the goal
    sp = _messages(path, "/so101/setpoint_js")
    assert len(sp) == len(js)
    np.testing.assert_allclose(sp[-1][1].position, goal, atol=1e-6)
    moving = [m.position for _, m in sp if len(m.position)]
    assert np.abs(np.asarray(moving[0]) - goal).max() > 0.05 and len(moving) > RATE_HZ / 2
    assert len(_messages(path, "/so101/gripper/measured_js")) == len(js)
    assert len(_messages(path, "/so101/measured_cp")) == len(js) == len(_messages(path, "/tf"))
    # the command, who sent it, and the state it caused
    commands = [m.string for _, m in _messages(path, "/so101/commands")]
    assert any('"cmd":"move_jp"' in c and "session" in c and "0.2" in c for c in commands), commands
    states = [(m.state, m.is_busy) for _, m in _messages(path, "/so101/operating_state")]
    assert ("ENABLED", True) in states and states[-1] == ("ENABLED", False)
    assert len(_messages(path, "/robot_description")) == 1

    # rosbags reads the same file (and its bag directory) with the same counts and QoS
    for where in (path, path.parent):
        with Reader(where) as bag:
            conns = {c.topic: c for c in bag.connections}
            assert bag.topics["/so101/measured_js"].msgcount == len(js)
            assert conns["/so101/measured_js"].msgtype == "sensor_msgs/msg/JointState"
            assert conns["/so101/operating_state"].ext.offered_qos_profiles[0].durability.name == "TRANSIENT_LOCAL"
            times = [t for _, t, _ in bag.messages(connections=[conns["/so101/measured_js"]])]
            assert times == logs.tolist()


def test_crtk_ctl_record_and_blackbox(robot, daemon, capsys):
    sock = str(daemon.socket_path)
    out = daemon.tmp / "ctl.mcap"
    assert ctl_main(["--socket", sock, "record", str(out), "--duration", "0.5", "--ns", "so101/gripper"]) == 0
    text = capsys.readouterr().out
    assert str(daemon.tmp / "ctl" / "ctl.mcap") in text and "lost 0" in text
    with open(daemon.tmp / "ctl" / "ctl.mcap", "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert "/so101/gripper/measured_js" in topics and "/so101/measured_js" not in topics
    # refusals name what is wrong
    with pytest.raises(CommandError, match="unknown namespace 'nope'") as info:
        robot.record(str(daemon.tmp / "nope.mcap"), namespaces=["nope"])
    assert info.value.code == "unknown_namespace" and not (daemon.tmp / "nope").exists()
    with pytest.raises(CommandError, match="exists already") as info:
        robot.record(str(daemon.tmp / "ctl.mcap"))
    assert info.value.code == "bad_request"
    # on request: the last BLACKBOX_S seconds (of cycles: the window is in cycles), every cycle
    wait_until(lambda: robot.period_statistics()["cycles"] > BLACKBOX_S * RATE_HZ + 100, 30,
               what="a black box's worth of cycles")
    assert ctl_main(["--socket", sock, "blackbox", str(daemon.tmp / "asked")]) == 0
    js = _messages(daemon.tmp / "asked" / "asked.mcap", "/so101/measured_js")
    assert len(js) == int(BLACKBOX_S * RATE_HZ)
    assert (np.diff([t for t, _ in js]) > 0).all()
    # a path that exists is refused, in one line naming it
    assert ctl_main(["--socket", sock, "blackbox", str(daemon.tmp / "asked")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "exists already" in err and str(daemon.tmp / "asked") in err


def test_a_recording_ends_with_the_session_that_started_it(daemon):
    other = connect(socket=str(daemon.socket_path), timeout=10.0)
    started = other.record(str(daemon.tmp / "orphan.mcap"))
    other.close()  # a client that goes away leaves no recording running: the bag is closed
    wait_until(lambda: (daemon.tmp / "orphan" / "metadata.yaml").exists(), 20, what="the bag closed")
    assert len(_messages(Path(started["path"]), "/so101/operating_state")) == 1  # closed: the index reads


def test_the_black_box_is_written_on_a_fault(robot, daemon):
    sim = RemoteSim(daemon.sim_control_path())
    robot.enable()
    wait_until(lambda: robot.period_statistics()["cycles"] > BLACKBOX_S * RATE_HZ + 100, 30,
               what="a black box's worth of cycles")
    mark = robot.connection.event_count
    t_fault = time.time()
    sim.set_fault(4, "error_bits", 0x04)  # overheat: FAULT at once
    ev = robot.wait_for_event("blackbox_written", 20.0, kind="status", since=mark)
    assert ev is not None, "no blackbox_written event"
    sim.clear_faults()
    path = Path(ev.data["path"])
    assert str(path) in ev.data["message"] and path.parent.parent == daemon.tmp / "blackbox"
    js = _messages(path, "/so101/measured_js")
    assert len(js) == int(BLACKBOX_S * RATE_HZ)  # the configured window, every cycle
    logs = np.array([t for t, _ in js])
    assert (np.diff(logs) > 0).all()
    assert logs[0] < t_fault * 1e9 < logs[-1]  # the seconds before the fault, and the fault
    errors = [m.string for _, m in _messages(path, "/so101/error")]
    assert any("overheat" in e.lower() or "error" in e.lower() for e in errors), errors
    states = [m.state for _, m in _messages(path, "/so101/operating_state")]
    assert states[-1] == "FAULT"
    robot.disable()


def _stream_messages(path: Path) -> dict[str, list[int]]:
    """log times per topic of a file without its footer (a killed writer): read record by record."""
    topics: dict[int, str] = {}
    out: dict[str, list[int]] = {}
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Channel):
                    topics[record.id] = record.topic
                elif isinstance(record, Message):
                    out.setdefault(topics[record.channel_id], []).append(record.log_time)
        except Exception:  # the torn end of the file
            pass
    return out


def test_a_killed_daemons_recording_loses_at_most_a_second(tmp_path_factory):
    import tempfile
    tmp = Path(tempfile.mkdtemp(prefix="crtk-kill-"))
    d = _start(tmp)
    try:
        r = connect(socket=str(d.socket_path), timeout=10.0)
        # one small namespace: rosbags alone would close a 1 MiB chunk only every ~2 s of it
        started = r.record(str(tmp / "killed.mcap"), namespaces=["so101/gripper"])
        wait_until(lambda: os.path.exists(started["path"]) and os.path.getsize(started["path"]) > 0, 10,
                   what="the recording on disk")
        r.enable()
        r.device("so101").move_jp([0.3, 0, 0, 0, 0]).wait(timeout=10)
        time.sleep(1.0)  # recording on; then the daemon dies at once
        t_kill = time.time_ns()
        d.proc.kill()
        d.proc.wait(10)
        r.close()
        times = _stream_messages(Path(started["path"]))
        js = times["/so101/gripper/measured_js"]
        assert len(js) > RATE_HZ  # what it recorded is readable
        assert (np.diff(js) > 0).all()
        lost_s = (t_kill - js[-1]) * 1e-9
        print(f"killed daemon: the recording's last sample {lost_s:.3f} s before the kill")
        assert lost_s <= 1.0
    finally:
        d.stop()


def test_recording_from_start_up_rotates_bags_without_a_gap(tmp_path_factory):
    import tempfile
    tmp = Path(tempfile.mkdtemp(prefix="crtk-rot-"))
    folder = tmp / "bags"
    prof = _profile(tmp, rotate_s=1.0)
    d = DaemonProcess(["--profile", str(prof), "--sim", "--record", str(folder)], tmp / "so101.sock", tmp / "log")
    try:
        assert f"recording every cycle into {folder}" in d.output()
        wait_until(lambda: len(list(folder.glob("*/metadata.yaml"))) >= 2, 30, what="two closed bags")
        assert d.terminate() == 0  # a normal stop closes the bag being written
    finally:
        d.stop()
    bags = sorted(folder.iterdir())
    assert len(bags) >= 3 and all((b / "metadata.yaml").exists() for b in bags)
    spans = []
    for b in bags:
        meta = yaml.safe_load((b / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        custom = meta["custom_data"]
        first, last = int(custom["first_cycle"]), int(custom["last_cycle"])
        js = _messages(b / f"{b.name}.mcap", "/so101/measured_js")
        assert len(js) == last - first + 1 == int(custom["samples"]) and custom["lost"] == "0"
        assert len(_messages(b / f"{b.name}.mcap", "/robot_description")) == 1  # each bag stands alone
        assert len(_messages(b / f"{b.name}.mcap", "/so101/operating_state")) >= 1
        spans.append((first, last, js[0][0], js[-1][0]))
    for (_, last, _, t_last), (first, _, t_first, _) in zip(spans, spans[1:]):
        assert first == last + 1 and t_first > t_last  # the next bag starts at the next cycle
    assert all(t1 - t0 < 1.0e9 for _, _, t0, t1 in spans)  # at most rotate_s of cycles each


def test_a_write_error_stops_the_recording_not_the_robot(robot, daemon):
    arm = robot.device("so101")
    robot.enable()
    mark = robot.connection.event_count
    started = robot.record(str(daemon.tmp / "full.mcap"))
    wait_until(lambda: os.path.getsize(started["path"]) > 0, 10, what="the recording on disk")
    # the front process may write no file beyond 200 kB from now on (the disk is "full"); Python
    # ignores SIGXFSZ, so a write beyond it fails with EFBIG as a full disk fails with ENOSPC
    pid = daemon.proc.pid
    limit = os.path.getsize(started["path"]) + 200_000
    old = resource.prlimit(pid, resource.RLIMIT_FSIZE)
    resource.prlimit(pid, resource.RLIMIT_FSIZE, (limit, old[1]))  # the soft limit: restored below
    try:
        ev = robot.wait_for_event("recording_failed", 30.0, kind="warning", since=mark)
        assert ev is not None, "no recording_failed warning"
        assert started["path"] in ev.data["message"] and "robot goes on" in ev.data["message"]
        result = robot.record_stop(started["recording"])
        assert "File too large" in result["error"]
        # the robot never noticed: ENABLED, cycling, and it moves
        assert robot.operating_state() == "ENABLED"
        c0 = robot.period_statistics()["cycles"]
        assert arm.move_jp([0.1, 0.1, 0, 0, 0]).wait(timeout=10)
        assert robot.period_statistics()["cycles"] > c0 and robot.operating_state() == "ENABLED"
    finally:
        resource.prlimit(pid, resource.RLIMIT_FSIZE, old)
    # and recording works again once there is room
    again = robot.record(str(daemon.tmp / "after.mcap"), duration_s=0.2)
    assert robot.record_stop(again["recording"], wait=True, timeout=20)["samples"] > 0

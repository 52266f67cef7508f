"""The Python client and crtk-ctl against a scripted fake of the daemon's wire (docs/protocol.md).

The fake is a test double of the socket protocol only: a thread on a Unix socket that answers
requests from a small table and pushes events when a test says so. The end-to-end test against
the real daemon lives elsewhere.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
import tempfile
import threading
import time

import numpy as np
import pytest

from crtk_bridge.client import (
    connect, default_socket_path, matrix_from_quaternion, pose_matrix, pose_pq, quaternion_from_matrix)
from crtk_bridge.client.cli import main
from crtk_bridge.client.connection import PROTOCOL_VERSION, Connection, DaemonConnectionError
from crtk_bridge.errors import CommandError

from .conftest import wait_until

JOINTS = ["shoulder_pan", "elbow"]
#: what a position-only backend lists: no servo_jf / interpolate_jf
ARM_COMMANDS = ["enable", "disable", "pause", "resume", "home", "unhome", "servo_jp", "servo_jr",
                "servo_jv", "interpolate_jp", "interpolate_jr", "interpolate_jv", "move_jp",
                "move_jr", "hold", "free"]


def state(name="DISABLED", homed=True, busy=False, seq=0):
    return {"state": name, "is_homed": homed, "is_busy": busy, "busy_seq": seq, "stamp": 1.5}


def ok(req, data=None):
    return {"id": req["id"], "ok": True, "data": data}


def err(req, code, message):
    return {"id": req["id"], "ok": False, "error": {"code": code, "message": message}}


def os_event(st):
    return {"event": "operating_state", "data": dict(st)}


class FakeDaemon:
    """Accepts sessions on ``path``; pushes the current operating_state on connect; answers each
    request with ``handlers[cmd](req, session)`` (which sends any lines it likes, or none)."""

    def __init__(self, path):
        self.path = path
        self.robot = "so101"
        self.state = state()
        self.requests: list[dict] = []
        self.sessions: list[socket.socket] = []
        self.handlers = {
            "list": lambda r, s: s.send(ok(r, {
                "robot": self.robot, "protocol_version": PROTOCOL_VERSION, "daemon_version": "0.1.0",
                "namespaces": [
                    {"name": "so101", "joints": JOINTS, "commands": ARM_COMMANDS,
                     "queries": ["measured_js"], "topics": ["measured_js"]},
                    {"name": "so101/gripper", "joints": ["gripper"], "commands": ["move_jp"],
                     "queries": ["measured_js"], "topics": ["measured_js"]}]})),
            "operating_state": lambda r, s: s.send(ok(r, self.state)),
            "measured_js": lambda r, s: s.send(ok(r, {
                "stamp": 123.25, "frame_id": "", "name": JOINTS, "position": [0.1, -0.2],
                "velocity": [0.0, 0.5], "effort": []})),
        }
        self._lsock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._lsock.bind(path)
        self._lsock.listen()
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            try:
                conn, _ = self._lsock.accept()
            except OSError:
                return
            session = _Session(conn, self._lock)
            self.sessions.append(session)
            session.send(os_event(self.state))
            threading.Thread(target=self._serve, args=(session,), daemon=True).start()

    def _serve(self, session):
        f = session.sock.makefile("rb")
        try:
            for line in f:
                req = json.loads(line)
                self.requests.append(req)
                handler = self.handlers.get(req["cmd"])
                if handler is None:
                    session.send(err(req, "unknown_command", f"no command {req['cmd']!r}"))
                else:
                    handler(req, session)
        except (OSError, ValueError):
            pass

    def push(self, msg):
        for s in list(self.sessions):
            s.send(msg)

    def set_state(self, **kw):
        self.state = dict(self.state, **kw)
        self.push(os_event(self.state))

    def drop_sessions(self):
        for s in self.sessions:
            s.close()

    def close(self):
        self._lsock.close()
        self.drop_sessions()


class _Session:
    def __init__(self, sock, lock):
        self.sock = sock
        self._lock = lock

    def send(self, msg):
        with self._lock:
            try:
                self.sock.sendall((json.dumps(msg) + "\n").encode())
            except OSError:
                pass

    def close(self):
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


@pytest.fixture
def sockdir():
    d = tempfile.mkdtemp(prefix="crtk", dir="/tmp")  # AF_UNIX paths must stay short
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def fake(sockdir):
    daemon = FakeDaemon(os.path.join(sockdir, "so101.sock"))
    yield daemon
    daemon.close()


@pytest.fixture
def robot(fake):
    r = connect(socket=fake.path, timeout=3.0)
    yield r
    r.close()


# -- paths --------------------------------------------------------------------------------------

def test_default_socket_path_follows_xdg_runtime_dir(monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/run/user/1000")
    assert default_socket_path("so101") == "/run/user/1000/crtk-bridge/so101.sock"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert default_socket_path("so101") == f"/tmp/crtk-bridge-{os.getuid()}/so101.sock"


# -- connection ---------------------------------------------------------------------------------

def test_replies_matched_by_id_across_interleaved_events_frames_and_reordering(fake, robot):
    conn = robot.connection
    warnings = []
    conn.on_event = warnings.append
    held = []

    def slow(req, s):  # answered only after the next request's reply
        held.append(req)

    def fast(req, s):
        s.send({"event": "warning", "data": {"stamp": 2.0, "ns": "so101", "code": "servo_timeout",
                                             "message": "servo stream stopped"}})
        s.send({"topic": "measured_js", "ns": "so101", "sub": 77, "data": {"position": [9.0]}})
        s.send(os_event(state("ENABLED", seq=3)))
        s.send(ok(req, {"answer": "fast"}))
        s.send({"topic": "measured_js", "ns": "so101", "sub": 77, "data": {"position": [8.0]}})
        s.send(ok(held[0], {"answer": "slow"}))

    fake.handlers["slow"] = slow
    fake.handlers["fast"] = fast
    results = {}
    t = threading.Thread(target=lambda: results.setdefault("slow", conn.request("slow")))
    t.start()
    assert wait_until(lambda: held)
    assert conn.request("fast") == {"answer": "fast"}
    t.join(3.0)
    assert results["slow"] == {"answer": "slow"}
    assert conn.operating_state["state"] == "ENABLED" and conn.operating_state["busy_seq"] == 3
    assert [e.data["code"] for e in conn.events] == ["servo_timeout"]
    assert warnings and warnings[0].kind == "warning"


def test_request_all_sends_every_request_before_waiting_and_returns_replies_in_order(fake, robot):
    """One round trip for several requests (the LeRobot plugin's arm + gripper goals): the fake
    answers only once it holds all three, so requests sent one after the other would time out."""
    held = []

    def hold(req, s):
        held.append(req)
        if len(held) == 3:
            for r in held:
                s.send(err(r, "out_of_limits", "so101: nope") if r["ns"] == "b" else ok(r, {"ns": r["ns"]}))

    fake.handlers["q"] = hold
    with pytest.raises(CommandError) as info:  # the failed one raises, once every reply is in
        robot.connection.request_all([("q", "a", None), ("q", "b", {"x": 1}), ("q", "c", None)], timeout=2.0)
    assert info.value.code == "out_of_limits" and [r["ns"] for r in held] == ["a", "b", "c"]
    assert held[1]["data"] == {"x": 1}
    held.clear()
    assert robot.connection.request_all([("q", ns, None) for ns in "acd"], timeout=2.0) == \
        [{"ns": "a"}, {"ns": "c"}, {"ns": "d"}]
    assert robot.connection.request("list")["robot"] == "so101"  # nothing left pending


def test_error_reply_raises_command_error_with_code_and_message(fake, robot):
    fake.handlers["move_jp"] = lambda r, s: s.send(err(
        r, "invalid_state", "so101: move_jp refused: robot is DISABLED (enable it first)"))
    with pytest.raises(CommandError) as info:
        robot.device("so101").move_jp([0.1, 0.2])
    assert info.value.code == "invalid_state"
    assert info.value.message == "so101: move_jp refused: robot is DISABLED (enable it first)"
    sent = fake.requests[-1]
    assert sent["ns"] == "so101" and sent["data"] == {"position": [0.1, 0.2]}


def test_vectors_sent_as_plain_floats_and_non_finite_refused_locally(fake, robot):
    fake.handlers["servo_jp"] = lambda r, s: s.send(ok(r))
    arm = robot.device()
    arm.servo_jp(np.array([1, 2], dtype=np.int32), (0.5, np.float32(0.25)))
    assert fake.requests[-1]["data"] == {"position": [1.0, 2.0], "velocity": [0.5, 0.25]}
    n = len(fake.requests)
    with pytest.raises(CommandError) as info:
        arm.servo_jp([float("nan"), 0.0])
    assert info.value.code == "bad_request"
    assert len(fake.requests) == n  # nothing sent


def test_pending_request_fails_promptly_when_daemon_closes(fake, robot):
    conn = robot.connection
    fake.handlers["hang"] = lambda r, s: threading.Timer(0.2, fake.drop_sessions).start()
    t0 = time.monotonic()
    with pytest.raises(ConnectionError) as info:
        conn.request("hang", timeout=10.0)
    assert time.monotonic() - t0 < 2.0
    assert fake.path in str(info.value)
    with pytest.raises(ConnectionError):
        conn.request("list")
    with pytest.raises(ConnectionError):  # waiters fail too
        conn.wait_for(lambda c: False, timeout=5.0)
    conn.close()
    conn.close()  # idempotent


def test_request_times_out_when_no_reply(fake, robot):
    fake.handlers["mute"] = lambda r, s: None
    t0 = time.monotonic()
    with pytest.raises(TimeoutError):
        robot.connection.request("mute", timeout=0.2)
    assert time.monotonic() - t0 < 2.0
    assert robot.connection.request("list")["robot"] == "so101"  # the session still works


def test_no_daemon_raises_connection_error_naming_the_path(sockdir):
    path = os.path.join(sockdir, "nobody.sock")
    with pytest.raises(ConnectionError) as info:
        Connection(path)
    assert isinstance(info.value, DaemonConnectionError)
    assert path in str(info.value) and "not running" in str(info.value)


# -- devices ------------------------------------------------------------------------------------

def test_namespaces_as_devices_and_children(robot):
    arm = robot.device("so101")
    assert robot.device() is arm and robot["so101"] is arm
    assert arm.joint_names == JOINTS
    assert arm.gripper is robot["so101/gripper"]
    assert arm.gripper.name == "so101/gripper" and arm.gripper.joint_names == ["gripper"]
    with pytest.raises(AttributeError):
        arm.wrist
    with pytest.raises(KeyError):
        robot.device("ur5")


def test_measured_js_returns_numpy_arrays_and_stamp(fake, robot):
    arm = robot.device()
    p, v, e, ts = arm.measured_js()
    assert isinstance(p, np.ndarray) and p.dtype == np.float64
    np.testing.assert_allclose(p, [0.1, -0.2])
    np.testing.assert_allclose(v, [0.0, 0.5])
    assert e.shape == (0,)  # not provided: empty (CRTK 4.1.6)
    assert ts == 123.25
    jp, ts2 = arm.measured_jp()
    np.testing.assert_allclose(jp, [0.1, -0.2])
    assert ts2 == 123.25
    assert fake.requests[-1] == {"id": fake.requests[-1]["id"], "cmd": "measured_js", "ns": "so101"}


def test_move_handle_ignores_stale_idle_and_waits_for_its_own_busy_seq(fake, robot):
    fake.set_state(state="ENABLED", busy_seq=4)  # idle, seq 4: stale for the next move
    assert wait_until(lambda: robot.connection.operating_state["state"] == "ENABLED")

    def move(req, s):  # protocol: busy edge before the reply
        fake.state = state("ENABLED", busy=True, seq=5)
        s.send(os_event(fake.state))
        s.send(ok(req, {"busy_seq": 5}))
        s.send(os_event(state("ENABLED", busy=False, seq=4)))  # a late stale idle must not count

    fake.handlers["move_jp"] = move
    handle = robot.device().move_jp([0.3, 0.4])
    assert handle.busy_seq == 5
    assert handle.wait(is_busy=True, timeout=1.0)
    assert handle.wait(timeout=0.3) is False
    assert handle.is_busy()
    done = []
    waiter = threading.Thread(target=lambda: done.append(handle.wait(timeout=5.0)))
    waiter.start()
    waiter.join(0.05)  # the window in which wait() must not return: the move is still busy
    assert waiter.is_alive() and not done
    fake.set_state(is_busy=False, busy_seq=5)
    assert wait_until(lambda: done)
    assert done == [True] and not handle.is_busy()


def test_instant_move_both_edges_before_wait(fake, robot):
    fake.set_state(state="ENABLED", busy_seq=1)

    def move(req, s):
        s.send(os_event(state("ENABLED", busy=True, seq=2)))
        s.send(ok(req, {"busy_seq": 2}))
        s.send(os_event(state("ENABLED", busy=False, seq=2)))

    fake.handlers["move_jr"] = move
    t0 = time.monotonic()
    assert robot.device().move_jr([0.0, 0.0]).wait(timeout=5.0)
    assert time.monotonic() - t0 < 2.0


def test_enable_true_when_state_reached_false_on_timeout_or_fault(fake, robot):
    arm = robot.device()

    def enable_async(req, s):  # replies before the control process has switched
        s.send(ok(req, fake.state))
        threading.Timer(0.1, fake.set_state, kwargs={"state": "ENABLED"}).start()

    fake.handlers["enable"] = enable_async
    assert arm.is_disabled()
    assert arm.enable(timeout=3.0) is True
    assert arm.is_enabled()

    fake.handlers["disable"] = lambda r, s: s.send(ok(r, fake.state))  # never switches
    t0 = time.monotonic()
    assert arm.disable(timeout=0.3) is False
    assert 0.25 < time.monotonic() - t0 < 2.0

    fake.state = state("DISABLED")

    def enable_faults(req, s):
        s.send(ok(req, fake.state))
        fake.push({"event": "error", "data": {"stamp": 3.0, "ns": "so101", "code": "bus_timeout",
                                              "message": "so101: servo 3 did not answer"}})
        fake.set_state(state="FAULT")

    fake.handlers["enable"] = enable_faults
    t0 = time.monotonic()
    assert arm.enable(timeout=10.0) is False
    assert time.monotonic() - t0 < 2.0  # a FAULT ends the wait at once
    assert arm.is_fault()

    fake.handlers["resume"] = lambda r, s: s.send(err(r, "invalid_state", "so101: resume refused"))
    with pytest.raises(CommandError) as info:
        arm.resume()
    assert info.value.code == "invalid_state"


def test_home_waits_for_its_own_busy_seq_and_is_homed(fake, robot):
    fake.set_state(state="ENABLED", is_homed=False, busy_seq=7)

    def home(req, s):
        fake.state = state("ENABLED", homed=False, busy=True, seq=8)
        s.send(os_event(fake.state))
        s.send(ok(req, fake.state))
        threading.Timer(0.2, fake.set_state, kwargs={"is_busy": False, "is_homed": True}).start()

    fake.handlers["home"] = home
    t0 = time.monotonic()
    assert robot.device().home(timeout=5.0) is True
    assert time.monotonic() - t0 >= 0.15  # did not return on the stale idle state (seq 7)
    assert robot.device().is_homed() and not robot.device().is_busy()


def test_subscription_queue_callback_and_disconnect(fake, robot):
    arm = robot.device()

    def subscribe(req, s):
        sub = 40 + len([r for r in fake.requests if r["cmd"] == "subscribe"])
        s.send(ok(req, {"sub": sub}))
        for i in range(3):  # frames right after the reply must not be lost
            s.send({"topic": req["data"]["topic"], "ns": req.get("ns"), "sub": sub,
                    "data": {"stamp": 10.0 + i, "position": [float(i), 0.0]}})

    fake.handlers["subscribe"] = subscribe
    fake.handlers["unsubscribe"] = lambda r, s: s.send(ok(r))
    sub = arm.subscribe("measured_js", 50)
    frames = [sub.get(timeout=2.0) for _ in range(3)]
    assert [f["stamp"] for f in frames] == [10.0, 11.0, 12.0]
    assert fake.requests[-1]["data"] == {"topic": "measured_js", "rate_hz": 50}
    sub.close()
    assert wait_until(lambda: fake.requests[-1]["cmd"] == "unsubscribe")
    assert fake.requests[-1]["data"] == {"sub": sub.sub}
    assert list(sub) == []  # closed: iteration ends

    got = []
    cb_sub = robot.device().subscribe("operating_state", 5, callback=got.append)
    assert "ns" not in [r for r in fake.requests if r["cmd"] == "subscribe"][-1]  # robot-wide
    assert wait_until(lambda: len(got) == 3)

    sub2 = arm.subscribe("measured_js", 50)
    fake.drop_sessions()
    with pytest.raises(ConnectionError):
        for _ in sub2:
            pass
    cb_sub.close()


# -- crtk-ctl -----------------------------------------------------------------------------------

def test_cli_refusal_exits_1_with_one_line_reason(fake, capsys):
    fake.handlers["move_jp"] = lambda r, s: s.send(err(
        r, "invalid_state", "so101: move_jp refused: robot is DISABLED (enable it first)"))
    code = main(["move_jp", "0.1", "-0.2", "--socket", fake.path])
    out = capsys.readouterr()
    assert code == 1
    # "refused" once: the daemon's own "move_jp refused: " is not repeated
    assert out.err == ("crtk-ctl: move_jp refused (invalid_state): so101: "
                       "robot is DISABLED (enable it first)\n")


def test_cli_no_daemon_exits_2_naming_the_socket(sockdir, capsys, monkeypatch):
    path = os.path.join(sockdir, "so101.sock")
    assert main(["--socket", path, "state"]) == 2
    err_text = capsys.readouterr().err
    assert err_text.count("\n") == 1 and path in err_text

    monkeypatch.setenv("XDG_RUNTIME_DIR", sockdir)  # no socket in the default directory
    assert main(["state"]) == 2
    err_text = capsys.readouterr().err
    assert err_text.count("\n") == 1 and os.path.join(sockdir, "crtk-bridge") in err_text


def test_cli_finds_the_only_socket_and_lists_several(sockdir, capsys, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", sockdir)
    os.mkdir(os.path.join(sockdir, "crtk-bridge"))
    daemon = FakeDaemon(os.path.join(sockdir, "crtk-bridge", "so101.sock"))
    try:
        assert main(["state", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["state"] == "DISABLED"
        assert main(["--robot", "so101", "state"]) == 0
        assert "DISABLED" in capsys.readouterr().out
        other = FakeDaemon(os.path.join(sockdir, "crtk-bridge", "koch.sock"))
        try:
            assert main(["state"]) == 2
            err_text = capsys.readouterr().err
            assert "koch.sock" in err_text and "so101.sock" in err_text
        finally:
            other.close()
    finally:
        daemon.close()


def test_cli_enable_exit_status_follows_the_state_reached(fake, capsys):
    fake.handlers["enable"] = lambda r, s: s.send(ok(r, fake.state))  # never enables
    assert main(["--socket", fake.path, "--timeout", "0.3", "enable"]) == 1
    err_text = capsys.readouterr().err
    assert err_text.startswith("crtk-ctl: enable: ENABLED not reached") and err_text.count("\n") == 1

    def enable(req, s):
        fake.state = state("ENABLED")
        s.send(os_event(fake.state))
        s.send(ok(req, fake.state))

    fake.handlers["enable"] = enable
    assert main(["enable", "--socket", fake.path]) == 0
    assert "ENABLED" in capsys.readouterr().out


def test_cli_get_json_and_human(fake, capsys):
    assert main(["--socket", fake.path, "--json", "get", "measured_js"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["position"] == [0.1, -0.2]
    assert main(["get", "measured_js", "--socket", fake.path]) == 0
    out = capsys.readouterr().out
    assert "shoulder_pan" in out and "+0.1000 rad" in out and "-0.2000 rad" in out


def test_cli_get_labels_each_joint_in_its_unit(fake, capsys):
    """A prismatic joint (``unit: m``, ``list``'s ``units``) prints in m, m/s and N, a revolute one
    in rad, rad/s and N·m; a daemon without ``units`` is read as all rad."""
    listed = fake.handlers["list"]

    class Capture:
        def send(self, msg):
            self.msg = msg

    def with_units(req, s):
        cap = Capture()
        listed(req, cap)
        info = cap.msg["data"]
        info["namespaces"][0]["units"] = ["rad", "rad"]
        info["namespaces"][1]["units"] = ["m"]
        s.send(cap.msg)

    fake.handlers["list"] = with_units
    fake.handlers["measured_js"] = lambda r, s: s.send(ok(r, {
        "stamp": 123.25, "frame_id": "", "name": ["gripper"], "position": [0.03], "velocity": [0.01],
        "effort": [20.0]}) if r.get("ns") == "so101/gripper" else ok(r, {
        "stamp": 123.25, "frame_id": "", "name": JOINTS, "position": [0.1, -0.2], "velocity": [0.0, 0.5],
        "effort": [1.5, 0.0]}))
    assert main(["list", "--socket", fake.path]) == 0
    out = capsys.readouterr().out
    assert "joints:   gripper (m)\n" in out and "joints:   shoulder_pan, elbow\n" in out, out
    fake.handlers["list"] = with_units
    assert main(["get", "measured_js", "--ns", "so101/gripper", "--socket", fake.path]) == 0
    out = capsys.readouterr().out
    assert "+0.0300 m " in out and "+0.0100 m/s" in out and "+20.0000 N" in out and "rad" not in out, out
    assert main(["get", "measured_js", "--socket", fake.path]) == 0
    out = capsys.readouterr().out
    assert "+0.1000 rad " in out and "+0.5000 rad/s" in out and "+1.5000 N·m" in out, out


def test_cli_move_wait_and_echo_count(fake, capsys):
    def move(req, s):
        s.send(os_event(state("ENABLED", busy=True, seq=1)))
        s.send(ok(req, {"busy_seq": 1}))
        threading.Timer(0.1, fake.push, args=(os_event(state("ENABLED", seq=1)),)).start()

    fake.handlers["move_jp"] = move
    assert main(["--socket", fake.path, "move_jp", "0.5", "-0.5", "--wait", "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["busy_seq"] == 1 and obj["done"] is True
    assert fake.requests[-1]["data"] == {"position": [0.5, -0.5]}

    assert main(["--socket", fake.path, "move_jp", "0.5"]) == 1  # wrong length, caught locally
    assert "bad_request" in capsys.readouterr().err

    def subscribe(req, s):
        s.send(ok(req, {"sub": 1}))
        for i in range(5):
            s.send({"topic": "measured_js", "ns": "so101", "sub": 1,
                    "data": {"stamp": 1.0 + i, "name": JOINTS, "position": [i, 0.0]}})

    fake.handlers["subscribe"] = subscribe
    fake.handlers["unsubscribe"] = lambda r, s: s.send(ok(r))
    assert main(["--socket", fake.path, "echo", "measured_js", "--count", "3", "--json"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [json.loads(x)["stamp"] for x in lines] == [1.0, 2.0, 3.0]


def test_cli_ctrl_c_exits_130_quietly(fake, capsys, monkeypatch):
    import crtk_bridge.client.cli as cli

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "connect", interrupted)
    assert main(["--socket", fake.path, "state"]) == 130
    assert capsys.readouterr().err == ""


def test_cli_usage_error_returns_2(capsys):
    assert main(["get", "no_such_topic"]) == 2
    assert "invalid choice" in capsys.readouterr().err


def test_stale_socket_file_is_reported_as_not_running(sockdir):
    path = os.path.join(sockdir, "stale.sock")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(path)  # a file left behind by a dead daemon: nobody listens
    s.close()
    with pytest.raises(ConnectionError) as info:
        Connection(path)
    assert path in str(info.value) and "refused" in str(info.value)


def test_request_from_a_callback_is_refused_instead_of_deadlocking(fake, robot):
    def subscribe(req, s):
        s.send(ok(req, {"sub": 5}))
        s.send({"topic": "measured_js", "ns": "so101", "sub": 5, "data": {"stamp": 1.0}})

    fake.handlers["subscribe"] = subscribe
    seen = []

    def cb(frame):
        try:
            robot.connection.request("list")
        except RuntimeError as exc:
            seen.append(exc)

    robot.device().subscribe("measured_js", 10, callback=cb)
    assert wait_until(lambda: seen)
    assert "callback" in str(seen[0])


# -- joint-space commands (issue 3) -------------------------------------------------------------

@pytest.mark.parametrize("method,cmd,field", [
    ("servo_jv", "servo_jv", "velocity"),
    ("servo_jr", "servo_jr", "position"),
    ("interpolate_jp", "interpolate_jp", "position"),
    ("interpolate_jr", "interpolate_jr", "position"),
    ("interpolate_jv", "interpolate_jv", "velocity"),
])
def test_stream_commands_send_their_payload_field(fake, robot, method, cmd, field):
    fake.handlers[cmd] = lambda r, s: s.send(ok(r))
    assert getattr(robot.device(), method)(np.array([0.25, -0.5])) is None
    sent = fake.requests[-1]
    assert sent["cmd"] == cmd and sent["ns"] == "so101" and sent["data"] == {field: [0.25, -0.5]}


def test_hold_and_free_send_no_payload(fake, robot):
    fake.handlers["hold"] = lambda r, s: s.send(ok(r))
    fake.handlers["free"] = lambda r, s: s.send(ok(r))
    arm = robot.device()
    arm.hold()
    assert fake.requests[-1] == {"id": fake.requests[-1]["id"], "cmd": "hold", "ns": "so101"}
    arm.free()
    assert fake.requests[-1]["cmd"] == "free" and "data" not in fake.requests[-1]


def test_unlisted_commands_refused_locally_naming_command_and_namespace(fake, robot):
    arm = robot.device()
    n = len(fake.requests)
    for call in (lambda: arm.servo_jf([0.1, 0.2]), lambda: arm.interpolate_jf([0.1, 0.2]),
                 lambda: arm.gripper.free(), lambda: arm.gripper.servo_jv([0.1])):
        with pytest.raises(CommandError) as info:
            call()
        assert info.value.code == "unsupported"
        assert "so101" in info.value.message
    assert "servo_jf" in str(pytest.raises(CommandError, arm.servo_jf, [0.0, 0.0]).value)
    assert "so101/gripper: free" in str(pytest.raises(CommandError, arm.gripper.free).value)
    assert len(fake.requests) == n  # nothing was sent
    assert arm.supports("servo_jv") and not arm.supports("servo_jf")


def test_daemon_unsupported_reply_raises_too(fake, robot):
    fake.handlers["list"] = lambda r, s: s.send(ok(r, {  # an older daemon: no commands listed
        "robot": "so101", "protocol_version": PROTOCOL_VERSION, "namespaces": [{"name": "so101", "joints": JOINTS}]}))
    fake.handlers["servo_jf"] = lambda r, s: s.send(err(r, "unsupported",
                                                        "so101: servo_jf is not supported by this robot"))
    r2 = connect(socket=fake.path, timeout=3.0)
    try:
        with pytest.raises(CommandError) as info:
            r2.device().servo_jf([0.0, 0.0])
        assert info.value.code == "unsupported" and fake.requests[-1]["cmd"] == "servo_jf"
    finally:
        r2.close()


def test_goal_queries_split_the_joint_state(fake, robot):
    fake.handlers["goal_js"] = lambda r, s: s.send(ok(r, {
        "stamp": 7.5, "name": JOINTS, "position": [], "velocity": [0.5, -0.5], "effort": []}))
    arm = robot.device()
    v, ts = arm.goal_jv()
    np.testing.assert_allclose(v, [0.5, -0.5])
    assert ts == 7.5
    p, ts = arm.goal_jp()
    assert p.shape == (0,) and ts == 7.5
    f, _ = arm.goal_jf()
    assert f.shape == (0,)


def warning(code, ns="so101", **extra):
    return {"event": "warning", "data": {"stamp": 2.0, "ns": ns, "code": code, "message": code, **extra}}


def test_wait_for_event_sees_only_new_matching_events(fake, robot):
    fake.push(warning("limit_clipped"))
    assert wait_until(lambda: robot.connection.event_count == 1)
    arm = robot.device()
    t0 = time.monotonic()
    assert arm.wait_for_event("limit_clipped", timeout=0.2) is None  # an old event does not count
    assert time.monotonic() - t0 >= 0.15
    mark = robot.connection.event_count
    assert robot.wait_for_event("limit_clipped", 0.1, since=0).data["code"] == "limit_clipped"

    threading.Timer(0.05, fake.push, args=(warning("servo_timeout", ns="so101/gripper"),)).start()
    threading.Timer(0.1, fake.push, args=({"event": "error", "data": {
        "stamp": 3.0, "ns": "so101", "code": "bus_timeout", "message": "no reply",
        "joint": "elbow"}},)).start()
    ev = arm.wait_for_event(kind="error", timeout=3.0)
    assert ev.kind == "error" and ev.data["joint"] == "elbow"
    # the gripper's warning is not about "so101", but it is there for the robot and the gripper
    assert arm.wait_for_event("servo_timeout", 0.05, since=mark) is None
    assert arm.gripper.wait_for_event("servo_timeout", 0.5, since=mark) is not None
    assert [e.data["code"] for e in robot.connection.events_since(mark)] == ["servo_timeout", "bus_timeout"]


def test_cli_new_stream_commands_hold_free(fake, capsys):
    for cmd in ("servo_jv", "interpolate_jp", "interpolate_jv", "hold", "free"):
        fake.handlers[cmd] = lambda r, s: s.send(ok(r))
    n = len(fake.requests)
    # a one-shot velocity command would stop as crtk-ctl disconnects: refused locally, nothing sent
    assert main(["--socket", fake.path, "servo_jv", "0.1", "-0.1"]) == 2
    assert "servo_jv needs --duration" in capsys.readouterr().err
    assert not [r for r in fake.requests[n:] if r["cmd"] == "servo_jv"]
    assert main(["--socket", fake.path, "servo_jv", "0.1", "-0.1", "--duration", "0.02"]) == 0
    # the first sample at once, then at the end, a stop (not the servo timeout, nor the disconnect)
    assert [(r["cmd"], r.get("data")) for r in fake.requests[-2:]] == [
        ("servo_jv", {"velocity": [0.1, -0.1]}), ("hold", None)]
    assert "servo_jv sent: 1 samples" in capsys.readouterr().out
    assert main(["--socket", fake.path, "interpolate_jp", "0.5", "0.25", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"cmd": "interpolate_jp", "ns": "so101", "ok": True}
    assert fake.requests[-1]["data"] == {"position": [0.5, 0.25]}
    n = len(fake.requests)
    t0 = time.monotonic()
    assert main(["--socket", fake.path, "interpolate_jv", "0", "0", "--duration", "0.2", "--rate", "50"]) == 0
    assert time.monotonic() - t0 >= 0.18
    # ticks at 0, 20, ..., 200 ms (one late reply on a loaded host skips a tick): the last is the hold
    sent = [r["cmd"] for r in fake.requests[n:] if r["cmd"] != "list"]
    assert 5 <= len(sent) <= 11 and sent == ["interpolate_jv"] * (len(sent) - 1) + ["hold"]
    assert main(["--socket", fake.path, "hold"]) == 0
    assert fake.requests[-1]["cmd"] == "hold"
    assert main(["--socket", fake.path, "free"]) == 0
    assert fake.requests[-1]["cmd"] == "free"
    capsys.readouterr()
    assert main(["--socket", fake.path, "servo_jf", "0.1", "0.1", "--duration", "0.1"]) == 1
    assert "servo_jf refused (unsupported)" in capsys.readouterr().err
    assert main(["--socket", fake.path, "servo_jv", "0.1"]) == 1  # wrong length, caught locally
    assert "bad_request" in capsys.readouterr().err


def test_cli_events_prints_until_count(fake, capsys):
    def push_events(s):
        s.send(os_event(state("ENABLED")))  # not printed: operating_state is not an event here
        s.send({"event": "status", "data": {"stamp": 1.0, "ns": "so101", "code": "state_changed",
                                            "message": "so101: ENABLED"}})
        s.send({"event": "error", "data": {"stamp": 2.0, "ns": "so101", "code": "servo_error",
                                           "message": "servo 3 reports overload",
                                           "joint": "elbow", "register": "Status", "value": 32}})
        s.send(warning("servo_timeout"))

    # the events arrive while crtk-ctl is still connecting (before the reply to its `list`):
    # they must be printed, not lost before the listener is set up
    answer_list = fake.handlers["list"]

    def list_after_events(r, s):
        push_events(s)
        answer_list(r, s)

    fake.handlers["list"] = list_after_events
    rc = []
    runner = threading.Thread(target=lambda: rc.append(main(["--socket", fake.path, "events", "--count", "2"])),
                              daemon=True)
    runner.start()
    runner.join(5.0)  # a deadline, not a pause: it returns as soon as the two events are printed
    assert rc == [0], "crtk-ctl events lost the events that arrived while it connected"
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    assert "status" in lines[0] and "state_changed" in lines[0]
    assert "servo_error" in lines[1] and "joint=elbow" in lines[1] and "register=Status" in lines[1] \
        and "value=32" in lines[1]

    # and events that arrive after it listens: pushed once its session has asked for `list`
    fake.handlers["list"] = answer_list
    n = len(fake.sessions)
    listed = threading.Event()

    def push_when_listed():
        wait_until(lambda: len(fake.sessions) > n and any(r["cmd"] == "list" for r in fake.requests),
                   5.0, what="crtk-ctl connected")
        push_events(fake.sessions[-1])
        listed.set()

    fake.requests.clear()
    threading.Thread(target=push_when_listed, daemon=True).start()
    assert main(["--socket", fake.path, "events", "--kind", "warning", "--count", "1", "--json"]) == 0
    assert listed.is_set()
    obj = json.loads(capsys.readouterr().out)
    assert obj["event"] == "warning" and obj["data"]["code"] == "servo_timeout"


# -- cartesian space (issue 4) ------------------------------------------------------------------


CART_COMMANDS = ARM_COMMANDS + ["servo_cp", "interpolate_cp", "move_cp", "servo_cr", "interpolate_cr",
                                "move_cr", "servo_cv", "interpolate_cv"]  # no servo_cf: no effort control
CART_QUERIES = ["measured_js", "measured_cp", "measured_cv", "setpoint_cp", "setpoint_cv", "goal_cp",
                "goal_cv", "forward_kinematics", "inverse_kinematics"]  # no measured_cf / setpoint_cf
#: a quarter turn about y: the tip's z axis along the base's x
QUAT_Y90 = [0.0, math.sqrt(0.5), 0.0, math.sqrt(0.5)]


def cart_list(fake):
    return lambda r, s: s.send(ok(r, {
        "robot": "so101", "protocol_version": PROTOCOL_VERSION, "daemon_version": "0.1.0",
        "namespaces": [
            {"name": "so101", "joints": JOINTS, "commands": CART_COMMANDS, "queries": CART_QUERIES,
             "topics": CART_QUERIES[:-2],
             "cartesian": {"base_frame": "base_link", "tip_frame": "tip", "frames": ["spatial", "body"]}},
            {"name": "so101/gripper", "joints": ["gripper"], "commands": ["move_jp"],
             "queries": ["measured_js"], "topics": ["measured_js"]}]}))


@pytest.fixture
def cart(fake):
    fake.handlers["list"] = cart_list(fake)
    r = connect(socket=fake.path, timeout=3.0)
    yield r.device("so101")
    r.close()


def wire_pose(stamp, position, orientation):
    return {"stamp": stamp, "frame_id": "base_link", "child_frame_id": "tip",
            "position": position, "orientation": orientation}


def test_quaternion_helpers_round_trip_every_branch():
    rng = np.random.default_rng(4)
    quats = [QUAT_Y90, [1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    quats += [list(q / np.linalg.norm(q)) for q in rng.normal(size=(50, 4))]
    for q in quats:
        R = matrix_from_quaternion(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
        back = quaternion_from_matrix(R)
        assert back[3] >= 0 and np.allclose(back, np.sign(q[3] or 1.0) * np.array(q), atol=1e-9)
    T = pose_matrix([0.1, 0.2, 0.3], QUAT_Y90)
    assert np.allclose(T[:3, 2], [1.0, 0.0, 0.0]) and np.allclose(T[3], [0, 0, 0, 1])
    p, q = pose_pq(T)
    assert np.allclose(p, [0.1, 0.2, 0.3]) and np.allclose(q, QUAT_Y90)


def test_cartesian_pose_queries_give_a_matrix_and_pq(fake, cart):
    fake.handlers["measured_cp"] = lambda r, s: s.send(ok(r, wire_pose(12.5, [0.3, -0.1, 0.2], QUAT_Y90)))
    fake.handlers["setpoint_cp"] = lambda r, s: s.send(ok(r, wire_pose(0.0, [], [])))
    T, ts = cart.measured_cp()
    assert ts == 12.5 and T.shape == (4, 4) and T.dtype == np.float64
    assert np.allclose(T[:3, 3], [0.3, -0.1, 0.2]) and np.allclose(T[:3, 2], [1, 0, 0])
    assert fake.requests[-1] == {"id": fake.requests[-1]["id"], "cmd": "measured_cp", "ns": "so101"}
    p, q, ts2 = cart.measured_cp_pq()
    assert ts2 == 12.5 and np.allclose(p, [0.3, -0.1, 0.2]) and np.allclose(q, QUAT_Y90)
    assert np.allclose(pose_matrix(p, q), T)
    # invalid data: natural shape, all NaN, ts 0 (never a silent identity)
    T0, ts0 = cart.setpoint_cp()
    assert ts0 == 0.0 and T0.shape == (4, 4) and np.all(np.isnan(T0))
    p0, q0, _ = cart.setpoint_cp_pq()
    assert p0.shape == (3,) and q0.shape == (4,) and np.all(np.isnan(p0)) and np.all(np.isnan(q0))


def test_twist_and_wrench_queries_pick_the_frame_namespace(fake, cart):
    fake.handlers["measured_cv"] = lambda r, s: s.send(ok(r, {
        "stamp": 3.0, "frame_id": "tip" if r["ns"].endswith("/body") else "base_link",
        "linear": [0.1, 0.2, 0.3], "angular": [0.4, 0.5, 0.6]}))
    v, ts = cart.measured_cv()
    assert ts == 3.0 and np.allclose(v, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    assert fake.requests[-1]["ns"] == "so101"
    cart.measured_cv(frame="body")
    assert fake.requests[-1]["ns"] == "so101/body" and fake.requests[-1]["cmd"] == "measured_cv"
    fake.handlers["goal_cv"] = lambda r, s: s.send(ok(r, {"stamp": 0.0, "linear": [], "angular": []}))
    g, ts = cart.goal_cv("body")
    assert ts == 0.0 and g.shape == (6,) and np.all(np.isnan(g)) and fake.requests[-1]["ns"] == "so101/body"
    n = len(fake.requests)
    with pytest.raises(CommandError) as info:
        cart.measured_cv(frame="tool")
    assert info.value.code == "bad_request" and "spatial, body" in info.value.message
    for call in (cart.measured_cf, cart.setpoint_cf, lambda: cart.servo_cf([0] * 6),
                 lambda: cart.interpolate_cf([0] * 6, frame="body"), cart.gripper.measured_cp,
                 lambda: cart.gripper.move_cp(np.eye(4)), lambda: cart.gripper.forward_kinematics([0.0])):
        with pytest.raises(CommandError) as info:
            call()
        assert info.value.code == "unsupported" and "so101" in info.value.message
    assert "measured_cf" in str(pytest.raises(CommandError, cart.measured_cf).value)
    assert len(fake.requests) == n  # all refused locally


@pytest.mark.parametrize("method", ["servo_cp", "interpolate_cp", "servo_cr", "interpolate_cr"])
def test_pose_commands_accept_a_matrix_or_a_pair(fake, cart, method):
    fake.handlers[method] = lambda r, s: s.send(ok(r))
    T = pose_matrix([0.25, 0.0, 0.125], QUAT_Y90)
    assert getattr(cart, method)(T) is None
    sent = fake.requests[-1]
    assert sent["cmd"] == method and sent["ns"] == "so101"
    assert sent["data"]["position"] == [0.25, 0.0, 0.125]
    assert np.allclose(sent["data"]["orientation"], QUAT_Y90, atol=1e-12)
    getattr(cart, method)(T.tolist())  # nested lists work too
    assert np.allclose(fake.requests[-1]["data"]["orientation"], QUAT_Y90)
    getattr(cart, method)((np.array([0.1, 0.2, 0.3]), [0.0, 0.0, 0.0, 2.0 / 1.5]))  # normalised
    assert fake.requests[-1]["data"] == {"position": [0.1, 0.2, 0.3], "orientation": [0.0, 0.0, 0.0, 1.0]}


def test_malformed_poses_and_twists_refused_locally(fake, cart):
    n = len(fake.requests)
    bad_rotation = np.eye(4)
    bad_rotation[0, 0] = 2.0
    nan_pose = np.eye(4)
    nan_pose[0, 3] = float("nan")
    for call in (lambda: cart.servo_cp(bad_rotation), lambda: cart.servo_cp(nan_pose),
                 lambda: cart.servo_cp(np.eye(3)), lambda: cart.move_cp(([0, 0], [0, 0, 0, 1])),
                 lambda: cart.move_cr(([0, 0, 0], [0, 0, 0, 0])),  # zero quaternion
                 lambda: cart.servo_cp(([0, 0, 0], [0, 0, 0, 3.0])),  # not unit: a mistake
                 lambda: cart.servo_cv([0.1, 0, 0]), lambda: cart.servo_cv([0, 0, 0, 0, 0, float("inf")]),
                 lambda: cart.inverse_kinematics(np.zeros((4, 4)))):
        with pytest.raises(CommandError) as info:
            call()
        assert info.value.code == "bad_request"
    assert len(fake.requests) == n


def test_move_cp_and_move_cr_return_handles(fake, cart):
    fake.set_state(state="ENABLED", busy_seq=2)
    assert wait_until(lambda: cart.operating_state() == "ENABLED")

    def move(req, s):
        seq = fake.state["busy_seq"] + 1
        s.send(os_event(state("ENABLED", busy=True, seq=seq)))
        s.send(ok(req, {"busy_seq": seq}))
        fake.state = state("ENABLED", seq=seq)
        threading.Timer(0.1, fake.push, args=(os_event(fake.state),)).start()

    fake.handlers["move_cp"] = move
    fake.handlers["move_cr"] = move
    h = cart.move_cp(([0.3, 0.0, 0.2], QUAT_Y90))
    assert h.busy_seq == 3 and h.cmd == "move_cp"
    assert fake.requests[-1]["data"] == {"position": [0.3, 0.0, 0.2], "orientation": QUAT_Y90}
    assert h.wait(timeout=3.0) and not h.is_busy()
    h2 = cart.move_cr(pose_matrix([0.0, 0.0, 0.01], [0, 0, 0, 1]))
    assert h2.busy_seq == 4 and h2.wait(timeout=3.0)
    assert fake.requests[-1]["data"] == {"position": [0.0, 0.0, 0.01], "orientation": [0.0, 0.0, 0.0, 1.0]}
    fake.handlers["move_cp"] = lambda r, s: s.send(err(r, "ik_failed", "so101: move_cp refused: IK did not converge"))
    with pytest.raises(CommandError) as info:
        cart.move_cp(np.eye(4))
    assert info.value.code == "ik_failed"


def test_twist_commands_frame_and_payload(fake, cart):
    fake.handlers["servo_cv"] = lambda r, s: s.send(ok(r))
    fake.handlers["interpolate_cv"] = lambda r, s: s.send(ok(r))
    cart.servo_cv(np.array([0.01, 0.02, 0.03, 0.1, 0.2, 0.3]))
    assert fake.requests[-1]["ns"] == "so101"
    assert fake.requests[-1]["data"] == {"linear": [0.01, 0.02, 0.03], "angular": [0.1, 0.2, 0.3]}
    cart.servo_cv([0, 0, 0.05, 0, 0, 0], frame="body")
    assert fake.requests[-1]["ns"] == "so101/body" and fake.requests[-1]["cmd"] == "servo_cv"
    cart.interpolate_cv([0, 0, 0.05, 0, 0, 0], "body")
    assert fake.requests[-1]["ns"] == "so101/body" and fake.requests[-1]["cmd"] == "interpolate_cv"


def test_forward_and_inverse_kinematics(fake, cart):
    fake.handlers["forward_kinematics"] = lambda r, s: s.send(ok(r, wire_pose(9.0, [0.3, 0.0, 0.2], QUAT_Y90)))
    T = cart.forward_kinematics(np.array([0.5, -0.5]))
    assert fake.requests[-1]["data"] == {"jp": [0.5, -0.5]}
    assert T.shape == (4, 4) and np.allclose(T[:3, 3], [0.3, 0.0, 0.2]) and np.allclose(T[:3, 2], [1, 0, 0])

    def ik(req, s):
        reach = req["data"]["position"][0] < 1.0
        s.send(ok(req, {"jp": [0.5, -0.5], "result": reach,
                        "message": "" if reach else "IK did not converge: position residual 0.6 m",
                        "residual_position": 0.0 if reach else 0.6, "residual_orientation": 0.0}))

    fake.handlers["inverse_kinematics"] = ik
    jp, ok_, msg = cart.inverse_kinematics(T, jp_seed=[0.1, 0.2])
    assert ok_ is True and isinstance(jp, np.ndarray) and np.allclose(jp, [0.5, -0.5])
    sent = fake.requests[-1]["data"]
    assert sent["jp"] == [0.1, 0.2] and sent["position"] == [0.3, 0.0, 0.2]
    assert np.allclose(sent["orientation"], QUAT_Y90)
    jp, ok_, msg = cart.inverse_kinematics(([1.5, 0.0, 0.0], [0, 0, 0, 1]))
    assert ok_ is False and "residual" in msg and "jp" not in fake.requests[-1]["data"]  # seed: the daemon's default

    fake.handlers["forward_kinematics"] = lambda r, s: s.send(err(
        r, "bad_request", "so101: forward_kinematics needs 'jp' with 2 numbers"))
    with pytest.raises(CommandError) as info:
        cart.forward_kinematics([0.0])
    assert info.value.code == "bad_request"


def test_cartesian_subscription_uses_the_frame_namespace(fake, cart):
    def subscribe(req, s):
        s.send(ok(req, {"sub": 9}))
        s.send({"topic": req["data"]["topic"], "ns": req.get("ns"), "sub": 9,
                "data": {"stamp": 2.0, "linear": [0, 0, 1], "angular": [0, 0, 0]}})

    fake.handlers["subscribe"] = subscribe
    fake.handlers["unsubscribe"] = lambda r, s: s.send(ok(r))
    with cart.subscribe("measured_cv", 20, frame="body") as sub:
        assert sub.get(timeout=2.0)["linear"] == [0, 0, 1]
    sent = [r for r in fake.requests if r["cmd"] == "subscribe"][-1]
    assert sent["ns"] == "so101/body" and sent["data"]["topic"] == "measured_cv"
    with pytest.raises(CommandError) as info:
        cart.subscribe("measured_cf", 20)
    assert info.value.code == "unsupported"


def test_cli_cartesian_get_human_and_json(fake, cart, capsys):
    fake.handlers["measured_cp"] = lambda r, s: s.send(ok(r, wire_pose(12.5, [0.3, -0.1, 0.2], QUAT_Y90)))
    fake.handlers["measured_cv"] = lambda r, s: s.send(ok(r, {
        "stamp": 3.0, "frame_id": "tip", "child_frame_id": "tip", "linear": [0.1, 0, 0], "angular": [0, 0, -0.25]}))
    assert main(["--socket", fake.path, "get", "measured_cp"]) == 0
    out = capsys.readouterr().out
    assert "+0.3000 -0.1000 +0.2000 m" in out and "+0.0000 +0.7071 +0.0000 +0.7071" in out
    assert "tip in base_link" in out and "stamp 12.500" in out
    assert main(["--socket", fake.path, "--json", "get", "measured_cp"]) == 0
    assert json.loads(capsys.readouterr().out)["orientation"] == QUAT_Y90
    assert main(["--socket", fake.path, "get", "measured_cv", "--frame", "body"]) == 0
    out = capsys.readouterr().out
    assert fake.requests[-1]["ns"] == "so101/body"
    assert "(body)" in out and "+0.1000 +0.0000 +0.0000 m/s" in out and "-0.2500 rad/s" in out
    assert main(["--socket", fake.path, "get", "measured_cf"]) == 1
    assert "get refused (unsupported)" in capsys.readouterr().err


def test_cli_cartesian_commands(fake, cart, capsys):
    fake.set_state(state="ENABLED")

    def move(req, s):
        s.send(os_event(state("ENABLED", busy=True, seq=1)))
        s.send(ok(req, {"busy_seq": 1}))
        threading.Timer(0.1, fake.push, args=(os_event(state("ENABLED", seq=1)),)).start()

    for cmd in ("move_cp", "move_cr"):
        fake.handlers[cmd] = move
    for cmd in ("servo_cp", "servo_cv", "servo_cr", "hold"):
        fake.handlers[cmd] = lambda r, s: s.send(ok(r))
    s = ["--socket", fake.path]
    assert main(s + ["move_cp", "0.3", "0", "0.2", "0", "0.7071", "0", "0.7071", "--wait", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["done"] is True
    sent = fake.requests[-1]["data"]
    assert sent["position"] == [0.3, 0.0, 0.2] and np.allclose(sent["orientation"], QUAT_Y90, atol=1e-4)
    assert main(s + ["move_cr", "0", "0", "-0.01"]) == 0  # no quaternion: no rotation
    assert fake.requests[-1]["data"] == {"position": [0.0, 0.0, -0.01], "orientation": [0.0, 0.0, 0.0, 1.0]}
    assert "move_cr accepted" in capsys.readouterr().out
    assert main(s + ["move_cr", "0", "-2.5e-03", "-1E-2"]) == 0  # exponents, as --json prints them
    assert fake.requests[-1]["data"]["position"] == [0.0, -0.0025, -0.01]
    capsys.readouterr()
    assert main(s + ["servo_cp", "0.3", "0", "0.2", "0", "0", "0", "1"]) == 0
    assert fake.requests[-1]["cmd"] == "servo_cp" and "servo_cp sent" in capsys.readouterr().out
    assert main(s + ["servo_cv", "0", "0", "0.02", "0", "0", "0", "--frame", "body"]) == 2  # one-shot
    assert "servo_cv needs --duration" in capsys.readouterr().err
    assert main(s + ["servo_cv", "0", "0", "0.02", "0", "0", "0", "--frame", "body", "--json",
                     "--duration", "0.02"]) == 0
    assert json.loads(capsys.readouterr().out) == {"cmd": "servo_cv", "ns": "so101", "ok": True, "frame": "body",
                                                   "samples": 1, "rate_hz": 50.0, "held": True}
    assert fake.requests[-2]["ns"] == "so101/body"
    assert fake.requests[-2]["data"] == {"linear": [0.0, 0.0, 0.02], "angular": [0.0, 0.0, 0.0]}
    assert (fake.requests[-1]["cmd"], fake.requests[-1]["ns"]) == ("hold", "so101")  # the stream's end
    assert main(s + ["servo_cv", "0", "0", "0.02"]) == 1  # 3 values: refused locally
    assert "bad_request" in capsys.readouterr().err
    assert main(s + ["move_cr", "0", "0", "0", "1"]) == 1
    assert "bad_request" in capsys.readouterr().err
    assert main(s + ["move_cp", "0.3", "0", "0.2"]) == 1  # 7 numbers needed
    assert "move_cp needs X Y Z QX QY QZ QW" in capsys.readouterr().err
    assert main(s + ["servo_cf", "0", "0", "0", "0", "0", "0", "--duration", "0.1"]) == 1
    assert "servo_cf refused (unsupported)" in capsys.readouterr().err


def test_cli_fk_and_ik(fake, cart, capsys):
    fake.handlers["forward_kinematics"] = lambda r, s: s.send(ok(r, wire_pose(9.0, [0.3, 0.0, 0.2], QUAT_Y90)))

    def ik(req, s):
        reach = req["data"]["position"][0] < 1.0
        s.send(ok(req, {"jp": [0.5, -0.25], "result": reach,
                        "message": "" if reach else "IK did not converge: position residual 0.6 m",
                        "residual_position": 0.0 if reach else 0.6, "residual_orientation": 0.0}))

    fake.handlers["inverse_kinematics"] = ik
    s = ["--socket", fake.path]
    assert main(s + ["fk", "0.5", "-0.25"]) == 0
    out = capsys.readouterr().out
    assert "forward_kinematics" in out and "+0.3000 +0.0000 +0.2000 m" in out
    assert fake.requests[-1]["data"] == {"jp": [0.5, -0.25]}
    assert main(s + ["fk", "0.5"]) == 1  # wrong length, caught locally
    assert "bad_request" in capsys.readouterr().err
    assert main(s + ["ik", "0.3", "0", "0.2", "0", "0", "0", "1", "--seed", "0.1", "0.2"]) == 0
    out = capsys.readouterr().out
    assert "shoulder_pan" in out and "+0.5000 rad" in out and "-0.2500 rad" in out
    assert fake.requests[-1]["data"]["jp"] == [0.1, 0.2]
    assert main(s + ["--json", "ik", "1.5", "0", "0.2", "0", "0", "0", "1"]) == 1
    captured = capsys.readouterr()
    assert json.loads(captured.out)["result"] is False
    assert captured.err.count("\n") == 1  # --json: the error is one JSON object too
    err = json.loads(captured.err)
    assert err["error"] == "ik_failed" and err["cmd"] == "ik" and "residual" in err["message"]


def test_success_reply_without_id_is_ignored_not_recorded_as_an_error(fake, robot):
    # the daemon fans out its control process's reply to an internal notice (id null, ok true)
    fake.push({"id": None, "ok": True, "data": None})
    fake.push({"id": None, "ok": False, "error": {"code": "bad_request", "message": "invalid JSON"}})
    assert wait_until(lambda: robot.connection.event_count == 1)
    assert [(e.kind, e.data["code"]) for e in robot.connection.events] == [("error", "bad_request")]
    assert robot.connection.request("list")["robot"] == "so101"


# -- timed streams, interrupts and words (issue 18) ---------------------------------------------


def list_with(fake, rate_hz=None, gripper_commands=("move_jp",)):
    """The fake's ``list`` with the daemon's loop rate and the gripper's commands."""
    def handler(r, s):
        data = {"robot": fake.robot, "protocol_version": PROTOCOL_VERSION, "daemon_version": "0.1.0",
                "namespaces": [
                    {"name": "so101", "joints": JOINTS, "commands": ARM_COMMANDS,
                     "queries": ["measured_js"], "topics": ["measured_js"]},
                    {"name": "so101/gripper", "joints": ["gripper"], "commands": list(gripper_commands),
                     "queries": ["measured_js"], "topics": ["measured_js"]}]}
        if rate_hz is not None:
            data["rate_hz"] = rate_hz
        s.send(ok(r, data))
    return handler


def test_stream_helper_ends_on_time_and_totals_a_relative_offset_with_slow_replies(fake):
    def slow(r, s):  # a reply per control cycle, as the daemon answers
        time.sleep(0.005)
        s.send(ok(r))

    fake.handlers["servo_jr"] = slow
    fake.handlers["hold"] = lambda r, s: s.send(ok(r))
    with connect(socket=fake.path, timeout=3.0) as robot:
        n = len(fake.requests)
        t0 = time.monotonic()
        report = robot.device("so101").stream("servo_jr", [0.05, -0.03], duration=0.3, rate_hz=1000)
        elapsed = time.monotonic() - t0
    sent = [r for r in fake.requests[n:] if r["cmd"] == "servo_jr"]
    assert report.samples == len(sent) and not report.held
    assert 2 <= len(sent) <= 62  # ticks missed while a reply came are skipped (the defect: 301 sent)
    total = np.sum([r["data"]["position"] for r in sent], axis=0)
    np.testing.assert_allclose(total, [0.05, -0.03], rtol=0, atol=1e-12)
    assert 0.3 <= elapsed <= 0.3 + 3.0  # generous: a loaded host


def test_cli_caps_the_rate_at_the_loop_rate_saying_so_once(fake, capsys):
    fake.handlers["list"] = list_with(fake, rate_hz=200.0)
    fake.handlers["servo_jp"] = lambda r, s: s.send(ok(r))
    n = len(fake.requests)
    assert main(["--socket", fake.path, "servo_jp", "0.1", "0.2", "--duration", "0.1", "--rate", "5000"]) == 0
    out, err = capsys.readouterr()
    assert err.splitlines() == ["crtk-ctl: --rate 5000 Hz is above so101's loop rate (200 Hz): streaming at 200 Hz"]
    assert "at up to 200 Hz" in out
    assert 2 <= len([r for r in fake.requests[n:] if r["cmd"] == "servo_jp"]) <= 21
    # under --json: one JSON object on stderr, the result on stdout
    assert main(["--socket", fake.path, "--json", "servo_jp", "0.1", "0.2", "--duration", "0.02", "--rate",
                 "1000"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(err)["warning"] == "rate_capped" and json.loads(out)["rate_hz"] == 200.0
    # at or below the loop rate: nothing said
    assert main(["--socket", fake.path, "servo_jp", "0.1", "0.2", "--duration", "0.02", "--rate", "200"]) == 0
    assert capsys.readouterr().err == ""


def test_stream_helper_caps_the_rate_with_a_warning(fake):
    fake.handlers["list"] = list_with(fake, rate_hz=100.0)
    fake.handlers["servo_jp"] = lambda r, s: s.send(ok(r))
    with connect(socket=fake.path, timeout=3.0) as robot:
        with pytest.warns(RuntimeWarning, match="above so101's loop rate: sending at 100 Hz"):
            report = robot.device("so101").stream("servo_jp", [0.1, 0.2], duration=0.05, rate_hz=500)
    assert report.rate_hz == 100.0
    with connect(socket=fake.path, timeout=3.0) as robot:
        dev = robot.device("so101")
        for bad in (0, -1.0, float("nan"), float("inf")):
            with pytest.raises(CommandError, match="duration must be a finite number > 0"):
                dev.stream("servo_jp", [0.1, 0.2], duration=bad)
        with pytest.raises(CommandError, match="not a stream command"):
            dev.stream("move_jp", [0.1, 0.2], duration=1.0)


def test_ctrl_c_during_a_stream_holds_and_says_so(fake, capsys, monkeypatch):
    from crtk_bridge.client.device import Device

    fake.handlers["servo_jv"] = lambda r, s: s.send(ok(r))
    fake.handlers["hold"] = lambda r, s: s.send(ok(r))
    calls = [0]
    real = Device.servo_jv

    def interrupted_third(self, v):
        calls[0] += 1
        if calls[0] == 3:
            raise KeyboardInterrupt
        real(self, v)

    monkeypatch.setattr(Device, "servo_jv", interrupted_third)
    assert main(["--socket", fake.path, "servo_jv", "0.1", "0", "--duration", "5"]) == 130
    assert capsys.readouterr().err == "crtk-ctl: interrupted: so101 servo_jv stream stopped with hold\n"
    cmds = [r["cmd"] for r in fake.requests if r["cmd"] != "list"]
    assert cmds[:2] == ["servo_jv", "servo_jv"] and set(cmds[2:]) == {"hold"}


def test_a_refused_sample_ends_the_stream_with_hold(fake, capsys):
    count = [0]

    def refuse_third(r, s):
        count[0] += 1
        s.send(ok(r) if count[0] < 3 else err(r, "step_too_large", "so101: servo_jr step too large"))

    fake.handlers["servo_jr"] = refuse_third
    fake.handlers["hold"] = lambda r, s: s.send(ok(r))
    assert main(["--socket", fake.path, "servo_jr", "0.1", "0", "--duration", "1"]) == 1
    assert "servo_jr refused (step_too_large)" in capsys.readouterr().err
    assert fake.requests[-1]["cmd"] == "hold"


def test_ctrl_c_during_home_holds_every_namespace_it_moves(fake, capsys, monkeypatch):
    from crtk_bridge.client.device import Device

    fake.handlers["list"] = list_with(fake, gripper_commands=("move_jp", "hold"))
    fake.handlers["hold"] = lambda r, s: s.send(ok(r))

    def interrupted(self, timeout):
        raise KeyboardInterrupt

    monkeypatch.setattr(Device, "home", interrupted)
    assert main(["--socket", fake.path, "home"]) == 130
    assert capsys.readouterr().err == "crtk-ctl: interrupted: so101 home stopped with hold (so101, so101/gripper)\n"
    assert [(r["cmd"], r.get("ns")) for r in fake.requests if r["cmd"] == "hold"] == [
        ("hold", "so101"), ("hold", "so101/gripper")]


def test_ctrl_c_without_a_motion_to_stop_stays_quiet(fake, capsys, monkeypatch):
    from crtk_bridge.client.device import Device

    def interrupted(self, timeout):
        raise KeyboardInterrupt

    monkeypatch.setattr(Device, "enable", interrupted)
    assert main(["--socket", fake.path, "enable"]) == 130
    assert capsys.readouterr().err == ""
    assert not [r for r in fake.requests if r["cmd"] == "hold"]


def test_ns_naming_a_frame_points_at_frame_option(fake, capsys):
    assert main(["--socket", fake.path, "--ns", "so101/body", "get", "measured_js"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "use --ns so101 --frame body" in err
    with connect(socket=fake.path, timeout=3.0) as robot:
        with pytest.raises(KeyError, match="use so101 with frame='body'"):
            robot.device("so101/body")


def test_robots_without_a_daemon_says_where_it_looked(sockdir, capsys, monkeypatch):
    import crtk_bridge.client.cli as cli
    import crtk_bridge.client.paths as paths

    monkeypatch.setenv("XDG_RUNTIME_DIR", sockdir)
    nowhere = os.path.join(sockdir, "run-crtk-bridge")
    monkeypatch.setattr(paths, "SYSTEM_SOCKET_DIR", nowhere)
    monkeypatch.setattr(cli, "SYSTEM_SOCKET_DIR", nowhere)
    assert main(["robots"]) == 2
    assert capsys.readouterr().err == (f"crtk-ctl: no crtk-bridge daemon running: no *.sock in {sockdir}/crtk-bridge "
                                       f"nor {nowhere} (start one: crtk-bridge --profile FILE [--sim])\n")
    os.makedirs(os.path.join(sockdir, "crtk-bridge"))
    open(os.path.join(sockdir, "crtk-bridge", "so101.sock"), "w").close()
    assert main(["robots"]) == 0 and capsys.readouterr().out == "so101\n"


def test_ctrl_c_while_a_waited_move_is_being_sent_still_holds(fake, capsys, monkeypatch):
    """Ctrl-C that lands while ``move_jp ... --wait`` waits for the move's reply (the daemon has
    the move: it runs) exited 130 silently, the arm going on to its goal: the window before the
    wait is as much the waited command's as the wait itself (issue 18 item 4; found in review)."""
    from crtk_bridge.client.device import Device

    fake.handlers["move_jp"] = lambda r, s: s.send(ok(r, {"busy_seq": 1}))
    fake.handlers["hold"] = lambda r, s: s.send(ok(r))
    real = Device._start_move

    def interrupted_as_the_reply_comes(self, cmd, data):
        real(self, cmd, data)  # the daemon accepted the move
        raise KeyboardInterrupt

    monkeypatch.setattr(Device, "_start_move", interrupted_as_the_reply_comes)
    assert main(["--socket", fake.path, "move_jp", "0.3", "0.4", "--wait"]) == 130
    assert capsys.readouterr().err == "crtk-ctl: interrupted: so101 move_jp stopped with hold\n"
    assert [r["cmd"] for r in fake.requests if r["cmd"] != "list"] == ["move_jp", "hold"]
    # without --wait the move runs to its end, as documented: nothing is stopped
    n = len(fake.requests)
    assert main(["--socket", fake.path, "move_jp", "0.3", "0.4"]) == 130
    assert not [r for r in fake.requests[n:] if r["cmd"] == "hold"]


def test_a_stream_of_more_samples_than_a_float_counts_is_refused_in_one_line(fake, capsys):
    """``--duration 1e307`` at 200 Hz: duration x rate overflows, and Pacing's round(inf) raised
    OverflowError, a traceback rather than the one-line refusal (found in review)."""
    fake.handlers["list"] = list_with(fake, rate_hz=200.0)
    n = len(fake.requests)
    assert main(["--socket", fake.path, "servo_jp", "0.1", "0.2", "--duration", "1e307", "--rate", "200"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad_request" in err and "1e+307 s at 200 Hz" in err, err
    assert not [r for r in fake.requests[n:] if r["cmd"] != "list"]  # nothing sent


def test_a_stream_refused_from_its_first_sample_stops_nothing_it_did_not_start(fake, capsys):
    """A stream whose first sample the daemon refuses started nothing; its 'hold on the way out'
    was still sent, and since any session may stop the robot, it stopped another session's move
    or teleop (the first sample refused ``read_only``), while crtk-ctl said only 'refused'
    (found in review). A sample accepted before the refusal still ends with hold."""
    fake.handlers["servo_jv"] = lambda r, s: s.send(err(r, "read_only", "so101: controlled by pid 4242 (teleop)"))
    fake.handlers["hold"] = lambda r, s: s.send(ok(r))
    assert main(["--socket", fake.path, "servo_jv", "0.1", "0", "--duration", "1"]) == 1
    assert "servo_jv refused (read_only)" in capsys.readouterr().err
    assert not [r for r in fake.requests if r["cmd"] == "hold"]
    count = [0]

    def refuse_second(r, s):
        count[0] += 1
        s.send(ok(r) if count[0] == 1 else err(r, "invalid_state", "so101: servo_jv refused: robot is PAUSED"))

    fake.handlers["servo_jv"] = refuse_second
    assert main(["--socket", fake.path, "servo_jv", "0.1", "0", "--duration", "1"]) == 1
    assert fake.requests[-1]["cmd"] == "hold"


@pytest.mark.parametrize("bad", [0, -1, -0.5, float("inf"), float("nan"), True, "5", None, [5]])
def test_a_timeout_that_is_not_a_finite_positive_number_is_refused_naming_it(bad):
    """connect / list_robots: a negative timeout hung a Zenoh connect for ever, inf and NaN
    escaped as OverflowError / ValueError from inside the socket or Zenoh set-up."""
    from crtk_bridge.client import list_robots
    from crtk_bridge.errors import CrtkBridgeError

    for where in (dict(socket="/nonexistent/crtk.sock"), dict(zenoh_connect="tcp/127.0.0.1:1")):
        with pytest.raises(CrtkBridgeError, match=r"^crtk-bridge client: timeout: must be a finite number of "
                                                  r"seconds > 0, got "):
            connect(timeout=bad, **where)
    with pytest.raises(CrtkBridgeError, match=r"^crtk-bridge client: timeout: "):
        list_robots(zenoh_connect="tcp/127.0.0.1:1", timeout=bad)
    with pytest.raises(CrtkBridgeError, match=r"^crtk-bridge client: timeout: "):
        list_robots(timeout=bad)

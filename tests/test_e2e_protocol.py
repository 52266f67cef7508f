"""Issue 9 defects 2-6 against a real daemon on the simulated SO-101: strictly typed payloads,
hostile framing, stops from any session, the client loss policy and relative streams in crtk-ctl.
"Nothing moved" is read from the simulator's control socket (the servos' Goal_Position)."""

from __future__ import annotations

import json
import os
import socket
import threading

import numpy as np
import pytest

from crtk_bridge.client import connect
from crtk_bridge.client.cli import main as ctl_main
from crtk_bridge.sim.control import control_request

from .conftest import wait_until
from .test_client_cartesian_e2e import daemon  # noqa: F401 - one so101 --sim daemon for the module

ARM = "so101"
Q_B = [0.0, -0.5, 0.5, 0.5, 0.0]  # arm in its x-z plane, away from singularities


class Raw:
    """A JSON-lines session; replies (messages with "ok") queue up in order, events are kept."""

    def __init__(self, path):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(str(path))
        self.replies: list[dict] = []
        self.cond = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.sock.makefile("rb"):
            msg = json.loads(line)
            if "ok" in msg:
                with self.cond:
                    self.replies.append(msg)
                    self.cond.notify_all()

    def send(self, raw: bytes) -> None:
        self.sock.sendall(raw)

    def reply(self, timeout=5.0) -> dict:
        with self.cond:
            assert self.cond.wait_for(lambda: self.replies, timeout), "no reply"
            return self.replies.pop(0)

    def call(self, cmd, ns=None, data=None, rid=1) -> dict:
        msg = {"id": rid, "cmd": cmd}
        if ns is not None:
            msg["ns"] = ns
        if data is not None:
            msg["data"] = data
        self.send(json.dumps(msg).encode() + b"\n")
        r = self.reply()
        assert r["id"] == rid
        return r

    def close(self):
        self.sock.close()


@pytest.fixture
def raw(daemon):  # noqa: F811
    s = Raw(daemon.socket_path)
    yield s
    s.call("disable")
    s.call("release")  # answered: control is free before the next test connects
    s.close()


def goals(daemon) -> np.ndarray:
    servos = control_request(daemon.sim_control_path(), {"cmd": "dump"})["servos"]
    return np.array([servos[k]["goal_position"] for k in sorted(servos, key=int)])


def code(r) -> str:
    return "ok" if r["ok"] else r["error"]["code"]


# ---------------------------------------------------------------- defect 2: typed payloads
ILL_TYPED = [
    ("move_jp", {"position": [True] * 5}, "data.position[0]"),
    ("move_jp", {"position": ["1.0"] * 5}, "data.position[0]"),
    ("move_jp", {"position": [0, 0, [1], 0, 0]}, "data.position[2]"),
    ("move_jp", {"position": [0, None, 0, 0, 0]}, "data.position[1]"),
    ("move_jp", {"position": [[0, 0, 0, 0, 0]]}, "data.position[0]"),
    ("move_jp", {"position": "0 0 0 0 0"}, "data.position"),
    ("move_jp", {"position": None}, "data.position"),
    ("move_jp", {"positon": [0.1] * 5}, "data"),
    ("move_jp", [1], "data"),
    ("move_jr", {"position": [True, False, False, False, False]}, "data.position[0]"),
    ("servo_jp", {"position": [0] * 5, "velocity": [True] * 5}, "data.velocity[0]"),
    ("servo_jp", {"position": [0] * 5, "velocity": None}, "data.velocity"),
    ("servo_jr", {"position": [True] * 5}, "data.position[0]"),
    ("interpolate_jp", {"position": ["0.1"] * 5}, "data.position[0]"),
    ("interpolate_jr", {"position": [0.1] * 4}, "data.position"),
    ("servo_jv", {"velocity": [True] * 5}, "data.velocity[0]"),
    ("interpolate_jv", {"velocity": [{"x": 1}] * 5}, "data.velocity[0]"),
    ("move_cp", {"position": [True, 0, 0.2], "orientation": [0, 0, 0, 1]}, "data.position[0]"),
    ("servo_cv", {"linear": [0, 0, "1"], "angular": [0, 0, 0]}, "data.linear[2]"),
    ("subscribe", {"topic": "measured_js", "rate_hz": True}, "data.rate_hz"),
    ("subscribe", {"topic": "measured_js", "rate_hz": "50"}, "data.rate_hz"),
    ("subscribe", {"topic": "measured_js", "rate_hz": None}, "data.rate_hz"),
    ("subscribe", {"topic": "measured_js", "rate_hz": 0}, "data.rate_hz"),
    ("unsubscribe", {"sub": True}, "data.sub"),
    ("enable", [1], "data"),
]


def test_ill_typed_payloads_are_refused_naming_the_field_and_move_nothing(daemon, raw):
    assert code(raw.call("enable")) == "ok"
    before = goals(daemon)
    for k, (cmd, data, field) in enumerate(ILL_TYPED, start=10):
        r = raw.call(cmd, ARM, data, rid=k)
        assert code(r) == "bad_request", (cmd, data, r)
        assert f"`{field}" in r["error"]["message"], (cmd, data, r)
    # a well-typed command still works on the same session, and nothing else moved the servos
    assert raw.call("operating_state", rid=99)["data"]["state"] == "ENABLED"
    assert np.abs(goals(daemon) - before).max() <= 1
    # integers are JSON numbers: accepted
    assert code(raw.call("servo_jr", ARM, {"position": [0, 0, 0, 0, 0]}, rid=100)) == "ok"


# ---------------------------------------------------------------- defect 3: hostile framing
def test_hostile_framing_gets_bad_request_and_the_session_lives(daemon, raw):
    assert code(raw.call("enable")) == "ok"
    before = goals(daemon)
    deep = b"[" * 1000 + b"0" + b"]" * 1000
    lines = [  # (line, the reply's id: the request's whenever an integer id can be read)
        (b'{"id":5,"cmd":"move_jp","ns":"so101","data":{"position":' + deep + b"}}\n", 5),  # 1000 levels, 2 KB
        (b'{"id":' + deep + b',"cmd":"list"}\n', None),  # where the id would be read from
        (deep + b"\n", None),
        (b'{"id":"7","cmd":"list"}\n', None),  # an id of another type is not echoed
        (b'{"id":7.5,"cmd":"list"}\n', None),
        (b'{"id":[7],"cmd":"list"}\n', None),
        (b'{"id":true,"cmd":"list"}\n', None),
        (b'{"id":8,"cmd":5}\n', 8),
        (b'{"id":8,"ns":"so101"}\n', 8),
        (b'{"id":8,"cmd":"list","ns":["so101"]}\n', 8),
        (b'{"id":8,"cmd":"list"\n', None),  # not JSON
        (b'\xff\xfe{"id":8,"cmd":"list"}\n', None),  # invalid UTF-8, and so not JSON
        (b'{"id":8,"cmd":"\xc3\x28"}\n', 8),
        (b"[1,2,3]\n", None),
        (b"null\n", None),
    ]
    for line, rid in lines:
        raw.send(line)
        r = raw.reply()
        assert code(r) == "bad_request" and r["id"] == rid, (line[:60], r)
        assert raw.call("operating_state", rid=1)["ok"]  # the session lives
    # a valid envelope with a malformed payload: bad_request (never internal), with its id
    for rid, data in ((11, [1]), (12, {"position": [[0.1] * 5]}), (13, 5), (14, "x")):
        r = raw.call("move_jp", ARM, data, rid=rid)
        assert code(r) == "bad_request" and r["id"] == rid, r
    # a line over the limit: one bad_request (id null), the rest of the line is discarded, the
    # session goes on with the next line
    raw.send(b'{"id":20,"cmd":"list","pad":"' + b"x" * 200_000 + b'"}\n{"id":21,"cmd":"operating_state"}\n')
    r = raw.reply()
    assert code(r) == "bad_request" and r["id"] is None and "65536" in r["error"]["message"]
    r = raw.reply()
    assert r["id"] == 21 and r["ok"]
    # blank lines get no reply
    raw.send(b"\n   \n\t\n")
    assert raw.call("operating_state", rid=22)["ok"] and not raw.replies
    assert raw.call("operating_state", rid=23)["data"]["state"] == "ENABLED"
    assert np.abs(goals(daemon) - before).max() <= 1


# ------------------------------------------------ issue 18 item 11: the reply carries the id it can read
RID = 31
#: (request line, the field its message names); each has the integer id RID, every other field
#: valid where the line does not make it wrong
WRONG_FIELDS = [
    *((b'{"id":31,"cmd":%s,"ns":"so101"}' % v, "`cmd`") for v in (b"5", b"5.5", b"true", b"null", b'["list"]',
                                                                  b'{"c":"list"}')),
    (b'{"id":31,"ns":"so101"}', "`cmd`"),  # missing
    *((b'{"id":31,"cmd":"measured_js","ns":%s}' % v, "`ns`") for v in (b"5", b"true", b'["so101"]', b'{"n":1}')),
    *((b'{"id":31,"cmd":"move_jp","ns":"so101","data":%s}' % v, "`data") for v in (b'"x"', b"5", b"true",
                                                                                  b"[1]", b'{"position":7}')),
    (b'{"id":31,"cmd":"move_jp","ns":"so101","data":{"position":' + b"[" * 40 + b"0" + b"]" * 40 + b"}}",
     "nested deeper than 32 levels"),
    # strings that are not UTF-8: the field named, never the decoder's own words
    (b'{"id":31,"cmd":"\xc3\x28","ns":"so101"}', "`cmd` is not valid UTF-8"),
    (b'{"id":31,"cmd":"measured_js","ns":"so\xff101"}', "`ns` is not valid UTF-8"),
    (b'{"id":31,"cmd":"move_jp","ns":"so101","data":{"position":[0,"\xe2\x82",0,0,0]}}',
     "`data.position[1]` is not valid UTF-8"),
    (b'{"id":31,"cmd":"move_jp","ns":"so101","data":{"posi\xfftion":[0,0,0,0,0]}}', "a key of `data` is not valid UTF-8"),
    (b'{"id":31,"cmd":"list","note":"\xff"}', "`note` is not valid UTF-8"),  # a field the envelope ignores
    (b'{"id":31,"\xff":1,"cmd":"list"}', "a key of the request is not valid UTF-8"),
]
#: an id that cannot be read as an integer: null (never an id the client did not send)
NO_ID = [
    (b'{"id":"31","cmd":"list"}', "`id`"), (b'{"id":31.0,"cmd":"list"}', "`id`"),
    (b'{"id":true,"cmd":"list"}', "`id`"), (b'{"id":[31],"cmd":"list"}', "`id`"),
    (b'{"id":{"n":31},"cmd":"list"}', "`id`"), (b'{"id":null,"cmd":"list"}', "`id`"),
    (b'{"cmd":"list"}', "`id`"), (b'{"id":"\xff","cmd":"list"}', "`id` is not valid UTF-8"),
    (b'{"id":31,"cmd":"list"', "invalid JSON"), (b'\xff{"id":31,"cmd":"list"}', "the line is not valid UTF-8"),
    (b'[31,"list"]', "object"),
]


def test_a_wrong_envelope_is_answered_with_the_id_it_can_read_naming_the_field(daemon, raw):
    assert code(raw.call("enable")) == "ok"
    before = goals(daemon)
    for cases, rid in ((WRONG_FIELDS, RID), (NO_ID, None)):
        for line, says in cases:
            raw.send(line + b"\n")
            r = raw.reply()
            assert code(r) == "bad_request" and r["id"] == rid, (line, r)
            message = r["error"]["message"]
            assert says in message, (line, r)
            assert "codec" not in message and "decode" not in message, (line, r)
    assert raw.call("operating_state", rid=99)["data"]["state"] == "ENABLED"  # the session lives
    assert np.abs(goals(daemon) - before).max() <= 1  # and nothing moved


# ---------------------------------------------------------------- defect 4: a stop is never refused
def test_any_session_may_stop_and_refusals_name_the_holder(daemon, raw):
    holder = connect(socket=str(daemon.socket_path))
    try:
        arm = holder.device(ARM)
        assert arm.enable(5.0)
        r = raw.call("move_jr", ARM, {"position": [0.05, 0, 0, 0, 0]}, rid=2)
        assert code(r) == "read_only"
        assert f"pid {os.getpid()}" in r["error"]["message"] and f"uid {os.getuid()}" in r["error"]["message"]
        assert code(raw.call("enable", rid=3)) == "read_only"
        handle = arm.move_jr([0.3, 0, 0, 0, 0])
        assert code(raw.call("hold", ARM, rid=4)) == "ok"  # the running move decelerates
        assert handle.wait(timeout=5.0)
        assert code(raw.call("pause", rid=5)) == "ok"
        wait_until(lambda: arm.operating_state() == "PAUSED", 5, what="PAUSED seen by the holder")
        assert arm.resume(5.0)  # the holder still holds control
        assert code(raw.call("disable", rid=6)) == "ok"
        wait_until(lambda: arm.operating_state() == "DISABLED", 5, what="DISABLED seen by the holder")
        assert code(raw.call("enable", rid=7)) == "read_only"  # stops took nobody's control
        assert arm.enable(5.0)
        assert arm.disable(5.0)
    finally:
        holder.close()


# ---------------------------------------------------------------- defect 5: client loss policy
def ctl(daemon, capsys, *argv) -> tuple[int, str, str]:
    code_ = ctl_main(["--socket", str(daemon.socket_path), *argv])
    out = capsys.readouterr()
    return code_, out.out, out.err


def test_commands_with_an_end_complete_after_crtk_ctl_leaves(daemon, capsys):
    watcher = connect(socket=str(daemon.socket_path))
    try:
        arm = watcher.device(ARM)
        assert arm.enable(5.0)
        watcher.release()
        goal = [0.4, 0.2, -0.2, 0.1, 0.0]
        c, out, err = ctl(daemon, capsys, "move_jp", *map(str, goal))  # no --wait: it leaves at once
        assert c == 0 and "accepted" in out, err
        wait_until(lambda: np.allclose(arm.measured_jp()[0], goal, atol=0.02), 10, what="arm at the move goal")
        goal2 = [0.5, 0.2, -0.2, 0.1, 0.0]
        c, out, err = ctl(daemon, capsys, "interpolate_jp", *map(str, goal2))
        assert c == 0, err
        wait_until(lambda: np.allclose(arm.measured_jp()[0], goal2, atol=0.02), 5, what="arm at the goal")
        c, out, err = ctl(daemon, capsys, "servo_jv", "0.2", "0", "0", "0", "0")
        assert c == 2 and "needs --duration" in err
    finally:
        watcher.close()


# ---------------------------------------------------------------- defect 6: relative streams
def test_relative_streams_move_by_the_offset_in_total(daemon, capsys):
    watcher = connect(socket=str(daemon.socket_path))
    try:
        arm = watcher.device(ARM)
        assert arm.enable(5.0)
        assert arm.move_jp(Q_B).wait(timeout=10.0)
        watcher.release()
        p0 = arm.setpoint_jp()[0]
        c, _, err = ctl(daemon, capsys, "servo_jr", "0.05", "0", "0", "0", "0", "--duration", "0.5")
        assert c == 0, err
        np.testing.assert_allclose(arm.setpoint_jp()[0] - p0, [0.05, 0, 0, 0, 0], atol=1e-9)
        g0 = arm.setpoint_jp()[0]
        c, _, err = ctl(daemon, capsys, "interpolate_jr", "0", "0", "0", "0", "0.1", "--duration", "0.4")
        assert c == 0, err
        np.testing.assert_allclose(arm.goal_jp()[0] - g0, [0, 0, 0, 0, 0.1], atol=1e-9)
        wait_until(lambda: np.allclose(arm.setpoint_jp()[0] - g0, [0, 0, 0, 0, 0.1], atol=1e-6), 5,
                   what="interpolation at its goal")
        T0, _ = arm.setpoint_cp()
        c, _, err = ctl(daemon, capsys, "servo_cr", "0", "0", "0.01", "--duration", "0.3")
        assert c == 0, err
        T1, ts = arm.setpoint_cp()
        assert ts > 0
        moved = T1[:3, 3] - T0[:3, 3]
        assert abs(moved[2] - 0.01) < 0.002 and np.linalg.norm(moved[:2]) < 0.002, moved
        watcher.acquire()
        assert arm.disable(5.0)
    finally:
        watcher.close()

"""Malformed or hostile requests are refused with a reply; they never fault the robot."""

from __future__ import annotations

import json
import socket

import pytest

from crtk_bridge.client import connect

# every simulated robot; the robot is left ENABLED, which sim_daemon restores
pytestmark = [pytest.mark.requires(), pytest.mark.reuse_daemon]


def _raw(path):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(path)
    return s, s.makefile("rb")


def _reply(f, rid):
    while True:
        msg = json.loads(f.readline())
        if msg.get("id") == rid and "ok" in msg:
            return msg


def test_oversized_and_unencodable_requests_are_refused_not_faults(sim_daemon):
    path = str(sim_daemon.socket_path)
    s, f = _raw(path)
    s.sendall(b'{"id":1,"cmd":"enable"}\n')
    assert _reply(f, 1)["ok"]
    arm_ns = sim_daemon.robot.arm
    # a number the wire codec cannot carry: a bad_request reply, the session stays usable
    s.sendall(b'{"id":2,"cmd":"servo_jp","ns":"%s","data":{"position":[0],"x":%d}}\n' % (arm_ns.encode(), 10**30))
    r = _reply(f, 2)
    assert not r["ok"] and r["error"]["code"] == "bad_request"
    s.sendall(b'{"id":3,"cmd":"operating_state"}\n')
    assert _reply(f, 3)["data"]["state"] == "ENABLED"
    # a request line far beyond any real command: refused, and the robot is still ENABLED
    pad = "x" * 200_000
    s.sendall(('{"id":4,"cmd":"servo_jp","ns":"%s","data":{"pad":"%s"}}\n' % (arm_ns, pad)).encode())
    r = json.loads(f.readline())
    while "ok" not in r:  # skip pushed events
        r = json.loads(f.readline())
    assert not r["ok"] and r["error"]["code"] == "bad_request"
    s.close()
    robot = connect(socket=path)
    try:
        state = robot.connection.request("operating_state")["state"]
        assert state == "ENABLED"
        assert not [e for e in robot.connection.events if e.kind == "error"]
    finally:
        robot.close()


def test_error_messages_are_one_line_whatever_strings_the_client_sends(sim_daemon):
    """A field name, command, namespace or topic with control characters is named in the error
    escaped (``\\n``, ``\\x1b``): every error message stays one line, no terminal escape passes."""
    arm = sim_daemon.robot.arm
    calibration = "calibration" in sim_daemon.robot.capabilities  # else refused before the file is read
    s, f = _raw(str(sim_daemon.socket_path))
    try:
        cases = [
            ({"cmd": "servo_jp", "ns": arm, "data": {"\n": None}}, "\\n"),  # field names quoted as is
            ({"cmd": "servo_jp", "ns": arm, "data": {"a\r\x1b[2Jb": None}}, "a\\r\\x1b[2Jb"),
            ({"cmd": "servo_jp", "ns": arm, "data": {"\u2028\x85\x7f": None}}, "\\u2028\\x85\\x7f"),
            ({"cmd": "subscribe", "ns": arm, "data": {"topic": "measured_js", "\x07\t": 1}}, "\\x07\\t"),
            *([({"cmd": "calibrate", "data": {"action": "import", "grippers": ["x\ny"], "file": {"x\ny": {}}}},
                "x\\ny")] if calibration else []),  # refused by the control process
            ({"cmd": "bad\ncmd"}, "bad\\ncmd"),
            ({"cmd": "measured_js", "ns": "x\ny"}, "x\\ny"),
            ({"cmd": "subscribe", "ns": arm, "data": {"topic": "measured_js\x00"}}, "measured_js\\x00"),
        ]
        for rid, (req, named) in enumerate(cases, 1):
            s.sendall(json.dumps(dict(req, id=rid)).encode() + b"\n")
            r = _reply(f, rid)
            assert not r["ok"], (req, r)
            message = r["error"]["message"]
            assert not r["ok"] and r["error"]["code"] in ("bad_request", "unknown_command", "unknown_namespace")
            assert not any(ord(c) < 0x20 or 0x7F <= ord(c) <= 0x9F or c in "\u2028\u2029" for c in message), message
            assert named in message, message
    finally:
        s.close()

"""Malformed or hostile requests are refused with a reply; they never fault the robot."""

from __future__ import annotations

import json
import socket

from crtk_bridge.client import connect



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

"""What the loop publishes (core/loop.py ``_publish``): each namespace's setpoint and goal
(p, v, f), flags and stamps, and the measured state, as the controller holds them, whether a
namespace's joints are consecutive in the robot (copied as a slice) or not (by index). Cycle by
cycle, no daemon."""

from __future__ import annotations

import socket

import msgspec
import numpy as np
import pytest

from crtk_bridge.core.loop import ControlLoop
from crtk_bridge.core.snapshot import Layout, SnapshotBuffer
from crtk_bridge.server.link import ControlLink

from .test_controller import PROFILE, FakeActuator

_encode = msgspec.msgpack.Encoder().encode


def reordered(profile):
    """The profile with its first namespace's joints in reverse order: not consecutive."""
    first = profile.namespaces[0]
    ns = [msgspec.structs.replace(first, joints=list(reversed(first.joints)))] + list(profile.namespaces[1:])
    return msgspec.structs.replace(profile, namespaces=ns)


@pytest.mark.parametrize("profile", [PROFILE, reordered(PROFILE)], ids=["consecutive", "reordered"])
def test_the_snapshot_carries_each_namespaces_setpoint_goal_and_measured_state(profile):
    front, back = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    snap = SnapshotBuffer(Layout(len(profile.joints), len(profile.namespaces)), create=True)
    act = FakeActuator(profile)
    act.pos[:] = np.linspace(-0.3, 0.3, act.n)
    loop = ControlLoop(profile, act, back, snap, realtime=False)
    c = loop.controller
    link = ControlLink(profile, front, snap, lambda msg: None)
    runner = loop.runner
    try:
        def cycle(n=1):
            for _ in range(n):
                runner.work(c, loop._receive)
                loop._publish()
                c.outbox.clear()

        link._post(_encode({"id": 1, "cmd": "enable", "ns": None, "data": None}))
        cycle(5)
        assert c.state.value == "ENABLED"
        arm, grip = profile.namespaces[0].name, profile.namespaces[1].name
        m = c.namespaces[arm]
        target = (m.setpoint_p + 0.01).tolist()
        link._post(_encode({"id": 2, "cmd": "interpolate_jp", "ns": arm, "data": {"position": target}}))
        link._post(_encode({"id": 3, "cmd": "servo_jf", "ns": grip, "data": {"effort": [0.1]}})
                   if c.can("effort", grip) else _encode({"id": 3, "cmd": "hold", "ns": grip, "data": None}))
        cycle(3)
        for ns in (arm, grip):
            m = c.namespaces[ns]
            sp, goal, meas = (link.joint_state(t, ns) for t in ("setpoint_js", "goal_js", "measured_js"))
            has_p, has_v, has_f = m.setpoint_fields()
            assert sp["stamp"] == m.setpoint_stamp > 0
            assert sp["position"] == (m.setpoint_p.tolist() if has_p else [])
            assert sp["velocity"] == (m.setpoint_v.tolist() if has_v else [])
            assert sp["effort"] == (m.setpoint_f.tolist() if has_f else [])
            g_p, g_v, g_f = m.goal_fields()
            assert goal["position"] == (m.goal_p.tolist() if g_p else [])
            assert goal["velocity"] == (m.goal_v.tolist() if g_v else [])
            assert goal["effort"] == (m.goal_f.tolist() if g_f else [])
            assert meas["position"] == c.feedback.position[m.idx].tolist()
        assert link.joint_state("goal_js", arm)["position"] == pytest.approx(target)
        # the setpoint moved from where the joints were toward the goal, joint by joint in the
        # namespace's order (a reordered namespace gets its own joints' values, not the robot's order)
        sp = np.array(link.joint_state("setpoint_js", arm)["position"])
        here = act.pos[c.namespaces[arm].idx]
        assert np.all(np.abs(sp - here) <= 0.01 + 1e-12)
    finally:
        front.close()
        back.close()
        snap.close(unlink=True)

"""End to end, joint space (issue 3): every joint command through the socket of a real daemon on
the simulated SO-101, checked on what the simulator measures, on setpoint_js / goal_js (fields per
crtk-spec 4.2.5, stamps) and on the operating_state events a second, raw session sees."""

from __future__ import annotations

import time

import numpy as np
import pytest

from crtk_bridge.client import CommandError, connect
from crtk_bridge.client.device import joint_state
from crtk_bridge.sim.control import control_request

from .conftest import RawSession, wait_until

TOL = 0.02  # rad: sim quantisation 0.0015 rad; the first-order servo lag settles well inside this
V_MAX = 3.0  # rad/s, shoulder_pan .. elbow_flex in profiles/so101.yaml
DT = 1.0 / 200  # loop period
ARM_IDS = ("1", "2", "3", "4", "5")
GRIPPER_ID = "6"


@pytest.fixture
def rig(sim_daemon):
    """An enabled arm (client) plus a raw session recording operating_state events."""
    robot = connect(socket=str(sim_daemon.socket_path))
    raw = RawSession(str(sim_daemon.socket_path))
    arm = robot.device("so101")
    try:
        assert arm.enable(5.0)
        yield robot, arm, raw, sim_daemon.sim_control_path()
    finally:
        raw.close()
        robot.close()


def fields(js) -> tuple[bool, bool, bool]:
    p, v, f, _ = js
    return (len(p) > 0, len(v) > 0, len(f) > 0)


def measured(arm) -> np.ndarray:
    return arm.measured_jp()[0]


def at(arm, goal, tol=TOL) -> bool:
    return bool(np.allclose(measured(arm), goal, atol=tol))


def settled(arm, window=0.1, tol=0.003) -> np.ndarray | None:
    """The measured position if it changes by less than ``tol`` over ``window`` s, else None."""
    a = measured(arm)
    time.sleep(window)  # the observation window of a stillness check
    b = measured(arm)
    return b if np.max(np.abs(b - a)) < tol else None


def wait_still(arm, timeout=3.0, what="arm still") -> np.ndarray:
    """Wait until the arm stops moving; return where it stopped."""
    out = []

    def still():
        b = settled(arm)
        if b is not None:
            out.append(b)
        return b is not None

    wait_until(still, timeout, what=what)
    return out[-1]


def torque(sim: str) -> dict[str, int]:
    return {sid: s["torque_enable"] for sid, s in control_request(sim, {"cmd": "dump"})["servos"].items()}


def caught_up(raw: RawSession, arm) -> None:
    seq = arm.operating_state_full()["busy_seq"]
    wait_until(lambda: raw.states and raw.states[-1]["busy_seq"] == seq and not raw.states[-1]["is_busy"], 5,
               what="raw session caught up")


def test_validity_stamps_and_unsupported_effort_commands(sim_daemon):
    robot = connect(socket=str(sim_daemon.socket_path))
    try:
        arm = robot.device("so101")
        # disabled: setpoint and goal invalid (stamp 0), still served
        assert arm.setpoint_js()[3] == 0.0 and arm.goal_js()[3] == 0.0
        assert fields(arm.setpoint_js()) == (False, False, False)
        # position-only STS3215: velocity commands by integration, no effort commands
        for ns in robot.list()["namespaces"]:
            for cmd in ("servo_jp", "servo_jr", "servo_jv", "interpolate_jp", "interpolate_jr", "interpolate_jv",
                        "move_jp", "move_jr", "hold", "free"):
                assert cmd in ns["commands"], (ns["name"], cmd)
            assert "servo_jf" not in ns["commands"] and "interpolate_jf" not in ns["commands"]
        assert arm.enable(5.0)
        for call in (lambda: arm.servo_jf([0.0] * 5), lambda: arm.interpolate_jf([0.0] * 5)):
            with pytest.raises(CommandError) as err:
                call()
            assert err.value.code == "unsupported"
        # the daemon refuses it too (a client that does not check), naming command and namespace
        reply = robot.connection.request
        with pytest.raises(CommandError) as err:
            reply("servo_jf", "so101", {"effort": [0.0] * 5})
        assert err.value.code == "unsupported" and "servo_jf" in err.value.message and "so101" in err.value.message
        # enabled, nothing commanded yet: still invalid
        assert arm.setpoint_js()[3] == 0.0 and arm.goal_js()[3] == 0.0
        arm.servo_jp(measured(arm))
        assert arm.setpoint_js()[3] > 0
        assert arm.disable(5.0)
        assert arm.setpoint_js()[3] == 0.0 and arm.goal_js()[3] == 0.0
    finally:
        robot.close()


def test_servo_jp_jr_jv_setpoints_goal_and_watchdog(rig):
    robot, arm, raw, sim = rig
    p0 = measured(arm)
    seq0 = arm.operating_state_full()["busy_seq"]
    n_states = len(raw.states)

    # servo_jp: position only; goal invalid; the arm follows
    target = p0 + np.array([0.2, -0.1, 0.1, 0.0, 0.0])
    arm.servo_jp(target)
    sp = arm.setpoint_js()
    assert fields(sp) == (True, False, False) and sp[3] > 0
    np.testing.assert_allclose(sp[0], target, atol=1e-9)
    assert arm.goal_js()[3] == 0.0
    wait_until(lambda: at(arm, target), 5, what="servo_jp target reached")

    # servo_jp with velocity feed-forward: position and velocity
    arm.servo_jp(target, [0.1, 0, 0, 0, 0])
    assert fields(arm.setpoint_js()) == (True, True, False)

    # servo_jr: relative to the current setpoint
    arm.servo_jr([0.0, 0.0, 0.0, 0.15, 0.0])
    expect = target + np.array([0.0, 0.0, 0.0, 0.15, 0.0])
    np.testing.assert_allclose(arm.setpoint_jp()[0], expect, atol=1e-9)
    wait_until(lambda: at(arm, expect), 5, what="servo_jr target reached")

    # servo_jv at 50 Hz for 0.4 s: the setpoint position integrates v (position-only hardware)
    v = np.array([0.5, 0.0, 0.0, 0.0, 0.0])
    start = arm.setpoint_jp()[0]
    t0 = time.monotonic()
    while time.monotonic() - t0 < 0.4:
        arm.servo_jv(v)
        time.sleep(0.02)  # paces the 50 Hz stream
    sp = arm.setpoint_js()
    assert fields(sp) == (True, True, False) and sp[3] > 0
    np.testing.assert_allclose(sp[1], v, atol=1e-9)
    moved = sp[0][0] - start[0]
    assert 0.15 < moved < 0.35, moved  # ~0.5 rad/s * 0.4 s, plus the time since the last command
    assert arm.goal_js()[3] == 0.0

    # the stream stops: the watchdog holds after safety.servo_timeout_s and says so
    mark = robot.connection.event_count
    ev = arm.wait_for_event("servo_timeout", timeout=2.0, since=mark)
    assert ev is not None and ev.kind == "warning" and "servo_jv" in ev.data["message"]
    held = wait_still(arm, 3, "arm holding after the servo timeout")
    sp = arm.setpoint_js()
    assert fields(sp) == (True, False, False)  # holding: a position setpoint
    np.testing.assert_allclose(held, sp[0], atol=TOL)
    assert settled(arm, 0.3) is not None

    # servo and interpolate never raise is_busy
    assert arm.operating_state_full()["busy_seq"] == seq0
    assert all(not s["is_busy"] for s in raw.states[n_states:])


def test_servo_step_too_large_refused_and_limit_clipping_warned(rig):
    robot, arm, raw, sim = rig
    p0 = arm.setpoint_jp()[0] if arm.setpoint_jp()[1] else measured(arm)
    arm.servo_jp(p0)
    with pytest.raises(CommandError) as err:
        arm.servo_jp(p0 + np.array([0.0, 0.5, 0.0, 0.0, 0.0]))
    assert err.value.code == "step_too_large" and "shoulder_lift" in err.value.message
    np.testing.assert_allclose(arm.setpoint_jp()[0], p0, atol=1e-9)  # the refused step changed nothing
    with pytest.raises(CommandError) as err:
        arm.interpolate_jp(p0 + np.array([0.0, 0.0, -0.5, 0.0, 0.0]))
    assert err.value.code == "step_too_large" and "elbow_flex" in err.value.message

    # bring elbow_flex near its limit (1.69), then servo past it: clipped, with a warning
    goal = p0.copy()
    goal[2] = 1.6
    assert arm.move_jp(goal).wait(timeout=10.0)
    mark = robot.connection.event_count
    beyond = goal.copy()
    beyond[2] = 1.8
    arm.servo_jp(beyond)
    ev = arm.wait_for_event("limit_clipped", timeout=2.0, since=mark)
    assert ev is not None and ev.kind == "warning"
    assert ev.data["joint"] == "elbow_flex" and ev.data["value"] == pytest.approx(1.8)
    assert arm.setpoint_jp()[0][2] == pytest.approx(1.69)
    wait_until(lambda: abs(measured(arm)[2] - 1.69) < TOL, 5, what="elbow at its limit")


def test_interpolate_jp_follows_a_20hz_stream_smoothly(rig):
    robot, arm, raw, sim = rig
    seq0 = arm.operating_state_full()["busy_seq"]
    p0 = measured(arm)
    arm.servo_jp(p0)
    frames = []
    sub = arm.subscribe("setpoint_js", 200, callback=frames.append)
    # a ramp of 0.08 rad per 50 ms command (1.6 rad/s) on shoulder_pan, then 0.04 on elbow_flex
    step = np.array([0.08, 0.0, 0.04, 0.0, 0.0])
    goal = p0.copy()
    n0 = 0
    for k in range(12):
        goal = goal + step
        arm.interpolate_jp(goal)
        if k == 0:
            sp = arm.setpoint_js()
            assert fields(sp) == (True, True, False) and sp[3] > 0
            n0 = len(frames)
        time.sleep(0.05)  # paces the 20 Hz stream
    g = arm.goal_js()
    assert fields(g) == (True, False, False) and g[3] > 0
    np.testing.assert_allclose(g[0], goal, atol=1e-9)
    wait_until(lambda: at(arm, goal), 5, what="interpolated goal reached")
    sub.close()

    # setpoint steps between frames never exceed v_max * (time between their stamps), and the
    # setpoint moved in many small steps, not in 0.08 rad jumps at each command
    pts = [joint_state(f) for f in frames[n0:] if f["stamp"] > 0 and f["position"]]
    assert len(pts) > 60
    steps = []
    for (pa, va, _, ta), (pb, vb, _, tb) in zip(pts, pts[1:]):
        # the interpolator's own per-cycle step, as setpoint velocity (step / dt)
        assert np.all(np.abs(vb) <= V_MAX + 1e-9), vb
        # frames are sampled on the server's clock and stamped with the cycle's wall time (which
        # jitters by a fraction of a period): bound the change by the cycles that can have run
        d = np.abs(pb - pa)
        if tb == ta:
            assert np.all(d == 0)
            continue
        cycles = max(1, round((tb - ta) / DT + 0.4))
        assert np.all(d <= V_MAX * DT * cycles + 1e-9), (d, tb - ta)
        steps.append(d[0] / cycles)
    assert max(steps) < 0.04  # interpolated: a per-cycle step well below the 0.08 command step
    assert sum(1 for s in steps if s > 1e-6) > 30  # it moved on most cycles

    # interpolate_jr: relative to the running interpolation goal
    arm.interpolate_jr([0.0, 0.1, 0.0, 0.0, 0.0])
    g2 = arm.goal_jp()[0]
    np.testing.assert_allclose(g2, goal + np.array([0.0, 0.1, 0.0, 0.0, 0.0]), atol=1e-9)
    wait_until(lambda: at(arm, g2), 5, what="interpolate_jr goal reached")

    # interpolate_jv: the goal is a velocity; setpoint carries the ramped v and the integrated p
    arm.interpolate_jv([0.0, 0.0, 0.0, 0.6, 0.0])
    g = arm.goal_js()
    assert fields(g) == (False, True, False)
    np.testing.assert_allclose(g[1], [0.0, 0.0, 0.0, 0.6, 0.0], atol=1e-9)
    wait_until(lambda: arm.setpoint_jv()[0][3] == pytest.approx(0.6), 2, what="setpoint velocity ramped up")
    assert fields(arm.setpoint_js()) == (True, True, False)
    w0 = measured(arm)[3]
    for _ in range(6):
        arm.interpolate_jv([0.0, 0.0, 0.0, 0.6, 0.0])
        time.sleep(0.05)  # paces the 20 Hz stream
    arm.interpolate_jv([0.0] * 5)
    wait_until(lambda: arm.setpoint_jv()[0][3] == 0.0, 2, what="setpoint velocity ramped down")
    assert measured(arm)[3] - w0 > 0.1  # wrist_flex moved at the commanded velocity

    assert arm.operating_state_full()["busy_seq"] == seq0  # no busy edges for interpolate
    assert all(not s["is_busy"] for s in raw.states)


def test_move_jp_jr_home_busy_edges_and_goal(rig):
    robot, arm, raw, sim = rig
    caught_up(raw, arm)
    n = len(raw.states)
    goal = np.array([0.6, 0.3, -0.4, 0.2, 0.0])
    h = arm.move_jp(goal)
    sp = arm.setpoint_js()
    assert fields(sp) == (True, True, False) and sp[3] > 0
    g = arm.goal_js()
    assert fields(g) == (True, False, False)
    np.testing.assert_allclose(g[0], goal, atol=1e-9)
    assert h.wait(timeout=10.0)
    wait_until(lambda: at(arm, goal), 5, what="move_jp goal reached")
    assert [s["is_busy"] for s in raw.states[n:] if s["busy_seq"] == h.busy_seq] == [True, False]

    # move_jr during a move is relative to the running goal, not to the setpoint
    far = np.array([-0.6, 0.3, -0.4, 0.2, 0.0])
    h1 = arm.move_jp(far)
    h2 = arm.move_jr([0.0, 0.0, 0.0, 0.0, 0.5])
    assert h2.busy_seq == h1.busy_seq + 1
    np.testing.assert_allclose(arm.goal_jp()[0], far + [0, 0, 0, 0, 0.5], atol=1e-9)
    assert h1.wait(timeout=10.0) and h2.wait(timeout=10.0)
    wait_until(lambda: at(arm, far + [0, 0, 0, 0, 0.5]), 5, what="move_jr goal reached")
    # a servo command invalidates the goal
    arm.servo_jp(measured(arm))
    assert arm.goal_js()[3] == 0.0

    # home: busy edges too, ends at the profile home (0 for every joint of the SO-101)
    caught_up(raw, arm)
    n = len(raw.states)
    assert arm.home(15.0)
    wait_until(lambda: at(arm, np.zeros(5)), 5, what="home reached")
    wait_until(lambda: raw.busy_edges()[-1] is False and len(raw.states) > n + 1, 5, what="home idle edge")
    assert [s["is_busy"] for s in raw.states[n:]][:1] == [True] and raw.states[-1]["is_busy"] is False


def test_pause_refuses_motion_and_holds_hold_stops_a_move(rig):
    robot, arm, raw, sim = rig
    start = measured(arm)
    goal = start.copy()
    goal[0] = 1.8  # shoulder_pan limit 1.92; jerk-limited braking from v_max takes ~0.6 rad
    h = arm.move_jp(goal)
    wait_until(lambda: measured(arm)[0] - start[0] > 0.1, 5, what="arm moving")
    assert arm.pause(5.0) and arm.is_paused()
    assert not h.is_busy()  # the pause ended the move: its idle edge came
    stopped = wait_still(arm, 3, "arm stopped on pause")
    assert stopped[0] < goal[0] - 0.3
    for call in (lambda: arm.move_jp(goal), lambda: arm.servo_jp(stopped), lambda: arm.interpolate_jp(stopped),
                 lambda: arm.hold()):
        with pytest.raises(CommandError) as err:
            call()
        assert err.value.code == "invalid_state" and "PAUSED" in err.value.message
    assert settled(arm, 0.3) is not None
    np.testing.assert_allclose(measured(arm), stopped, atol=TOL)  # held while paused

    assert arm.resume(5.0) and arm.is_enabled()
    assert settled(arm, 0.2) is not None  # resume does not restart the move
    np.testing.assert_allclose(measured(arm), stopped, atol=TOL)

    # hold stops a running move short of its goal, with the idle edge
    back = stopped.copy()
    back[0] = -1.8
    h = arm.move_jp(back)
    wait_until(lambda: stopped[0] - measured(arm)[0] > 0.1, 5, what="arm moving back")
    arm.hold()
    assert h.wait(timeout=2.0)
    held = wait_still(arm, 3, "arm stopped on hold")
    assert held[0] > back[0] + 0.3
    assert fields(arm.setpoint_js()) == (True, False, False)
    assert settled(arm, 0.3) is not None


def test_free_torques_off_the_namespace_and_move_resumes_without_a_jump(rig):
    robot, arm, raw, sim = rig
    assert all(torque(sim)[i] == 1 for i in ARM_IDS + (GRIPPER_ID,))
    arm.free()
    wait_until(lambda: all(torque(sim)[i] == 0 for i in ARM_IDS), 2, what="arm torque off")
    assert torque(sim)[GRIPPER_ID] == 1  # the gripper namespace is untouched
    assert arm.is_enabled()
    assert arm.setpoint_js()[3] == 0.0 and arm.goal_js()[3] == 0.0

    # move shoulder_lift "by hand" (in the simulator) while free: the arm follows the hand
    control_request(sim, {"cmd": "write", "id": 2, "register": "Present_Position", "value": 2048 + 400})
    wait_until(lambda: abs(measured(arm)[1] - 400 * 2 * np.pi / 4096) < TOL, 2, what="hand motion measured")
    before = measured(arm)
    h = arm.move_jp(before + np.array([0.0, 0.0, 0.0, 0.0, 0.3]))
    wait_until(lambda: all(torque(sim)[i] == 1 for i in ARM_IDS), 2, what="arm torque back on")
    after = measured(arm)
    np.testing.assert_allclose(after[:4], before[:4], atol=TOL)  # no snap back to the old setpoint
    assert h.wait(timeout=5.0)
    np.testing.assert_allclose(measured(arm)[:4], before[:4], atol=TOL)
    assert arm.is_enabled()

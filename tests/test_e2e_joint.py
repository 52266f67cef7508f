"""End to end, joint space (issue 3): every joint command through the socket of a real daemon on
each simulated robot (SO-101 on Feetech, Koch on Dynamixel, the CANopen pan / tilt unit), checked
on what the simulator measures, on setpoint_js / goal_js (fields per crtk-spec 4.2.5, stamps) and
on the operating_state events a second, raw session sees. Joints are chosen by index
(``SimRobot.j``: the five-joint arm's joint k, or an arm's last), limits and rates from the
profile."""

from __future__ import annotations

import time

import numpy as np
import pytest

from crtk_bridge.backends import backend_class
from crtk_bridge.client import CommandError, connect
from crtk_bridge.client.device import joint_state
from crtk_bridge.core.actuator import Actuator

from .conftest import RawSession, wait_until

# every simulated robot; each test leaves its arm ENABLED somewhere sim_daemon can move it back from
pytestmark = [pytest.mark.requires("arm"), pytest.mark.reuse_daemon]  # arm poses in rad, stopping distances

TOL = 0.02  # rad: sim quantisation 0.0015 rad; the first-order servo lag settles well inside this

# What legitimately differs per backend (keyed by the profile's backend type):
# setpoint_js fields (position, velocity, effort) under servo_jv / interpolate_jv. The STS3215 is
# position-only: the velocity is integrated into a position setpoint. Dynamixel servos run velocity
# mode natively, CiA 402 drives CSV, a UR speedJ (backends/ur/backend.py): the setpoint has no
# position (core/motion.py setpoint_fields, crtk-spec 4.2.5).
VELOCITY_SETPOINT_FIELDS = {"feetech": (True, True, False), "dynamixel": (False, True, False),
                            "canopen402": (False, True, False), "ur": (False, True, False)}
#: namespaces whose every joint can follow an effort command (profiles: the Koch's XL330 gripper,
#: the CANopen drives' CST); the others must not advertise servo_jf / interpolate_jf
EFFORT_NAMESPACES = {"koch/gripper", "pantilt"}


@pytest.fixture
def rig(sim_daemon):
    """An enabled arm (client) plus a raw session recording operating_state events."""
    robot = connect(socket=str(sim_daemon.socket_path))
    raw = RawSession(str(sim_daemon.socket_path))
    arm = robot.device(sim_daemon.robot.arm)
    try:
        assert arm.enable(5.0)
        yield robot, arm, raw, sim_daemon.robot.sim(sim_daemon.sim_control_path())
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


def caught_up(raw: RawSession, arm) -> None:
    seq = arm.operating_state_full()["busy_seq"]
    wait_until(lambda: raw.states and raw.states[-1]["busy_seq"] == seq and not raw.states[-1]["is_busy"], 5,
               what="raw session caught up")


def test_validity_stamps_and_unsupported_effort_commands(sim_daemon):
    bot = sim_daemon.robot
    n = bot.n
    robot = connect(socket=str(sim_daemon.socket_path))
    try:
        arm = robot.device(bot.arm)
        # disabled: setpoint and goal invalid (stamp 0), still served
        assert arm.setpoint_js()[3] == 0.0 and arm.goal_js()[3] == 0.0
        assert fields(arm.setpoint_js()) == (False, False, False)
        # velocity commands everywhere (integrated on the position-only STS3215, native on
        # Dynamixel and CiA 402); effort only where every joint can (EFFORT_NAMESPACES): not on
        # the STS3215 (no current mode) nor the Koch's XL430s (no current sensor); the Koch's
        # XL330 gripper has it (test_e2e_capabilities.py), the SO-101's gripper not.
        for ns in robot.list()["namespaces"]:
            for cmd in ("servo_jp", "servo_jr", "servo_jv", "interpolate_jp", "interpolate_jr", "interpolate_jv",
                        "move_jp", "move_jr", "hold", "free"):
                assert cmd in ns["commands"], (ns["name"], cmd)
            effort = ns["name"] in EFFORT_NAMESPACES
            assert ("servo_jf" in ns["commands"]) is effort and ("interpolate_jf" in ns["commands"]) is effort
        assert arm.enable(5.0)
        if bot.arm in EFFORT_NAMESPACES:  # nothing to refuse: the effort commands are test_e2e_capabilities'
            assert arm.disable(5.0)
            return
        for call in (lambda: arm.servo_jf([0.0] * n), lambda: arm.interpolate_jf([0.0] * n)):
            with pytest.raises(CommandError) as err:
                call()
            assert err.value.code == "unsupported"
        # the daemon refuses it too (a client that does not check), naming command and namespace
        reply = robot.connection.request
        with pytest.raises(CommandError) as err:
            reply("servo_jf", bot.arm, {"effort": [0.0] * n})
        assert err.value.code == "unsupported" and "servo_jf" in err.value.message and bot.arm in err.value.message
        # enabled, nothing commanded yet: still invalid
        assert arm.setpoint_js()[3] == 0.0 and arm.goal_js()[3] == 0.0
        arm.servo_jp(measured(arm))
        assert arm.setpoint_js()[3] > 0
        assert arm.disable(5.0)
        assert arm.setpoint_js()[3] == 0.0 and arm.goal_js()[3] == 0.0
    finally:
        robot.close()


def test_servo_jp_jr_jv_setpoints_goal_and_watchdog(rig, sim_robot):
    robot, arm, raw, sim = rig
    bot = sim_robot
    p0 = measured(arm)
    seq0 = arm.operating_state_full()["busy_seq"]
    n_states = len(raw.states)

    # servo_jp: position only; goal invalid; the setpoint follows the target (at velocity_max),
    # the arm follows the setpoint
    target = p0 + bot.vec((0, 0.2), (1, -0.1), (bot.j(2), 0.1))
    arm.servo_jp(target)
    sp = arm.setpoint_js()
    assert fields(sp) == (True, False, False) and sp[3] > 0
    wait_until(lambda: np.allclose(arm.setpoint_jp()[0], target, atol=1e-9), 2, what="setpoint at the servo target")
    assert arm.goal_js()[3] == 0.0
    wait_until(lambda: at(arm, target), 5, what="servo_jp target reached")

    # servo_jp with velocity feed-forward: position and velocity
    arm.servo_jp(target, bot.vec((0, 0.1)))
    assert fields(arm.setpoint_js()) == (True, True, False)

    # servo_jr: relative to the current setpoint
    arm.servo_jr(bot.vec((bot.j(3), 0.15)))
    expect = target + bot.vec((bot.j(3), 0.15))
    wait_until(lambda: np.allclose(arm.setpoint_jp()[0], expect, atol=1e-9), 2, what="setpoint at the servo_jr target")
    wait_until(lambda: at(arm, expect), 5, what="servo_jr target reached")

    # servo_jv at 50 Hz for 0.6 s: the joint moves at v (setpoint fields per backend). The speed is
    # taken between two measured samples after the first 0.3 s (past any acceleration ramp: a
    # UR's speedJ ramps), by the samples' own stamps, so a client or loop starved by a loaded
    # host cannot make it look slow or fast
    v = bot.vec((0, 0.5))
    t0 = time.monotonic()
    first = last = None
    while time.monotonic() - t0 < 0.6:
        arm.servo_jv(v)
        if time.monotonic() - t0 > 0.3:
            js = arm.measured_js()
            first = first or js
            last = js
        time.sleep(0.02)  # paces the 50 Hz stream
    sp = arm.setpoint_js()
    assert fields(sp) == VELOCITY_SETPOINT_FIELDS[bot.backend] and sp[3] > 0
    np.testing.assert_allclose(sp[1], v, atol=1e-9)
    assert last[3] - first[3] > 0.1, (first[3], last[3])
    speed = (last[0][0] - first[0][0]) / (last[3] - first[3])
    assert 0.35 < speed < 0.65, speed  # 0.5 rad/s asked
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


def test_servo_step_too_large_refused_and_limit_clipping_warned(rig, sim_robot):
    robot, arm, raw, sim = rig
    bot = sim_robot
    p0 = arm.setpoint_jp()[0] if arm.setpoint_jp()[1] else measured(arm)
    arm.servo_jp(p0)
    e = bot.j(2)  # elbow_flex on the five-joint arms
    with pytest.raises(CommandError) as err:
        arm.servo_jp(p0 + bot.vec((1, 0.5)))
    assert err.value.code == "step_too_large" and bot.joint_names[1] in err.value.message
    np.testing.assert_allclose(arm.setpoint_jp()[0], p0, atol=1e-9)  # the refused step changed nothing
    with pytest.raises(CommandError) as err:
        arm.interpolate_jp(p0 + bot.vec((e, -0.5)))
    assert err.value.code == "step_too_large" and bot.joint_names[e] in err.value.message

    # bring the joint near its limit, then servo past it: clipped, with a warning
    limit = bot.pos_max[e]
    goal = p0.copy()
    goal[e] = limit - 0.09
    assert arm.move_jp(goal).wait(timeout=10.0)
    mark = robot.connection.event_count
    beyond = goal.copy()
    beyond[e] = limit + 0.11
    arm.servo_jp(beyond)
    ev = arm.wait_for_event("limit_clipped", timeout=2.0, since=mark)
    assert ev is not None and ev.kind == "warning"
    assert ev.data["joint"] == bot.joint_names[e] and ev.data["value"] == pytest.approx(limit + 0.11)
    wait_until(lambda: arm.setpoint_jp()[0][e] == pytest.approx(limit), 2, what="setpoint at the limit")
    wait_until(lambda: abs(measured(arm)[e] - limit) < TOL, 5, what="joint at its limit")


def test_interpolate_jp_follows_a_20hz_stream_smoothly(rig, sim_robot):
    robot, arm, raw, sim = rig
    bot = sim_robot
    seq0 = arm.operating_state_full()["busy_seq"]
    p0 = measured(arm)
    arm.servo_jp(p0)
    frames = []
    sub = arm.subscribe("setpoint_js", 200, callback=frames.append)
    # a ramp of 0.08 rad per 50 ms command (1.6 rad/s) on shoulder_pan, then 0.04 on elbow_flex
    v_max, dt = bot.vel_max, 1.0 / bot.rate_hz  # the profile's velocity limits, the loop period
    step = bot.vec((0, 0.08), (bot.j(2), 0.04))
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
    # a cycle's stamp is at most its lateness after its tick (0.9 period, or what the loop
    # reports for these last cycles if more: a loaded host, a hardware-paced loop catching up)
    jitter = max(0.9 * dt, robot.connection.request("period_statistics").get("lateness_max_s", 0.0))
    # a backend that starts its cycle itself (wait_cycle: a UR's packets, queued while a cycle ran
    # late) may run the cycle after a late one at once: one more cycle may fit
    catch_up = 1 if backend_class(bot.backend).wait_cycle is not Actuator.wait_cycle else 0  # it can pace
    steps = []
    for (pa, va, _, ta), (pb, vb, _, tb) in zip(pts, pts[1:]):
        # the interpolator's own per-cycle step, as setpoint velocity (step / dt); a frame with no
        # velocity is the position hold that follows the stream's servo timeout (a slow host can
        # take longer than the timeout to see the goal reached): it holds, at zero velocity
        assert np.all(np.abs(vb if len(vb) else np.zeros_like(pb)) <= v_max + 1e-9), vb
        # frames are sampled on the server's clock and stamped with the cycle's wall time (which
        # jitters by the cycle's lateness): bound the change by the cycles that can have run
        d = np.abs(pb - pa)
        if tb == ta:
            assert np.all(d == 0)
            continue
        cycles = max(1, int((tb - ta + jitter) / dt + 1e-9)) + catch_up
        assert np.all(d <= v_max * dt * cycles + 1e-9), (d, tb - ta)
        steps.append(d[0] / cycles)
    assert max(steps) < 0.04  # interpolated: a per-cycle step well below the 0.08 command step
    assert sum(1 for s in steps if s > 1e-6) > 30  # it moved on most cycles

    # interpolate_jr: relative to the running interpolation goal
    arm.interpolate_jr(bot.vec((1, 0.1)))
    g2 = arm.goal_jp()[0]
    np.testing.assert_allclose(g2, goal + bot.vec((1, 0.1)), atol=1e-9)
    wait_until(lambda: at(arm, g2), 5, what="interpolate_jr goal reached")

    # interpolate_jv: the goal is a velocity; setpoint carries the ramped v (and, on position-only
    # hardware, the integrated p)
    w = bot.j(3)  # wrist_flex on the five-joint arms
    vw = bot.vec((w, 0.6))
    arm.interpolate_jv(vw)
    g = arm.goal_js()
    assert fields(g) == (False, True, False)
    np.testing.assert_allclose(g[1], vw, atol=1e-9)
    wait_until(lambda: arm.setpoint_jv()[0][w] == pytest.approx(0.6), 2, what="setpoint velocity ramped up")
    assert fields(arm.setpoint_js()) == VELOCITY_SETPOINT_FIELDS[bot.backend]
    w0 = measured(arm)[w]
    for _ in range(6):
        arm.interpolate_jv(vw)
        time.sleep(0.05)  # paces the 20 Hz stream
    arm.interpolate_jv([0.0] * bot.n)
    wait_until(lambda: arm.setpoint_jv()[0][w] == 0.0, 2, what="setpoint velocity ramped down")
    assert measured(arm)[w] - w0 > 0.1  # the joint moved at the commanded velocity

    assert arm.operating_state_full()["busy_seq"] == seq0  # no busy edges for interpolate
    # (the enable before it was busy while DISABLED: a transition; interpolate never is)
    assert all(not s["is_busy"] for s in raw.states if s["state"] == "ENABLED")


def test_move_jp_jr_home_busy_edges_and_goal(rig, sim_robot):
    robot, arm, raw, sim = rig
    bot = sim_robot
    caught_up(raw, arm)
    n = len(raw.states)
    goal = bot.goals["reach"]
    h = arm.move_jp(goal)
    sp = arm.setpoint_js()
    assert fields(sp) == (True, True, False) and sp[3] > 0
    g = arm.goal_js()
    assert fields(g) == (True, False, False)
    np.testing.assert_allclose(g[0], goal, atol=1e-9)
    assert h.wait(timeout=10.0)
    wait_until(lambda: at(arm, goal), 5, what="move_jp goal reached")
    # h.wait() saw the idle edge on the client's session; the raw session got the same event in
    # the same server pass, but its reader thread may not have run yet (a loaded host): wait for
    # it, then check that the edges are exactly one True then one False
    wait_until(lambda: any(s["busy_seq"] == h.busy_seq and not s["is_busy"] for s in list(raw.states[n:])), 5,
               what="idle edge on the raw session")
    assert [s["is_busy"] for s in raw.states[n:] if s["busy_seq"] == h.busy_seq] == [True, False]

    # move_jr during a move is relative to the running goal, not to the setpoint
    far = bot.goals["far"]
    h1 = arm.move_jp(far)
    rel = bot.vec((bot.j(4), 0.5))  # wrist_roll on the five-joint arms
    h2 = arm.move_jr(rel)
    assert h2.busy_seq == h1.busy_seq + 1
    np.testing.assert_allclose(arm.goal_jp()[0], far + rel, atol=1e-9)
    assert h1.wait(timeout=10.0) and h2.wait(timeout=10.0)
    wait_until(lambda: at(arm, far + rel), 5, what="move_jr goal reached")
    # a servo command invalidates the goal
    arm.servo_jp(measured(arm))
    assert arm.goal_js()[3] == 0.0

    # home: busy edges too, ends at the profile home
    caught_up(raw, arm)
    n = len(raw.states)
    assert arm.home(15.0)
    wait_until(lambda: at(arm, bot.home), 5, what="home reached")
    wait_until(lambda: raw.busy_edges()[-1] is False and len(raw.states) > n + 1, 5, what="home idle edge")
    assert [s["is_busy"] for s in raw.states[n:]][:1] == [True] and raw.states[-1]["is_busy"] is False


def test_pause_refuses_motion_and_holds_hold_stops_a_move(rig, sim_robot):
    robot, arm, raw, sim = rig
    bot = sim_robot
    start = measured(arm)
    goal = start.copy()
    goal[0] = bot.pos_max[0] - 0.12  # braking at the stop deceleration takes ~0.15 rad
    h = arm.move_jp(goal)
    wait_until(lambda: measured(arm)[0] - start[0] > 0.1, 5, what="arm moving")
    assert arm.pause(5.0) and arm.is_paused()
    assert not h.is_busy()  # the pause ended the move: its idle edge came
    stopped = wait_still(arm, 3, "arm stopped on pause")
    assert stopped[0] < goal[0] - 0.3
    # a device that stops itself on pause (CiA 402 quick stop) is still before core's braking
    # ramp ends; until it does, a hold is a stop (never refused)
    wait_until(lambda: not np.any(arm.setpoint_jv()[0]), 3, what="the braking setpoint at rest")
    for call in (lambda: arm.move_jp(goal), lambda: arm.servo_jp(stopped), lambda: arm.interpolate_jp(stopped)):
        with pytest.raises(CommandError) as err:
            call()
        assert err.value.code == "invalid_state" and "PAUSED" in err.value.message
    arm.hold()  # a stop is never refused: of a paused arm at rest, a no-op
    assert arm.is_paused()
    assert settled(arm, 0.3) is not None
    np.testing.assert_allclose(measured(arm), stopped, atol=TOL)  # held while paused

    assert arm.resume(5.0) and arm.is_enabled()
    assert settled(arm, 0.2) is not None  # resume does not restart the move
    np.testing.assert_allclose(measured(arm), stopped, atol=TOL)

    # hold stops a running move short of its goal, with the idle edge
    back = stopped.copy()
    back[0] = bot.pos_min[0] + 0.12
    h = arm.move_jp(back)
    wait_until(lambda: stopped[0] - measured(arm)[0] > 0.1, 5, what="arm moving back")
    arm.hold()
    assert h.wait(timeout=2.0)
    held = wait_still(arm, 3, "arm stopped on hold")
    assert held[0] > back[0] + 0.3
    assert fields(arm.setpoint_js()) == (True, False, False)
    assert settled(arm, 0.3) is not None


def _stop_deceleration(bot, j: int) -> float:
    """rad/s^2 the daemon brakes arm joint ``j`` at: the profile's, or its default bounded by
    what the backend says the hardware follows (profile.stop_deceleration)."""
    from crtk_bridge.backends import create_backend
    from crtk_bridge.profile import load_profile, stop_deceleration

    p = load_profile(bot.profile)
    i = p.joint_index(bot.joint_names[j])
    return stop_deceleration(p.joints[i].limits, create_backend(p).deceleration_limit(i))


def test_hold_during_a_fast_move_stops_within_the_stopping_distance(rig, sim_robot):
    """issue 18 item 2: hold sent during a fast move_jp brakes at the joint's stop deceleration,
    not at the move's acceleration and jerk (which let the SO-101 travel ~0.87 rad further). From
    the braking setpoint seen just after the hold (speed v), the arm comes to rest within
    v^2 / (2 d) + one cycle (docs/protocol.md, Safety: <= 0.25 rad for the SO-101 from 3 rad/s)."""
    robot, arm, raw, sim = rig
    bot = sim_robot
    d, v_max, dt = _stop_deceleration(bot, 0), bot.vel_max[0], 1.0 / bot.rate_hz
    start = measured(arm)
    start[0] = bot.pos_min[0] + 0.1
    assert arm.move_jp(start).wait(timeout=10.0)
    goal = start.copy()
    goal[0] = bot.pos_max[0] - 0.1
    h = arm.move_jp(goal)
    def fast() -> bool:
        v = arm.setpoint_jv()[0]
        return len(v) > 0 and abs(v[0]) >= 0.95 * v_max

    wait_until(fast, 5, what="joint 0 near velocity_max")
    arm.hold()
    assert h.wait(timeout=2.0)
    p1, v1, _, _ = arm.setpoint_js()  # braking already (or at rest on a slow host)
    wait_until(lambda: not np.any(arm.setpoint_jv()[0]), 3, what="the braking setpoint at rest")
    rest = arm.setpoint_jp()[0]
    bound = v1[0] ** 2 / (2 * d) + abs(v1[0]) * dt + 1e-6
    assert 0.0 <= rest[0] - p1[0] <= bound, (rest[0] - p1[0], bound, v1[0])
    assert rest[0] < goal[0] - 0.3  # stopped well short of the goal
    held = wait_still(arm, 3, "arm still after hold")
    np.testing.assert_allclose(held, rest, atol=TOL)  # the arm itself is where the setpoint stopped


def test_free_torques_off_the_namespace_and_move_resumes_without_a_jump(rig, sim_robot):
    robot, arm, raw, sim = rig
    bot = sim_robot
    assert all(bot.torque(sim).values())
    arm.free()
    wait_until(lambda: all(bot.free(sim, bot.arm_ids).values()), 2, what="arm free (torque off)")
    if bot.gripper_id is not None:
        assert not bot.free(sim, [bot.gripper_id])[bot.gripper_id]  # the gripper namespace is untouched
    assert arm.is_enabled()
    assert arm.setpoint_js()[3] == 0.0 and arm.goal_js()[3] == 0.0

    # move shoulder_lift "by hand" (in the simulator) by 0.6 rad while free: the arm follows
    h_j = 1
    sid = int(bot.arm_ids[h_j])
    start = measured(arm)
    bot.row.set_present(sim, sid, bot.row.present(sim, sid) + round(0.6 * bot.counts_per_rad[str(sid)]))
    wait_until(lambda: abs(measured(arm)[h_j] - start[h_j] - 0.6) < TOL, 2, what="hand motion measured")
    before = measured(arm)
    m = bot.j(4) if bot.j(4) != h_j else 0  # wrist_roll on the five-joint arms
    others = [i for i in range(bot.n) if i != m]
    h = arm.move_jp(before + bot.vec((m, 0.3)))
    wait_until(lambda: not any(bot.free(sim, bot.arm_ids).values()), 2, what="arm torque back on")
    after = measured(arm)
    np.testing.assert_allclose(after[others], before[others], atol=TOL)  # no snap back to the old setpoint
    assert h.wait(timeout=5.0)
    np.testing.assert_allclose(measured(arm)[others], before[others], atol=TOL)
    assert arm.is_enabled()

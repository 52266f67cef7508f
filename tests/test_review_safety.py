"""Safety review: setpoints on every path stay bounded by the joint limits and velocity_max
without jumps, and a stop is never refused (nor ignored). Driven through the controller with the
fake actuator of test_controller (measured = last commanded)."""

from __future__ import annotations

import numpy as np
import pytest

from crtk_bridge.core.state import OperatingState

from .conftest import only_on, wait_until
from .test_controller import PROFILE, FakeActuator, make_rig
from .test_shutdown_park import loop_rig  # noqa: F401 (a fixture)


@pytest.fixture
def rig():
    return make_rig(FakeActuator(PROFILE))


def _max_step_ratio(c, act, cycle, n):
    """Cycle ``n`` times; the largest per-cycle change of any joint's written position setpoint,
    as a fraction of that joint's ``velocity_max * dt``."""
    vmax = np.array([j.limits.velocity_max for j in PROFILE.joints])
    worst = 0.0
    last = act.pos.copy()
    for _ in range(n):
        cycle()
        worst = max(worst, float(np.max(np.abs(act.pos - last) / (vmax * c.dt))))
        last = act.pos.copy()
    return worst


GRIPPER = PROFILE.joint_index("gripper")
G_MIN = PROFILE.joints[GRIPPER].limits.position_min


@pytest.mark.parametrize("command", ["move_jp", "servo_jp", "interpolate_jp", "interpolate_jv", "servo_jv"])
def test_a_joint_enabled_outside_its_limits_is_brought_back_without_a_jump(rig, command):
    """A gripper squeezed (or moved by hand) 0.3 rad past its lower limit, then enabled: the first
    command that moves it must bring it back at velocity_max at most, never snap it to the limit
    in one cycle."""
    c, act, clock, cycle, req = rig
    act.pos[GRIPPER] = G_MIN - 0.3
    cycle()
    assert req("enable")["ok"]
    cycle(3)
    assert act.pos[GRIPPER] == pytest.approx(G_MIN - 0.3)  # enable holds it where it is
    target = [G_MIN + 0.02]  # within safety.servo_step_max of where it is
    if command == "interpolate_jv" or command == "servo_jv":
        r = req(command, "so101/gripper", velocity=[1.0])
    else:
        r = req(command, "so101/gripper", position=target)
    assert r["ok"], r
    ratio = _max_step_ratio(c, act, cycle, 30)
    assert ratio <= 1.0 + 1e-6, f"{command}: the gripper setpoint moved {ratio:.0f}x velocity_max in one cycle"
    assert act.pos[GRIPPER] > G_MIN - 0.3  # and it does come back


def _enable_with_gripper_outside(act, cycle, req):
    act.pos[GRIPPER] = G_MIN - 0.3
    cycle()
    assert req("enable")["ok"]
    cycle()


def test_park_of_a_joint_outside_its_limits_does_not_jump(rig):
    c, act, clock, cycle, req = rig
    _enable_with_gripper_outside(act, cycle, req)
    assert c.park()
    ratio = _max_step_ratio(c, act, cycle, 30)
    assert ratio <= 1.0 + 1e-6, f"park moved the gripper {ratio:.0f}x velocity_max in one cycle"


def test_a_joint_outside_its_limits_is_not_driven_farther_out(rig):
    c, act, clock, cycle, req = rig
    _enable_with_gripper_outside(act, cycle, req)
    assert req("servo_jv", "so101/gripper", velocity=[-1.0])["ok"]
    cycle(20)
    assert act.pos[GRIPPER] == pytest.approx(G_MIN - 0.3)


# ---------------------------------------------------------------- a stop is never refused (nor ignored)
HOME = np.array([j.home for j in PROFILE.joints])


def _arm_moving(act, cycle):
    before = act.pos.copy()
    cycle()
    return bool(np.any(act.pos != before))


@pytest.mark.parametrize("homed", [True, False])
def test_hold_during_home_is_accepted_and_stops_it(rig, homed):
    c, act, clock, cycle, req = rig
    act.pos[:] = 0.8
    cycle()
    assert req("enable")["ok"]
    if not homed:
        assert req("unhome")["ok"]
    assert req("home")["ok"]
    cycle(20)
    assert _arm_moving(act, cycle)
    c.outbox.clear()
    r = req("hold", "so101")
    assert r["ok"], r
    cycle(400)
    assert not _arm_moving(act, cycle), "the home move went on after hold"
    assert np.abs(act.pos - HOME).max() > 0.3  # stopped short of home
    assert not c.is_busy and c.is_homed is homed  # an interrupted home homes nothing
    assert [s["data"]["is_busy"] for s in c.outbox if s.get("event") == "operating_state"][-1] is False


@pytest.mark.parametrize("stop", ["pause", "hold"])
def test_a_stop_ends_a_shutdown_park_of_a_paused_arm(rig, stop):
    """SIGTERM with the arm PAUSED parks it (torque off would drop it); a pause or hold sent
    meanwhile must stop that motion like it does from ENABLED."""
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("pause")["ok"] and c.state is OperatingState.PAUSED
    assert c.park()
    cycle(20)
    assert _arm_moving(act, cycle)
    r = req(stop, "so101" if stop == "hold" else None)
    assert r["ok"], r
    cycle(400)
    assert not c.in_motion() and not _arm_moving(act, cycle), f"{stop} did not stop the park"
    rest = np.array([PROFILE.shutdown.rest[j.name] for j in PROFILE.joints])
    assert np.abs(act.pos - rest).max() > 0.3


# ---------------------------------------------------------------- servo_cv / interpolate_cv: huge twists
@pytest.mark.parametrize("command", ["servo_cv", "interpolate_cv"])
def test_a_huge_twist_moves_at_velocity_max_in_its_direction_never_nan(rig, command):
    """A finite but huge twist (1e308 m/s) overflowed the Jacobian solve: NaN setpoints went to
    the backend and the next cycle's SVD raised (the loop faults the robot: torque off, the arm
    drops). It is followed like any too-fast twist: at the joints' velocity limit, same direction."""
    c, act, clock, cycle, req = rig
    act.pos[:] = [0.1, 0.5, 0.5, 0.3, 0.1, 0.2]
    cycle()
    assert req("enable")["ok"]
    start = act.pos.copy()
    assert req(command, "so101", linear=[0.0, 1e308, 0.0], angular=[0.0, 0.0, 0.0])["ok"]
    cycle(10)
    huge = act.pos - start
    assert np.all(np.isfinite(act.pos)) and c.state is OperatingState.ENABLED
    assert _max_step_ratio(c, act, cycle, 5) <= 1.0 + 1e-6
    # the same direction as a modest twist along y
    assert req("hold", "so101")["ok"]
    cycle(200)
    act.pos[:] = start
    assert req("disable")["ok"] and req("enable")["ok"]
    assert req(command, "so101", linear=[0.0, 1.0, 0.0], angular=[0.0, 0.0, 0.0])["ok"]
    cycle(10)
    modest = act.pos - start
    cos = huge[:5] @ modest[:5] / (np.linalg.norm(huge[:5]) * np.linalg.norm(modest[:5]))
    assert cos > 0.99


# ---------------------------------------------------------------- native move_cp: is_busy never stuck
@pytest.mark.parametrize("how", ["pause", "fault", "disable"])
def test_a_native_move_interrupted_by_a_stop_or_fault_ends_busy_for_subscribers(how):
    """A running move_cp (native cartesian backend) that a pause, a fault or a disable ends must
    push is_busy false: it was pushed true in the new state and never corrected (clients waiting
    for the move's end hung)."""
    from crtk_bridge.core.actuator import Fault

    from .test_native_cartesian import POSE, FakeNativeArm

    c, act, clock, cycle, req = make_rig(FakeNativeArm(PROFILE))
    assert req("enable")["ok"]
    cycle(2)
    assert req("move_cp", "so101", **POSE)["ok"]
    cycle(3)
    assert c.is_busy
    c.outbox.clear()
    if how == "fault":
        c.on_read(act.new_feedback(), Fault("bus_timeout", "so101: no reply", transient=False))
    else:
        assert req(how)["ok"]
    cycle(5)
    pushed = [m["data"] for m in c.outbox if m.get("event") == "operating_state"]
    assert not c.is_busy
    assert pushed and pushed[-1]["is_busy"] is False, pushed


@pytest.mark.parametrize("how", ["park", "slow pause"])
def test_a_native_cartesian_stream_ends_at_once_on_park_and_on_pause(how):
    """A servo_cv stream on a native cartesian backend kept going to the backend during a
    shutdown park (the park's joint trajectory then started from a stale position) and during a
    pause transition that takes cycles (a pause must stop the motion when it is asked)."""
    from crtk_bridge.core.actuator import CartesianMode

    from .test_native_cartesian import FakeNativeArm

    class SlowPause(FakeNativeArm):
        def _pause_steps(self):
            for _ in range(5):
                yield

    c, act, clock, cycle, req = make_rig(SlowPause(PROFILE))
    assert req("enable")["ok"]
    cycle(2)
    assert req("servo_cv", "so101", linear=[0.0, 0.02, 0.0], angular=[0.0, 0.0, 0.0])["ok"]
    cycle(2)
    assert act.writes[-1][0] is CartesianMode.TWIST
    if how == "park":
        assert c.park()
    else:
        c.handle({"id": 99, "cmd": "pause", "ns": None, "data": {}})
        assert c.state is OperatingState.ENABLED and c.is_busy  # the pause transition runs
    cycle()
    assert act.writes[-1][0] is CartesianMode.NONE, f"the twist still went out after {how}"


# ---------------------------------------------------------------- huge efforts on a joint with no effort_max
@only_on("koch-dynamixel")
def test_a_huge_effort_is_limited_by_the_servo_not_a_fault(sim_daemon):
    """The Koch gripper (no effort_max in the profile) offers servo_jf. servo_jf 1e308 N*m passed
    the controller (finite, clipped to an infinite effort_max) and overflowed in the Dynamixel
    backend's conversion (round(inf)): backend_exception FAULT, torque off on the whole arm. It is
    sent as the servo's Current_Limit."""
    from crtk_bridge.client import connect
    from crtk_bridge.sim.control import control_request

    bot = sim_daemon.robot
    gid = bot.servo_id[bot.gripper_joint]
    sim = sim_daemon.sim_control_path()
    robot = connect(socket=str(sim_daemon.socket_path))
    try:
        arm, gripper = robot.device("koch"), robot.device("koch/gripper")
        assert arm.enable(5.0)
        gripper.servo_jf([1e308])
        dump = lambda: control_request(sim, {"cmd": "dump"})["servos"][str(gid)]  # noqa: E731
        wait_until(lambda: dump()["operating_mode"] == 0 and dump()["goal_current"] > 0, 3.0,
                   what="gripper in current mode with a positive Goal_Current")
        assert arm.is_enabled(), "a huge effort faulted the robot"
        gripper.servo_jf([-1e308])
        wait_until(lambda: dump()["goal_current"] < 0, 3.0, what="a negative Goal_Current")
        assert arm.is_enabled()
        assert arm.disable(5.0)
    finally:
        robot.close()


# ---------------------------------------------------------------- the wall clock steps back (NTP)
def test_a_wall_clock_step_back_does_not_disable_the_servo_watchdog(loop_rig, monkeypatch):
    """The control loop timed motion with the wall clock: when NTP stepped it back (a lab PC
    that boots before its time is synced), a servo_jv stream whose client hung was never timed
    out (the arm ran on to its limit), an interpolate_jp ran the other way at velocity_max, and a
    transition never hit its time limit. Motion is timed on a clock that never steps."""
    import time

    real, step = time.time, [0.0]
    monkeypatch.setattr(time, "time", lambda: real() + step[0])  # the wall clock, as NTP may set it
    r = loop_rig()
    assert r.request("enable")["ok"]
    assert r.request("servo_jv", "so101", velocity=[0.2, 0, 0, 0, 0])["ok"]
    step[0] = -3600.0
    wait_until(lambda: r.events("servo_timeout"), 3.0, what="the servo watchdog after the clock stepped back")
    held = r.act.pos.copy()
    cycles = r.loop._v["cycles"]
    n = int(cycles[0])
    wait_until(lambda: cycles[0] > n + 20, 2.0, what="more cycles")
    np.testing.assert_allclose(r.act.pos, held)


def test_hold_aborts_a_native_home_with_one_reply_each_and_the_busy_edge():
    from .test_transitions import HookedActuator

    c, act, clock, cycle, req = make_rig(HookedActuator(PROFILE, enable_cycles=1))
    c.handle({"id": 1, "cmd": "enable"})
    cycle(3)
    c.handle({"id": 2, "cmd": "home"})
    assert c.is_busy
    c.outbox.clear()
    assert req("hold", "so101")["ok"]  # a stop during a native home: accepted
    home_reply = [m for m in c.outbox if m.get("id") == 2]
    assert len(home_reply) == 1 and home_reply[0]["error"]["code"] == "aborted"
    steps = act.bus.count("home-step")
    cycle(5)
    assert act.bus.count("home-step") == steps  # the backend's homing steps stopped
    assert not c.is_busy and not c.is_homed
    assert [m["data"]["is_busy"] for m in c.outbox if m.get("event") == "operating_state"][-1] is False

"""The controller (state machine + motion) driven directly with a fake actuator, cycle by cycle."""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import numpy as np
import pytest

from crtk_bridge.core.actuator import Actuator, Capabilities, CommandMode, Fault, Traits, effective_period_s
from crtk_bridge.core.control import Controller
from crtk_bridge.core.cycle import CycleRunner
from crtk_bridge.core.motion import Mode
from crtk_bridge.core.state import TRANSITIONS, OperatingState, StateCommand
from crtk_bridge.errors import BackendError
from crtk_bridge.profile import load_profile

PROFILE = load_profile("profiles/so101.yaml")


class FakeActuator(Actuator):
    """A perfect position-controlled robot: measured = last commanded. Open once built (no bus);
    ``traits`` are :class:`Traits` fields beside its joints' ``CAPS``."""

    CAPS = Capabilities(position=True, measures_velocity=True)

    def __init__(self, profile, **traits):
        super().__init__(profile)
        self.torque = False
        self.pos = np.zeros(self.n)
        self.fail_enable = False
        self.calls: list[str] = []
        self._traits_kw = traits
        self.open()

    def _open_hook(self):
        pass

    def _traits_hook(self):
        return Traits(joints=(self.CAPS,) * self.n, **self._traits_kw)

    def _enable_steps(self, feedback):
        self.calls.append("enable")
        if self.fail_enable:
            raise BackendError("so101: joint 'gripper' (id 6) did not confirm Torque_Enable")
        feedback.position[:] = self.pos  # the pose it holds, from the device (not the last sample)
        self.torque = True
        yield from ()

    def _disable_steps(self):
        self.calls.append("disable")
        self.torque = False
        yield from ()

    def _close_hook(self):
        pass

    def _read(self, fb):
        fb.position[:] = self.pos
        fb.stamp = 1.0
        return None

    def _write(self, cmd):
        if self.torque:
            sel = cmd.mode == CommandMode.POSITION
            self.pos[sel] = cmd.position[sel]
        return None


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t

    def sleep(self, dt):
        self.t += dt


@pytest.fixture
def rig():
    return make_rig(FakeActuator(PROFILE))


def make_rig(act, profile=None):
    """(controller, actuator, clock, cycle(n), req(cmd, ns, **data)) around fake actuator ``act``,
    on ``profile`` (default: the test profile)."""
    clock = Clock()
    c = Controller(profile or PROFILE, act, clock, effective_period_s(profile or PROFILE, act))
    ids = itertools.count(1)
    runner = CycleRunner(act, c.dt, clock=clock, sleep=clock.sleep)  # the loop's cycle, on the fake clock

    def cycle(n=1):
        for _ in range(n):
            runner.cycle(c)

    def req(cmd, ns=None, **data):
        rid = next(ids)
        c.handle({"id": rid, "cmd": cmd, "ns": ns, "data": data})
        replies = [m for m in c.outbox if m.get("id") == rid]
        assert len(replies) == 1, "exactly one reply per request"
        return replies[0]

    cycle()
    return c, act, clock, cycle, req


def states(c):
    return [m["data"] for m in c.outbox if m.get("event") == "operating_state"]


def test_starts_disabled_and_never_enables_itself(rig):
    c, act, clock, cycle, req = rig
    cycle(50)
    assert c.state is OperatingState.DISABLED
    assert act.calls == [] and not act.torque
    assert c.is_homed  # absolute encoders: no homing needed


def _drive_to(state, c, act, cycle, req):
    if state is OperatingState.ENABLED:
        assert req("enable")["ok"]
    elif state is OperatingState.PAUSED:
        assert req("enable")["ok"] and req("pause")["ok"]
    elif state is OperatingState.FAULT:
        assert req("enable")["ok"]
        c.on_read(act.new_feedback(), Fault("bus_timeout", "so101: no reply from id 3", joint="elbow_flex", transient=False))
    assert c.state is state


@pytest.mark.parametrize("start,command", sorted(TRANSITIONS, key=lambda k: (k[0].value, k[1].value)))
def test_every_cell_of_the_transition_table(rig, start, command):
    c, act, clock, cycle, req = rig
    _drive_to(start, c, act, cycle, req)
    expected = TRANSITIONS[(start, command)]
    reply = req(command.value)
    if expected.target is None:
        assert not reply["ok"] and reply["error"]["code"] == "invalid_state"
        assert start.value in reply["error"]["message"] and command.value in reply["error"]["message"]
        assert c.state is start
    else:
        assert reply["ok"], reply
        assert c.state is expected.target
        assert reply["data"]["state"] == expected.target.value
    if command is StateCommand.UNHOME:
        assert not c.is_homed


def test_spec_table_matches_crtk_3_3():
    S = OperatingState
    spec = {  # crtk-spec 3.3, rows DISABLED / ENABLED / PAUSED / FAULT; columns enable disable pause resume
        S.DISABLED: (S.ENABLED, S.DISABLED, None, None),
        S.ENABLED: (S.ENABLED, S.DISABLED, S.PAUSED, None),
        S.PAUSED: (None, S.DISABLED, S.PAUSED, S.ENABLED),
        S.FAULT: (S.ENABLED, S.DISABLED, None, None),
    }
    cols = (StateCommand.ENABLE, StateCommand.DISABLE, StateCommand.PAUSE, StateCommand.RESUME)
    for state, row in spec.items():
        for cmd, target in zip(cols, row):
            assert TRANSITIONS[(state, cmd)].target is target, (state, cmd)
    assert TRANSITIONS[(S.FAULT, StateCommand.ENABLE)].retry and TRANSITIONS[(S.FAULT, StateCommand.DISABLE)].retry


def test_enable_holds_where_the_arm_is(rig):
    c, act, clock, cycle, req = rig
    act.pos[:] = [0.1, -0.2, 0.3, 0.0, 0.5, 0.2]
    cycle()
    assert req("enable")["ok"]
    cycle(10)
    np.testing.assert_allclose(act.pos, [0.1, -0.2, 0.3, 0.0, 0.5, 0.2])
    assert act.torque


def test_motion_refused_while_disabled_paused_or_unhomed(rig):
    c, act, clock, cycle, req = rig
    r = req("move_jp", "so101", position=[0.1] * 5)
    assert r["error"]["code"] == "invalid_state" and "DISABLED" in r["error"]["message"]
    assert req("enable")["ok"] and req("pause")["ok"]
    r = req("servo_jp", "so101", position=[0.0] * 5)
    assert r["error"]["code"] == "invalid_state" and "PAUSED" in r["error"]["message"]
    assert req("resume")["ok"] and req("unhome")["ok"]
    r = req("move_jp", "so101", position=[0.1] * 5)
    assert r["error"]["code"] == "not_homed"
    assert not any(s["is_busy"] for s in states(c))  # no busy edge for refused moves


def test_move_reaches_goal_with_busy_edges(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    c.outbox.clear()
    r = req("move_jp", "so101", position=[0.5, -0.3, 0.2, 0.1, -0.4])
    assert r["ok"] and r["data"]["busy_seq"] == 1
    # the busy=True edge precedes the reply
    first_busy = next(i for i, m in enumerate(c.outbox) if m.get("event") == "operating_state")
    assert c.outbox[first_busy]["data"]["is_busy"] and first_busy < c.outbox.index(r)
    cycle(2000)
    np.testing.assert_allclose(act.pos[:5], [0.5, -0.3, 0.2, 0.1, -0.4], atol=1e-9)
    busy = [s["is_busy"] for s in states(c)]
    assert busy == [True, False]
    goal = c.namespaces["so101"]
    assert goal.goal_stamp > 0 and goal.level is Mode.MOVE


def test_instantaneous_move_still_has_both_edges(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    c.outbox.clear()
    assert req("move_jp", "so101/gripper", position=[0.0])["ok"]
    cycle(3)
    assert [s["is_busy"] for s in states(c)] == [True, False]


def test_move_is_jerk_limited_and_respects_velocity_limit(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("move_jp", "so101", position=[1.5, 0, 0, 0, 0])["ok"]
    prev, vmax = act.pos[0], 0.0
    for _ in range(1000):
        cycle()
        vmax = max(vmax, abs(act.pos[0] - prev) / c.dt)
        prev = act.pos[0]
    assert vmax <= PROFILE.joints[0].limits.velocity_max + 1e-6
    assert vmax > 0.5 * PROFILE.joints[0].limits.velocity_max


def test_new_move_replans_mid_motion_and_move_jr_is_relative_to_goal(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("move_jp", "so101", position=[1.0, 0, 0, 0, 0])["ok"]
    cycle(40)
    mid = act.pos[0]
    assert 0 < mid < 1.0
    assert req("move_jr", "so101", position=[-0.5, 0, 0, 0, 0])["ok"]  # goal 1.0 - 0.5
    np.testing.assert_allclose(c.namespaces["so101"].goal_p[0], 0.5)
    steps = []
    for _ in range(1500):
        before = act.pos[0]
        cycle()
        steps.append(act.pos[0] - before)
    assert act.pos[0] == pytest.approx(0.5, abs=1e-9)
    # continuous: no step bigger than v_max * dt (re-planned from the current state)
    assert max(abs(s) for s in steps) <= PROFILE.joints[0].limits.velocity_max * c.dt + 1e-9


def test_move_out_of_limits_names_joint_and_limit(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    r = req("move_jp", "so101", position=[0, 0, 3.0, 0, 0])
    assert r["error"]["code"] == "out_of_limits"
    assert "elbow_flex" in r["error"]["message"] and "1.69" in r["error"]["message"]


def test_wrong_vector_length_is_bad_request(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    r = req("servo_jp", "so101", position=[0.0] * 6)
    assert r["error"]["code"] == "bad_request" and "5 values" in r["error"]["message"]


def test_servo_jp_latest_wins_step_limit_and_clipping(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    for k in range(1, 11):
        assert req("servo_jp", "so101", position=[0.01 * k, 0, 0, 0, 0])["ok"]
    cycle()
    v_max = PROFILE.joints[0].limits.velocity_max
    assert act.pos[0] == pytest.approx(v_max * c.dt)  # the latest target, followed at velocity_max
    cycle(6)
    assert act.pos[0] == pytest.approx(0.10)
    assert not c.is_busy
    r = req("servo_jp", "so101", position=[1.0, 0, 0, 0, 0])
    assert r["error"]["code"] == "step_too_large" and "shoulder_pan" in r["error"]["message"]
    # walk near the limit, then beyond: clipped with one warning
    c.outbox.clear()
    for k in range(1, 40):
        req("servo_jp", "so101/gripper", position=[min(0.1 * k, 1.9)])
        cycle(6)  # 0.1 rad in 6 cycles: within the gripper's velocity_max
    assert act.pos[5] == pytest.approx(PROFILE.joints[5].limits.position_max)
    warnings = [m for m in c.outbox if m.get("event") == "warning" and m["data"]["code"] == "limit_clipped"]
    assert len(warnings) == 1 and "gripper" in warnings[0]["data"]["message"]


def test_servo_jr_adds_to_setpoint_and_setpoint_fields(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    m = c.namespaces["so101"]
    assert m.setpoint_fields() == (False, False, False)  # no command yet: invalid
    assert req("servo_jr", "so101", position=[0.05, 0.05, 0, 0, 0])["ok"]
    assert req("servo_jr", "so101", position=[0.05, 0, 0, 0, 0])["ok"]  # adds to the first's target
    cycle(7)  # 0.1 rad at velocity_max 3 rad/s, 0.015 rad per cycle
    np.testing.assert_allclose(act.pos[:2], [0.10, 0.05])
    assert m.setpoint_fields() == (True, False, False)  # servo_jp: position only
    assert req("servo_jp", "so101", position=[0.1, 0.05, 0, 0, 0], velocity=[0.2, 0, 0, 0, 0])["ok"]
    assert m.setpoint_fields() == (True, True, False)  # with feed-forward
    assert req("move_jp", "so101", position=[0, 0, 0, 0, 0])["ok"]
    cycle()
    assert m.setpoint_fields() == (True, True, False)  # move: p(t), v(t)


def test_servo_watchdog_holds_and_warns(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("servo_jp", "so101", position=[0.1, 0, 0, 0, 0])["ok"]
    c.outbox.clear()
    cycle(int(PROFILE.safety.servo_timeout_s / c.dt) + 5)
    w = [m for m in c.outbox if m.get("event") == "warning"]
    assert [m["data"]["code"] for m in w] == ["servo_timeout"]
    assert act.pos[0] == pytest.approx(0.1)


def test_pause_decelerates_a_move_and_ends_busy(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("move_jp", "so101", position=[1.5, 0, 0, 0, 0])["ok"]
    cycle(30)
    assert c.is_busy
    c.outbox.clear()
    assert req("pause")["ok"]
    assert not c.is_busy
    positions = []
    for _ in range(300):
        cycle()
        positions.append(act.pos[0])
    assert positions[-1] == positions[-2]  # at rest
    assert positions[-1] < 1.5  # did not continue to the goal
    steps = np.diff(positions)
    assert np.all(steps >= -1e-12)  # decelerated forward, no jump back


def test_home_moves_to_home_and_sets_homed(rig):
    c, act, clock, cycle, req = rig
    act.pos[:] = [0.3, 0.3, 0.3, 0.3, 0.3, 0.3]
    cycle()
    assert req("enable")["ok"] and req("unhome")["ok"]
    assert not c.is_homed
    c.outbox.clear()
    r = req("home")
    assert r["ok"] and r["data"]["is_busy"]
    cycle(1000)
    np.testing.assert_allclose(act.pos, [j.home for j in PROFILE.joints], atol=1e-9)
    s = states(c)
    assert [x["is_busy"] for x in s] == [True, False] and s[-1]["is_homed"]


def test_fault_turns_torque_off_and_enable_retries(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    c.outbox.clear()
    for _ in range(PROFILE.safety.bus_errors_max - 1):
        c.on_read(act.new_feedback(), Fault("bus_timeout", "so101: no reply", transient=True))
    assert c.state is OperatingState.ENABLED  # transient errors are tolerated a few times
    c.on_read(act.new_feedback(), Fault("bus_timeout", "so101: joint 'elbow_flex' (id 3) did not answer", joint="elbow_flex"))
    assert c.state is OperatingState.FAULT and not act.torque
    err = [m["data"] for m in c.outbox if m.get("event") == "error"]
    assert err and err[0]["code"] == "bus_timeout" and "elbow_flex" in err[0]["message"]
    act.fail_enable = True
    r = req("enable")
    assert not r["ok"] and r["error"]["code"] == "fault" and c.state is OperatingState.FAULT
    act.fail_enable = False
    assert req("enable")["ok"] and c.state is OperatingState.ENABLED


def test_client_lost_stops_motion(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("servo_jp", "so101", position=[0.1, 0, 0, 0, 0])["ok"]
    c.outbox.clear()
    c.handle({"id": None, "cmd": "_client_lost"})
    assert any(m.get("event") == "warning" and m["data"]["code"] == "control_released" for m in c.outbox)
    assert c.namespaces["so101"].mode.name == "HOLD"


# ---------------------------------------------------------------- issue 3: every joint command


def test_supported_commands_follow_capabilities(rig):
    c, act, clock, cycle, req = rig
    cmds = c.supported_commands()
    for name in ("servo_jp", "servo_jr", "servo_jv", "interpolate_jp", "interpolate_jr", "interpolate_jv",
                 "move_jp", "move_jr", "hold", "free"):
        assert name in cmds
    assert "servo_jf" not in cmds and "interpolate_jf" not in cmds  # no effort control
    assert req("enable")["ok"]
    r = req("servo_jf", "so101", effort=[0.0] * 5)
    assert r["error"]["code"] == "unsupported" and "effort control" in r["error"]["message"]


def test_servo_jv_integrates_on_position_hardware_and_times_out(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("servo_jv", "so101", velocity=[0.5, 0, 0, 0, 0])["ok"]
    cycle(40)  # 0.2 s at 200 Hz
    assert act.pos[0] == pytest.approx(0.1, abs=1e-9)
    m = c.namespaces["so101"]
    assert m.setpoint_fields() == (True, True, False)
    assert m.goal_fields() == (False, False, False)
    c.outbox.clear()
    cycle(int(PROFILE.safety.servo_timeout_s / c.dt) + 2)
    held = act.pos[0]
    cycle(20)
    assert act.pos[0] == held  # the watchdog stopped the velocity
    assert [m["data"]["code"] for m in c.outbox if m.get("event") == "warning"] == ["servo_timeout"]


def test_servo_jv_is_clipped_to_velocity_limit(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("servo_jv", "so101", velocity=[100.0, 0, 0, 0, 0])["ok"]
    cycle(1)
    assert act.pos[0] == pytest.approx(PROFILE.joints[0].limits.velocity_max * c.dt)


def test_interpolate_jp_smooths_a_slow_stream(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    m = c.namespaces["so101"]
    steps = []
    goal = 0.0
    for k in range(20):  # 20 Hz goals on a 200 Hz loop: 10 cycles apart
        goal += 0.02
        assert req("interpolate_jp", "so101", position=[goal, 0, 0, 0, 0])["ok"]
        for _ in range(10):
            before = act.pos[0]
            cycle()
            steps.append(act.pos[0] - before)
    cycle(20)
    assert act.pos[0] == pytest.approx(goal)
    assert max(steps) < 0.02 / 2  # a goal's 0.02 rad is spread over several cycles, not one jump
    assert m.setpoint_fields() == (True, True, False)
    gp = m.goal_p[0]
    assert m.goal_fields() == (True, False, False) and gp == pytest.approx(goal)
    assert not c.is_busy
    assert m.cmd_period == pytest.approx(10 * c.dt, rel=0.1)  # the period estimate converged


def test_interpolate_jr_is_relative_to_the_last_goal(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("interpolate_jp", "so101", position=[0.1, 0, 0, 0, 0])["ok"]
    assert req("interpolate_jr", "so101", position=[0.1, 0, 0, 0, 0])["ok"]
    assert c.namespaces["so101"].goal_p[0] == pytest.approx(0.2)


def test_interpolate_jv_ramps_at_the_acceleration_limit(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    m = c.namespaces["so101"]
    assert req("interpolate_jv", "so101", velocity=[1.0, 0, 0, 0, 0])["ok"]
    cycle(1)
    assert m.setpoint_v[0] == pytest.approx(PROFILE.joints[0].limits.acceleration_max * c.dt)
    for _ in range(30):
        req("interpolate_jv", "so101", velocity=[1.0, 0, 0, 0, 0])
        cycle(2)
    assert m.setpoint_v[0] == pytest.approx(1.0)
    assert m.goal_fields() == (False, True, False)


def test_hold_stops_a_move_and_servo_resets_goal(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("move_jp", "so101", position=[1.5, 0, 0, 0, 0])["ok"]
    cycle(30)
    assert req("hold", "so101")["ok"]
    cycle(200)
    assert not c.is_busy and 0 < act.pos[0] < 1.5
    assert [s["is_busy"] for s in states(c)][-1] is False
    m = c.namespaces["so101"]
    assert req("servo_jp", "so101", position=list(m.setpoint_p))["ok"]
    assert m.goal_fields() == (False, False, False)  # no interpolate/move goal while servoing


def test_free_then_move_starts_from_where_the_hand_left_it(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("free", "so101/gripper")["ok"]
    cycle()
    assert c.command.mode[5] == CommandMode.FREE and c.command.mode[0] == CommandMode.POSITION
    assert c.namespaces["so101/gripper"].setpoint_fields() == (False, False, False)
    act.pos[5] = 0.7  # moved by hand
    cycle(3)
    assert req("move_jp", "so101/gripper", position=[0.7])["ok"]
    cycle()
    assert c.command.mode[5] == CommandMode.POSITION and act.pos[5] == pytest.approx(0.7, abs=1e-6)


def test_tracking_error_faults_naming_the_joint(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("move_jp", "so101", position=[1.5, 0, 0, 0, 0])["ok"]
    frozen = act.pos.copy()
    orig_write = act._write
    act._write = lambda cmd: None  # the joint stops following
    for _ in range(400):
        act.pos[:] = frozen
        cycle()
        if c.state is OperatingState.FAULT:
            break
    act._write = orig_write
    assert c.state is OperatingState.FAULT and not act.torque
    err = [m["data"] for m in c.outbox if m.get("event") == "error"][-1]
    assert err["code"] == "tracking_error" and err["joint"] == "shoulder_pan" and err["value"] > 0.6


def test_servo_error_fault_carries_register_and_value(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    c.on_read(act.new_feedback(), Fault("servo_error", "so101: joint 'gripper' (id 6) reports overload (Status=0x20)",
                                        joint="gripper", register="Status", value=0x20, transient=False))
    err = [m["data"] for m in c.outbox if m.get("event") == "error"][-1]
    assert (err["code"], err["joint"], err["register"], err["value"]) == ("servo_error", "gripper", "Status", 0x20)
    assert c.state is OperatingState.FAULT


# ---------------------------------------------------------------- review findings (second reader)


def test_enable_holds_the_fresh_position_not_a_stale_sample(rig):
    c, act, clock, cycle, req = rig
    act.pos[:] = 0.0
    cycle()  # the controller's sample: all zeros
    act.pos[1] = -0.5  # the shoulder sags after that sample, before enable is handled
    assert req("enable")["ok"]
    cycle(5)
    assert act.pos[1] == pytest.approx(-0.5)  # not driven back to the stale 0.0


def test_enable_outside_limits_holds_instead_of_snapping_to_the_limit(rig):
    c, act, clock, cycle, req = rig
    act.pos[4] = -3.1  # wrist_roll turned by hand beyond its -2.744 limit
    cycle()
    assert req("enable")["ok"]
    cycle(5)
    assert act.pos[4] == pytest.approx(-3.1)
    # a move brings it back inside, from where it is
    assert req("move_jp", "so101", position=[0, 0, 0, 0, -2.0])["ok"]
    cycle(1000)
    assert act.pos[4] == pytest.approx(-2.0)


def test_refused_command_leaves_free_joints_free(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("free", "so101")["ok"]
    cycle()
    r = req("move_jp", "so101", position=[0, 0, 3.0, 0, 0])  # out of limits
    assert r["error"]["code"] == "out_of_limits"
    cycle()
    assert c.namespaces["so101"].mode is Mode.FREE
    assert all(c.command.mode[:5] == CommandMode.FREE)


def test_write_faults_count_even_between_good_reads(rig):
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    orig = act._write
    act._write = lambda cmd: Fault("bus_timeout", "so101: sync write failed", transient=True)
    cycle(PROFILE.safety.bus_errors_max)
    act._write = orig
    assert c.state is OperatingState.FAULT


class VelocityActuator(FakeActuator):
    """Native velocity control: the joint integrates the velocity command itself."""

    CAPS = Capabilities(position=True, velocity=True, measures_velocity=True)

    def _write(self, cmd):
        if self.torque:
            for i, mode in enumerate(cmd.mode):
                if mode == CommandMode.VELOCITY:
                    self.pos[i] += cmd.velocity[i] * (1 / 200)
                elif mode == CommandMode.POSITION:
                    self.pos[i] = cmd.position[i]
        return None


def test_native_velocity_stops_at_the_position_limit():
    c, act, clock, cycle, req = make_rig(VelocityActuator(PROFILE))
    c.handle({"id": 1, "cmd": "enable"})
    for _ in range(600):  # 3 s of servo_jv at 2 rad/s toward a 1.92 rad limit
        c.handle({"id": 2, "cmd": "servo_jv", "ns": "so101", "data": {"velocity": [2.0, 0, 0, 0, 0]}})
        cycle()
    limit = PROFILE.joints[0].limits.position_max
    assert act.pos[0] <= limit + 0.02 and act.pos[0] > limit - 0.1
    assert c.state is OperatingState.ENABLED


def test_pause_stops_an_effort_stream():
    class EffortActuator(FakeActuator):
        CAPS = Capabilities(position=True, effort=True, measures_velocity=True)

    c, act, clock, cycle, req = make_rig(EffortActuator(PROFILE))  # its first cycle read
    c.handle({"id": 1, "cmd": "enable"})
    c.handle({"id": 2, "cmd": "servo_jf", "ns": "so101", "data": {"effort": [0.5, 0, 0, 0, 0]}})
    c.step()
    assert c.command.mode[0] == CommandMode.EFFORT
    c.handle({"id": 3, "cmd": "pause"})
    c.step()
    assert c.command.mode[0] == CommandMode.POSITION  # holding, not pushing


class CheckingActuator(FakeActuator):
    """A device that checks move goals against its own limits over a few cycles (as a UR asks its
    controller), refusing any joint beyond 1 rad."""

    def goal_check_steps(self, ns, cmd, goal):
        def steps():
            for _ in range(3):
                yield
            if np.any(np.abs(goal) > 1.0):
                from crtk_bridge.errors import CommandError

                raise CommandError("out_of_limits", f"{ns}: goal beyond the device's own limit")
        return steps()


def test_a_move_waiting_on_the_devices_goal_check_has_one_busy_seq_and_one_edge_each_way():
    c, act, clock, cycle, req = make_rig(CheckingActuator(PROFILE, goal_check=True))
    assert req("enable")["ok"]
    c.outbox.clear()
    seq0 = c.busy_seq

    def move(rid, position):
        c.handle({"id": rid, "cmd": "move_jp", "ns": "so101", "data": {"position": position}})
        for _ in range(20):
            replies = [m for m in c.outbox if m.get("id") == rid]
            if replies:
                return replies[0]
            cycle()
        raise AssertionError("no reply")

    r = move(101, [0.5, -0.3, 0.2, 0.1, -0.4])
    assert r["ok"] and r["data"]["busy_seq"] == seq0 + 1  # the check and the move: one busy_seq
    cycle(2000)
    np.testing.assert_allclose(act.pos[:5], [0.5, -0.3, 0.2, 0.1, -0.4], atol=1e-9)
    assert [(s["is_busy"], s["busy_seq"]) for s in states(c)] == [(True, seq0 + 1), (False, seq0 + 1)]
    # a goal the device refuses: its own edges, and the next move a new busy_seq
    c.outbox.clear()
    r = move(102, [1.5, 0, 0, 0, 0])
    assert not r["ok"] and r["error"]["code"] == "out_of_limits"
    assert [(s["is_busy"], s["busy_seq"]) for s in states(c)] == [(True, seq0 + 2), (False, seq0 + 2)]
    c.outbox.clear()
    r = move(103, [0.0, 0, 0, 0, 0])
    assert r["ok"] and r["data"]["busy_seq"] == seq0 + 3
    cycle(2000)
    assert [(s["is_busy"], s["busy_seq"]) for s in states(c)] == [(True, seq0 + 3), (False, seq0 + 3)]


# ---------------------------------------------------------------- the controller's public API
_ROOT = Path(__file__).resolve().parents[1]
#: receivers that name a controller outside its package (the loop's ``c``, ``self.controller``...)
_RECEIVER = r"\b(?:c|ctl|controller|self\.c|self\.controller|rig\.c|loop\.controller)"


def _private_controller_uses(text: str, private: set[str]) -> list[str]:
    return [m for m in re.findall(_RECEIVER + r"\.(_[a-z]\w*)\b", text) if m in private]


def _controller_private_names(c: Controller) -> set[str]:
    names = {k for k in vars(c) if k.startswith("_") and not k.startswith("__")}
    for cls in type(c).__mro__:
        names |= {k for k in vars(cls) if k.startswith("_") and not k.startswith("__")}
    return names


def test_no_private_controller_attribute_is_used_outside_its_package(rig):
    """The loop, the benches and the tests use the controller through its public API only
    (event, push_state, enter_fault, measured_valid, torque_switched_off...): its privates may
    move between the modules of core/control/ without anyone outside noticing."""
    c = rig[0]
    private = _controller_private_names(c)
    assert {"_consecutive_bus_errors", "_abort_motion", "_running"} <= private  # the scan knows them
    package = _ROOT / "crtk_bridge" / "core" / "control"
    found = []
    for top in ("crtk_bridge", "clients", "tests", "bench"):
        for path in sorted((_ROOT / top).rglob("*.py")):
            if package in path.parents:
                continue
            found += [f"{path.relative_to(_ROOT)}: {name}"
                      for name in _private_controller_uses(path.read_text(), private)]
    assert found == []
    # the scan does find such a use (the loop before the controller had a public API)
    old_loop = "stamp if c" "._consecutive_bus_errors < m else 0.0\n        self.controller" "._abort_motion()"
    assert _private_controller_uses(old_loop, private) == ["_consecutive_bus_errors", "_abort_motion"]


def test_period_s_is_required():
    with pytest.raises(TypeError):
        Controller(PROFILE, FakeActuator(PROFILE), Clock())  # type: ignore[call-arg]

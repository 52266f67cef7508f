"""End to end, velocity bounds (issue 9, defect 1) on each simulated robot: what reaches the device's
goal (a servo's Goal_Position register, a drive's target, a UR controller's servo target; the
conformance row's ``goal`` hook, in device units) never moves faster than the joint's
velocity_max, whatever the client sends (an absurd servo_jp feed-forward followed by
interpolate_jv, servo_jp steps at the servo_step_max)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from crtk_bridge.client import connect
from crtk_bridge.profile import load_profile

from .conftest import wait_until

pytestmark = pytest.mark.requires("arm")  # every simulated arm (goal registers in rad-sized steps)


def goal_samples(bot, sim, sid: int, seconds: float, until=None) -> list[tuple[float, float, int]]:
    """(sent, answered, goal) of one device, as fast as the control socket answers, for
    ``seconds`` (or, with ``until``, until ``until(value)`` holds, within 5 s): the goal was
    read somewhere between ``sent`` and ``answered``."""
    out = []
    end = time.monotonic() + (5.0 if until else seconds)
    while time.monotonic() < end and not (until and out and until(out[-1][2])):
        t0 = time.monotonic()
        value = bot.row.goal(sim, sid)
        out.append((t0, time.monotonic(), value))
    return out


def travel_rate(samples, g_from: int, g_to: int, units_per_rad: float) -> tuple[float, int]:
    """Average speed (rad/s) of the goal register from its last sample at ``g_from`` to its first
    at ``g_to``, over the longest time that can separate those two reads, and how many distinct
    values it took on the way. A simulator thread stalled at the start of the motion (a loaded
    host) can only shorten the apparent time by the stall, hence the tests' generous factor."""
    i_from = max(i for i, (_, _, g) in enumerate(samples) if g == g_from)
    i_to = min(i for i, (_, _, g) in enumerate(samples) if g == g_to and i > i_from)
    elapsed = samples[i_to][1] - samples[i_from][0]
    between = {g for _, _, g in samples[i_from + 1:i_to]}
    return abs(g_to - g_from) / units_per_rad / elapsed, len(between)


def test_goal_register_never_moves_faster_than_velocity_max(sim_daemon):
    bot = sim_daemon.robot
    profile = load_profile(bot.profile)
    sim = bot.sim(sim_daemon.sim_control_path())
    robot = connect(socket=str(sim_daemon.socket_path))
    try:
        arm = robot.device(bot.arm)
        assert arm.enable(5.0)
        roll = bot.j(4)  # wrist_roll on the five-joint arms
        name = bot.joint_names[roll]
        v_max = profile.joints[profile.joint_index(name)].limits.velocity_max
        sid = int(bot.arm_ids[roll])
        units = bot.counts_per_rad[str(sid)]  # device units per rad, signed by the joint's direction
        per_rad = abs(units)
        tol = 2 * max(1.0, per_rad * 2 * math.pi / 4096)  # two ticks of a 4096-tick servo, or two units
        p0 = arm.measured_jp()[0]

        # the reproduction: a 1e6 rad/s feed-forward on wrist_roll (velocity_max 4), then
        # interpolate_jv of zeros. Before the fix the ramp started at the feed-forward and the goal
        # jumped to the joint limit in one cycle; now nothing moves: the setpoint stood still
        arm.servo_jp(p0, bot.vec((roll, 1e6)))
        sp_v = arm.setpoint_jv()[0]
        assert abs(sp_v[roll]) <= v_max
        g0 = bot.row.goal(sim, sid)
        for _ in range(10):
            arm.interpolate_jv([0.0] * bot.n)
        samples = goal_samples(bot, sim, sid, 0.4)
        assert all(abs(g - g0) <= tol for _, _, g in samples), (g0, [g for _, _, g in samples])
        assert abs(arm.measured_jp()[0][roll] - p0[roll]) < 0.02

        # servo_jp steps just under safety.servo_step_max, back and forth: the goal register
        # travels at velocity_max, never in one jump
        step = 0.9 * profile.safety.servo_step_max
        base = arm.measured_jp()[0]  # (koch: interpolate_jv ran in native velocity mode, no p setpoint)
        arm.servo_jp(base)
        wait_until(lambda: arm.setpoint_jp()[1] > 0 and np.allclose(arm.setpoint_jp()[0], base), 2,
                   what="setpoint at the measured position")
        for sign in (1, -1, 1):
            g_from = bot.row.goal(sim, sid)
            target = base + bot.vec((roll, sign * step))
            t_cmd = time.monotonic()  # the goal cannot change before the command is sent
            arm.servo_jp(target)
            expected = g_from + sign * step * units
            samples = goal_samples(bot, sim, sid, 0.0, until=lambda g: abs(g - expected) <= tol)
            g_to = samples[-1][2]
            assert abs(g_to - expected) <= tol, (g_from, g_to, expected)  # it got there
            rate, intermediate = travel_rate([(t_cmd, t_cmd, g_from)] + samples, g_from, g_to, per_rad)
            # step / velocity_max: 79 ms of travel on wrist_roll (16 cycles): never one jump
            assert rate < 2 * v_max and intermediate >= 4, (rate, intermediate)
            base = target
        wait_until(lambda: abs(arm.measured_jp()[0][roll] - base[roll]) < 0.02, 3, what="wrist_roll at target")
        assert arm.is_enabled()  # followed within the tracking bound, no fault
        np.testing.assert_allclose(arm.setpoint_jp()[0], base, atol=1e-9)
    finally:
        robot.close()

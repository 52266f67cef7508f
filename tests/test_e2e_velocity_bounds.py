"""End to end, velocity bounds (issue 9, defect 1) on each simulated robot: what reaches the servos'
Goal_Position registers never moves faster than the joint's velocity_max, whatever the client
sends (an absurd servo_jp feed-forward followed by interpolate_jv, servo_jp steps at the
servo_step_max)."""

from __future__ import annotations

import math
import time

import numpy as np

from crtk_bridge.client import connect
from crtk_bridge.profile import load_profile
from crtk_bridge.sim.control import control_request

from .conftest import wait_until

RAD_PER_TICK = 2 * math.pi / 4096  # both robots' servos
DT = 1.0 / 200  # both profiles' loop period


def goal_samples(sim: str, sid: int, seconds: float, until=None) -> list[tuple[float, float, int]]:
    """(sent, answered, Goal_Position) of one servo, as fast as the control socket answers, for
    ``seconds`` (or, with ``until``, until ``until(value)`` holds, within 5 s): the register was
    read somewhere between ``sent`` and ``answered``."""
    out = []
    end = time.monotonic() + (5.0 if until else seconds)
    while time.monotonic() < end and not (until and out and until(out[-1][2])):
        t0 = time.monotonic()
        reply = control_request(sim, {"cmd": "read", "id": sid, "register": "Goal_Position"})
        out.append((t0, time.monotonic(), reply["value"]))
    return out


def travel_rate(samples, g_from: int, g_to: int) -> tuple[float, int]:
    """Average speed (rad/s) of the goal register from its last sample at ``g_from`` to its first
    at ``g_to``, over the longest time that can separate those two reads, and how many distinct
    values it took on the way. A simulator thread stalled at the start of the motion (a loaded
    host) can only shorten the apparent time by the stall, hence the tests' generous factor."""
    i_from = max(i for i, (_, _, g) in enumerate(samples) if g == g_from)
    i_to = min(i for i, (_, _, g) in enumerate(samples) if g == g_to and i > i_from)
    elapsed = samples[i_to][1] - samples[i_from][0]
    between = {g for _, _, g in samples[i_from + 1:i_to]}
    return abs(g_to - g_from) * RAD_PER_TICK / elapsed, len(between)


def test_goal_register_never_moves_faster_than_velocity_max(sim_daemon):
    bot = sim_daemon.robot
    profile = load_profile(bot.profile)
    v_max = {j.name: j.limits.velocity_max for j in profile.joints}
    sim = sim_daemon.sim_control_path()
    robot = connect(socket=str(sim_daemon.socket_path))
    try:
        arm = robot.device(bot.arm)
        assert arm.enable(5.0)
        roll = bot.joint_names.index("wrist_roll")
        sid = bot.servo_id["wrist_roll"]
        p0 = arm.measured_jp()[0]

        # the reproduction: a 1e6 rad/s feed-forward on wrist_roll (velocity_max 4), then
        # interpolate_jv of zeros. Before the fix the ramp started at the feed-forward and the goal
        # jumped to the joint limit in one cycle; now nothing moves: the setpoint stood still
        arm.servo_jp(p0, bot.vec(wrist_roll=1e6))
        sp_v = arm.setpoint_jv()[0]
        assert abs(sp_v[roll]) <= v_max["wrist_roll"]
        g0 = control_request(sim, {"cmd": "read", "id": sid, "register": "Goal_Position"})["value"]
        for _ in range(10):
            arm.interpolate_jv([0.0] * bot.n)
        samples = goal_samples(sim, sid, 0.4)
        assert all(abs(g - g0) <= 2 for _, _, g in samples), (g0, [g for _, _, g in samples])
        assert abs(arm.measured_jp()[0][roll] - p0[roll]) < 0.02

        # servo_jp steps just under safety.servo_step_max, back and forth: the goal register
        # travels at velocity_max, never in one jump
        step = 0.9 * profile.safety.servo_step_max
        base = arm.measured_jp()[0]  # (koch: interpolate_jv ran in native velocity mode, no p setpoint)
        arm.servo_jp(base)
        wait_until(lambda: arm.setpoint_jp()[1] > 0 and np.allclose(arm.setpoint_jp()[0], base), 2,
                   what="setpoint at the measured position")
        for sign in (1, -1, 1):
            g_from = control_request(sim, {"cmd": "read", "id": sid, "register": "Goal_Position"})["value"]
            target = base + bot.vec(wrist_roll=sign * step)
            t_cmd = time.monotonic()  # the goal cannot change before the command is sent
            arm.servo_jp(target)
            expected = g_from + sign * step / RAD_PER_TICK
            samples = goal_samples(sim, sid, 0.0, until=lambda g: abs(g - expected) <= 2)
            g_to = samples[-1][2]
            assert abs(g_to - expected) <= 2, (g_from, g_to, expected)  # it got there
            rate, intermediate = travel_rate([(t_cmd, t_cmd, g_from)] + samples, g_from, g_to)
            # step / velocity_max = 79 ms of travel (16 cycles): never one jump
            assert rate < 2 * v_max["wrist_roll"] and intermediate >= 4, (rate, intermediate)
            base = target
        wait_until(lambda: abs(arm.measured_jp()[0][roll] - base[roll]) < 0.02, 3, what="wrist_roll at target")
        assert arm.is_enabled()  # followed within the tracking bound, no fault
        np.testing.assert_allclose(arm.setpoint_jp()[0], base, atol=1e-9)
    finally:
        robot.close()

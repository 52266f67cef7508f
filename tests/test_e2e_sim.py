"""End to end: the daemon as a real subprocess on each simulated robot (SO-101 on Feetech, Koch on
Dynamixel, the CANopen pan / tilt unit), driven through the client; the devices inspected through
the simulator's control socket with the conformance rows' hooks (tests/conftest.py RemoteSim)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from crtk_bridge.client import CommandError, connect

from .conftest import DaemonProcess, RawSession, standalone_sim, wait_until

pytestmark = pytest.mark.requires("arm")  # every simulated arm (it checks measured velocity, rad goals)

TOL = 0.02  # rad: sim servo quantisation is 2*pi/4096 = 0.0015 rad; first-order lag settles well inside this


def test_daemon_end_to_end_on_a_simulated_robot(sim_daemon):
    bot = sim_daemon.robot
    robot = connect(socket=str(sim_daemon.socket_path))
    raw = RawSession(str(sim_daemon.socket_path))
    try:
        arm = robot.device(bot.arm)
        assert arm.joint_names == list(bot.joint_names)
        if bot.gripper is not None:
            gripper = arm.gripper
            assert gripper.name == bot.gripper

        # starts DISABLED and refuses motion
        assert arm.operating_state() == "DISABLED" and arm.is_disabled()
        with pytest.raises(CommandError) as err:
            arm.move_jp(bot.goals["small"])
        assert err.value.code == "invalid_state" and "DISABLED" in str(err.value)
        with pytest.raises(CommandError):
            arm.servo_jp([0.0] * bot.n)
        sim = bot.sim(sim_daemon.sim_control_path())
        assert sorted(sim.devices()) == sorted(bot.servo_ids)
        assert not any(bot.torque(sim).values())

        # enable, home
        assert arm.enable(5.0) and arm.is_enabled()
        assert all(bot.torque(sim).values())
        assert arm.home(30.0) and arm.is_homed() and not arm.is_busy()

        # move_jp reaches the goal; both busy edges seen by a raw session
        wait_until(lambda: raw.states and raw.states[-1]["busy_seq"] == arm.operating_state_full()["busy_seq"]
                   and not raw.states[-1]["is_busy"], 5, what="raw session caught up with the home edges")
        edges_before = len(raw.states)
        goal = bot.goals["small"]
        handle = arm.move_jp(goal)
        assert handle.wait(timeout=15.0)
        wait_until(lambda: np.allclose(arm.measured_jp()[0], goal, atol=TOL), 5, what="measured position at the goal")
        pos, vel, eff, ts = arm.measured_js()
        assert ts > 0 and len(pos) == bot.n and len(vel) == bot.n
        gp, gts = arm.goal_jp()
        assert gts > 0 and np.allclose(gp, goal)
        wait_until(lambda: raw.busy_edges()[-2:] == [True, False] and len(raw.states) > edges_before, 5,
                   what="busy true/false edges")
        new = [s["is_busy"] for s in raw.states[edges_before:]]
        assert new[0] is True and new[-1] is False

        if bot.gripper is not None:  # its own namespace sharing the operating state
            assert gripper.move_jp([0.5]).wait(timeout=10.0)
            wait_until(lambda: abs(gripper.measured_jp()[0][0] - 0.5) < TOL, 5, what="gripper at 0.5")

        # servo_jp stream: a ramp at ~100 Hz; is_busy stays false; the arm follows
        seq_before = raw.states[-1]["busy_seq"]
        start = arm.setpoint_jp()[0]
        for k in range(1, 61):
            arm.servo_jp(start + bot.vec((0, 0.005 * k)))
            time.sleep(0.01)  # paces the stream at ~100 Hz (not a wait for a result)
            assert not arm.is_busy()
        target = start + bot.vec((0, 0.3))
        wait_until(lambda: np.allclose(arm.measured_jp()[0], target, atol=TOL), 5, what="servo stream followed")
        sp, sts = arm.setpoint_jp()
        assert sts > 0 and np.allclose(sp, target)
        assert raw.states[-1]["busy_seq"] == seq_before  # servo raised no busy edge

        # out-of-limit goal refused with joint named
        with pytest.raises(CommandError) as err:
            arm.move_jp(bot.vec((bot.j(2), bot.pos_max[bot.j(2)] + 1.0)))
        assert err.value.code == "out_of_limits" and bot.joint_names[bot.j(2)] in str(err.value)

        # disable: torque off everywhere
        assert arm.disable(5.0) and arm.is_disabled()
        assert not any(bot.torque(sim).values())
    finally:
        raw.close()
        robot.close()
    assert sim_daemon.terminate() == 0
    assert not sim_daemon.socket_path.exists()


def test_second_session_is_read_only_while_first_holds_control(sim_daemon):
    ns = sim_daemon.robot.arm
    a = connect(socket=str(sim_daemon.socket_path))
    b = connect(socket=str(sim_daemon.socket_path))
    try:
        assert a.device(ns).enable(5.0)
        with pytest.raises(CommandError) as err:
            b.device(ns).move_jr([0.0] * sim_daemon.robot.n)
        assert err.value.code == "read_only"
        pos, ts = b.device(ns).measured_jp()  # queries stay open to everyone
        assert ts > 0
        assert b.device(ns).disable(5.0)  # but a stop is never refused (docs/protocol.md, Control)
        a.close()

        def enabled_by_b():
            try:
                return b.device(ns).enable(1.0)
            except CommandError as exc:
                assert exc.code == "read_only"
                return False

        assert wait_until(enabled_by_b, 5, what="control freed on disconnect")
        assert b.device(ns).disable(5.0)
    finally:
        a.close()
        b.close()


def test_sigterm_mid_motion_turns_torque_off(short_tmp, sim_robot):
    """Standalone simulator (crtk-sim <device>) + daemon on a profile wired to it."""
    bot = sim_robot
    with standalone_sim(bot, short_tmp) as (profile, sim):
        daemon = DaemonProcess(["--profile", str(profile), "--no-realtime"], short_tmp / "d.sock", short_tmp / "d.log")
        try:
            robot = connect(socket=str(daemon.socket_path))
            arm = robot.device(bot.arm)
            assert arm.enable(5.0)
            arm.move_jp(bot.goals["wide"])
            pan = int(bot.arm_ids[0])
            start = bot.row.present(sim, pan)
            wait_until(lambda: bot.row.present(sim, pan) != start, 5, what="arm moving in the simulator")
            status = daemon.terminate()
            robot.close()
            assert status == 0, daemon.output()
            assert not daemon.socket_path.exists()
            assert daemon.output().count("realtime_unavailable") == 1  # said once, ran anyway
            assert sorted(sim.devices()) == sorted(bot.servo_ids)
            torque = bot.torque(sim)
            assert not any(torque.values()), torque
        finally:
            daemon.stop()

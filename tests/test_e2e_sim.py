"""End to end: the daemon as a real subprocess on the simulated SO-101, driven through the client."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from crtk_bridge.client import CommandError, connect
from crtk_bridge.sim.control import control_request

from .conftest import SO101, so101_data, DaemonProcess, RawSession, wait_until

TOL = 0.02  # rad: sim servo quantisation is 2*pi/4096 = 0.0015 rad; first-order lag settles well inside this


def test_daemon_end_to_end_on_simulated_so101(sim_daemon):
    robot = connect(socket=str(sim_daemon.socket_path))
    raw = RawSession(str(sim_daemon.socket_path))
    try:
        arm = robot.device("so101")
        gripper = arm.gripper
        assert arm.joint_names == ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]
        assert gripper.name == "so101/gripper"

        # starts DISABLED and refuses motion
        assert arm.operating_state() == "DISABLED" and arm.is_disabled()
        with pytest.raises(CommandError) as err:
            arm.move_jp([0.1, 0.2, 0.3, 0.0, 0.0])
        assert err.value.code == "invalid_state" and "DISABLED" in str(err.value)
        with pytest.raises(CommandError):
            arm.servo_jp([0.0] * 5)
        sim = sim_daemon.sim_control_path()
        dump = control_request(sim, {"cmd": "dump"})
        assert all(s["torque_enable"] == 0 for s in dump["servos"].values())

        # enable, home
        assert arm.enable(5.0) and arm.is_enabled()
        dump = control_request(sim, {"cmd": "dump"})
        assert all(s["torque_enable"] == 1 for s in dump["servos"].values())
        assert arm.home(30.0) and arm.is_homed() and not arm.is_busy()

        # move_jp reaches the goal; both busy edges seen by a raw session
        wait_until(lambda: raw.states and raw.states[-1]["busy_seq"] == arm.operating_state_full()["busy_seq"]
                   and not raw.states[-1]["is_busy"], 5, what="raw session caught up with the home edges")
        edges_before = len(raw.states)
        goal = np.array([0.1, 0.2, 0.3, 0.0, 0.0])
        handle = arm.move_jp(goal)
        assert handle.wait(timeout=15.0)
        wait_until(lambda: np.allclose(arm.measured_jp()[0], goal, atol=TOL), 5, what="measured position at the goal")
        pos, vel, eff, ts = arm.measured_js()
        assert ts > 0 and len(pos) == 5 and len(vel) == 5
        gp, gts = arm.goal_jp()
        assert gts > 0 and np.allclose(gp, goal)
        wait_until(lambda: raw.busy_edges()[-2:] == [True, False] and len(raw.states) > edges_before, 5,
                   what="busy true/false edges")
        new = [s["is_busy"] for s in raw.states[edges_before:]]
        assert new[0] is True and new[-1] is False

        # gripper is its own namespace sharing the operating state
        assert gripper.move_jp([0.5]).wait(timeout=10.0)
        wait_until(lambda: abs(gripper.measured_jp()[0][0] - 0.5) < TOL, 5, what="gripper at 0.5")

        # servo_jp stream: a ramp at ~100 Hz; is_busy stays false; the arm follows
        seq_before = raw.states[-1]["busy_seq"]
        start = arm.setpoint_jp()[0]
        for k in range(1, 61):
            arm.servo_jp(start + np.array([0.005 * k, 0, 0, 0, 0]))
            time.sleep(0.01)  # paces the stream at ~100 Hz (not a wait for a result)
            assert not arm.is_busy()
        target = start + np.array([0.3, 0, 0, 0, 0])
        wait_until(lambda: np.allclose(arm.measured_jp()[0], target, atol=TOL), 5, what="servo stream followed")
        sp, sts = arm.setpoint_jp()
        assert sts > 0 and np.allclose(sp, target)
        assert raw.states[-1]["busy_seq"] == seq_before  # servo raised no busy edge

        # out-of-limit goal refused with joint named
        with pytest.raises(CommandError) as err:
            arm.move_jp([0.0, 0.0, 3.0, 0.0, 0.0])
        assert err.value.code == "out_of_limits" and "elbow_flex" in str(err.value)

        # disable: torque off everywhere
        assert arm.disable(5.0) and arm.is_disabled()
        dump = control_request(sim, {"cmd": "dump"})
        assert all(s["torque_enable"] == 0 for s in dump["servos"].values())
    finally:
        raw.close()
        robot.close()
    assert sim_daemon.terminate() == 0
    assert not sim_daemon.socket_path.exists()


def test_second_session_is_read_only_while_first_holds_control(sim_daemon):
    a = connect(socket=str(sim_daemon.socket_path))
    b = connect(socket=str(sim_daemon.socket_path))
    try:
        assert a.device("so101").enable(5.0)
        with pytest.raises(CommandError) as err:
            b.device("so101").disable()
        assert err.value.code == "read_only"
        pos, ts = b.device("so101").measured_jp()  # queries stay open to everyone
        assert ts > 0
        a.close()
        assert wait_until(lambda: b.device("so101").disable(1.0), 5, what="control freed on disconnect")
    finally:
        a.close()
        b.close()


def test_sigterm_mid_motion_turns_torque_off(short_tmp):
    """Standalone simulator + daemon on a profile whose port is the simulator's link."""
    link, control = short_tmp / "tty", short_tmp / "sim.sock"
    sim = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", "feetech", "--profile", str(SO101),
                            "--link", str(link), "--control", str(control)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        wait_until(lambda: link.exists() and control.exists() or sim.poll() is not None, 15, what="simulator link")
        assert sim.poll() is None, sim.stderr.read().decode()
        data = so101_data()
        data["backend"]["port"] = str(link)
        profile = short_tmp / "so101-sim.yaml"
        profile.write_text(yaml.safe_dump(data))
        daemon = DaemonProcess(["--profile", str(profile), "--no-realtime"], short_tmp / "d.sock", short_tmp / "d.log")
        try:
            robot = connect(socket=str(daemon.socket_path))
            arm = robot.device("so101")
            assert arm.enable(5.0)
            arm.move_jp([1.2, -1.0, 1.0, 0.5, 1.5])
            wait_until(lambda: control_request(str(control), {"cmd": "dump"})["servos"]["1"]["present_velocity"] != 0,
                       5, what="arm moving in the simulator")
            status = daemon.terminate()
            robot.close()
            assert status == 0, daemon.output()
            assert not daemon.socket_path.exists()
            assert daemon.output().count("realtime_unavailable") == 1  # said once, ran anyway
            servos = control_request(str(control), {"cmd": "dump"})["servos"]
            assert len(servos) == 6 and all(s["torque_enable"] == 0 for s in servos.values()), servos
        finally:
            daemon.stop()
    finally:
        sim.terminate()
        sim.wait(10)

"""End to end on a UR: ``crtk-bridge --profile profiles/ur5e.yaml --sim`` (the daemon starts the UR
controller simulator on a free 127.0.0.N and points backend.host at it), driven through the
socket with the Python client, checked on what the simulated controller reports over its
control socket. One daemon serves the module."""

from __future__ import annotations

import numpy as np
import pytest

from crtk_bridge.client import connect
from crtk_bridge.sim.control import control_request

from .conftest import ROOT, DaemonProcess, wait_until

UR5E = ROOT / "profiles" / "ur5e.yaml"
READY = [0.0, -1.57, 1.57, -1.57, -1.57, 0.0]


@pytest.fixture(scope="module")
def daemon():
    import shutil
    import tempfile
    from pathlib import Path

    d = Path(tempfile.mkdtemp(prefix="crtk-"))
    proc = DaemonProcess(["--profile", str(UR5E), "--sim"], d / "ur.sock", d / "daemon.log")
    yield proc
    proc.stop()
    shutil.rmtree(d, ignore_errors=True)


def sim_state(daemon) -> dict:
    return control_request(daemon.sim_control_path(), {"cmd": "state"})


def test_ur_through_the_socket(daemon):
    robot = connect(socket=str(daemon.socket_path))
    try:
        arm = robot.device("ur5e")
        info = arm.list()
        # native cartesian commands and the TCP wrench are offered; effort commands are not
        assert {"servo_cp", "move_cp", "servo_cv", "servo_jv", "free"} <= set(info["commands"])
        assert "servo_jf" not in info["commands"] and "measured_cf" in info["queries"]
        assert sim_state(daemon)["robot_mode"] == "POWER_OFF"
        assert arm.enable(10.0)
        st = sim_state(daemon)
        assert st["robot_mode"] == "RUNNING" and st["runtime_state"] == "PLAYING"
        assert arm.move_jp(READY).wait(timeout=15)
        # the speed slider reaches clients in operating_state
        assert arm.operating_state_full()["target_speed_fraction"] == pytest.approx(1.0)
        control_request(daemon.sim_control_path(), {"cmd": "speed_slider", "fraction": 0.5})
        wait_until(lambda: arm.operating_state_full().get("target_speed_fraction") == pytest.approx(0.5), 3,
                   what="target_speed_fraction 0.5 in operating_state")
        control_request(daemon.sim_control_path(), {"cmd": "speed_slider", "fraction": 1.0})
        # servo_jp over the socket, tracked by the arm
        q = np.array(arm.measured_jp()[0])
        for k in range(1, 51):
            arm.servo_jp(list(q + np.array([0, 0, 0, 0, 0, 0.004 * k])))
        goal = q + np.array([0, 0, 0, 0, 0, 0.2])
        wait_until(lambda: np.allclose(sim_state(daemon)["q"], goal, atol=2e-3), 5, what="the arm at the target")
        # measured_cp is the controller's TCP pose, measured_cf its TCP wrench (base frame)
        control_request(daemon.sim_control_path(), {"cmd": "wrench", "force": [5.0, 0.0, -2.0, 0.0, 0.3, 0.0]})
        wait_until(lambda: np.allclose(robot.connection.request("measured_cf", "ur5e")["force"], [5.0, 0.0, -2.0]),
                   3, what="measured_cf")
        cp = robot.connection.request("measured_cp", "ur5e")
        assert cp["frame_id"] == "base" and cp["child_frame_id"] == "tool0"
        np.testing.assert_allclose(cp["position"], sim_state(daemon)["tcp_pose"][:3], atol=1e-3)
        # the controller's packets pace the loop: one period of 2 ms
        assert robot.connection.request("period_statistics")["period_s"] == pytest.approx(0.002)
        assert arm.disable(10.0)
        assert sim_state(daemon)["robot_mode"] == "POWER_OFF"
    finally:
        robot.close()

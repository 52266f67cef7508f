"""End to end, robots on buses of different kinds (issue 19 item 7), with ``--sim`` starting one
simulator per bus: a UR5e with a Dynamixel XL330 gripper (the CRTK spec's ``/UR`` +
``/UR/gripper``), and a CiA 402 pan / tilt whose pan homes natively beside an SO-101 arm on a
Feetech bus (test profiles in tests/profiles/). The robot behaves as its buses declare: the arm
resumes from where its own safeguard stop left it, the speed slider reaches clients, the gripper
offers effort; the CANopen robot starts not homed and ``home`` runs the drive's own homing."""

from __future__ import annotations

import time

import numpy as np
import pytest

from crtk_bridge.client import connect
from crtk_bridge.sim.control import control_request

from .conftest import ROOT, DaemonProcess, wait_until
from .test_e2e_multibus import Buses

UR_GRIPPER = ROOT / "tests" / "profiles" / "ur5e_xl330_gripper.yaml"
PANTILT_SO101 = ROOT / "tests" / "profiles" / "pantilt_homing_so101.yaml"
QUICK = {"cmd": "timings", "power_on_s": 0.1, "brake_release_s": 0.1, "unlock_delay_s": 0.3}


def ur(sims: Buses, request: dict) -> dict:
    reply = control_request(sims.sims["arm"], request)
    assert reply.get("ok"), (request, reply)
    return reply


def test_a_ur_arm_with_a_servo_gripper_resumes_where_the_arm_stopped(short_tmp):
    d = DaemonProcess(["--profile", str(UR_GRIPPER), "--sim"], short_tmp / "urg.sock", short_tmp / "daemon.log")
    try:
        sims = Buses(d, {"arm", "hand"})  # one simulator per bus: the UR controller, the servo bus
        ur(sims, QUICK)
        robot = connect(socket=str(d.socket_path))
        try:
            info = robot.list()
            assert info["backend"] == "ur+dynamixel"
            cmds = {ns["name"]: ns["commands"] for ns in info["namespaces"]}
            assert "servo_jf" in cmds["ur5e/gripper"] and "servo_jf" not in cmds["ur5e"]
            assert "move_cp" in cmds["ur5e"]  # the UR's native cartesian control, through the composite
            arm, hand = robot.device("ur5e"), robot.device("ur5e/gripper")
            assert arm.enable(20.0)
            assert sims.torque("hand") == [1]
            # the UR's speed slider reaches clients through the robot of two buses
            wait_until(lambda: arm.operating_state_full().get("target_speed_fraction") == pytest.approx(1.0), 3,
                       what="target_speed_fraction in operating_state")
            ur(sims, {"cmd": "speed_slider", "fraction": 0.5})
            wait_until(lambda: arm.operating_state_full().get("target_speed_fraction") == pytest.approx(0.5), 3,
                       what="target_speed_fraction 0.5")
            ur(sims, {"cmd": "speed_slider", "fraction": 1.0})
            # a long move, stopped on its way by the controller's own safeguard stop
            q0 = np.array(ur(sims, {"cmd": "state"})["q"])
            goal = q0 + np.array([0.8, 0, 0, 0, 0, 0])
            arm.move_jp(list(goal))
            wait_until(lambda: abs(ur(sims, {"cmd": "state"})["q"][0] - q0[0]) > 0.2, 5, what="the move under way")
            ur(sims, {"cmd": "stop", "kind": "safeguard"})
            wait_until(lambda: arm.operating_state() == "PAUSED", 3, what="PAUSED")
            ur(sims, {"cmd": "release", "kind": "safeguard"})
            time.sleep(0.2)
            stopped = np.array(ur(sims, {"cmd": "state"})["q"])
            assert abs(stopped[0] - goal[0]) > 0.05  # stopped short of the goal
            assert arm.resume(5.0) and arm.operating_state() == "ENABLED"
            # the arm's namespace resumes from where the arm stopped (the measured pose), so the
            # arm does not rush on to where core's own braking ramp would have left it
            time.sleep(0.3)
            np.testing.assert_allclose(ur(sims, {"cmd": "state"})["q"], stopped, atol=2e-3)
            # the gripper on its own bus still follows effort commands (current control)
            hand.servo_jf([0.035])  # 0.1 A = 100 XL330 units
            wait_until(lambda: sims.servos("hand")["6"]["operating_mode"] == 0
                       and sims.servos("hand")["6"]["goal_current"] == 100, 3, what="gripper in current mode")
            assert arm.disable(10.0)
            assert ur(sims, {"cmd": "state"})["robot_mode"] == "POWER_OFF" and sims.torque("hand") == [0]
        finally:
            robot.close()
    finally:
        d.stop()


def test_a_drive_that_homes_itself_beside_servos_homes_natively(short_tmp):
    d = DaemonProcess(["--profile", str(PANTILT_SO101), "--sim"], short_tmp / "pt.sock", short_tmp / "daemon.log")
    try:
        sims = Buses(d, {"can", "arm"})
        robot = connect(socket=str(d.socket_path))
        try:
            pantilt, arm = robot.device("pantilt"), robot.device("so101")
            assert not pantilt.is_homed()  # the pan drive needs homing: the robot starts not homed
            assert pantilt.enable(10.0)
            before = sims.arm_ticks("arm")
            assert pantilt.home(20.0)
            wait_until(lambda: pantilt.is_homed(), 3, what="is_homed")
            # the drive homed itself (method 37: here is zero); the servo arm was not moved to its home
            wait_until(lambda: abs(pantilt.measured_jp()[0][0]) < 0.01, 3, what="pan at zero")
            np.testing.assert_allclose(sims.arm_ticks("arm"), before, atol=3)
            assert arm.operating_state() == "ENABLED" and arm.is_homed()
            assert pantilt.disable(10.0)
        finally:
            robot.close()
    finally:
        d.stop()

"""End to end, capabilities per namespace (issue 8 item 4): a namespace offers the commands its own
joints can follow. On the Koch the gripper (XL330, current sensing) offers servo_jf /
interpolate_jf and the arm (two XL430s, none) does not; on the OpenManipulator-X (all XM430) the
arm does. Checked on `list`, on what the daemon executes and refuses, and on the simulated servo."""

from __future__ import annotations

import numpy as np
import pytest

from crtk_bridge.client import CommandError, connect
from crtk_bridge.sim.control import control_request

from .conftest import ROOT, SIM_ROBOTS, DaemonProcess, only_on, wait_until

EFFORT_CMDS = ("servo_jf", "interpolate_jf")
OMX = ROOT / "profiles" / "openmanipulator_x.yaml"


def servo(sim: str, sid: int) -> dict:
    reply = control_request(sim, {"cmd": "dump"})
    assert reply.get("ok"), reply
    return reply["servos"][str(sid)]


def commands(robot) -> dict[str, list[str]]:
    return {ns["name"]: ns["commands"] for ns in robot.list()["namespaces"]}


@only_on("koch-dynamixel")
def test_koch_gripper_offers_and_executes_effort_the_arm_does_not(sim_daemon):
    bot = SIM_ROBOTS["koch-dynamixel"]
    sim = sim_daemon.sim_control_path()
    gid = bot.servo_id[bot.gripper_joint]
    robot = connect(socket=str(sim_daemon.socket_path))
    try:
        listed = commands(robot)
        assert all(c in listed["koch/gripper"] for c in EFFORT_CMDS), listed["koch/gripper"]
        assert not any(c in listed["koch"] for c in EFFORT_CMDS), listed["koch"]
        arm, gripper = robot.device("koch"), robot.device("koch/gripper")
        assert arm.enable(5.0)
        assert servo(sim, gid)["operating_mode"] == 5  # current-based position until told otherwise
        # 0.035 N*m at 0.35 N*m/A = 0.1 A = 100 XL330 current units (1 mA)
        gripper.servo_jf([0.035])
        wait_until(lambda: servo(sim, gid)["operating_mode"] == 0 and servo(sim, gid)["goal_current"] == 100,
                   3.0, what="gripper servo in current mode with Goal_Current 100")
        assert servo(sim, gid)["torque_enable"] == 1
        assert gripper.setpoint_js()[2] == pytest.approx([0.035])
        # the arm refuses, naming the joints that cannot (a client that does not check `list`)
        with pytest.raises(CommandError) as err:
            robot.connection.request("servo_jf", "koch", {"effort": [0.0] * 5})
        assert err.value.code == "unsupported"
        assert "koch: servo_jf" in err.value.message and "'shoulder_pan', 'shoulder_lift'" in err.value.message
        # measured effort per namespace: the gripper reports it, the arm (XL430 load is no effort) not
        assert len(gripper.measured_js()[2]) == 1 and len(arm.measured_js()[2]) == 0
        assert arm.disable(5.0)
    finally:
        robot.close()


def test_openmanipulator_x_arm_lists_effort_and_runs_on_sim(short_tmp):
    d = DaemonProcess(["--profile", str(OMX), "--sim"], short_tmp / "omx.sock", short_tmp / "daemon.log")
    try:
        robot = connect(socket=str(d.socket_path))
        try:
            listed = commands(robot)
            assert set(listed) == {"openmanipulator_x", "openmanipulator_x/gripper"}
            for ns in listed.values():
                assert all(c in ns for c in EFFORT_CMDS), ns
            sim = d.sim_control_path()
            ids = sorted(int(k) for k in control_request(sim, {"cmd": "dump"})["servos"])
            assert ids == [11, 12, 13, 14, 15]
            arm = robot.device("openmanipulator_x")
            assert arm.enable(5.0)
            assert arm.move_jp([0.2, -0.3, 0.4, 0.1]).wait(timeout=10.0)
            goal = np.array([0.2, -0.3, 0.4, 0.1])
            wait_until(lambda: np.allclose(arm.measured_js()[0], goal, atol=0.03), 3.0,
                       what="the simulated servos settled at the goal (first-order lag)")
            arm.servo_jf([0.0, 0.0, 0.0, 0.05])
            # 0.05 N*m / 1.78 N*m/A / 2.69 mA = 10.4 -> 10 XM430 current units
            wait_until(lambda: servo(sim, 14)["operating_mode"] == 0 and servo(sim, 14)["goal_current"] == 10,
                       3.0, what="joint4 in current mode with Goal_Current 10")
            assert arm.disable(5.0)
        finally:
            robot.close()
    finally:
        d.stop()

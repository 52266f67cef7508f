"""Cartesian CRTK end to end on the simulated SO-101 (issue 4)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from crtk_bridge.client import CommandError, connect

from .conftest import only_on, wait_until

POS_TOL = 0.005  # m: servo quantisation (0.0015 rad) times the arm's ~0.4 m reach, plus lag


def pose(c, query="measured_cp"):
    d = c.request(query, "so101")
    return np.array(d["position"]), np.array(d["orientation"]), d["stamp"]


@only_on("so101-feetech")  # the Koch profile has no URDF: no cartesian commands
def test_cartesian_queries_commands_and_validity(sim_daemon):
    robot = connect(socket=str(sim_daemon.socket_path))
    c = robot.connection
    try:
        info = {n["name"]: n for n in c.request("list")["namespaces"]}
        assert "move_cp" in info["so101"]["commands"] and "servo_cf" not in info["so101"]["commands"]
        assert "measured_cp" in info["so101"]["queries"] and "measured_cp" not in info["so101/gripper"]["queries"]
        with pytest.raises(CommandError) as err:
            c.request("servo_cf", "so101", {"force": [0, 0, 0], "torque": [0, 0, 0]})
        assert err.value.code == "unsupported"

        # measured_cp carries the stamp of the joint sample it comes from
        p0, q0, ts = pose(c)
        assert ts > 0 and np.linalg.norm(q0) == pytest.approx(1.0)
        assert c.request("setpoint_cp", "so101")["stamp"] == 0.0  # disabled: invalid
        assert robot.device("so101").enable(5.0)
        assert c.request("setpoint_cp", "so101")["stamp"] == 0.0  # no command yet

        # move_cp to a reachable pose (FK of a valid joint vector)
        target = c.request("forward_kinematics", "so101", {"jp": [0.3, 0.4, -0.3, 0.2, 0.1]})
        seq = c.request("move_cp", "so101", {"position": target["position"], "orientation": target["orientation"]})["busy_seq"]
        wait_until(lambda: c.idle_seq >= seq, 15, what="move_cp done")
        wait_until(lambda: np.linalg.norm(pose(c)[0] - target["position"]) < POS_TOL, 5, what="tip at the move_cp target")
        g = c.request("goal_cp", "so101")
        assert g["stamp"] > 0 and np.allclose(g["position"], target["position"], atol=1e-6)
        sp = c.request("setpoint_cp", "so101")
        assert sp["stamp"] > 0 and np.allclose(sp["position"], target["position"], atol=1e-4)

        # unreachable goal refused, robot unchanged
        with pytest.raises(CommandError) as err:
            c.request("move_cp", "so101", {"position": [1.0, 1.0, 1.0], "orientation": [0, 0, 0, 1]})
        assert err.value.code == "ik_failed" and "reach" in str(err.value)

        # servo_cp stream: a 2 cm circle at ~100 Hz, in the arm's vertical plane (the plane through
        # the shoulder_pan axis): a 5-joint arm keeps a fixed orientation there, not sideways
        centre, quat, _ = pose(c, "setpoint_cp")
        radial = centre[:2] - np.array([0.0388353, 0.0])  # shoulder_pan axis position (URDF)
        radial = np.array([*radial / np.linalg.norm(radial), 0.0])
        up = np.array([0.0, 0.0, 1.0])
        worst = 0.0
        for k in range(121):
            a = 2 * math.pi * k / 120
            goal = centre + 0.02 * ((math.cos(a) - 1.0) * radial + math.sin(a) * up)
            c.request("servo_cp", "so101", {"position": goal.tolist(), "orientation": quat.tolist()})
            sp = c.request("setpoint_cp", "so101")
            worst = max(worst, float(np.linalg.norm(np.array(sp["position"]) - goal)))
            time.sleep(0.01)  # paces the stream
        assert worst < 1e-3  # every setpoint on the circle (IK solved each point)
        wait_until(lambda: np.linalg.norm(pose(c)[0] - centre) < POS_TOL, 5, what="back at the circle start")

        # servo_cv: a twist moves the tip along +z; setpoint_cp becomes invalid? no: integrated -> valid
        z0 = pose(c)[0][2]
        for _ in range(30):
            c.request("servo_cv", "so101", {"linear": [0, 0, 0.05], "angular": [0, 0, 0]})
            time.sleep(0.01)
        wait_until(lambda: pose(c)[0][2] > z0 + 0.005, 5, what="tip moved up under servo_cv")
        cv = c.request("setpoint_cv", "so101")
        assert cv["stamp"] > 0 and cv["linear"][2] > 0.03
        body = c.request("measured_cv", "so101/body")
        assert body["frame_id"] == "gripper_frame_link" and len(body["linear"]) == 3

        # servo_cr: relative, in the base frame
        wait_until(lambda: c.request("setpoint_js", "so101")["velocity"] == [] or
                   not any(c.request("setpoint_js", "so101")["velocity"]), 2, what="servo_cv stream stopped")
        p1 = pose(c, "setpoint_cp")[0]
        c.request("servo_cr", "so101", {"position": [0.0, 0.0, -0.01], "orientation": [0, 0, 0, 1]})
        # the setpoint follows the servo target at velocity_max: wait for it to get there
        wait_until(lambda: pose(c, "setpoint_cp")[0] == pytest.approx(p1 + np.array([0, 0, -0.01]), abs=1e-3), 2,
                   what="setpoint_cp at the servo_cr target")

        # inverse_kinematics query round trip
        ik = c.request("inverse_kinematics", "so101", {"position": target["position"], "orientation": target["orientation"]})
        assert ik["result"] is True
        fk = c.request("forward_kinematics", "so101", {"jp": ik["jp"]})
        assert np.allclose(fk["position"], target["position"], atol=1e-3)
        robot.device("so101").disable(5.0)
        assert c.request("setpoint_cp", "so101")["stamp"] == 0.0
    finally:
        robot.close()

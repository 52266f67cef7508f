"""Cartesian CRTK end to end on every simulated robot with a URDF (issue 4; the UR5e, issue 11):
the SO-101 through the daemon's IK and twist mapping, the UR through its controller's own
cartesian control (``native_cartesian``: servoL / speedL, its TCP pose). Targets are FK of joint
vectors the profile's kinematics chose (tests/cartesian_targets.py), never literals."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from crtk_bridge.client import CommandError, connect
from crtk_bridge.profile import load_profile

from .cartesian_targets import targets, wait_still
from .conftest import wait_until

pytestmark = pytest.mark.requires("kinematics")

POS_TOL = 0.005  # m: servo quantisation (0.0015 rad) times the arm's ~0.4 m reach, plus lag


def pose(c, ns, query="measured_cp"):
    d = c.request(query, ns)
    return np.array(d["position"]), np.array(d["orientation"]), d["stamp"]


def test_cartesian_queries_commands_and_validity(sim_daemon):
    r = sim_daemon.robot
    ns, native = r.arm, "native_cartesian" in r.capabilities
    tg = targets(r)
    kin = load_profile(r.profile).namespace(ns).kinematics
    robot = connect(socket=str(sim_daemon.socket_path))
    c = robot.connection
    try:
        info = {n["name"]: n for n in c.request("list")["namespaces"]}
        assert "move_cp" in info[ns]["commands"] and "servo_cf" not in info[ns]["commands"]
        assert "measured_cp" in info[ns]["queries"]
        if r.gripper is not None:
            assert "measured_cp" not in info[r.gripper]["queries"]
        with pytest.raises(CommandError) as err:
            c.request("servo_cf", ns, {"force": [0, 0, 0], "torque": [0, 0, 0]})
        assert err.value.code == "unsupported"
        # measured_cf: a native backend's own TCP wrench (UR actual_TCP_force), else Jᵀ⁺ of the
        # measured joint efforts; served exactly where one of them is measured
        measured = native or bool(c.request("measured_js", ns)["effort"])
        assert ("measured_cf" in info[ns]["queries"]) == measured
        if measured:
            cf = c.request("measured_cf", ns)
            assert cf["stamp"] > 0 and cf["frame_id"] == kin.base_frame and cf["child_frame_id"] == kin.tip_frame
            assert len(cf["force"]) == 3 and len(cf["torque"]) == 3
            assert np.all(np.isfinite(cf["force"] + cf["torque"]))

        # measured_cp carries the stamp of the joint sample it comes from
        p0, q0, ts = pose(c, ns)
        assert ts > 0 and np.linalg.norm(q0) == pytest.approx(1.0)
        assert c.request("setpoint_cp", ns)["stamp"] == 0.0  # disabled: invalid
        assert robot.device(ns).enable(20.0)
        assert c.request("setpoint_cp", ns)["stamp"] == 0.0  # no command yet
        seq = c.request("move_jp", ns, {"position": tg.start.tolist()})["busy_seq"]
        wait_until(lambda: c.idle_seq >= seq, 15, what="move_jp to the start pose")

        # move_cp to a reachable pose (FK of a valid joint vector)
        target = c.request("forward_kinematics", ns, {"jp": tg.a.tolist()})
        seq = c.request("move_cp", ns, {"position": target["position"], "orientation": target["orientation"]})["busy_seq"]
        wait_until(lambda: c.idle_seq >= seq, 15, what="move_cp done")
        wait_until(lambda: np.linalg.norm(pose(c, ns)[0] - target["position"]) < POS_TOL, 5, what="tip at the move_cp target")
        g = c.request("goal_cp", ns)
        assert g["stamp"] > 0 and np.allclose(g["position"], target["position"], atol=1e-6)
        # (a native backend's setpoint is its goal from the cycle its move ended in: that cycle's
        # snapshot may reach the front just after is_busy's false edge)
        wait_until(lambda: (sp := c.request("setpoint_cp", ns))["stamp"] > 0
                   and np.allclose(sp["position"], target["position"], atol=1e-4), 2, what="setpoint_cp at the target")

        # unreachable goal refused, robot unchanged
        far = {"position": tg.beyond_reach(), "orientation": [0, 0, 0, 1]}
        with pytest.raises(CommandError) as err:
            c.request("move_cp", ns, far)
        if native:  # no IK: the controller's own check (isPoseWithinSafetyLimits) refuses it, naming the pose
            assert err.value.code == "out_of_limits" and "safety limits" in str(err.value)
        else:
            assert err.value.code == "ik_failed" and "reach" in str(err.value)
        assert c.request("goal_cp", ns)["position"] == pytest.approx(target["position"], abs=1e-6)

        # servo_cp stream: a 2 cm circle at ~100 Hz, in the arm's vertical plane (normal to the
        # shoulder lift's axis): a 5-joint arm keeps a fixed orientation there, not sideways
        centre, quat, _ = pose(c, ns, "setpoint_cp")
        radial = tg.arm_plane(tg.a)
        up = np.array([0.0, 0.0, 1.0])
        worst = 0.0
        for k in range(121):
            a = 2 * math.pi * k / 120
            goal = centre + 0.02 * ((math.cos(a) - 1.0) * radial + math.sin(a) * up)
            c.request("servo_cp", ns, {"position": goal.tolist(), "orientation": quat.tolist()})
            sp = c.request("setpoint_cp", ns)
            worst = max(worst, float(np.linalg.norm(np.array(sp["position"]) - goal)))
            time.sleep(0.01)  # paces the stream
        # every setpoint on the circle (IK solved each point; a native backend got each pose)
        assert worst < 1e-3
        wait_until(lambda: np.linalg.norm(pose(c, ns)[0] - centre) < POS_TOL, 5, what="back at the circle start")
        assert c.request("goal_cp", ns)["stamp"] == 0.0  # a servo stream has no goal

        # servo_cv: a twist moves the tip along +z; setpoint_cv is the twist (integrated: valid)
        z0 = pose(c, ns)[0][2]
        for _ in range(30):
            c.request("servo_cv", ns, {"linear": [0, 0, 0.05], "angular": [0, 0, 0]})
            time.sleep(0.01)
        wait_until(lambda: pose(c, ns)[0][2] > z0 + 0.005, 5, what="tip moved up under servo_cv")
        cv = c.request("setpoint_cv", ns)
        assert cv["stamp"] > 0 and cv["linear"][2] > 0.03
        body = c.request("measured_cv", f"{ns}/body")
        assert body["frame_id"] == kin.tip_frame and len(body["linear"]) == 3
        c.request("hold", ns)  # the twist ends here, not at its watchdog: the arm stays where it can move

        # servo_cr: relative, in the base frame
        if native:
            # relative to the pose the controller measures (server/cartesian.py): once the arm
            # stopped, that pose is the base
            wait_until(lambda: c.request("setpoint_cv", ns)["stamp"] == 0.0, 2, what="servo_cv stream ended")
            p1 = wait_still(lambda: pose(c, ns)[0], lambda: np.linalg.norm(c.request("measured_cv", ns)["linear"]))
        else:
            wait_until(lambda: c.request("setpoint_js", ns)["velocity"] == [] or
                       not any(c.request("setpoint_js", ns)["velocity"]), 2, what="servo_cv stream stopped")
            p1 = pose(c, ns, "setpoint_cp")[0]
        c.request("servo_cr", ns, {"position": [0.0, 0.0, -0.01], "orientation": [0, 0, 0, 1]})
        # the setpoint follows the servo target at velocity_max: wait for it to get there
        wait_until(lambda: pose(c, ns, "setpoint_cp")[0] == pytest.approx(p1 + np.array([0, 0, -0.01]), abs=1e-3), 2,
                   what="setpoint_cp at the servo_cr target")
        wait_until(lambda: np.linalg.norm(pose(c, ns)[0] - (p1 + [0, 0, -0.01])) < POS_TOL, 5,
                   what="tip at the servo_cr target")

        # inverse_kinematics query round trip
        ik = c.request("inverse_kinematics", ns, {"position": target["position"], "orientation": target["orientation"]})
        assert ik["result"] is True
        fk = c.request("forward_kinematics", ns, {"jp": ik["jp"]})
        assert np.allclose(fk["position"], target["position"], atol=1e-3)
        robot.device(ns).disable(10.0)
        assert c.request("setpoint_cp", ns)["stamp"] == 0.0
        assert c.request("goal_cp", ns)["stamp"] == 0.0
    finally:
        robot.close()

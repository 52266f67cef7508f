"""The client's cartesian API and crtk-ctl's cartesian commands against the real daemon on every
simulated robot with a URDF (issue 4; the UR5e's native cartesian control, issue 11).

One daemon per robot for the module (``start_sim_daemon``, on a socket in a short temp dir); every
wait has a deadline. Targets are FK of joint vectors from the profile (tests/cartesian_targets.py).
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from crtk_bridge.client import CommandError, connect, pose_matrix, pose_pq
from crtk_bridge.client.cli import main

from .cartesian_targets import targets, wait_still
from .conftest import SIM_ROBOTS, start_sim_daemon, wait_until

pytestmark = pytest.mark.requires("kinematics")

POS_TOL = 0.005  # m: tip within 5 mm (servo quantisation times the reach, plus lag)


def _module_daemon(robot):
    d = Path(tempfile.mkdtemp(prefix="crtk-"))  # AF_UNIX paths must stay short
    proc = start_sim_daemon(robot, d)
    try:
        yield proc
    finally:
        proc.stop()
        shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="module")
def robot_daemon(sim_robot):
    """One daemon per robot for this module."""
    yield from _module_daemon(sim_robot)


@pytest.fixture(scope="module")
def daemon():
    """One so101 --sim daemon for a module (tests/test_e2e_protocol.py and
    tests/reliability/test_fuzz_protocol.py import it)."""
    yield from _module_daemon(SIM_ROBOTS["so101-feetech"])


@pytest.fixture
def arm(robot_daemon):
    robot = connect(socket=str(robot_daemon.socket_path), timeout=5.0)
    try:
        yield robot.device(robot_daemon.robot.arm)
    finally:
        robot.close()


def native(daemon) -> bool:
    """The backend does cartesian control itself (a UR): no IK, no Jacobian mapping in the daemon."""
    return "native_cartesian" in daemon.robot.capabilities


def enabled(arm):
    assert arm.enable(20.0), "robot did not enable"
    return arm


def tip_error(arm, target) -> float:
    T, ts = arm.measured_cp()
    assert ts > 0
    return float(np.linalg.norm(T[:3, 3] - np.asarray(target)[:3, 3]))


def ctl(daemon, capsys, *argv) -> tuple[int, str, str]:
    code = main(["--socket", str(daemon.socket_path), *argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_measured_cp_matrix_is_consistent_with_pq_and_fk(arm, robot_daemon):
    T, ts = arm.measured_cp()
    p, q, ts_pq = arm.measured_cp_pq()
    assert ts > 0 and ts_pq >= ts
    assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
    R = T[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.linalg.norm(q) == pytest.approx(1.0) and q[3] >= 0
    assert np.allclose(pose_matrix(p, q), T, atol=1e-3)  # the robot is still (disabled)
    jp, _ = arm.measured_jp()
    # the daemon's FK of the measured joints: on a native backend, the controller's own TCP pose
    # agrees with it (same base and tip frames, the same quaternion order)
    assert np.allclose(arm.forward_kinematics(jp), T, atol=1e-3)
    if "measured_cf" in arm._robot.connection.request("list")["namespaces"][0]["queries"]:
        w, ts_w = arm.measured_cf()
        assert ts_w > 0 and w.shape == (6,) and np.all(np.isfinite(w))
    if robot_daemon.robot.gripper is not None:
        # the body frame is not for poses; the gripper namespace has no kinematics
        with pytest.raises(CommandError) as info:
            arm.gripper.measured_cp()
        assert info.value.code == "unsupported"


def test_move_cp_reaches_fk_of_a_joint_vector_via_client_and_ctl(arm, robot_daemon, capsys):
    tg = targets(robot_daemon.robot)
    enabled(arm)
    _back_to(arm, tg.start)
    target = arm.forward_kinematics(tg.a)
    h = arm.move_cp(target)
    assert h.wait(timeout=15.0), "move_cp did not end"
    wait_until(lambda: tip_error(arm, target) < POS_TOL, 5, what="tip at the move_cp target")
    G, ts = arm.goal_cp()
    assert ts > 0 and np.allclose(G[:3, 3], target[:3, 3], atol=1e-6)
    jp, _ = arm.measured_jp()
    # the exact solution, found from another seed (IK), or where the native backend's straight
    # line from the start pose ended
    assert np.allclose(jp, tg.a, atol=0.02)

    # move_cr: 2 cm up in the base frame, the tip follows
    h = arm.move_cr(([0.0, 0.0, 0.02], [0.0, 0.0, 0.0, 1.0]))
    assert h.wait(timeout=15.0)
    up = target.copy()
    up[2, 3] += 0.02
    wait_until(lambda: tip_error(arm, up) < POS_TOL, 5, what="tip 2 cm higher after move_cr")

    # the same through crtk-ctl (its own session: the client gives control up first)
    arm._robot.release()
    target_b = arm.forward_kinematics(tg.b)
    p, q = pose_pq(target_b)
    code, out, err = ctl(robot_daemon, capsys, "move_cp", *map(str, [*p, *q]), "--wait", "--json")
    assert code == 0, err
    assert json.loads(out)["done"] is True
    wait_until(lambda: tip_error(arm, target_b) < POS_TOL, 5, what="tip at crtk-ctl's move_cp target")
    code, out, _ = ctl(robot_daemon, capsys, "--json", "get", "measured_cp")
    assert code == 0 and np.linalg.norm(np.array(json.loads(out)["position"]) - p) < POS_TOL
    code, out, _ = ctl(robot_daemon, capsys, "get", "measured_cp")
    assert code == 0
    line = next(x for x in out.splitlines() if x.strip().startswith("position"))
    assert line.endswith(" m (x y z)")
    printed = np.array([float(v) for v in line.split()[1:4]])  # 4 decimals
    assert np.linalg.norm(printed - p) < POS_TOL


def test_ik_fk_round_trip_client_and_ctl(arm, robot_daemon, capsys):
    tg = targets(robot_daemon.robot)
    n = len(tg.a)
    target = arm.forward_kinematics(tg.a)
    jp, ok, msg = arm.inverse_kinematics(target, jp_seed=[0.0] * n)
    assert ok, msg
    back = arm.forward_kinematics(jp)
    assert np.linalg.norm(back[:3, 3] - target[:3, 3]) < 1e-3
    assert np.allclose(back[:3, :3], target[:3, :3], atol=0.02)
    far = tg.beyond_reach()
    jp2, ok2, msg2 = arm.inverse_kinematics((far, [0, 0, 0, 1]))
    assert not ok2 and "reach" in msg2 and jp2.shape == (n,)

    p, q = pose_pq(target)
    code, out, err = ctl(robot_daemon, capsys, "--json", "ik", *map(str, [*p, *q]), "--seed", *["0"] * n)
    assert code == 0, err
    reply = json.loads(out)
    assert reply["result"] is True
    code, out, _ = ctl(robot_daemon, capsys, "--json", "fk", *map(str, reply["jp"]))
    assert code == 0 and np.linalg.norm(np.array(json.loads(out)["position"]) - p) < 1e-3
    code, out, err = ctl(robot_daemon, capsys, "ik", *map(str, far), "0", "0", "0", "1")
    assert code == 1 and out == ""
    assert err.count("\n") == 1 and "ik refused (ik_failed)" in err and "reach" in err


def test_unreachable_move_cp_refused_with_ik_failed(arm, robot_daemon, capsys):
    enabled(arm)
    seq = arm.operating_state_full()["busy_seq"]
    before, _ = arm.measured_jp()
    far = targets(robot_daemon.robot).beyond_reach()
    # no IK on a native backend: the controller's own check (isPoseWithinSafetyLimits) refuses it
    code, why = ("out_of_limits", "safety limits") if native(robot_daemon) else ("ik_failed", "reach")
    with pytest.raises(CommandError) as info:
        arm.move_cp((far, [0.0, 0.0, 0.0, 1.0]))
    assert info.value.code == code and why in info.value.message
    arm._robot.release()
    code_ctl, _, err = ctl(robot_daemon, capsys, "move_cp", *map(str, far), "0", "0", "0", "1", "--wait")
    assert code_ctl == 1 and f"move_cp refused ({code})" in err and err.count("\n") == 1
    if native(robot_daemon):
        # the controller is asked first (a GOAL_CHECK transition: is_busy while it answers), so
        # each refused request raised one busy edge pair (the false edge is pushed just after
        # the refusal's reply); no move started
        def idle():
            st = arm.operating_state_full()
            return None if st["is_busy"] else st

        assert wait_until(idle, 5, what="is_busy false after the refused goal checks")["busy_seq"] == seq + 2
    else:
        assert arm.operating_state_full()["busy_seq"] == seq  # no move started
    G, ts = arm.goal_cp()
    assert ts == 0 or np.linalg.norm(G[:3, 3] - far) > 0.1  # the refused goal is nobody's goal
    assert np.allclose(arm.measured_jp()[0], before, atol=0.01)


def _held_pose(arm, native: bool) -> np.ndarray:
    """Where the arm holds: its setpoint_cp, or on a native backend (which integrates a twist
    itself: the daemon holds no position setpoint for it) its measured pose once it stopped."""
    if not native:
        T, ts = arm.setpoint_cp()
        assert ts > 0
        return T
    wait_still(lambda: arm.measured_cp()[0][:3, 3], lambda: np.linalg.norm(arm.measured_cv()[0][:3]))
    return arm.measured_cp()[0]


def _stream_cv(arm, twist, frame, native, duration=0.3, rate=100.0):
    """servo_cv for ``duration`` s; returns the held position's displacement (m). On a native
    backend, until the tip also moved 0.7 of what the twist gives in ``duration`` (within 3 s):
    its controller integrates the twist on its own clock, which a simulated controller on a
    loaded host loses ticks of."""
    T0 = _held_pose(arm, native)
    far = 0.7 * float(np.linalg.norm(twist[:3])) * duration

    def streaming() -> bool:
        t = time.monotonic() - t0
        if t < duration:
            return True
        return native and t < 3.0 and np.linalg.norm(arm.measured_cp()[0][:3, 3] - T0[:3, 3]) < far

    t0 = time.monotonic()
    k = 0
    while streaming():
        arm.servo_cv(twist, frame=frame)
        k += 1
        time.sleep(max(0.0, t0 + k / rate - time.monotonic()))
    arm.hold()
    T1 = _held_pose(arm, native)
    return T1[:3, 3] - T0[:3, 3], T0


def _back_to(arm, q):
    assert arm.move_jp(q).wait(timeout=15.0)
    wait_until(lambda: np.allclose(arm.measured_jp()[0], q, atol=0.01), 5, what=f"arm at {q}")


def test_servo_cv_body_and_spatial_frames_go_to_their_namespaces(arm, robot_daemon, capsys):
    nat, q_b = native(robot_daemon), targets(robot_daemon.robot).b
    enabled(arm)
    _back_to(arm, q_b)
    v = 0.03
    # spatial: +z of the base frame is up
    d, T0 = _stream_cv(arm, [0, 0, v, 0, 0, 0], "spatial", nat)
    assert np.linalg.norm(d) > 0.005
    assert d @ [0, 0, 1] / np.linalg.norm(d) > 0.95, d
    # body: +z of the tip frame, which points forward and down here
    tip_z = T0[:3, 2]
    assert tip_z @ [0, 0, 1] < -0.3  # so the two frames give clearly different motions
    _back_to(arm, q_b)
    d, T0 = _stream_cv(arm, [0, 0, v, 0, 0, 0], "body", nat)
    assert np.linalg.norm(d) > 0.005
    assert d @ T0[:3, 2] / np.linalg.norm(d) > 0.95, (d, T0[:3, 2])
    assert d[2] < 0  # went down: the body frame was used, not the spatial one

    # the body-frame twist query is the spatial one in the tip's axes
    def streaming_at_twist():
        # the joint velocity reaches the twist in a few cycles (acceleration-limited): compare the
        # two frames only once it is steady, i.e. the spatial twist is the same before and after
        # the body query (two queries are two samples; during the ramp they differ)
        arm.servo_cv([0, 0, v, 0, 0, 0], frame="spatial")
        vs0, _ = arm.setpoint_cv()
        vb, tb = arm.setpoint_cv(frame="body")
        vs, ts = arm.setpoint_cv()
        steady = vs[2] > 0.02 and np.allclose(vs0, vs, atol=2e-4)
        return (vs, ts, vb, tb) if steady else None

    vs, ts, vb, tb = wait_until(streaming_at_twist, 3, what="setpoint_cv steady at the commanded twist")
    arm.hold()
    assert ts > 0 and tb > 0 and vs[2] > 0.02
    T = _held_pose(arm, nat)
    assert np.allclose(vb[:3], T[:3, :3].T @ vs[:3], atol=2e-3)

    # crtk-ctl servo_cv --frame body reaches the daemon's <arm>/body namespace
    arm._robot.release()
    _, _, z0 = arm.measured_cp_pq()[0]
    code, out, err = ctl(robot_daemon, capsys, "servo_cv", "0", "0", str(v), "0", "0", "0", "--frame", "body",
                         "--duration", "0.3", "--rate", "100")
    assert code == 0 and "servo_cv sent (body)" in out, err
    wait_until(lambda: arm.measured_cp_pq()[0][2] < z0 - 0.003, 5, what="tip moved down under body servo_cv")

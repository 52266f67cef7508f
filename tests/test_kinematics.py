"""Kinematics of the SO-101 arm (crtk_bridge.core.kinematics) against an independent numpy chain."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pinocchio")

from crtk_bridge.core.kinematics import Kinematics, matrix_from_quaternion, quaternion_from_matrix  # noqa: E402
from crtk_bridge.errors import ProfileError  # noqa: E402

URDF = Path(__file__).resolve().parent.parent / "profiles" / "urdf" / "so101.urdf"
ARM = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]

# so101_new_calib.urdf joint origins (xyz m, rpy rad), all axes z: typed in from the kinematics
# table (servo research notes, SO-101 section), NOT read from the URDF under test.
CHAIN = [
    ((0.0388353, -8.97657e-09, 0.0624), (3.14159, 4.18253e-17, -3.14159)),  # shoulder_pan
    ((-0.0303992, -0.0182778, -0.0542), (-1.5708, -1.5708, 0.0)),  # shoulder_lift
    ((-0.11257, -0.028, 0.0), (0.0, 0.0, 1.5708)),  # elbow_flex
    ((-0.1349, 0.0052, 0.0), (0.0, 0.0, -1.5708)),  # wrist_flex
    ((0.0, -0.0611, 0.0181), (1.5708, 0.0486795, 3.14159)),  # wrist_roll
]
TIP = ((-0.0079, -0.000218121, -0.0981274), (0.0, 3.14159, 0.0))  # gripper_frame_joint (fixed)


def rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def transform(xyz, rpy):
    """URDF <origin>: translation, then fixed-axis roll-pitch-yaw R = Rz(y) Ry(p) Rx(r)."""
    T = np.eye(4)
    T[:3, :3] = rot_z(rpy[2]) @ rot_y(rpy[1]) @ rot_x(rpy[0])
    T[:3, 3] = xyz
    return T


def numpy_fk(q):
    T = np.eye(4)
    for (xyz, rpy), qi in zip(CHAIN, q):
        R = np.eye(4)
        R[:3, :3] = rot_z(qi)  # revolute about z
        T = T @ transform(xyz, rpy) @ R
    return T @ transform(*TIP)


def rot_angle(R1, R2):
    c = (np.trace(R1.T @ R2) - 1) / 2
    return math.acos(max(-1.0, min(1.0, c)))


@pytest.fixture(scope="module")
def kin():
    return Kinematics(URDF, "base_link", "gripper_frame_link", ARM)


@pytest.mark.parametrize(
    "q",
    [
        [0.0, 0.0, 0.0, 0.0, 0.0],
        [0.5, -0.3, 0.8, -0.4, 1.2],
        [-1.2, 1.0, -1.1, 1.3, -2.0],
        [1.8, -1.6, 1.5, 0.2, 2.5],
    ],
)
def test_fk_matches_independent_chain(kin, q):
    q = np.array(q)
    expected = numpy_fk(q)
    pos, quat = kin.fk(q)
    np.testing.assert_allclose(pos, expected[:3, 3], atol=1e-9)
    assert quat.shape == (4,) and quat[3] >= 0
    assert abs(np.linalg.norm(quat) - 1) < 1e-12
    assert rot_angle(matrix_from_quaternion(quat), expected[:3, :3]) < 1e-6
    np.testing.assert_allclose(kin.fk_matrix(q), expected, atol=1e-9)


def test_fk_zero_pose_figures(kin):
    # q = 0 (middle of every range): tip about 0.39 m ahead, 0.23 m up, tool z pointing forward
    T = kin.fk_matrix(np.zeros(5))
    np.testing.assert_allclose(T[:3, 3], [0.3914, 0.0, 0.2265], atol=5e-4)
    np.testing.assert_allclose(T[:3, 2], [1.0, 0.0, 0.0], atol=1e-4)


def test_quaternion_order_is_xyzw():
    q = quaternion_from_matrix(rot_z(math.pi / 2))
    np.testing.assert_allclose(q, [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(matrix_from_quaternion([0, 0, 1, 1]), rot_z(math.pi / 2), atol=1e-12)


def test_joint_order_is_the_callers(kin):
    shuffled = [ARM[i] for i in (4, 2, 0, 3, 1)]
    k2 = Kinematics(URDF, "base_link", "gripper_frame_link", shuffled)
    q = np.array([0.3, -0.2, 0.5, 0.1, -0.7])
    q2 = q[[4, 2, 0, 3, 1]]
    np.testing.assert_allclose(k2.fk_matrix(q2), kin.fk_matrix(q), atol=1e-12)
    np.testing.assert_allclose(k2.jacobian(q2), kin.jacobian(q)[:, [4, 2, 0, 3, 1]], atol=1e-12)
    np.testing.assert_allclose(k2.lower, kin.lower[[4, 2, 0, 3, 1]])
    p, quat = kin.fk(q)
    q_ik, ok, *_ = k2.ik(p, quat, q2 + 0.05)
    assert ok
    np.testing.assert_allclose(k2.fk_matrix(q_ik), kin.fk_matrix(q), atol=1e-3)


def test_limits_from_urdf_and_override(kin):
    np.testing.assert_allclose(kin.lower, [-1.91986, -1.74533, -1.69, -1.65806, -2.74385])
    np.testing.assert_allclose(kin.upper, [1.91986, 1.74533, 1.69, 1.65806, 2.84121])
    k = Kinematics(URDF, "base_link", "gripper_frame_link", ARM)
    k.set_limits([-1, -1, -1, -1, -1], [1, 1, 1, 1, 1])
    np.testing.assert_allclose(k.upper, 1.0)
    with pytest.raises(ValueError, match="lower limit must be < upper"):
        k.set_limits([0, 0, 0, 0, 0], [1, 1, 0, 1, 1])


# ---------------------------------------------------------------- Jacobian


def _fd_jacobian(kin, q, frame, h=1e-6):
    T0 = kin.fk_matrix(q)
    J = np.zeros((6, len(q)))
    for i in range(len(q)):
        dq = np.zeros(len(q))
        dq[i] = h
        Tp, Tm = kin.fk_matrix(q + dq), kin.fk_matrix(q - dq)
        v = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)  # tip origin velocity, base axes
        dR = (Tp[:3, :3] - Tm[:3, :3]) / (2 * h)
        W = dR @ T0[:3, :3].T  # skew(omega), base axes
        w = np.array([W[2, 1], W[0, 2], W[1, 0]])
        if frame == "body":
            R = T0[:3, :3]
            v, w = R.T @ v, R.T @ w
        J[:3, i], J[3:, i] = v, w
    return J


@pytest.mark.parametrize("frame", ["spatial", "body"])
def test_jacobian_matches_finite_differences(kin, frame):
    rng = np.random.default_rng(7)
    for _ in range(5):
        q = rng.uniform(kin.lower, kin.upper)
        np.testing.assert_allclose(kin.jacobian(q, frame), _fd_jacobian(kin, q, frame), atol=1e-6)


def test_twist_and_wrench(kin):
    rng = np.random.default_rng(3)
    q = rng.uniform(kin.lower * 0.8, kin.upper * 0.8)
    qd = rng.normal(size=5)
    for frame in ("spatial", "body"):
        J = kin.jacobian(q, frame)
        np.testing.assert_allclose(kin.twist(q, qd, frame), J @ qd, atol=1e-12)
        # efforts produced by a known wrench are mapped back to a wrench that reproduces them
        w_true = rng.normal(size=6)
        tau = J.T @ w_true
        w = kin.wrench_from_efforts(q, tau, frame)
        np.testing.assert_allclose(J.T @ w, tau, atol=1e-9)
        assert np.linalg.norm(w) <= np.linalg.norm(w_true) + 1e-9  # minimum-norm solution
    with pytest.raises(ValueError, match="spatial"):
        kin.jacobian(q, "world")


# ---------------------------------------------------------------- IK


def test_ik_round_trip_warm(kin):
    """Random valid q over the full ranges, seeded near q (as servo_cp / move_cp from the setpoint)."""
    rng = np.random.default_rng(12345)
    for _ in range(100):
        q = rng.uniform(kin.lower, kin.upper)
        pos, quat = kin.fk(q)
        seed = np.clip(q + rng.normal(0, 0.1, 5), kin.lower, kin.upper)
        q_ik, ok, res_p, res_o, msg = kin.ik(pos, quat, seed)
        assert ok, (q, msg)
        assert msg == "ok" and res_p <= 1e-3 and res_o <= 1e-2
        T = kin.fk_matrix(q_ik)
        assert np.linalg.norm(T[:3, 3] - pos) < 1e-3
        assert rot_angle(T[:3, :3], matrix_from_quaternion(quat)) < 1e-2
        assert np.all(q_ik >= kin.lower) and np.all(q_ik <= kin.upper)


def test_ik_round_trip_cold(kin):
    """Usual working poses (inner 60 % of each range), solved from q = 0."""
    rng = np.random.default_rng(777)
    for _ in range(50):
        q = rng.uniform(kin.lower * 0.6, kin.upper * 0.6)
        pos, quat = kin.fk(q)
        q_ik, ok, res_p, res_o, msg = kin.ik(pos, quat, np.zeros(5))
        assert ok, (q, msg)
        T = kin.fk_matrix(q_ik)
        assert np.linalg.norm(T[:3, 3] - pos) < 1e-3
        assert rot_angle(T[:3, :3], matrix_from_quaternion(quat)) < 1e-2


def test_ik_warm_start_is_few_iterations(kin):
    q = np.array([0.3, -0.4, 0.6, 0.2, -0.5])
    pos, quat = kin.fk(q + 0.01)
    _, ok, *_ = kin.ik(pos, quat, q)
    assert ok and kin.last_iterations <= 5


def test_ik_refuses_unreachable(kin):
    pos, quat = kin.fk(np.zeros(5))
    target = pos + np.array([1.0, 0.0, 0.0])
    q_ik, ok, res_p, res_o, msg = kin.ik(target, quat, np.zeros(5))
    assert not ok
    assert res_p > 0.3
    assert msg.startswith("IK did not converge: position residual") and " m > 0.001 m" in msg
    assert np.all(np.isfinite(q_ik))
    assert np.all(q_ik >= kin.lower) and np.all(q_ik <= kin.upper)


def test_ik_lost_orientation_on_5_dof(kin):
    """Position is solved exactly; an orientation yawed out of the arm's plane is not reachable."""
    q = np.array([0.2, -0.3, 0.5, 0.4, 0.1])
    T = kin.fk_matrix(q)
    R_bad = T[:3, :3] @ rot_x(0.5)  # tool tilted sideways about its x axis
    quat = quaternion_from_matrix(R_bad)
    q_ik, ok, res_p, res_o, msg = kin.ik(T[:3, 3], quat, q, restarts=0)
    assert not ok and res_p < 1e-6 and res_o > 0.05
    assert "orientation residual" in msg and "position residual" not in msg
    # accepting position-only solutions
    _, ok, *_ = kin.ik(T[:3, 3], quat, q, tol_orientation=math.inf, restarts=0)
    assert ok


def test_ik_respects_limits(kin):
    k = Kinematics(URDF, "base_link", "gripper_frame_link", ARM)
    lo = np.array([-0.5, -0.5, -0.5, -0.5, -0.5])
    hi = np.array([0.5, 0.5, 0.5, 0.5, 0.5])
    k.set_limits(lo, hi)
    rng = np.random.default_rng(5)
    for _ in range(30):
        q = rng.uniform(kin.lower, kin.upper)  # mostly outside the narrowed limits
        pos, quat = kin.fk(q)
        q_ik, ok, *_ = k.ik(pos, quat, np.zeros(5), restarts=1)
        assert np.all(q_ik >= lo) and np.all(q_ik <= hi)
        inside = np.all(q >= lo) and np.all(q <= hi)
        if not inside:
            continue
        assert ok


def test_ik_bad_input_is_a_status(kin):
    q, ok, res_p, _, msg = kin.ik([0.2, 0, 0.2], [0, 0, 0, 0], np.zeros(5))
    assert not ok and "orientation" in msg and math.isnan(res_p)
    q, ok, _, _, msg = kin.ik([math.nan, 0, 0.2], [0, 0, 0, 1], np.zeros(5))
    assert not ok and "position" in msg
    q, ok, _, _, msg = kin.ik([0.2, 0, 0.2], [0, 0, 0, 1], np.zeros(4))
    assert not ok and "seed" in msg and q.shape == (5,)


# ---------------------------------------------------------------- errors


def test_missing_joint_names_urdf_and_joint():
    with pytest.raises(ProfileError) as e:
        Kinematics(URDF, "base_link", "gripper_frame_link", ARM[:4] + ["wrist_twist"])
    assert str(URDF) in str(e.value) and "'wrist_twist'" in str(e.value)


@pytest.mark.parametrize("base,tip,bad", [("base", "gripper_frame_link", "base"), ("base_link", "tool0", "tool0")])
def test_missing_frame_names_urdf_and_frame(base, tip, bad):
    with pytest.raises(ProfileError) as e:
        Kinematics(URDF, base, tip, ARM)
    assert str(URDF) in str(e.value) and repr(bad) in str(e.value)


def test_unreadable_urdf(tmp_path):
    with pytest.raises(ProfileError, match="not found"):
        Kinematics(tmp_path / "nope.urdf", "base_link", "gripper_frame_link", ARM)
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'>")
    with pytest.raises(ProfileError) as e:
        Kinematics(bad, "base_link", "gripper_frame_link", ARM)
    assert str(bad) in str(e.value)


def test_moving_base_frame_refused():
    with pytest.raises(ProfileError, match="moved by joint"):
        Kinematics(URDF, "upper_arm_link", "gripper_frame_link", ARM)


def test_gripper_is_locked_out(kin):
    assert kin.n == 5 and kin.model.nq == 5
    k6 = Kinematics(URDF, "base_link", "moving_jaw_so101_v1_link", ARM + ["gripper"])
    assert k6.n == 6


def test_base_frame_below_a_world_link(tmp_path, kin):
    """The URDF root need not be the base frame: a world link with the arm mounted offset and
    rotated; poses, spatial Jacobians and IK are still in base_link's frame."""
    text = URDF.read_text().replace(
        '<link name="base_link">',
        '<link name="world"/>\n  <joint name="mount" type="fixed"><parent link="world"/>'
        '<child link="base_link"/><origin xyz="0.3 -0.2 0.75" rpy="0.1 0.2 1.0"/></joint>\n'
        '  <link name="base_link">',
        1,
    )
    path = tmp_path / "mounted.urdf"
    path.write_text(text)
    k = Kinematics(path, "base_link", "gripper_frame_link", ARM)
    q = np.array([0.4, -0.5, 0.7, 0.3, -0.9])
    np.testing.assert_allclose(k.fk_matrix(q), kin.fk_matrix(q), atol=1e-12)
    for frame in ("spatial", "body"):
        np.testing.assert_allclose(k.jacobian(q, frame), kin.jacobian(q, frame), atol=1e-12)
    pos, quat = kin.fk(q)
    q_ik, ok, *_ = k.ik(pos, quat, q + 0.1)
    assert ok
    np.testing.assert_allclose(k.fk(q_ik)[0], pos, atol=1e-3)
    w = Kinematics(path, "world", "gripper_frame_link", ARM)
    assert not np.allclose(w.fk_matrix(q), kin.fk_matrix(q))

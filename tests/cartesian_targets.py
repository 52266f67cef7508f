"""Reachable cartesian targets for the cartesian end-to-end modules, on any robot with a URDF:
computed from the robot's profile (its URDF, base and tip frames, joint limits), never written
as literals, so the same tests run on a 5-joint SO-101 and a 6-joint UR5e.

Joint configurations are drawn from a fixed-seed sample inside the arm's limits and kept only
where a test can use them: the tip above the base, the tool pointing down (so a body-frame +z
and a base-frame +z give clearly different motions), well away from singularities (the largest
smallest singular value of the Jacobian: of its position rows on an arm with fewer than six
joints, which cannot hold every orientation), with room to move (scored down near the limits).
Their forward kinematics are the targets.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np

from crtk_bridge.core.kinematics import Kinematics, matrix_from_quaternion, quaternion_from_matrix
from crtk_bridge.profile import load_profile

from .conftest import SimRobot, wait_until

SAMPLES = 3000  # joint vectors tried (a few ms of Jacobians)
SPAN = 2.0  # rad: each joint drawn within +-SPAN of 0, inside its limits (a 2 pi joint's other turns add nothing)
MARGIN = 0.3  # rad inside the limits (room for the tests' motions around them)
ABOVE_BASE = 0.05  # m: the tip this far above the base frame's origin (the table)
CLEARANCE = 0.5  # rad: a configuration closer than this to the sampled box scores less (room to move)
NEAR = 0.8  # rad: the other configurations are this close (max over joints) to the start one, so that
# a straight line or an IK solve from one to the other stays on one solution branch
APART = 0.05  # m: their tips at least this far from each other...
FAR = 0.2  # m: ...and from the start tip at most this far (short moves)
STILL_M_S = 1e-4  # m/s: the tip's measured speed once the arm stopped...
STILL_M = 1e-5  # m: ...and how far it may move between two polls


def wait_still(tip, speed, timeout: float = 5.0) -> np.ndarray:
    """Wait until the arm stopped: ``speed()`` (the tip's measured linear speed, m/s) near zero
    and ``tip()`` (its measured position) where the previous poll saw it. Returns the position.
    Where the daemon holds no position setpoint to compare with (a native backend's twist is
    integrated by its controller), this is how a test knows the arm settled."""
    last = [np.asarray(tip())]

    def still():
        now = np.asarray(tip())
        moved, last[0] = float(np.linalg.norm(now - last[0])), now
        return moved < STILL_M and speed() < STILL_M_S

    wait_until(still, timeout, what="the arm still")
    return last[0]


@dataclass(frozen=True)
class Targets:
    """What the cartesian tests need of one arm (joint vectors in the namespace's joint order)."""

    kin: Kinematics
    start: np.ndarray  # the best-conditioned configuration: where the tests start from
    a: np.ndarray  # another, near start: a move_cp / IK target
    b: np.ndarray  # a third, near start, tip apart from both
    pan_axis: np.ndarray  # the first joint's origin in the base frame (m)
    reach: float  # m: the farthest the tip got from pan_axis over the sample

    def fk(self, q) -> tuple[np.ndarray, np.ndarray]:
        return self.kin.fk(np.asarray(q, dtype=float))

    def arm_plane(self, q) -> np.ndarray:
        """The horizontal unit vector of the vertical plane the arm moves in at ``q``: normal to the
        second joint's axis (the shoulder lift's, horizontal), where a 5-joint arm can move its tip
        with a fixed orientation."""
        axis = self.kin.jacobian(np.asarray(q, dtype=float))[3:, 1]  # a revolute joint's angular column
        radial = np.cross(axis, [0.0, 0.0, 1.0])
        p, _ = self.fk(q)
        radial /= np.linalg.norm(radial)
        return radial if radial @ (p - self.pan_axis) >= 0 else -radial  # pointing outward

    def beyond_reach(self) -> list[float]:
        """A position twice the arm's reach from its first joint, in the direction of the start tip."""
        p, _ = self.fk(self.start)
        d = p - self.pan_axis
        return (self.pan_axis + 2.0 * self.reach * d / np.linalg.norm(d)).tolist()

    def slow_failing_ik(self) -> tuple[dict, float]:
        """An IK target near the start pose that IK cannot reach and takes longest to give up on,
        from zero (cold), and its solve time here (s). Tried: the start and a / b poses with the tool
        turned 90 degrees about the base z axis (unreachable for a 5-joint arm), or turned half a
        turn about its own z axis and pulled in to 0.9 of the reach (unreachable for a UR5e)."""
        Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        n = len(self.start)
        worst: tuple[float, dict] | None = None
        for q in (self.start, self.a, self.b):
            p, quat = self.fk(q)
            R = matrix_from_quaternion(quat)
            d = p - self.pan_axis
            edge = self.pan_axis + 0.9 * self.reach * d / np.linalg.norm(d)
            for pos, rot in ((p, Rz @ R), (edge, R @ np.diag([-1.0, -1.0, 1.0]))):
                t0 = time.perf_counter()
                _, ok, *_ = self.kin.ik(pos, quaternion_from_matrix(rot), np.zeros(n), 1e-3, 1e-2)
                took = time.perf_counter() - t0
                if not ok and (worst is None or took > worst[0]):
                    worst = (took, {"position": pos.tolist(), "orientation": quaternion_from_matrix(rot).tolist(),
                                    "jp": [0.0] * n})
        assert worst is not None, "no unreachable IK target found near the start pose"
        return worst[1], worst[0]


def targets(robot: SimRobot) -> Targets:
    return _targets(str(robot.profile), robot.arm)


@functools.cache
def _targets(profile: str, arm: str) -> Targets:
    p = load_profile(profile)
    ns = p.namespace(arm)
    k = ns.kinematics
    assert k is not None, f"{profile}: namespace {arm} has no kinematics section"
    kin = Kinematics(k.urdf, k.base_frame, k.tip_frame, list(ns.joints))
    by_name = {j.name: j for j in p.joints}
    lo = np.maximum([by_name[j].limits.position_min + MARGIN for j in ns.joints], -SPAN)
    hi = np.minimum([by_name[j].limits.position_max - MARGIN for j in ns.joints], SPAN)
    kin.set_limits([by_name[j].limits.position_min for j in ns.joints],  # as the daemon's IK
                   [by_name[j].limits.position_max for j in ns.joints])
    n = len(ns.joints)
    pan_axis = np.array(kin.model.jointPlacements[1].translation)
    rng = np.random.default_rng(0)

    def score(q: np.ndarray) -> float:
        T = kin.fk_matrix(q)
        if T[2, 3] < ABOVE_BASE or T[2, 2] > -0.3:  # below the base, or the tool not pointing down
            return -1.0
        clearance = min(1.0, float(np.min(np.minimum(q - lo, hi - q))) / CLEARANCE)
        J = kin.jacobian(q)
        return clearance * float(np.linalg.svd(J if n >= 6 else J[:3], compute_uv=False).min())

    qs = lo + (hi - lo) * rng.random((SAMPLES, n))
    reach = float(max(np.linalg.norm(kin.fk(q)[0] - pan_axis) for q in qs))
    start = max(qs, key=score)
    # the others: from a sample around start
    near = np.clip(start + NEAR * (2.0 * rng.random((SAMPLES, n)) - 1.0), lo, hi)
    chosen = [start]
    tip0 = kin.fk(start)[0]
    scored = sorted(((score(q), i) for i, q in enumerate(near)), reverse=True)
    for s, i in scored:
        q = near[i]
        T = kin.fk_matrix(q)
        if (s > 0 and np.linalg.norm(T[:3, 3] - tip0) < FAR
                and all(np.linalg.norm(T[:3, 3] - kin.fk(c)[0]) > APART for c in chosen)):
            chosen.append(q)
            if len(chosen) == 3:
                break
    assert len(chosen) == 3, f"{profile}: too few well-conditioned configurations near {start}"
    return Targets(kin=kin, start=start, a=chosen[1], b=chosen[2], pan_axis=pan_axis, reach=reach)

"""Kinematics of one CRTK namespace's serial chain: FK, Jacobians, twist/wrench maps and IK.

A thin wrapper over pinocchio in its own idiom: an immutable ``model`` built once from the URDF
named in the profile, one reusable ``data``, free functions of ``(model, data, q)``, frames looked
up by name once and then used by index.

Conventions (every method, SI units):

* Joint vectors (``q``, ``qd``, ``tau``) are numpy float arrays in the order of ``joint_names``
  given to the constructor (the namespace's joints), in rad, rad/s, N*m. URDF joints that are
  not in ``joint_names`` (e.g. the gripper of the arm namespace) are locked at 0 and removed
  from the model (``pinocchio.buildReducedModel``).
* Poses are the tip frame in the base frame: position ``[x, y, z]`` (m) and unit quaternion
  ``[x, y, z, w]`` (the ROS / ``geometry_msgs`` order, *not* Eigen's constructor order), returned
  with ``w >= 0``. The base frame must be fixed to the URDF root (no chain joint moves it).
* 6-vectors and Jacobian rows are ``[linear(3); angular(3)]``, pinocchio's order.
* Two reference frames, matching CRTK's ``spatial/`` and ``body/`` namespaces:

  ``"spatial"``  pinocchio ``LOCAL_WORLD_ALIGNED`` (re-expressed in the base frame if the base is
                 not the URDF root): the tip's linear velocity (of the tip origin, not of the
                 point at the base origin) and angular velocity, both in the **base frame's axes**.
  ``"body"``     pinocchio ``LOCAL``: the same point, both parts in the **tip frame's axes**.

  (pinocchio's ``WORLD`` -- linear velocity of the point coincident with the base origin -- is
  never used: it is not what a CRTK client expects from ``measured_cv``.)

Thread-safety: one instance owns one ``data``; do not call it from two threads at once. The
real-time methods (``fk``, ``fk_matrix``, ``jacobian``, ``twist``, ``wrench_from_efforts``,
``ik``) never block and never log; ``ik`` reports failure in its return value, never by raising.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

try:
    import pinocchio as pin
except ImportError as exc:  # pragma: no cover - depends on the installation
    raise ImportError(
        "crtk_bridge.core.kinematics needs pinocchio: pip install pin"
    ) from exc

from ..errors import ProfileError
from ..vectors import matrix_from_quaternion, quaternion_from_matrix  # noqa: F401 - used here and re-exported

_FRAMES = {"spatial": pin.ReferenceFrame.LOCAL_WORLD_ALIGNED, "body": pin.ReferenceFrame.LOCAL}

# IK internals. Damping grows with the error (Levenberg-Marquardt style): large, careful steps
# far from the target, plain Gauss-Newton (quadratic convergence) close to it; the floor keeps
# the solve well-posed at singularities (arm stretched out, wrist straight).
_DAMP_P_FLOOR = 1e-6  # m^2
_DAMP_P_GAIN = 0.1  # times |e_p|^2
_DAMP_O_FLOOR = 1e-4  # rad^2
_DAMP_O_GAIN = 0.01  # times |e_o|^2
_STEP_MAX = 0.5  # rad: largest joint step per iteration (cold starts overshoot otherwise)
# Stop iterating below these (success is judged by the caller's tolerances); far below the
# STS3215's resolution (1.5 mrad per tick), so a slow servo_cp stream still moves smoothly.
_CONVERGED_P = 1e-6  # m
_CONVERGED_O = 1e-5  # rad
_STALLED = 1e-9  # rad: a step this small means a local minimum or an unreachable target
_PROGRESS_MIN = 1e-7  # m (+ 0.1 m/rad of orientation): less improvement than this is no progress
_PROGRESS_O_WEIGHT = 0.1
_PROGRESS_PATIENCE = 4  # iterations without progress before giving up
_RANK_TOL = 1e-9
# Twist -> joint velocity (joint_velocity): damping only near a position singularity, where the
# smallest singular value of the position Jacobian falls below the band; there the joint speeds
# stay bounded (at most 1 / (2 sqrt(lam)) rad/s per m/s) at the price of a tip-speed shortfall.
_TWIST_SINGULAR_BAND = 0.02  # m/rad
_TWIST_DAMP_P = 1e-4  # m^2 at the singularity
_TWIST_DAMP_O = 1e-4  # rad^2, orientation in the nullspace (as the IK floor)
_BEYOND_REACH_ITER = 10  # singular values below this are treated as 0 for the nullspace projector


class Kinematics:
    """FK, Jacobians and IK of the chain ``base_frame`` -> ``tip_frame`` over ``joint_names``.

    Built once, on the lifecycle path (reads the URDF: blocks on file I/O). Raises
    :class:`~crtk_bridge.errors.ProfileError` naming the URDF path and the missing joint or
    frame, or what else is wrong (unreadable file, invalid URDF, a joint that is not 1-DoF, a
    base frame moved by a joint).

    Attributes: ``model`` (reduced pinocchio model, do not modify), ``data``, ``joint_names``,
    ``n``, ``lower`` / ``upper`` (position limits in ``joint_names`` order, rad; from the URDF
    until :meth:`set_limits`), ``urdf_path``, ``base_frame``, ``tip_frame``.
    """

    def __init__(
        self,
        urdf_path: str | Path,
        base_frame: str,
        tip_frame: str,
        joint_names: Sequence[str],
    ):
        self.urdf_path = str(urdf_path)
        self.base_frame = base_frame
        self.tip_frame = tip_frame
        self.joint_names = list(joint_names)
        src = self.urdf_path
        if not self.joint_names:
            raise ProfileError(f"{src}: kinematics needs at least one joint")
        dup = sorted({j for j in self.joint_names if self.joint_names.count(j) > 1})
        if dup:
            raise ProfileError(f"{src}: joint(s) {', '.join(dup)} listed twice")
        if not Path(src).is_file():
            raise ProfileError(f"{src}: URDF file not found")
        try:
            full = pin.buildModelFromUrdf(src)
        except Exception as exc:  # pinocchio raises ValueError / RuntimeError on bad XML
            raise ProfileError(f"{src}: cannot build a model from this URDF: {exc}") from exc

        urdf_joints = [n for n in list(full.names)[1:]]
        missing = [j for j in self.joint_names if not full.existJointName(j)]
        if missing:
            raise ProfileError(
                f"{src}: joint(s) {', '.join(repr(j) for j in missing)} not in the URDF "
                f"(its joints: {', '.join(urdf_joints)})"
            )
        for name, what in ((base_frame, "base frame"), (tip_frame, "tip frame")):
            if not full.existFrame(name):
                links = [f.name for f in full.frames if f.type == pin.FrameType.BODY]
                raise ProfileError(
                    f"{src}: {what} {name!r} not in the URDF (its links: {', '.join(links)})"
                )
        for j in self.joint_names:
            jm = full.joints[full.getJointId(j)]
            if jm.nq != 1 or jm.nv != 1:
                raise ProfileError(
                    f"{src}: joint {j!r} is a {jm.shortname()} with nq={jm.nq}; only 1-DoF "
                    "revolute / prismatic joints are supported"
                )

        # Lock every other joint at its neutral position (0 for revolute / prismatic).
        lock = [full.getJointId(n) for n in urdf_joints if n not in self.joint_names]
        if lock:
            model = pin.buildReducedModel(full, lock, pin.neutral(full))
        else:
            model = full
        self.model = model
        self.data = model.createData()
        self.n = model.nv
        assert self.n == len(self.joint_names)

        # Map between joint_names order (the caller's) and the model's tree order.
        model_idx = np.array(
            [model.joints[model.getJointId(j)].idx_q for j in self.joint_names], dtype=np.intp
        )
        self._to_model = np.argsort(model_idx)  # q_model = q_user[_to_model]
        self._to_user = model_idx  # q_user = q_model[_to_user]
        self._identity_order = bool(np.all(model_idx == np.arange(self.n)))

        self._tip = model.getFrameId(tip_frame)
        self._base = model.getFrameId(base_frame)
        if model.frames[self._base].parentJoint != 0:
            joint = model.names[model.frames[self._base].parentJoint]
            raise ProfileError(
                f"{src}: base frame {base_frame!r} is moved by joint {joint!r}; the base frame "
                "must be fixed to the URDF root"
            )
        pin.framesForwardKinematics(model, self.data, pin.neutral(model))
        oMb = self.data.oMf[self._base].copy()
        self._base_identity = bool(oMb.isIdentity(1e-12))
        self._bMo = oMb.inverse()
        self._R_bo = self._bMo.rotation.copy()
        self._oMb = oMb

        self.lower = self._user(model.lowerPositionLimit.copy())
        self.upper = self._user(model.upperPositionLimit.copy())
        self._lo_m = model.lowerPositionLimit.copy()
        self._hi_m = model.upperPositionLimit.copy()
        self._eyes = [np.eye(i) for i in range(self.n + 1)]
        self._q = np.zeros(self.n)  # model-order scratch for permuted inputs
        # Upper bound of the distance from the first joint's origin to the tip (triangle
        # inequality over the chain's fixed offsets): a target beyond it is out of reach
        # whatever the joints do, so ik() skips its restarts.
        chain = [j for j in model.supports[model.frames[self._tip].parentJoint] if j != 0]
        self._reach_center = self.data.oMi[chain[0]].translation.copy() if chain else np.zeros(3)
        self._reach_m = sum(float(np.linalg.norm(model.jointPlacements[j].translation)) for j in chain[1:])
        self._reach_m += float(np.linalg.norm(model.frames[self._tip].placement.translation))
        self.last_iterations = 0  # IK iterations of the last ik() call (all attempts), for benches
        self._make_restart_seeds()

    def _make_restart_seeds(self) -> None:
        # Fixed, spread-out seeds (model order) so that ik() is deterministic: the same call
        # always returns the same answer.
        rng = np.random.default_rng(0x5101)
        mid = 0.5 * (self._lo_m + self._hi_m)
        span = self._hi_m - self._lo_m
        self._restart_seeds = [mid.copy()] + [
            self._lo_m + span * (0.1 + 0.8 * rng.random(self.n)) for _ in range(15)
        ]

    # ------------------------------------------------------------------ helpers
    def _model_q(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.shape != (self.n,):
            raise ValueError(f"expected {self.n} joint values ({', '.join(self.joint_names)}), got shape {q.shape}")
        if self._identity_order:
            return q
        np.take(q, self._to_model, out=self._q)
        return self._q

    def _user(self, v: np.ndarray) -> np.ndarray:
        """Model order -> joint_names order (last axis)."""
        return v if self._identity_order else v[..., self._to_user]

    def _model(self, v: np.ndarray) -> np.ndarray:
        return v if self._identity_order else v[..., self._to_model]

    # ------------------------------------------------------------------ limits
    def set_limits(self, lower: Sequence[float], upper: Sequence[float]) -> None:
        """Override the URDF's position limits (rad, ``joint_names`` order); the profile's limits
        are authoritative. IK solutions are clamped to these. Raises ValueError."""
        lo = np.asarray(lower, dtype=float).copy()
        hi = np.asarray(upper, dtype=float).copy()
        if lo.shape != (self.n,) or hi.shape != (self.n,):
            raise ValueError(f"limits need {self.n} values each ({', '.join(self.joint_names)})")
        if not np.all(lo < hi):
            bad = [self.joint_names[i] for i in np.flatnonzero(~(lo < hi))]
            raise ValueError(f"lower limit must be < upper limit for {', '.join(bad)}")
        self.lower, self.upper = lo, hi
        self._lo_m = self._model(lo).copy()
        self._hi_m = self._model(hi).copy()
        self._make_restart_seeds()

    # ------------------------------------------------------------------ FK
    def _placement(self, qm: np.ndarray):
        pin.forwardKinematics(self.model, self.data, qm)
        oMt = pin.updateFramePlacement(self.model, self.data, self._tip)
        return oMt if self._base_identity else self._bMo * oMt

    def link_poses(self, q: np.ndarray) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """Every link of the model (URDF links; joints outside ``joint_names`` at 0) but the base,
        in the base frame at joint positions ``q``: ``(link, position[3], quaternion[4] x,y,z,w)``,
        what robot_state_publisher puts on /tf, for a 3D view of the URDF (recording/live.py)."""
        if not hasattr(self, "_links"):
            self._links = [i for i, f in enumerate(self.model.frames)
                           if f.type == pin.FrameType.BODY and i != self._base]
        pin.framesForwardKinematics(self.model, self.data, self._model_q(q))
        out = []
        for i in self._links:
            M = self.data.oMf[i] if self._base_identity else self._bMo * self.data.oMf[i]
            out.append((self.model.frames[i].name, M.translation.copy(), quaternion_from_matrix(M.rotation)))
        return out

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tip pose in the base frame: ``(position[3] m, quaternion[4] x,y,z,w with w >= 0)``."""
        M = self._placement(self._model_q(q))
        return M.translation.copy(), quaternion_from_matrix(M.rotation)

    def fk_matrix(self, q: np.ndarray) -> np.ndarray:
        """Tip pose in the base frame as a 4x4 homogeneous matrix (m)."""
        return self._placement(self._model_q(q)).homogeneous

    # ------------------------------------------------------------------ Jacobian and its uses
    def jacobian(self, q: np.ndarray, frame: str = "spatial") -> np.ndarray:
        """Tip Jacobian, 6 x n, rows ``[linear; angular]``, columns in ``joint_names`` order.

        ``frame="spatial"``: pinocchio ``LOCAL_WORLD_ALIGNED`` -- velocity of the tip origin and
        angular velocity, both in base-frame axes (CRTK ``spatial/``).
        ``frame="body"``: pinocchio ``LOCAL`` -- the same, in tip-frame axes (CRTK ``body/``).
        Raises ValueError on an unknown frame.
        """
        rf = _FRAMES.get(frame)
        if rf is None:
            raise ValueError(f"frame must be 'spatial' or 'body', got {frame!r}")
        J = pin.computeFrameJacobian(self.model, self.data, self._model_q(q), self._tip, rf)
        if frame == "spatial" and not self._base_identity:
            J[:3] = self._R_bo @ J[:3]
            J[3:] = self._R_bo @ J[3:]
        return self._user(J)

    def twist(self, q: np.ndarray, qd: np.ndarray, frame: str = "spatial") -> np.ndarray:
        """Tip twist ``J(q) @ qd``: ``[v (m/s); w (rad/s)]`` in ``frame`` (see :meth:`jacobian`)."""
        return self.jacobian(q, frame) @ np.asarray(qd, dtype=float)

    def wrench_from_efforts(self, q: np.ndarray, tau: np.ndarray, frame: str = "spatial") -> np.ndarray:
        """Tip wrench ``[force (N); torque (N*m)]`` whose static joint efforts are ``tau``.

        Solves ``J(q)^T @ w = tau`` in the least-squares, minimum-norm sense:
        ``w = pinv(J^T) @ tau`` (SVD, singular values below 1e-6 relative dropped). ``w`` is the
        wrench the tool *exerts on its environment*, at the tip origin, in ``frame``'s axes (see
        :meth:`jacobian`); the external wrench acting on the tool is ``-w``. On a chain with
        fewer than 6 joints ``J^T`` is wide, so infinitely many wrenches give the same efforts:
        the one returned has no component the joints cannot feel (the minimum-norm one, with
        forces and torques weighted alike in that norm). Efforts are used as given: gravity and
        friction are not compensated.
        """
        J = self.jacobian(q, frame)
        return np.linalg.pinv(J.T, rcond=1e-6) @ np.asarray(tau, dtype=float)

    def joint_velocity(self, q: np.ndarray, twist: np.ndarray, frame: str = "spatial",
                       frozen: np.ndarray | None = None) -> np.ndarray:
        """Joint velocities (rad/s, ``joint_names`` order) giving the tip ``twist`` ``[v; w]``
        (m/s, rad/s, in ``frame``'s axes, see :meth:`jacobian`) at ``q``.

        The same task priority as :meth:`ik`: the linear velocity is the primary task, solved
        exactly wherever the position Jacobian has full rank (damped only within 2 cm/rad of a
        position singularity, so the joint speeds stay bounded there); the angular velocity is
        fitted in the least-squares sense in that task's nullspace. On the 5-joint SO-101 that
        means the tip follows the commanded linear velocity and the orientation follows the
        commanded angular velocity as far as the two remaining joints allow (docs/cartesian.md).
        ``frozen`` (bool per joint) marks joints that must not move, e.g. resting on a limit:
        the others do the work. Real-time safe: no logging, a few small arrays, microseconds
        (bench/bench_kinematics.py).
        """
        J = self.jacobian(q, frame)
        if frozen is not None and frozen.any():
            J[:, frozen] = 0.0
        tw = np.asarray(twist, dtype=float)
        return self._priority_solve(J, tw[:3], tw[3:], _TWIST_DAMP_P, _TWIST_DAMP_O, _TWIST_SINGULAR_BAND)

    # ------------------------------------------------------------------ IK
    def ik(
        self,
        target_position: Sequence[float],
        target_quaternion: Sequence[float],
        q_seed: np.ndarray,
        tol_position: float = 1e-3,
        tol_orientation: float = 1e-2,
        max_iter: int = 100,
        restarts: int = 4,
    ) -> tuple[np.ndarray, bool, float, float, str]:
        """Joint positions placing the tip at a pose (base frame), within the position limits.

        Returns ``(q, ok, residual_position_m, residual_orientation_rad, message)``; never raises
        on a bad or unreachable target (``ok`` False, ``message`` says why; ``q`` is then the best
        configuration found, inside the limits, never NaN).

        Method: iterative, seeded with ``q_seed`` (clamped into the limits), task-priority
        damped least squares on the pose error split into a translation error ``p* - p`` (base
        axes) and a rotation error ``log3(R* R^T)`` (base axes, rad) -- the two halves of the SE3
        error, kept apart rather than coupled as in ``log6`` so that position can be the primary
        task:

        1. position (primary): ``dq1 = Jp^+ e_p`` (damped pseudo-inverse of the 3 x n position
           Jacobian of the spatial Jacobian);
        2. orientation (secondary), restricted to the exact nullspace ``N`` of ``Jp``:
           ``dq2 = (Jo N)^+ (e_o - Jo dq1)``; ``dq = dq1 + dq2``, at most 0.5 rad per joint.
        3. ``q += dq``, clamped to the limits; joints resting on a limit and pushed outward are
           frozen (their Jacobian columns zeroed) and the step recomputed.

        Damping is Levenberg-Marquardt-like (grows with the error, vanishes near the solution),
        so a warm start (``q_seed`` = the previous solution or the measured position) converges
        in 2-4 iterations. Iteration stops at convergence (1e-6 m, 1e-5 rad), when the step
        stalls, or after ``max_iter``.

        On the SO-101 (5 joints) a pose has 6 components and the arm has 5: position (3) is
        solved exactly wherever it is reachable; of the orientation, the approach pitch (wrist
        flex) and the roll about the approach axis (wrist roll) are reachable, and the third
        component -- the approach axis' heading, i.e. swinging the tool sideways out of the
        arm's vertical plane, which only shoulder_pan could do and shoulder_pan is spent on
        position -- is lost: the orientation error is then minimised in the least-squares sense
        without giving up any position. A pose computed by FK of any configuration within the
        limits is reachable exactly, so FK(IK(FK(q))) matches FK(q).

        ``ok`` is True only when the final position residual ``|p* - p|`` <= ``tol_position``
        (m) and the rotation angle between target and achieved orientation <=
        ``tol_orientation`` (rad). When that fails from ``q_seed``, up to ``restarts`` more
        attempts start from fixed, spread-out seeds (deterministic) and the best result is
        kept (smallest position residual, then orientation); restarts are skipped when the
        target is farther than the chain's reach. A warm-started stream (``servo_cp``) should
        pass ``restarts=0``: a failure there costs ``restarts`` + 1 solves. Cold solves from far
        away may still fail for unusual (folded) configurations near the joint limits; warm
        starts from the current setpoint are the intended use. To accept position-only
        solutions on a 5-DOF arm (best orientation, whatever its error) pass
        ``tol_orientation=math.inf``.
        """
        qs = np.asarray(q_seed, dtype=float)
        if qs.shape != (self.n,) or not np.all(np.isfinite(qs)):
            q0 = np.zeros(self.n) if qs.shape != (self.n,) else np.nan_to_num(qs)
            return np.clip(q0, self.lower, self.upper), False, math.nan, math.nan, (
                f"IK seed must be {self.n} finite joint positions, got {q_seed!r}"
            )
        p_des = np.asarray(target_position, dtype=float)
        if p_des.shape != (3,) or not np.all(np.isfinite(p_des)):
            return np.clip(qs, self.lower, self.upper), False, math.nan, math.nan, (
                f"IK target position must be 3 finite numbers, got {target_position!r}"
            )
        try:
            if len(target_quaternion) != 4:
                raise ValueError(f"quaternion needs 4 values [x, y, z, w], got {len(target_quaternion)}")
            R_des = matrix_from_quaternion(target_quaternion)
        except (ValueError, TypeError) as exc:
            return np.clip(qs, self.lower, self.upper), False, math.nan, math.nan, (
                f"IK target orientation invalid: {exc}"
            )
        if not self._base_identity:  # the solver works in the URDF root frame
            p_des = self._oMb.act(p_des)
            R_des = self._oMb.rotation @ R_des

        beyond = float(np.linalg.norm(p_des - self._reach_center)) - self._reach_m > tol_position
        if beyond:  # out of reach: a short best-effort solve (arm stretched toward it), no restarts
            max_iter = min(max_iter, _BEYOND_REACH_ITER)
            restarts = 0
        q, err_p, err_o = self._solve(np.clip(self._model(qs), self._lo_m, self._hi_m), p_des, R_des, max_iter)
        iters = self.last_iterations
        ok = err_p <= tol_position and err_o <= tol_orientation
        if ok:
            restarts = 0
        for seed in self._restart_seeds[: max(0, restarts)]:
            q2, ep2, eo2 = self._solve(seed.copy(), p_des, R_des, max_iter)
            iters += self.last_iterations
            # keep the best so far: position first (primary task), then orientation
            if (ep2 <= tol_position, -eo2 if ep2 <= tol_position else -ep2) > (
                err_p <= tol_position, -err_o if err_p <= tol_position else -err_p
            ):
                q, err_p, err_o = q2, ep2, eo2
            ok = err_p <= tol_position and err_o <= tol_orientation
            if ok:
                break
        self.last_iterations = iters
        q_out = self._user(q).copy() if not self._identity_order else q
        if ok:
            msg = "ok"
        else:
            parts = []
            if not err_p <= tol_position:
                parts.append(f"position residual {err_p:.3g} m > {tol_position:.3g} m")
            if not err_o <= tol_orientation:
                parts.append(f"orientation residual {err_o:.3g} rad > {tol_orientation:.3g} rad")
            msg = "IK did not converge: " + ", ".join(parts)
            if beyond:
                msg += f" (target is beyond the arm's reach of {self._reach_m:.3g} m)"
            if self.n < 6 and err_p <= tol_position:
                msg += f" (a {self.n}-joint arm cannot reach every orientation at a given position)"
        return q_out, ok, err_p, err_o, msg

    def _solve(self, q: np.ndarray, p_des: np.ndarray, R_des: np.ndarray, max_iter: int):
        """Iterate from ``q`` (model order, inside the limits; modified in place). Returns
        ``(q, position error m, orientation error rad)`` at the final ``q``."""
        model, data, tip = self.model, self.data, self._tip
        lo, hi = self._lo_m, self._hi_m
        LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        e_p = np.empty(3)
        err_p = err_o = math.inf
        it = 0
        prev = math.inf
        slow = 0
        while True:
            J = pin.computeFrameJacobian(model, data, q, tip, LWA)  # runs the FK pass too
            M = pin.updateFramePlacement(model, data, tip)
            np.subtract(p_des, M.translation, out=e_p)
            e_o = pin.log3(R_des @ M.rotation.T)
            err_p = math.sqrt(e_p @ e_p)
            err_o = math.sqrt(e_o @ e_o)
            if (err_p < _CONVERGED_P and err_o < _CONVERGED_O) or it >= max_iter:
                break
            # No progress for a few iterations: out of reach, a local minimum, or a pose whose
            # orientation a <6-joint chain cannot match (the nullspace optimum is reached).
            metric = err_p + _PROGRESS_O_WEIGHT * err_o
            slow = slow + 1 if prev - metric < _PROGRESS_MIN else 0
            if slow >= _PROGRESS_PATIENCE:
                break
            prev = metric
            it += 1
            dq = self._ik_step(J, e_p, e_o, err_p, err_o)
            at_lo = (q <= lo) & (dq < 0)
            at_hi = (q >= hi) & (dq > 0)
            if at_lo.any() or at_hi.any():
                J = J * (~(at_lo | at_hi))  # freeze those joints, re-solve with the others
                dq = self._ik_step(J, e_p, e_o, err_p, err_o)
            big = np.abs(dq).max()
            if big > _STEP_MAX:
                dq *= _STEP_MAX / big
            elif big < _STALLED:
                break
            q += dq
            np.clip(q, lo, hi, out=q)
        self.last_iterations = it
        return q, err_p, err_o

    def _ik_step(self, J: np.ndarray, e_p: np.ndarray, e_o: np.ndarray, err_p: float, err_o: float) -> np.ndarray:
        """One task-priority damped least-squares step (model order)."""
        lam_p = _DAMP_P_FLOOR + _DAMP_P_GAIN * err_p * err_p
        lam_o = _DAMP_O_FLOOR + _DAMP_O_GAIN * err_o * err_o
        return self._priority_solve(J, e_p, e_o, lam_p, lam_o)

    def _priority_solve(self, J: np.ndarray, e_p: np.ndarray, e_o: np.ndarray, lam_p: float, lam_o: float,
                        singular_band: float = 0.0) -> np.ndarray:
        """``dq`` with ``Jp dq = e_p`` (damped least squares, primary) and ``Jo dq ~ e_o`` in the
        nullspace of ``Jp`` (secondary). Column order in = order out. With ``singular_band`` > 0
        (m/rad) the position damping ``lam_p`` applies only as the smallest singular value of
        ``Jp`` drops below the band, growing to ``lam_p`` at the singularity (Nakamura-Hanafusa /
        Chiaverini); away from it the primary task is solved exactly."""
        Jp = J[:3]
        Jo = J[3:]
        U, s, Vt = np.linalg.svd(Jp, full_matrices=True)  # Jp = U diag(s) Vt[:3]
        if singular_band > 0.0:
            closeness = 1.0 - (s[-1] / singular_band) ** 2
            lam_p = lam_p * closeness if closeness > 0.0 else 0.0
        dq = Vt[:3].T @ ((s / (s * s + lam_p)) * (U.T @ e_p)) if lam_p > 0.0 else \
            Vt[:3].T @ (np.divide(1.0, s, out=np.zeros_like(s), where=s > _RANK_TOL) * (U.T @ e_p))
        r = int(np.count_nonzero(s > _RANK_TOL))
        # Exact nullspace of Jp: the right singular vectors with zero singular value.
        Nb = Vt[r:]  # (n - r) x n basis, rows orthonormal
        if Nb.shape[0]:
            A = Jo @ Nb.T  # 3 x (n - r)
            e2 = e_o - Jo @ dq
            # damped least squares in nullspace coordinates: (A^T A + lam I) z = A^T e2
            z = np.linalg.solve(A.T @ A + lam_o * self._eyes[A.shape[1]], A.T @ e2)
            dq += Nb.T @ z
        return dq

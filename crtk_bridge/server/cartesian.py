"""Cartesian CRTK for one namespace, in the front process: queries from the snapshot, position-
and effort-level commands translated to joint commands before they reach the control loop.

Why IK here and not in the loop: IK costs 0.1 ms warm and up to tens of ms cold (bench/), which
the real-time loop must not pay; FK and Jacobians for queries are pure functions of a joint
sample. So ``servo_cp`` becomes ``servo_jp`` of the IK solution, ``servo_cf`` ``servo_jf`` of
Jᵀ·wrench, ..., and the loop's limits, watchdog, busy edges and faults apply unchanged.
Twists (``servo_cv``, ``interpolate_cv``) are only validated here: a twist holds at one
configuration only, so the control process maps it every cycle (core/twist.py).

A namespace whose backend does cartesian control itself (``native_cartesian``: a UR's
``servoL`` / ``speedL`` / ``moveL``) gets its pose and twist commands passed through unchanged
(relative ones composed with the pose the backend measures), no IK, and its ``measured_cp`` is
the backend's own tip pose; ``setpoint_cp``, ``setpoint_cv`` and ``goal_cp`` are what it was
commanded (core/native_cartesian.py), while that command is in force.

IK never runs on the front's event loop: position-level commands and ``inverse_kinematics`` run
on one worker thread per namespace (FIFO, so a namespace's IK requests keep their order) with
their own pinocchio model and data (a ``Kinematics`` is not thread-safe), while the loop goes on
serving every other session. Queries (FK, Jacobians: microseconds) stay on the loop.

Conventions (docs/protocol.md, "Cartesian"):
* poses are the tip frame in the base frame, ``position`` [m] + ``orientation`` quaternion
  ``[x, y, z, w]``;
* twists ``linear`` [m/s] + ``angular`` [rad/s], wrenches ``force`` [N] + ``torque`` [N·m], in the
  base frame's axes at the tip (``spatial``, the default) or in the tip frame's axes (``body``, via
  the ``<ns>/body`` namespace);
* relative commands (``*_cr``) are in the base frame: the translation is added to the current
  position, the rotation pre-multiplies the current orientation;
* cartesian data carries the stamp of the joint sample it was computed from; stamp 0 when that
  data is invalid (``setpoint_cp`` is valid only while the active command is position based).
"""

from __future__ import annotations

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numpy as np

from .. import vectors
from ..core.kinematics import Kinematics
from ..profile import KinematicsConfig, Profile
from ..vectors import matrix_from_quaternion, quaternion_from_matrix
from .protocol import ProtocolError

POSE_CMDS = ("servo_cp", "interpolate_cp", "move_cp")
RELATIVE_CMDS = ("servo_cr", "interpolate_cr", "move_cr")
TWIST_CMDS = ("servo_cv", "interpolate_cv")
WRENCH_CMDS = ("servo_cf", "interpolate_cf")
#: cartesian command -> the joint command it becomes
JOINT_EQUIVALENT = {
    "servo_cp": "servo_jp", "interpolate_cp": "interpolate_jp", "move_cp": "move_jp",
    "servo_cr": "servo_jr", "interpolate_cr": "interpolate_jp", "move_cr": "move_jp",
    "servo_cv": "servo_jv", "interpolate_cv": "interpolate_jv",
    "servo_cf": "servo_jf", "interpolate_cf": "interpolate_jf",
}
#: what a native cartesian backend receives (relative commands arrive composed, as *_cp)
NATIVE_ROUTED = POSE_CMDS + RELATIVE_CMDS + TWIST_CMDS
FRAMED = ("measured_cv", "measured_cf", "setpoint_cv", "setpoint_cf", "goal_cv") + TWIST_CMDS + WRENCH_CMDS


class CartesianSpace:
    def __init__(self, profile: Profile, ns: str, config: KinematicsConfig, joint_commands: list[str],
                 measures_effort: bool, native: bool = False, measures_wrench: bool = False):
        self.ns = ns
        self.cfg = config
        self.native = native  # the backend takes cartesian setpoints and measures the tip pose
        self.native_wrench = native and measures_wrench  # ...and the tip wrench (UR actual_TCP_force)
        spec = profile.namespace(ns)
        idx = [profile.joint_index(j) for j in spec.joints]
        lower = [profile.joints[i].limits.position_min for i in idx]
        upper = [profile.joints[i].limits.position_max for i in idx]
        # two solvers: one for the event loop's queries, one owned by the IK worker thread
        self.kin, self._ik_kin = (Kinematics(config.urdf, config.base_frame, config.tip_frame, list(spec.joints))
                                  for _ in range(2))
        for kin in (self.kin, self._ik_kin):
            kin.set_limits(lower, upper)
        self._ik_worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"ik {ns}")
        self.n = len(idx)
        self.commands = [c for c, j in JOINT_EQUIVALENT.items() if j in joint_commands]
        self.queries = ["measured_cp", "measured_cv", "setpoint_cp", "setpoint_cv", "goal_cp", "goal_cv",
                        "forward_kinematics", "inverse_kinematics"]
        if measures_effort or self.native_wrench:
            self.queries.append("measured_cf")
        if "servo_jf" in joint_commands:
            self.queries.append("setpoint_cf")

    # ---------------------------------------------------------------- payloads
    def _pose(self, stamp: float, q: np.ndarray | None) -> dict:
        if q is None:
            return {"stamp": 0.0, "frame_id": self.cfg.base_frame, "child_frame_id": self.cfg.tip_frame,
                    "position": [], "orientation": []}
        p, quat = self.kin.fk(q)
        return {"stamp": stamp, "frame_id": self.cfg.base_frame, "child_frame_id": self.cfg.tip_frame,
                "position": p.tolist(), "orientation": quat.tolist()}

    def _native_pose(self, st: dict) -> dict:
        if not st["native_stamp"] > 0:
            return self._pose(0.0, None)
        return self._commanded_pose(st["native_stamp"], st["native_p"], st["native_q"])

    def _commanded_pose(self, stamp: float, p: np.ndarray, quat: np.ndarray) -> dict:
        return {"stamp": stamp, "frame_id": self.cfg.base_frame, "child_frame_id": self.cfg.tip_frame,
                "position": p.tolist(), "orientation": quaternion_from_matrix(matrix_from_quaternion(quat)).tolist()}

    @staticmethod
    def _native_twist(st: dict, frame: str) -> np.ndarray:
        """The twist a native backend runs, in ``frame``'s axes (turned by the measured tip orientation)."""
        v = st["native_tw"]
        if st["native_tw_body"] == (frame == "body"):
            return v
        rot = matrix_from_quaternion(st["native_q"])
        if frame == "body":
            rot = rot.T
        return np.concatenate([rot @ v[:3], rot @ v[3:]])

    def _six(self, kind: str, stamp: float, vec: np.ndarray | None, frame: str) -> dict:
        a, b = ("linear", "angular") if kind == "twist" else ("force", "torque")
        base = {"stamp": stamp if vec is not None else 0.0,
                "frame_id": self.cfg.base_frame if frame == "spatial" else self.cfg.tip_frame,
                "child_frame_id": self.cfg.tip_frame}
        if vec is None:
            base.update({a: [], b: []})
        else:
            base.update({a: vec[:3].tolist(), b: vec[3:].tolist()})
        return base

    # ---------------------------------------------------------------- queries
    def query(self, cmd: str, st: dict, frame: str) -> dict:
        """``st`` is the namespace's joint state from one snapshot read (see ControlLink.ns_arrays)."""
        if cmd == "measured_cp":
            if self.native:  # the backend's own TCP pose, with the stamp of its sample
                return self._native_pose(st)
            return self._pose(st["measured_stamp"], st["measured_p"] if st["measured_stamp"] else None)
        if cmd == "measured_cv":
            ok = st["measured_stamp"] and st["measures_velocity"]
            v = self.kin.twist(st["measured_p"], st["measured_v"], frame) if ok else None
            return self._six("twist", st["measured_stamp"], v, frame)
        if cmd == "measured_cf" and self.native_wrench:  # measured by the backend at the tip, base axes
            w = st["native_f"] if st["native_stamp"] > 0 else None
            if w is not None and frame == "body":
                rot = matrix_from_quaternion(st["native_q"]).T
                w = np.concatenate([rot @ w[:3], rot @ w[3:]])
            return self._six("wrench", st["native_stamp"], w, frame)
        if cmd == "measured_cf":
            ok = st["measured_stamp"] and st["measures_effort"]
            w = self.kin.wrench_from_efforts(st["measured_p"], st["measured_f"], frame) if ok else None
            return self._six("wrench", st["measured_stamp"], w, frame)
        if self.native:  # what the backend was commanded, while a cartesian command of it is in force
            if cmd == "setpoint_cp" and st["native_sp_stamp"] > 0:
                return self._commanded_pose(st["native_sp_stamp"], st["native_sp_p"], st["native_sp_q"])
            if cmd == "goal_cp" and st["native_goal_stamp"] > 0:
                return self._commanded_pose(st["native_goal_stamp"], st["native_goal_p"], st["native_goal_q"])
            if cmd == "setpoint_cv" and st["native_tw_stamp"] > 0:
                return self._six("twist", st["native_tw_stamp"], self._native_twist(st, frame), frame)
        if cmd == "setpoint_cp":  # spec 4.2.6: valid only when the active command is position based
            return self._pose(st["setpoint_stamp"], st["setpoint_p"] if st["setpoint_has_p"] else None)
        if cmd == "setpoint_cv":
            ok = st["setpoint_has_v"] and st["setpoint_has_p"]
            v = self.kin.twist(st["setpoint_p"], st["setpoint_v"], frame) if ok else None
            return self._six("twist", st["setpoint_stamp"], v, frame)
        if cmd == "setpoint_cf":
            ok = st["setpoint_has_f"]
            w = self.kin.wrench_from_efforts(st["measured_p"], st["setpoint_f"], frame) if ok else None
            return self._six("wrench", st["setpoint_stamp"], w, frame)
        if cmd == "goal_cp":
            return self._pose(st["goal_stamp"], st["goal_p"] if st["goal_has_p"] else None)
        if cmd == "goal_cv":
            ok = st["goal_has_v"]
            v = self.kin.twist(st["measured_p"], st["goal_v"], frame) if ok else None
            return self._six("twist", st["goal_stamp"], v, frame)
        raise ProtocolError("unknown_command", f"{self.ns}: unknown cartesian query {cmd!r}")

    def forward_kinematics(self, data: Any) -> dict:
        q = self._vec(data, "jp", self.n, "forward_kinematics")
        return self._pose(time.time(), q)  # a computed pose: stamped when computed

    async def _off_loop(self, fn: Callable, *args: Any) -> Any:
        """Run ``fn(*args)`` on this namespace's IK worker (in arrival order); the event loop
        serves other requests meanwhile. Exceptions (ProtocolError) propagate to the caller."""
        return await asyncio.get_running_loop().run_in_executor(self._ik_worker, fn, *args)

    def close(self) -> None:
        """Stop the IK worker; requests still queued are dropped (the daemon is stopping)."""
        self._ik_worker.shutdown(wait=False, cancel_futures=True)

    async def inverse_kinematics(self, data: Any, st: dict) -> dict:
        """The ``inverse_kinematics`` query, solved on the IK worker."""
        return await self._off_loop(self._inverse_kinematics, data, st)

    def _inverse_kinematics(self, data: Any, st: dict) -> dict:  # IK worker thread
        p, quat = self._target(data, "inverse_kinematics")
        seed = data.get("jp")
        seed = self._vec(data, "jp", self.n, "inverse_kinematics") if seed else st["measured_p"]
        q, ok, rp, ro, msg = self._ik_kin.ik(p, quat, seed, self.cfg.ik_tolerance_position,
                                             self.cfg.ik_tolerance_orientation)
        return {"jp": q.tolist(), "result": bool(ok), "message": msg,
                "residual_position": float(rp), "residual_orientation": float(ro)}

    # ---------------------------------------------------------------- commands -> joint commands
    async def translate(self, cmd: str, data: Any, st: dict, frame: str, busy: bool) -> tuple[str, dict]:
        """The command the control process runs for cartesian ``cmd``: the joint equivalent of a
        pose (IK on the worker) or wrench, or the validated twist itself. ``st`` is the joint
        state when the command arrived. Raises ProtocolError (ik_failed, bad_request)."""
        if self.native and cmd in NATIVE_ROUTED:
            return self._native_command(cmd, data, st, frame)
        if cmd in POSE_CMDS or cmd in RELATIVE_CMDS:
            return await self._off_loop(self._translate_pose, cmd, data, st, busy)
        if cmd in TWIST_CMDS:  # mapped every cycle in the control process (core/twist.py)
            return cmd, {"linear": self._vec(data, "linear", 3, cmd).tolist(),
                         "angular": self._vec(data, "angular", 3, cmd).tolist(), "frame": frame}
        wrench = np.concatenate([self._vec(data, "force", 3, cmd), self._vec(data, "torque", 3, cmd)])
        J = self.kin.jacobian(st["measured_p"], frame)
        return JOINT_EQUIVALENT[cmd], {"effort": (J.T @ wrench).tolist()}

    def _native_command(self, cmd: str, data: Any, st: dict, frame: str) -> tuple[str, dict]:
        """For a native cartesian backend: the pose or twist itself, validated; a relative
        command composed (base frame, as everywhere) with the pose the backend measures."""
        if cmd in TWIST_CMDS:
            return cmd, {"linear": self._vec(data, "linear", 3, cmd).tolist(),
                         "angular": self._vec(data, "angular", 3, cmd).tolist(), "frame": frame}
        p, quat = self._target(data, cmd)
        if cmd in RELATIVE_CMDS:
            if not st["native_stamp"] > 0:
                raise ProtocolError("invalid_state", f"{self.ns}: {cmd} refused: no measured pose to be relative to")
            p = st["native_p"] + p
            quat = quaternion_from_matrix(matrix_from_quaternion(quat) @ matrix_from_quaternion(st["native_q"]))
            cmd = cmd[:-1] + "p"  # servo_cr -> servo_cp ...
        return cmd, {"position": p.tolist(), "orientation": quat.tolist()}

    def _translate_pose(self, cmd: str, data: Any, st: dict, busy: bool) -> tuple[str, dict]:  # IK worker
        joint_cmd = JOINT_EQUIVALENT[cmd]
        current = st["setpoint_p"] if st["setpoint_has_p"] else st["measured_p"]
        if cmd in POSE_CMDS:
            p, quat = self._target(data, cmd)
            return joint_cmd, {"position": self._ik(cmd, p, quat, current).tolist()}
        # relative: the delta composed with the current pose
        dp, dquat = self._target(data, cmd)
        if cmd == "servo_cr":
            base = current
        elif cmd == "move_cr":
            base = st["goal_p"] if busy and st["goal_has_p"] else current
        else:  # interpolate_cr: relative to the last interpolate goal while a stream runs
            base = st["goal_p"] if st["goal_has_p"] else current
        T = self._ik_kin.fk_matrix(base)
        p = T[:3, 3] + dp
        R = matrix_from_quaternion(dquat) @ T[:3, :3]  # base frame: pre-multiply
        q = self._ik(cmd, p, quaternion_from_matrix(R), base)
        if cmd == "servo_cr":
            return joint_cmd, {"position": (q - current).tolist()}  # accumulates in the loop
        return joint_cmd, {"position": q.tolist()}

    def _ik(self, cmd: str, p: np.ndarray, quat: np.ndarray, seed: np.ndarray) -> np.ndarray:
        restarts = 4 if cmd.startswith("move") else 0  # streams: one warm solve, never a slow search
        q, ok, rp, ro, msg = self._ik_kin.ik(p, quat, seed, self.cfg.ik_tolerance_position,
                                             self.cfg.ik_tolerance_orientation, restarts=restarts)
        if not ok:
            raise ProtocolError("ik_failed", f"{self.ns}: {cmd} refused: {msg}")
        return q

    def _target(self, data: Any, cmd: str) -> tuple[np.ndarray, np.ndarray]:
        """(position, unit quaternion) of a pose payload (crtk_bridge/vectors.py). Raises ProtocolError."""
        try:
            return vectors.pose(data, f"{self.ns}: {cmd}")
        except vectors.InvalidVector as exc:
            raise ProtocolError(exc.code, exc.message) from None

    def _vec(self, data: Any, field: str, n: int, cmd: str) -> np.ndarray:
        """``data[field]``: ``n`` finite numbers (crtk_bridge/vectors.py). Raises ProtocolError."""
        try:
            return vectors.field(data, field, n, f"{self.ns}: {cmd}")
        except vectors.InvalidVector as exc:
            raise ProtocolError(exc.code, exc.message) from None

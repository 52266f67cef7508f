"""Velocity-level cartesian commands (``servo_cv``, ``interpolate_cv``), mapped every cycle.

A twist is not a joint velocity: ``J(q)⁺·twist`` holds only at the ``q`` it was computed at. So
the control process keeps the commanded twist and, each cycle before the namespace's motion
step, maps it to joint velocities at the current position setpoint
(:meth:`~crtk_bridge.core.kinematics.Kinematics.joint_velocity`: task priority, linear velocity
first, as docs/cartesian.md says for the 5-joint SO-101). The joint motion then runs exactly as
for ``servo_jv`` / ``interpolate_jv`` (``motion.py``): integrated into a position setpoint on
position-only hardware (or sent as velocity on native velocity hardware), stopped at the
position limits, with the servo watchdog and the same ``setpoint_js`` / ``goal_js`` fields.

Bounds applied here, every cycle, on top of motion's:

* position limits: a joint resting on a limit and pushed outward is frozen (its Jacobian column
  zeroed) and the twist re-solved with the others, so the tip keeps its course as long as it can;
* velocity limits: the joint velocity vector is scaled down as a whole (not clipped joint by
  joint) so that no joint exceeds its ``velocity_max``; the tip keeps its direction, slower;
* acceleration limits: ``servo_cv`` changes the joint velocity by at most
  ``acceleration_max · dt`` per cycle (again scaled as a whole); ``interpolate_cv`` maps its goal
  twist to the joint velocity goal that ``interpolate_jv``'s ramp then follows at
  ``acceleration_max``.

The stream ends when anything else drives the namespace: another motion command, ``hold``,
pause, client loss, the watchdog, a fault (the namespace leaves the velocity mode or the
controller calls :meth:`TwistMotion.cancel`).

Why in the control process and not in the front: the front used to map the twist once, at
request time, so the tip followed it only at the first instant (``servo_cv`` 0.02 m/s for 1 s
moved the SO-101 tip 3.2 mm instead of 20 mm). A Jacobian solve costs tens of microseconds
(bench/bench_kinematics.py: "twist -> joint velocity"), well within a cycle.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .. import vectors
from ..profile import Profile
from .motion import Mode, NamespaceMotion

TWIST_COMMANDS = ("servo_cv", "interpolate_cv")
FRAMES = ("spatial", "body")


class TwistMotion:
    """The twist stream of one namespace with a kinematics section. Not thread-safe.

    ``kin`` is a :class:`~crtk_bridge.core.kinematics.Kinematics` over the namespace's joints,
    built in the control process (see :func:`build_twist_motions`).
    """

    def __init__(self, motion: NamespaceMotion, kin: Any):
        self.motion = motion
        self.kin = kin
        self.twist = np.zeros(6)  # servo: the commanded twist; interpolate: the goal twist
        self.frame = "spatial"
        self.mode: Mode | None = None  # SERVO_V or INTERP_V while a twist drives the namespace
        self._frozen = np.zeros(motion.n, dtype=bool)
        self._dv_max = motion.acc_max * motion.dt

    @property
    def active(self) -> bool:
        return self.mode is not None and self.motion.mode is self.mode

    def servo(self, twist: np.ndarray, frame: str, now: float) -> None:
        """``servo_cv``: follow ``twist`` from the next cycle on (until the next command)."""
        m = self.motion
        # from the velocity the setpoint really has (no jump), toward the twist's at acceleration_max
        m.servo_v(m.carried_velocity(), now)  # SERVO_V level: watchdog, setpoint fields, goal invalid
        self.twist[:] = twist
        self.frame = frame
        self.mode = Mode.SERVO_V

    def interpolate(self, twist: np.ndarray, frame: str, now: float) -> None:
        """``interpolate_cv``: the joint velocity ramps (at the acceleration limits) toward the
        velocity that gives ``twist``, re-mapped every cycle."""
        self.twist[:] = twist
        self.frame = frame
        self.motion.interpolate_v(self._map(), now)
        self.mode = Mode.INTERP_V

    def cancel(self) -> None:
        """Another command took the namespace over."""
        self.mode = None

    def update(self) -> None:
        """One cycle, before the namespace's motion step: re-map the twist at the setpoint."""
        if self.mode is None:
            return
        m = self.motion
        if m.mode is not self.mode:  # hold, stop, watchdog, fault, free: the stream is over
            self.mode = None
            return
        qd = self._map()
        if self.mode is Mode.SERVO_V:
            dv = qd - m.setpoint_v
            worst = float(np.max(np.abs(dv) / self._dv_max))
            if worst > 1.0:
                dv /= worst
            m.setpoint_v += dv
        else:
            m.goal_v[:] = qd

    def _map(self) -> np.ndarray:
        m = self.motion
        p = m.setpoint_p
        # the solve is linear in the twist: solve for it scaled to components <= 1 and scale the
        # result back, so a huge (finite) twist cannot overflow into inf / NaN setpoints
        scale = max(1.0, float(np.max(np.abs(self.twist))))
        twist = self.twist / scale if scale > 1.0 else self.twist
        qd = self.kin.joint_velocity(p, twist, self.frame)
        frozen = self._frozen
        np.logical_or((p <= m.pos_min) & (qd < 0.0), (p >= m.pos_max) & (qd > 0.0), out=frozen)
        if frozen.any():
            qd = self.kin.joint_velocity(p, twist, self.frame, frozen)
            qd[frozen] = 0.0
        worst = float(np.max(np.abs(qd) / m.vel_max))  # of the scaled twist's joint velocity
        if worst * scale > 1.0:
            qd /= worst
        elif scale > 1.0:
            qd *= scale
        return qd


def parse_twist(ns: str, cmd: str, data: Any) -> tuple[np.ndarray, str]:
    """``{"linear": [3], "angular": [3], "frame"?: "spatial"|"body"}`` -> (twist[6], frame).
    Raises :class:`~crtk_bridge.vectors.InvalidVector` (``bad_request``, a ValueError) with a
    one-line message naming the namespace and the field."""
    twist = vectors.six(data, "linear", "angular", f"{ns}: {cmd}")
    frame = data.get("frame", "spatial")
    if frame not in FRAMES:
        raise vectors.InvalidVector(f"{ns}: {cmd} frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    return twist, frame


def build_twist_motions(profile: Profile, namespaces: dict[str, NamespaceMotion]) -> dict[str, TwistMotion]:
    """One :class:`TwistMotion` per namespace whose profile entry has a ``kinematics`` section.

    Lifecycle path: reads the URDFs (blocks on file I/O; raises ProfileError naming the URDF and
    what is wrong). Called where the controller is built, i.e. in the control process after the
    fork, so the pinocchio model and data belong to the process that uses them every cycle (and
    the front builds its own for queries and IK). Each solver is exercised once here so that the
    first cycle of a stream does not pay first-call costs."""
    out: dict[str, TwistMotion] = {}
    specs = [ns for ns in profile.namespaces if ns.kinematics is not None]
    if not specs:
        return out
    from .kinematics import Kinematics  # pinocchio only where a profile has kinematics

    for spec in specs:
        m = namespaces[spec.name]
        cfg = spec.kinematics
        kin = Kinematics(cfg.urdf, cfg.base_frame, cfg.tip_frame, list(spec.joints))
        kin.set_limits(m.pos_min, m.pos_max)
        tm = TwistMotion(m, kin)
        kin.joint_velocity(np.clip(np.zeros(m.n), m.pos_min, m.pos_max), np.zeros(6))
        out[spec.name] = tm
    return out

"""Validation of motion commands: shape, finiteness, step size and joint limits (docs/architecture.md,
"Limits").

What a command carries is read by :mod:`crtk_bridge.vectors` (the one reader the client and the
front use too) and refused here with one line naming the namespace, the command, the field and
the joint. These are the command's refusals; the guarantee of the profile's limits on what
reaches a motor is the motion layer's output (``motion.NamespaceMotion.fill``), and
:meth:`~crtk_bridge.core.actuator.Actuator.write` refuses a non-finite setpoint for every backend.
"""

from __future__ import annotations

from operator import le, sub
from typing import Any

import numpy as np

from ... import vectors
from ...errors import fmt_number
from ..motion import NamespaceMotion
from ..native_cartesian import parse_pose
from ..twist import parse_twist
from .common import Refused

_WARN_INTERVAL_S = 1.0  # at most one clipping warning per namespace per second


class ValidationMixin:
    """Command validation of :class:`~.controller.Controller` (whose state it shares)."""

    def _vector(self, ns: str, cmd: str, motion: NamespaceMotion, values: Any, field: str) -> np.ndarray:
        """``values``: one finite number per joint of ``motion``. Raises Refused(bad_request)."""
        try:
            return vectors.floats(values, f"{ns}: {cmd} {field}", motion.n, motion.joint_names)
        except vectors.InvalidVector as exc:
            raise Refused(exc.code, exc.message) from None

    def _pose(self, ns: str, cmd: str, data: Any) -> tuple[np.ndarray, np.ndarray]:
        """(position, unit quaternion) of a pose command. Raises Refused(bad_request)."""
        try:
            return parse_pose(ns, cmd, data)
        except vectors.InvalidVector as exc:
            raise Refused(exc.code, exc.message) from None

    def _twist(self, ns: str, cmd: str, data: Any) -> tuple[np.ndarray, str]:
        """(twist [6], frame) of a twist command. Raises Refused(bad_request)."""
        try:
            return parse_twist(ns, cmd, data)
        except vectors.InvalidVector as exc:
            raise Refused(exc.code, exc.message) from None

    def _check_step(self, m: NamespaceMotion, p: np.ndarray, base: np.ndarray, cmd: str) -> None:
        """A position stream's step beyond ``safety.servo_step_max`` is refused, naming the joint."""
        limit = self.safety.servo_step_max
        # Python floats over a few joints: a tenth of numpy's calls (abs, argmax) per request
        if max(map(abs, map(sub, p.tolist(), base.tolist()))) <= limit:
            return
        step = np.abs(p - base)
        worst = int(np.argmax(step))
        if step[worst] > limit:
            raise Refused(
                "step_too_large",
                f"{m.name}: {cmd} refused: joint {m.joint_names[worst]!r} would jump {fmt_number(step[worst])} rad "
                f"from {fmt_number(base[worst])} (safety.servo_step_max = {self.safety.servo_step_max})",
            )

    def _check_goal(self, m: NamespaceMotion, goal: np.ndarray) -> None:
        """A move goal outside the joint limits is refused, naming the joint and its limits."""
        bad = np.flatnonzero((goal < m.pos_min) | (goal > m.pos_max))
        if bad.size:
            j = int(bad[0])
            raise Refused(
                "out_of_limits",
                f"{m.name}: move refused: goal {fmt_number(goal[j])} rad for joint {m.joint_names[j]!r} is outside "
                f"its limits [{fmt_number(m.pos_min[j])}, {fmt_number(m.pos_max[j])}]",
            )

    def _clip(self, m: NamespaceMotion, p: np.ndarray) -> np.ndarray:
        """A stream's position clipped to the joint limits, said in a rate-limited warning
        (``p`` itself when it is within them: the request's own new array)."""
        if all(map(le, m.pos_min.tolist(), p.tolist())) and all(map(le, p.tolist(), m.pos_max.tolist())):
            return p  # (Python floats: np.clip and np.any cost ~10 us per request)
        clipped = np.clip(p, m.pos_min, m.pos_max)
        now = self.clock()
        if np.any(clipped != p) and now - m.last_clip_warning >= _WARN_INTERVAL_S:
            m.last_clip_warning = now
            j = int(np.argmax(np.abs(clipped - p)))
            self.event(
                "warning", "limit_clipped",
                f"{m.name}: setpoint of joint {m.joint_names[j]!r} ({fmt_number(p[j])} rad) clipped to its limit "
                f"[{fmt_number(m.pos_min[j])}, {fmt_number(m.pos_max[j])}]", m.name, joint=m.joint_names[j], value=float(p[j]),
            )
        return clipped

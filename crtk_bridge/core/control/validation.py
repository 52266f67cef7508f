"""Validation of motion commands: shape, finiteness, step size and joint limits."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...errors import fmt_number
from ..motion import NamespaceMotion
from .common import Refused

_WARN_INTERVAL_S = 1.0  # at most one clipping warning per namespace per second


class ValidationMixin:
    """Command validation of :class:`~.controller.Controller` (whose state it shares)."""

    def _vector(self, ns: str, cmd: str, motion: NamespaceMotion, values: Any, field: str) -> np.ndarray:
        if not isinstance(values, (list, tuple)) or len(values) != motion.n:
            got = len(values) if isinstance(values, (list, tuple)) else type(values).__name__
            raise Refused(
                "bad_request",
                f"{ns}: {cmd} needs {field} with {motion.n} values ({', '.join(motion.joint_names)}), got {got}",
            )
        try:
            vec = np.array(values, dtype=float)
        except (TypeError, ValueError):
            raise Refused("bad_request", f"{ns}: {cmd} {field} must be numbers") from None
        if not np.all(np.isfinite(vec)):
            raise Refused("bad_request", f"{ns}: {cmd} {field} contains a non-finite value")
        return vec

    def _check_step(self, m: NamespaceMotion, p: np.ndarray, base: np.ndarray, cmd: str) -> None:
        step = np.abs(p - base)
        worst = int(np.argmax(step))
        if step[worst] > self.safety.servo_step_max:
            raise Refused(
                "step_too_large",
                f"{m.name}: {cmd} refused: joint {m.joint_names[worst]!r} would jump {fmt_number(step[worst])} rad "
                f"from {fmt_number(base[worst])} (safety.servo_step_max = {self.safety.servo_step_max})",
            )

    def _clip(self, m: NamespaceMotion, p: np.ndarray) -> np.ndarray:
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

"""Requests the controller relays to the backend or to another layer: calibration, native
cartesian commands (core/native_cartesian.py), twists (core/twist.py), and the device's own
goal check before a move."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...errors import BackendError, CommandError
from ..actuator import Lifecycle, Steps, Transition
from ..motion import Mode
from ..state import OperatingState
from .common import Refused


class RelaysMixin:
    """Calibration, native cartesian and twist commands, goal checks of
    :class:`~.controller.Controller` (whose state it shares)."""

    def _calibrate(self, data: dict) -> Any:
        """``calibrate`` (docs/calibration.md): ``begin`` a sweep by hand from the middle pose,
        ``status`` (range seen per joint, rad), ``end`` (the joints' calibration keys), ``cancel``;
        only while DISABLED: the joints move by hand with torque off. ``import`` converts another
        tool's calibration file, in any state (nothing moves, nothing is written here)."""
        action = data.get("action")
        grippers = list(data.get("grippers", ()))
        if action == "import":
            try:
                return {"calibration": self.actuator.calibration_import(data.get("format", "lerobot"),
                                                                       data.get("file", {}), grippers)}
            except BackendError as exc:
                raise Refused("bad_request", str(exc)) from None
        if action == "cancel":
            self.actuator.calibration_cancel()
            return None
        if self.state is not OperatingState.DISABLED or self._running is not None:
            self.actuator.calibration_cancel()  # a sweep under way ends: the joints may move now
            what = self.state.value + (f", {self._running.transition.kind.value} under way" if self._running else "")
            raise Refused("invalid_state", f"{self.robot}: calibrate needs the robot DISABLED (it is {what}): the "
                                           f"joints are moved by hand with torque off; disable it first"
                                           + ("" if action == "begin" else "; the calibration sweep was cancelled"))
        if action == "begin":
            self.actuator.calibration_cancel()

            def failed(exc: Exception) -> Refused:
                return Refused("unsupported", str(exc))

            t = Transition(self.robot, Lifecycle.CALIBRATE, self.actuator.calibration_begin(),
                           self.traits.timeout_s(Lifecycle.CALIBRATE))
            return self._start(t, lambda: {"joints": list(self.profile.joint_names)}, failed)
        try:
            if action == "status":
                return {"seen": self.actuator.calibration_seen()}
            return {"calibration": self.actuator.calibration_result(grippers)}
        except BackendError as exc:
            raise Refused("invalid_state", str(exc)) from None

    def _end_cartesian(self, ns: str) -> None:
        tm = self.twist_motions.get(ns)
        if tm is not None:
            tm.cancel()
        nc = self.native_cartesian.get(ns)
        if nc is not None:
            was_busy = self.is_busy
            nc.cancel()
            if was_busy and not self.is_busy:  # the command pre-empted a native move
                self.push_state()

    def _native_cartesian_command(self, cmd: str, ns: str, data: dict) -> Any:
        """A cartesian command for a backend that does cartesian control itself: no IK, no
        mapping; the backend receives the pose or twist (core/native_cartesian.py)."""
        self._check_can_move(ns, cmd)
        if cmd == "move_cp":
            p, q = self._pose(ns, cmd, data)
            check = self.actuator.goal_check_steps(ns, cmd, np.concatenate([p, q])) if self.traits.goal_check else None
            if check is not None:  # the device's own limits first; the move starts when they agree
                return self._start(self._goal_check(check), lambda: self._native_accept(cmd, ns, data),
                                   self._goal_refused)
        return self._native_accept(cmd, ns, data)

    def _goal_check(self, steps: Steps) -> Transition:
        return Transition(self.robot, Lifecycle.GOAL_CHECK, steps,
                          self.traits.timeout_s(Lifecycle.GOAL_CHECK))

    def _goal_refused(self, exc: Exception) -> Refused:
        """A GOAL_CHECK that refused the goal (or could not ask): the move is refused, the robot
        holds where it is (no FAULT: nothing moved)."""
        self._checked_seq = None
        if isinstance(exc, CommandError):
            return Refused(exc.code, exc.message)
        return Refused("out_of_limits", f"{self.robot}: move refused: the device could not check the goal "
                       f"against its own limits: {exc}")

    def _native_accept(self, cmd: str, ns: str, data: dict) -> Any:
        nc = self.native_cartesian[ns]
        m = nc.motion
        was_busy = self.is_busy
        was_free = m.mode is Mode.FREE
        try:
            nc.command(cmd, data, self.clock(), self.feedback.cartesian)  # the joints hold: the backend drives them now
        except CommandError as exc:  # bad_request (crtk_bridge/vectors.py), a step or twist beyond safety
            raise Refused(exc.code, exc.message) from None
        if was_free:
            m.setpoint_p[:] = self.feedback.position[m.idx]
        tm = self.twist_motions.get(ns)
        if tm is not None:
            tm.cancel()
        if cmd == "move_cp":
            self._move_edge()
            return {"busy_seq": self.busy_seq}
        if was_busy and not self.is_busy:  # a stream pre-empted a move
            self.push_state()
        return None

    def _twist_command(self, cmd: str, ns: Any, data: dict) -> None:
        """servo_cv / interpolate_cv: the twist is kept and mapped every cycle (core/twist.py)."""
        m = self.namespaces.get(ns)
        if m is None:
            raise Refused("unknown_namespace", f"{self.robot}: unknown namespace {ns!r} (have: {', '.join(self.namespaces)})")
        tm = self.twist_motions.get(ns)
        if tm is None:
            raise Refused("unsupported", f"{ns}: {cmd} is not supported: the namespace has no kinematics section")
        if not self.can("velocity", ns):
            raise Refused("unsupported", f"{ns}: {cmd} is not supported: no velocity or position control")
        self._check_can_move(ns, cmd)
        twist, frame = self._twist(ns, cmd, data)
        if m.mode is Mode.FREE:
            m.reset(self.feedback.position[m.idx])  # start from where the joints are
        was_busy = self.is_busy
        if cmd == "servo_cv":
            tm.servo(twist, frame, self.clock())
        else:
            tm.interpolate(twist, frame, self.clock())
        if was_busy and not self.is_busy:  # the stream pre-empted a move
            self.push_state()
        return None

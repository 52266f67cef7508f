"""Cartesian commands for a backend with its own cartesian control (``native_cartesian``).

A controller such as a UR's plans and servos in cartesian space itself (``servoL``, ``speedL``,
``moveL``) and reports its TCP pose. For its namespaces the controller does no IK and no
Jacobian mapping: ``servo_cp`` / ``interpolate_cp`` / ``move_cp`` and ``servo_cv`` /
``interpolate_cv`` become the row of :class:`~crtk_bridge.core.actuator.CartesianCommand` the
backend receives every cycle (the namespace's joints in CommandMode.NONE meanwhile), and the
measured tip pose comes from :class:`~crtk_bridge.core.actuator.CartesianFeedback`.

CRTK rules kept here: a servo / interpolate stream silent for ``safety.servo_timeout_s`` stops
(the joints hold where they are, with a ``servo_timeout`` warning); ``move_cp`` raises
``is_busy`` until the backend reports the move done (``done_seq``); any other command of the
namespace, a pause, a fault or the client leaving ends the cartesian command, and the joints
then hold where they are (the namespace's position setpoint follows the measured joints while
the backend drives).

Bounds (``safety``), as the joint path bounds ``servo_jp`` steps: a ``servo_cp`` /
``interpolate_cp`` pose farther than ``cartesian_step_max`` (m) or turned more than
``cartesian_rotation_step_max`` (rad) from the last pose of the running stream (else from the
measured pose) is refused with ``step_too_large``; a twist faster than ``cartesian_velocity_max``
(m/s) or ``cartesian_angular_velocity_max`` (rad/s) is refused with ``out_of_limits``. Refused, not
scaled: the bound is the profile's safety limit, not what the hardware can do, and a client whose
twist silently went slower would integrate a wrong pose; the previous command stays in force.
``move_cp`` is not bounded by a step: the backend plans it (as ``move_jp``).

What it commanded is the namespace's cartesian setpoint and goal (the front serves them as
``setpoint_cp``, ``setpoint_cv``, ``goal_cp``; the joints have no setpoint of core's meanwhile):
the pose of the running ``servo_cp`` / ``interpolate_cp`` stream, then of a finished ``move_cp``
(the goal its trajectory ended on; none while the backend's own trajectory runs); the twist of a
running ``servo_cv`` / ``interpolate_cv``; the goal of the last ``move_cp`` / ``interpolate_cp``.
They stay valid after a stream's watchdog or a move's end (the joints then hold there), and
end with :meth:`NativeCartesian.cancel` (another command, a stop, a pause, a fault).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .. import vectors
from ..errors import CommandError, fmt_number
from ..profile import Safety

from .actuator import FRAME_BODY, FRAME_SPATIAL, CartesianCommand, CartesianFeedback, CartesianMode, CommandMode
from .motion import NamespaceMotion
from .twist import parse_twist

POSE_COMMANDS = ("servo_cp", "interpolate_cp", "move_cp")
NATIVE_COMMANDS = POSE_COMMANDS + ("servo_cv", "interpolate_cv")
_NONE = int(CommandMode.NONE)


class NativeCartesian:
    """Row ``row`` of the cartesian command / feedback: namespace ``motion``'s cartesian side."""

    def __init__(self, motion: NamespaceMotion, row: int, safety: Safety):
        self.motion = motion
        self.row = row
        self.timeout_s = safety.servo_timeout_s
        self.safety = safety
        self.mode = CartesianMode.NONE
        self.position = np.zeros(3)
        self.orientation = np.array([0.0, 0.0, 0.0, 1.0])
        self.twist = np.zeros(6)
        self.frame = FRAME_SPATIAL
        self.seq = 0  # MOVE goals sent
        self.done_seq = 0  # MOVE goals the backend finished
        self.last_cmd_time = 0.0
        # what was commanded (module docstring); stamp: when, 0 = none
        self.setpoint_stamp = 0.0  # pose: self.position / self.orientation
        self.twist_stamp = 0.0  # twist: self.twist in self.frame
        self.goal_stamp = 0.0
        self.goal_position = np.zeros(3)
        self.goal_orientation = np.array([0.0, 0.0, 0.0, 1.0])

    @property
    def active(self) -> bool:
        return self.mode is not CartesianMode.NONE

    @property
    def busy(self) -> bool:
        return self.mode is CartesianMode.MOVE and self.done_seq < self.seq

    def command(self, cmd: str, data: Any, now: float, measured: CartesianFeedback) -> None:
        """Take ``cmd`` (validated here: :class:`~crtk_bridge.vectors.InvalidVector` naming the
        namespace and field, CommandError for a step or twist beyond the ``safety`` bounds;
        nothing changes then). ``measured``: the latest feedback, the base of a stream's first step. The
        namespace's joint motion holds and is no longer written."""
        ns = self.motion.name
        if cmd in POSE_COMMANDS:
            p, q = parse_pose(ns, cmd, data)
            if cmd != "move_cp":
                self._check_step(cmd, p, q, measured)
            self.position[:], self.orientation[:] = p, q
            self.mode = CartesianMode.MOVE if cmd == "move_cp" else CartesianMode.POSE
            if cmd == "move_cp":
                self.seq += 1
            self.setpoint_stamp = 0.0 if cmd == "move_cp" else now  # a move's setpoints are the backend's
            self.twist_stamp = 0.0
            if cmd == "servo_cp":
                self.goal_stamp = 0.0
            else:
                self.goal_position[:], self.goal_orientation[:], self.goal_stamp = p, q, now
        else:
            twist, frame = parse_twist(ns, cmd, data)
            self._check_twist(cmd, twist)
            self.twist[:] = twist
            self.frame = FRAME_BODY if frame == "body" else FRAME_SPATIAL
            self.mode = CartesianMode.TWIST
            self.twist_stamp = now
            self.setpoint_stamp = self.goal_stamp = 0.0
        self.last_cmd_time = now
        m = self.motion
        m.hold()
        m.level = None  # the joints have no setpoint of core's while the backend drives them
        m.setpoint_stamp = 0.0
        m.goal_level = None  # nor a goal: an earlier move_jp's is not the arm's goal any more
        m.goal_stamp = 0.0

    def _check_step(self, cmd: str, p: np.ndarray, q: np.ndarray, measured: CartesianFeedback) -> None:
        ns, sf = self.motion.name, self.safety
        if self.mode is CartesianMode.POSE:
            base_p, base_q, what = self.position, self.orientation, "the previous pose"
        elif measured.stamp > 0.0:
            k = self.row
            base_p, base_q, what = measured.position[k], measured.orientation[k], "the measured pose"
        else:
            raise CommandError("invalid_state", f"{ns}: {cmd} refused: the backend reports no measured pose "
                               "to bound the step from")
        dist = vectors.distance(p, base_p)
        if dist > sf.cartesian_step_max:
            raise CommandError("step_too_large", f"{ns}: {cmd} refused: the tip would jump {fmt_number(dist)} m "
                               f"from {what} (safety.cartesian_step_max = {sf.cartesian_step_max})")
        angle = vectors.rotation_angle(q, base_q)
        if angle > sf.cartesian_rotation_step_max:
            raise CommandError("step_too_large", f"{ns}: {cmd} refused: the tip would turn {fmt_number(angle)} rad "
                               f"from {what} (safety.cartesian_rotation_step_max = "
                               f"{sf.cartesian_rotation_step_max})")

    def _check_twist(self, cmd: str, twist: np.ndarray) -> None:
        ns, sf = self.motion.name, self.safety
        for speed, key, unit in ((vectors.norm(twist[:3]), "cartesian_velocity_max", "m/s"),
                                 (vectors.norm(twist[3:]), "cartesian_angular_velocity_max", "rad/s")):
            bound = getattr(sf, key)
            if speed > bound:
                raise CommandError("out_of_limits", f"{ns}: {cmd} refused: {'linear' if unit == 'm/s' else 'angular'} "
                                   f"speed {fmt_number(speed)} {unit} is above safety.{key} = {bound}")

    def cancel(self) -> None:
        """Another command, a stop or a fault took the namespace over: nothing commanded remains."""
        self.mode = CartesianMode.NONE
        self.setpoint_stamp = self.twist_stamp = self.goal_stamp = 0.0

    def update(self, now: float, measured_p: np.ndarray, feedback: CartesianFeedback) -> str | None:
        """One cycle, before the namespace's motion step. Returns a watchdog message when a
        stream just timed out."""
        if not self.active:
            return None
        self.done_seq = int(feedback.done_seq[self.row])
        self.motion.setpoint_p[:] = measured_p  # on the way out, hold where the backend left the arm
        if self.mode is not CartesianMode.MOVE and now - self.last_cmd_time > self.timeout_s:
            kind = "servo_cv / interpolate_cv" if self.mode is CartesianMode.TWIST else "servo_cp / interpolate_cp"
            self.mode = CartesianMode.NONE  # the joints hold where they are: the pose stays the setpoint
            self.twist_stamp = 0.0
            return f"{self.motion.name}: no {kind} command for {self.timeout_s} s; holding position"
        if self.mode is CartesianMode.MOVE and not self.busy:
            self.mode = CartesianMode.NONE  # the move ended: the joints hold where it stopped
            self.setpoint_stamp = now  # its goal, where the backend's trajectory ended
        return None

    def fill(self, joint_mode: np.ndarray, cart: CartesianCommand) -> None:
        """After the namespace's ``fill``: the cartesian row, and its joints left to the backend."""
        k = self.row
        cart.mode[k] = self.mode
        if not self.active:
            return
        joint_mode[self.motion.idx] = _NONE
        cart.position[k] = self.position
        cart.orientation[k] = self.orientation
        cart.linear[k] = self.twist[:3]
        cart.angular[k] = self.twist[3:]
        cart.frame[k] = self.frame
        cart.seq[k] = self.seq


def parse_pose(ns: str, cmd: str, data: Any) -> tuple[np.ndarray, np.ndarray]:
    """``{"position": [3], "orientation": [4]}`` -> (position, unit quaternion [x, y, z, w]).
    Raises :class:`~crtk_bridge.vectors.InvalidVector` naming the namespace and field."""
    return vectors.pose(data, f"{ns}: {cmd}")


def build_native_cartesian(namespaces: dict[str, NamespaceMotion], rows: list[str],
                           safety: Safety) -> dict[str, NativeCartesian]:
    """One :class:`NativeCartesian` per namespace the backend controls in cartesian space
    (``rows``: :meth:`~crtk_bridge.core.actuator.Actuator.cartesian_namespaces`)."""
    return {ns: NativeCartesian(namespaces[ns], k, safety) for k, ns in enumerate(rows)}


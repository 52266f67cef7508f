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
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .actuator import FRAME_BODY, FRAME_SPATIAL, CartesianCommand, CartesianFeedback, CartesianMode, CommandMode
from .motion import NamespaceMotion
from .twist import parse_twist, parse_vectors

POSE_COMMANDS = ("servo_cp", "interpolate_cp", "move_cp")
NATIVE_COMMANDS = POSE_COMMANDS + ("servo_cv", "interpolate_cv")
_NONE = int(CommandMode.NONE)


class NativeCartesian:
    """Row ``row`` of the cartesian command / feedback: namespace ``motion``'s cartesian side."""

    def __init__(self, motion: NamespaceMotion, row: int, timeout_s: float):
        self.motion = motion
        self.row = row
        self.timeout_s = timeout_s
        self.mode = CartesianMode.NONE
        self.position = np.zeros(3)
        self.orientation = np.array([0.0, 0.0, 0.0, 1.0])
        self.twist = np.zeros(6)
        self.frame = FRAME_SPATIAL
        self.seq = 0  # MOVE goals sent
        self.done_seq = 0  # MOVE goals the backend finished
        self.last_cmd_time = 0.0

    @property
    def active(self) -> bool:
        return self.mode is not CartesianMode.NONE

    @property
    def busy(self) -> bool:
        return self.mode is CartesianMode.MOVE and self.done_seq < self.seq

    def command(self, cmd: str, data: Any, now: float) -> None:
        """Take ``cmd`` (validated here; ValueError with a one-line message naming the namespace
        and field). The namespace's joint motion holds and is no longer written."""
        ns = self.motion.name
        if cmd in POSE_COMMANDS:
            self.position[:], self.orientation[:] = parse_pose(ns, cmd, data)
            self.mode = CartesianMode.MOVE if cmd == "move_cp" else CartesianMode.POSE
            if cmd == "move_cp":
                self.seq += 1
        else:
            self.twist[:], frame = parse_twist(ns, cmd, data)
            self.frame = FRAME_BODY if frame == "body" else FRAME_SPATIAL
            self.mode = CartesianMode.TWIST
        self.last_cmd_time = now
        m = self.motion
        m.hold()
        m.level = None  # the joints have no setpoint of core's while the backend drives them
        m.setpoint_stamp = 0.0

    def cancel(self) -> None:
        """Another command, a stop or a fault took the namespace over."""
        self.mode = CartesianMode.NONE

    def update(self, now: float, measured_p: np.ndarray, feedback: CartesianFeedback) -> str | None:
        """One cycle, before the namespace's motion step. Returns a watchdog message when a
        stream just timed out."""
        if not self.active:
            return None
        self.done_seq = int(feedback.done_seq[self.row])
        self.motion.setpoint_p[:] = measured_p  # on the way out, hold where the backend left the arm
        if self.mode is not CartesianMode.MOVE and now - self.last_cmd_time > self.timeout_s:
            kind = "servo_cv / interpolate_cv" if self.mode is CartesianMode.TWIST else "servo_cp / interpolate_cp"
            self.cancel()
            return f"{self.motion.name}: no {kind} command for {self.timeout_s} s; holding position"
        if self.mode is CartesianMode.MOVE and not self.busy:
            self.cancel()  # the move ended: the joints hold where it stopped
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
    Raises ValueError naming the namespace and field."""
    out = parse_vectors(ns, cmd, data, (("position", 3), ("orientation", 4)))
    norm = float(np.linalg.norm(out[1]))
    if not 0.5 < norm < 1.5:
        raise ValueError(f"{ns}: {cmd} orientation must be a unit quaternion [x, y, z, w]")
    return out[0], out[1] / norm


def build_native_cartesian(namespaces: dict[str, NamespaceMotion], rows: list[str],
                           timeout_s: float) -> dict[str, NativeCartesian]:
    """One :class:`NativeCartesian` per namespace the backend controls in cartesian space
    (``rows``: :meth:`~crtk_bridge.core.actuator.Actuator.cartesian_namespaces`)."""
    return {ns: NativeCartesian(namespaces[ns], k, timeout_s) for k, ns in enumerate(rows)}


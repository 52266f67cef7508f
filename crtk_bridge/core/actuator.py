"""The actuator interface: the one seam every backend implements.

A backend turns its bus into joint-space SI quantities (rad, rad/s, N*m) and back. Raw device
units (ticks, counts, RTDE vectors) never leave it; calibration from the profile is applied inside.

Two paths, as in ros2_control hardware components:

* Lifecycle path -- ``open()`` -> ``configure()`` -> ``enable()`` / ``disable()`` -> ``close()``.
  May block on the bus, raises :class:`~crtk_bridge.errors.BackendError`; each call is idempotent.
* Real-time path -- ``read(feedback)`` and ``write(command)``. Bounded time, never sleeps on
  purpose, never raises: they return ``None`` when all went well, else a :class:`Fault` naming the
  cause. Backends implement the hooks ``_read`` / ``_write``; the public methods turn any exception
  a hook lets escape into a Fault, so a backend bug faults the robot instead of killing the loop.

Buffers are pre-allocated (:meth:`Actuator.new_feedback`, :meth:`Actuator.new_command`) and filled
in place every cycle.
"""

from __future__ import annotations

import abc
import enum
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Sequence

import numpy as np

from ..profile import Profile


@dataclass(frozen=True)
class Capabilities:
    """What a backend, a joint or a group of joints can do; the server advertises per namespace
    only the CRTK commands its joints' capabilities allow (:func:`combine_capabilities`)."""

    position: bool = True  # accepts joint position setpoints
    velocity: bool = False  # accepts joint velocity setpoints
    effort: bool = False  # accepts joint effort setpoints
    measures_velocity: bool = True
    measures_effort: bool = False
    needs_homing: bool = False  # incremental encoders: is_homed starts False
    can_free: bool = True  # torque can be switched off with the robot powered (`free`)
    native_rate_hz: float | None = None  # rate the hardware paces (CANopen SYNC, RTDE); None = any


def combine_capabilities(caps: Sequence[Capabilities]) -> Capabilities:
    """What a group of joints (a namespace, a robot) can do together: a command is offered only
    if every joint can follow it, and the group needs homing if any joint does."""
    if not caps:
        return Capabilities()
    rates = [c.native_rate_hz for c in caps if c.native_rate_hz is not None]
    return Capabilities(
        position=all(c.position for c in caps), velocity=all(c.velocity for c in caps),
        effort=all(c.effort for c in caps), measures_velocity=all(c.measures_velocity for c in caps),
        measures_effort=all(c.measures_effort for c in caps), needs_homing=any(c.needs_homing for c in caps),
        can_free=all(c.can_free for c in caps), native_rate_hz=rates[0] if rates else None,
    )


class CommandMode(enum.IntEnum):
    """Per-joint control mode of a :class:`JointCommand`."""

    NONE = 0  # hold whatever the device is doing (no new goal this cycle)
    POSITION = 1
    VELOCITY = 2
    EFFORT = 3
    FREE = 4  # torque off on this joint while the robot is enabled (`free`)


@dataclass
class JointFeedback:
    """One cycle's measured joint state, SI units, filled in place by ``Actuator.read``."""

    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    stamp: float = 0.0  # time of measurement, seconds since the Unix epoch


@dataclass
class JointCommand:
    """One cycle's setpoints, SI units. ``mode[i]`` says which field joint ``i`` follows.

    ``velocity`` alongside POSITION is a feed-forward a backend may use or ignore.
    """

    mode: np.ndarray  # CommandMode per joint (uint8)
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


@dataclass(frozen=True)
class Fault:
    """Why a real-time call failed. ``code`` is a stable identifier (see docs/protocol.md)."""

    code: str  # e.g. "bus_timeout", "servo_error", "backend_exception"
    message: str  # human sentence naming robot, joint, register and value where known
    joint: str | None = None
    register: str | None = None
    value: Any = None
    transient: bool = True  # True: a retry next cycle may succeed (counted before FAULT)


@dataclass
class ActuatorInfo:
    """Static description a backend reports once it is open."""

    joint_names: list[str]
    capabilities: Capabilities
    details: dict[str, Any] = field(default_factory=dict)  # model numbers, firmware, port...


class Actuator(abc.ABC):
    """Base class of every backend. Subclasses fill the ``_hooks``; see the module docstring.

    Lifecycle methods are legal in this order: open -> configure -> (enable <-> disable)* ->
    close. ``close`` is legal at any time and idempotent; the backend is also a context manager.
    """

    #: capabilities of this backend type (a subclass may refine them per profile in __init__)
    capabilities: ClassVar[Capabilities] = Capabilities()
    #: the pip extra that installs this backend's SDK, named in BackendUnavailableError
    extra: ClassVar[str | None] = None

    def __init__(self, profile: Profile, *, source: str = "<profile>"):
        self.profile = profile
        self.robot = profile.name
        self.joint_names = profile.joint_names
        self.n = len(self.joint_names)
        self._open = False
        self._enabled = False

    # ---- lifecycle path (may block, raises BackendError) ----
    def open(self) -> None:
        """Open the bus and check every device answers. Blocks. Raises BackendError."""
        if not self._open:
            self._open_hook()
            self._open = True

    def configure(self) -> None:
        """Write the device configuration from the profile; torque stays off. Blocks."""
        self._configure_hook()

    def enable(self, feedback: JointFeedback) -> None:
        """Power the joints, holding them where they are (no surprise motion). Blocks.

        ``feedback`` is the latest measured state; backends write it as the goal before torque on.
        """
        self._enable_hook(feedback)
        self._enabled = True

    def disable(self) -> None:
        """Torque off on every joint. Blocks. Raises BackendError if a joint did not confirm."""
        self._disable_hook()
        self._enabled = False

    def close(self) -> None:
        """Torque off (best effort) and release the bus. Idempotent, never raises."""
        if not self._open:
            return
        try:
            self._disable_hook()
        except Exception:  # best effort on the way out
            pass
        try:
            self._close_hook()
        except Exception:
            pass
        self._open = False
        self._enabled = False

    def __enter__(self) -> "Actuator":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def is_enabled(self) -> bool:
        return self._enabled

    # ---- real-time path (bounded, returns a Fault instead of raising) ----
    def read(self, feedback: JointFeedback) -> Fault | None:
        """Fill ``feedback`` in place from one bus transaction. Never raises."""
        try:
            return self._read(feedback)
        except Exception as exc:  # a backend bug must fault the robot, not kill the loop
            return Fault("backend_exception", f"{self.robot}: read failed: {exc!r}", transient=False)

    def write(self, command: JointCommand) -> Fault | None:
        """Send ``command`` in one bus transaction. Never raises."""
        try:
            return self._write(command)
        except Exception as exc:
            return Fault("backend_exception", f"{self.robot}: write failed: {exc!r}", transient=False)

    def joint_capabilities(self, i: int) -> Capabilities:
        """What joint ``i`` can do. Default: the backend's :attr:`capabilities`; a backend that
        knows per joint (a current-sensing servo beside one without) overrides it."""
        return self.capabilities

    def capabilities_of(self, joints: Sequence[int]) -> Capabilities:
        """What the joints ``joints`` (indices) can do together, e.g. one namespace's."""
        return combine_capabilities([self.joint_capabilities(i) for i in joints])

    def new_feedback(self) -> JointFeedback:
        z = np.zeros(self.n)
        return JointFeedback(z.copy(), z.copy(), z.copy(), 0.0)

    def new_command(self) -> JointCommand:
        z = np.zeros(self.n)
        return JointCommand(np.zeros(self.n, dtype=np.uint8), z.copy(), z.copy(), z.copy())

    def info(self) -> ActuatorInfo:
        return ActuatorInfo(list(self.joint_names), self.capabilities)

    @staticmethod
    def now() -> float:
        return time.time()

    # ---- hooks for subclasses ----
    @abc.abstractmethod
    def _open_hook(self) -> None: ...

    def _configure_hook(self) -> None:
        pass

    @abc.abstractmethod
    def _enable_hook(self, feedback: JointFeedback) -> None: ...

    @abc.abstractmethod
    def _disable_hook(self) -> None: ...

    @abc.abstractmethod
    def _close_hook(self) -> None: ...

    @abc.abstractmethod
    def _read(self, feedback: JointFeedback) -> Fault | None: ...

    @abc.abstractmethod
    def _write(self, command: JointCommand) -> Fault | None: ...

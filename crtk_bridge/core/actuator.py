"""The actuator interface: the one seam every backend implements.

A backend turns its bus into joint-space SI quantities (rad, rad/s, N*m) and back. Raw device
units (ticks, counts, RTDE vectors) never leave it; calibration from the profile is applied inside.

Three paths, as in ros2_control hardware components:

* Start-up path -- ``open()`` -> ``configure()``, before the loop runs; ``close()`` after it.
  May block on the bus, raises :class:`~crtk_bridge.errors.BackendError`; idempotent.
* Lifecycle transitions -- enable, disable (also the torque-off of a fault), pause, resume,
  fault reset and, where the backend homes natively, home. They take as long as the hardware
  needs but never block the cycle: :meth:`Actuator.begin` returns a :class:`Transition` that the
  loop advances with ONE :meth:`Transition.step` per cycle, after that cycle's ``read``, until it
  reports done (or raises, or exceeds the backend's time limit, :meth:`Actuator.transition_timeout_s`).
  Meanwhile the loop keeps reading and publishing, the CRTK state stays as it was and ``is_busy``
  is true. A backend writes a transition as a generator (``_enable_steps`` ...): each ``yield``
  hands the cycle back and resumes one cycle later, so a CiA 402 controlword walk or "torque on,
  then wait until the servo confirms" interleaves with the cycle's own bus traffic on the same
  thread (a serial bus is used by one thread at a time). Blocking vendor calls that cannot be
  split go to :func:`on_worker`, a step generator that runs them on a thread and yields until
  they return. Backends with no steps of their own implement the blocking ``_enable_hook`` /
  ``_disable_hook`` instead, run in one step.
* Real-time path -- ``read(feedback)`` and ``write(command)``. Bounded time, never sleeps on
  purpose, never raises: they return ``None`` when all went well, else a :class:`Fault` naming the
  cause. Backends implement the hooks ``_read`` / ``_write``; the public methods turn any exception
  a hook lets escape into a Fault, so a backend bug faults the robot instead of killing the loop.
  ``write`` is called only while ENABLED or PAUSED unless the backend sets ``cyclic_write``
  (a CiA 402 chain needs SYNC, RPDOs and the controlword every cycle in every state); then it is
  called every cycle, with every joint in :attr:`CommandMode.NONE` outside ENABLED / PAUSED.

What else a backend declares (class attributes, refined per profile in ``__init__`` if needed):

* ``fault_reaction`` (:class:`FaultReaction`): what core does to the device when the robot
  enters FAULT -- switch torque off (serial servos; core runs :meth:`Actuator.begin_fault_reaction`,
  the DISABLE transition unless a composite applies each bus's own reaction), leave it holding,
  or nothing because the device already stopped itself.
* Device status (:class:`DeviceStatus`): a backend reports what the device says about itself
  (paused by the device, powered off by the device, fault with cause, fault cleared) with
  :meth:`Actuator.report_status` from its ``_read``; core takes it once per cycle
  (:meth:`Actuator.take_status`) and maps it onto the CRTK states with ONE table
  (``core/state.py``, ``DEVICE_STATUS``). A non-transient :class:`Fault` from ``read`` is a
  device FAULT too.
* Pacing: every cycle starts with :meth:`Actuator.wait_cycle` (``deadline``: the cycle
  runner's, core/cycle.py). With ``paces_cycle`` the device's clock paces the loop (a UR's next
  packet); otherwise the runner sleeps to its own clock's deadline and ``wait_cycle`` does what
  starts the backend's cycle (a CANopen SYNC).
  :func:`effective_period_s` is the ONE period the loop, motion, the server's rates and the
  statistics use, computed once at start-up.
* ``simulator`` (:class:`SimWiring`): how ``--sim`` wires the backend to its wire-level
  simulator (which ``crtk-sim`` device, which backend key takes the simulator's endpoint).
* Native cartesian control (``Capabilities.native_cartesian``): a controller with its own
  cartesian control and TCP pose (UR ``servoL`` / ``speedL`` / ``moveL``) receives cartesian
  setpoints in :attr:`JointCommand.cartesian` (one row per namespace of
  :meth:`Actuator.cartesian_namespaces`; the joints of a row are then in CommandMode.NONE) and
  supplies the measured tip pose in :attr:`JointFeedback.cartesian`, so core does no IK for them.

Buffers are pre-allocated (:meth:`Actuator.new_feedback`, :meth:`Actuator.new_command`) and filled
in place every cycle.
"""

from __future__ import annotations

import abc
import enum
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, ClassVar, Sequence

import msgspec
import numpy as np
from ruckig import InputParameter, OutputParameter, Result, Ruckig, RuckigError

from ..errors import BackendError
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
    native_cartesian: bool = False  # follows cartesian setpoints and measures the tip pose itself
    measures_wrench: bool = False  # native cartesian: also measures the tip wrench (CartesianFeedback.wrench)


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
        native_cartesian=all(c.native_cartesian for c in caps),
        measures_wrench=all(c.measures_wrench for c in caps),
    )


class CommandMode(enum.IntEnum):
    """Per-joint control mode of a :class:`JointCommand`."""

    NONE = 0  # hold whatever the device is doing (no new goal this cycle)
    POSITION = 1
    VELOCITY = 2
    EFFORT = 3
    FREE = 4  # torque off on this joint while the robot is enabled (`free`)


class CartesianMode(enum.IntEnum):
    """Per-row mode of a :class:`CartesianCommand` (native cartesian backends)."""

    NONE = 0  # no cartesian setpoint: the row's joints follow the joint command
    POSE = 1  # servo_cp / interpolate_cp: track ``position`` / ``orientation`` now (servoL)
    TWIST = 2  # servo_cv / interpolate_cv: follow ``linear`` / ``angular`` in ``frame`` (speedL)
    MOVE = 3  # move_cp: go to the pose, ending at rest (moveL); report ``done_seq`` = ``seq`` at the end


FRAME_SPATIAL, FRAME_BODY = 0, 1  # CartesianCommand.frame: base frame's axes / tip frame's axes


@dataclass
class CartesianCommand:
    """One cycle's cartesian setpoints for a native cartesian backend, one row per namespace of
    :meth:`Actuator.cartesian_namespaces`. Poses are the tip in the base frame (m, quaternion
    ``[x, y, z, w]``), twists m/s and rad/s. ``seq[k]`` numbers the row's MOVE goals."""

    mode: np.ndarray  # CartesianMode per row (uint8)
    position: np.ndarray  # (k, 3)
    orientation: np.ndarray  # (k, 4)
    linear: np.ndarray  # (k, 3)
    angular: np.ndarray  # (k, 3)
    frame: np.ndarray  # (k,) FRAME_SPATIAL / FRAME_BODY of the twist
    seq: np.ndarray  # (k,) int64


@dataclass
class CartesianFeedback:
    """The tip pose a native cartesian backend measures (its TCP pose), one row per namespace of
    :meth:`Actuator.cartesian_namespaces`, and ``done_seq[k]``: the last MOVE goal it finished."""

    position: np.ndarray  # (k, 3) m, base frame
    orientation: np.ndarray  # (k, 4) quaternion [x, y, z, w]
    done_seq: np.ndarray  # (k,) int64
    stamp: float = 0.0  # time of measurement; 0 = no valid pose
    #: (k, 6) force N + torque N*m at the tip, base frame axes, when ``measures_wrench`` (UR
    #: ``actual_TCP_force``); else zeros
    wrench: np.ndarray | None = None

    def copy_from(self, other: "CartesianFeedback") -> None:
        self.position[:] = other.position
        self.orientation[:] = other.orientation
        self.done_seq[:] = other.done_seq
        self.stamp = other.stamp
        if self.wrench is not None and other.wrench is not None:
            self.wrench[:] = other.wrench


@dataclass
class JointFeedback:
    """One cycle's measured joint state, SI units, filled in place by ``Actuator.read``."""

    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    stamp: float = 0.0  # time of measurement, seconds since the Unix epoch
    cartesian: CartesianFeedback | None = None  # native cartesian backends only


@dataclass
class JointCommand:
    """One cycle's setpoints, SI units. ``mode[i]`` says which field joint ``i`` follows.

    ``velocity`` alongside POSITION is a feed-forward a backend may use or ignore.
    """

    mode: np.ndarray  # CommandMode per joint (uint8)
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    cartesian: CartesianCommand | None = None  # native cartesian backends only


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


class Lifecycle(str, enum.Enum):
    """The lifecycle transitions a backend may take cycles over (see the module docstring)."""

    ENABLE = "enable"
    DISABLE = "disable"  # also the torque-off of a fault (FaultReaction.TORQUE_OFF)
    PAUSE = "pause"
    RESUME = "resume"
    FAULT_RESET = "fault_reset"  # before ENABLE when leaving FAULT
    HOME = "home"  # only where the backend homes natively (``native_homing``)
    GOAL_CHECK = "goal_check"  # a move goal asked of the device's own limits (:meth:`Actuator.goal_check_steps`)
    CALIBRATE = "calibrate"  # start a calibration sweep (:meth:`Actuator.calibration_begin`)


class DeviceStatus(str, enum.Enum):
    """What the device reports about itself; core maps it onto CRTK states (state.DEVICE_STATUS)."""

    OK = "ok"
    PAUSED = "paused"  # the device paused itself (UR safeguard stop)
    POWERED_OFF = "powered_off"  # the device removed power itself (e-stop, power button)
    FAULT = "fault"  # with a cause (a Fault)
    FAULT_CLEARED = "fault_cleared"  # the cause of a reported fault went away


class FaultReaction(str, enum.Enum):
    """What core does to the device when the robot enters FAULT."""

    TORQUE_OFF = "torque_off"  # run the DISABLE transition (serial servos: nothing holds them safely)
    HOLD = "hold"  # leave the device powered: it holds its position itself (drive quick stop)
    NONE = "none"  # nothing: the device already stopped itself (UR protective stop)


@dataclass(frozen=True)
class SimWiring:
    """How ``--sim`` runs a backend on its simulator (no port patching in the entry layer).

    ``device`` is the ``crtk-sim`` device name (``crtk_bridge.sim.cli``); the simulator prints or
    links an endpoint (a pty path, an address) that :meth:`Actuator.sim_profile` writes into the
    backend key ``endpoint_key`` of the profile the backend is then built from.
    """

    device: str
    endpoint_key: str = "port"
    #: a simulator that serves fixed TCP ports (a UR controller's) instead of a pty: ``--sim``
    #: picks a loopback address 127.0.0.x where these ports are free, passes it as ``--host`` and
    #: waits until the first one accepts; that address is the endpoint. Empty: a pty link.
    host_ports: tuple[int, ...] = ()


Steps = Iterator[None]


class Transition:
    """One lifecycle transition in progress. The loop calls :meth:`step` once per cycle.

    ``step()`` returns True once the transition is complete; it raises whatever the backend's
    steps raise (a BackendError naming robot, joint and register) when it failed. ``abort()``
    abandons it (closes the step generator, so its ``finally`` clauses run; idempotent).
    ``timeout_s`` is the backend's limit; enforcing it is the caller's job (core faults the robot
    naming the transition, :func:`~crtk_bridge.core.cycle.run_transition` raises).
    """

    __slots__ = ("robot", "kind", "timeout_s", "done", "_steps", "_on_finish")

    def __init__(self, robot: str, kind: Lifecycle, steps: Steps, timeout_s: float,
                 on_finish: Callable[[], None] | None = None):
        self.robot = robot
        self.kind = kind
        self.timeout_s = float(timeout_s)
        self.done = False
        self._steps = steps
        self._on_finish = on_finish

    def step(self) -> bool:
        if self.done:
            return True
        try:
            next(self._steps)
        except StopIteration:
            self.done = True
            if self._on_finish is not None:
                self._on_finish()
            return True
        except BaseException:
            self.done = True  # a failed transition is over; it is never stepped again
            raise
        return False

    def abort(self) -> None:
        if not self.done:
            self.done = True
            self._steps.close()

    def __repr__(self) -> str:
        return f"Transition({self.robot!r}, {self.kind.value}, done={self.done})"


def background_thread(target: Callable[[], Any], name: str) -> threading.Thread:
    """A daemon thread for blocking work beside the cycle (a transition's SDK call, a reconnect, a
    bus reopen), not started. It first drops the SCHED_FIFO class it inherits from the loop's
    thread back to SCHED_OTHER: a call that spins (ur_rtde waiting for the answer of a link that
    died) at the loop's own real-time priority, on the loop's pinned CPU, would never let the loop
    run again (threads of one FIFO priority do not preempt each other)."""

    def run() -> None:
        try:
            if os.sched_getscheduler(0) != os.SCHED_OTHER:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except (OSError, AttributeError):
            pass  # not Linux, or not permitted: it keeps what it inherited
        target()

    return threading.Thread(target=run, name=name, daemon=True)


def on_worker(fn: Callable[[], Any], name: str = "transition") -> Steps:
    """Steps that run the blocking call ``fn()`` on a worker thread, yielding every cycle until it
    returns; its exception is re-raised in the cycle that notices it. For vendor SDK calls that
    cannot be split (a UR power-on). Never for a bus the cycle's read also uses: a serial bus is
    one thread's at a time, so serial backends split their transitions into steps instead."""
    box: dict[str, BaseException] = {}

    def run() -> None:
        try:
            fn()
        except BaseException as exc:  # carried to the stepping thread
            box["exc"] = exc

    worker = background_thread(run, name)
    worker.start()
    while worker.is_alive():
        yield
    if "exc" in box:
        raise box["exc"]


def effective_period_s(profile: Profile, actuator: "Actuator") -> float:
    """The ONE cycle period (s): the hardware's when the backend paces the cycle, else the
    profile's ``loop.rate_hz``. Computed once at start-up; the loop, motion, the server's rates
    and the statistics all use it."""
    hw = actuator.cycle_period_s()
    return float(hw) if hw is not None else 1.0 / profile.loop.rate_hz


#: cycles an ENABLE stepped over cycles waits, after its steps, for a read with torque on
ENABLE_FRESH_READ_CYCLES = 3

#: default time limits (s) of lifecycle transitions; a backend overrides ``transition_timeouts_s``
DEFAULT_TRANSITION_TIMEOUTS_S: dict[Lifecycle, float] = {
    Lifecycle.ENABLE: 5.0, Lifecycle.DISABLE: 2.0, Lifecycle.PAUSE: 2.0, Lifecycle.RESUME: 2.0,
    Lifecycle.FAULT_RESET: 5.0, Lifecycle.HOME: 60.0, Lifecycle.CALIBRATE: 5.0,
    Lifecycle.GOAL_CHECK: 2.0,
}


class Actuator(abc.ABC):
    """Base class of every backend. Subclasses fill the ``_hooks``; see the module docstring.

    Order: open -> configure -> (ENABLE <-> DISABLE transitions, PAUSE / RESUME while enabled)*
    -> close. ``close`` is legal at any time and idempotent; the backend is also a context manager.
    """

    #: capabilities of this backend type (a subclass may refine them per profile in __init__)
    capabilities: ClassVar[Capabilities] = Capabilities()
    #: the pip extra that installs this backend's SDK, named in BackendUnavailableError
    extra: ClassVar[str | None] = None
    #: what core does to the device when the robot enters FAULT
    fault_reaction: ClassVar[FaultReaction] = FaultReaction.TORQUE_OFF
    #: True: ``write`` every cycle in every state (SYNC, RPDOs, controlword); False: only while
    #: ENABLED / PAUSED (serial servos: nothing goes on the bus while disabled)
    cyclic_write: ClassVar[bool] = False
    #: True: the hardware paces the loop through :meth:`wait_cycle` (and :meth:`cycle_period_s`)
    paces_cycle: ClassVar[bool] = False
    #: how ``--sim`` wires this backend to its simulator; None: no simulator
    simulator: ClassVar[SimWiring | None] = None
    #: backend keys ``--sim`` sets where the profile gives no value (absent or null): limits that
    #: the simulator, a Python process on the daemon's own (possibly loaded) PC, needs wider than
    #: the real device (a serial reply margin, a CAN TPDO deadline, an RTDE link timeout)
    SIM_DEFAULTS: ClassVar[dict[str, Any]] = {}
    #: time limit (s) of each lifecycle transition; exceeding it faults the robot
    transition_timeouts_s: ClassVar[dict[Lifecycle, float]] = DEFAULT_TRANSITION_TIMEOUTS_S
    #: True: PAUSE stops the device by itself (a CiA 402 quick stop ramp; a UR safeguard stop stops
    #: the arm with its own ramp) and it holds where it stopped, not where core's braking ramp
    #: ended; core takes the measured position on RESUME
    stops_itself_on_pause: ClassVar[bool] = False
    #: the device's speed scaling (0..1) set by its operator (a UR's speed slider), reported to
    #: clients in ``operating_state``; NaN: the device has none
    speed_fraction: float = float("nan")

    def __init__(self, profile: Profile, *, source: str = "<profile>"):
        self.profile = profile
        self.robot = profile.name
        self.joint_names = profile.joint_names
        self.n = len(self.joint_names)
        self._open = False
        self._enabled = False
        #: the device's last reported status (see :meth:`report_status`)
        self.device_status = DeviceStatus.OK
        self._status_news: tuple[DeviceStatus, Fault | None] | None = None
        self._read_fault: Fault | None = None  # the last read's fault (None: it succeeded)

    # ---- start-up path (may block, raises BackendError) ----
    def open(self) -> None:
        """Open the bus and check every device answers. Blocks. Raises BackendError."""
        if not self._open:
            self._open_hook()
            self._open = True

    def configure(self) -> None:
        """Write the device configuration from the profile; torque stays off. Blocks."""
        self._configure_hook()

    def close(self) -> None:
        """Torque off (best effort) and release the bus. Idempotent, never raises."""
        if not self._open:
            return
        try:
            self.disable()
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

    # ---- lifecycle transitions (advanced one step per cycle; steps raise BackendError) ----
    def begin(self, kind: Lifecycle, feedback: JointFeedback | None = None) -> Transition:
        """Start transition ``kind``; advance it with :meth:`Transition.step` once per cycle.

        ENABLE holds the joints where they are (no surprise motion): ``feedback`` is the latest
        measured state; backends set fresh goals from the device itself before torque on.
        DISABLE stops the real-time writes at once (before its first step). HOME is legal only
        when :attr:`native_homing`. Does not touch the bus itself; the first step does.
        """
        on_finish = None
        if kind is Lifecycle.ENABLE:
            steps = self._enable_then_fresh(feedback if feedback is not None else self.new_feedback())
            on_finish = self._finished_enable
        elif kind is Lifecycle.DISABLE:
            self._enabled = False  # no goal goes out from now on
            steps = self._disable_steps()
        elif kind is Lifecycle.PAUSE:
            steps = self._pause_steps()
        elif kind is Lifecycle.RESUME:
            steps = self._resume_steps()
        elif kind is Lifecycle.FAULT_RESET:
            steps = self._fault_reset_steps()
        elif kind is Lifecycle.HOME:
            if not self.native_homing:
                raise BackendError(f"{self.robot}: the backend does not home natively")
            steps = self._home_steps()
        else:  # pragma: no cover - Lifecycle is closed
            raise ValueError(kind)
        return Transition(self.robot, kind, steps, self.transition_timeout_s(kind), on_finish)

    def begin_fault_reaction(self) -> Transition:
        """The transition core runs when the robot enters FAULT and ``fault_reaction`` is
        TORQUE_OFF (kind DISABLE, stepped like any). Default: the DISABLE transition. A robot on
        several buses (the composite) overrides it to apply each bus's own reaction."""
        return self.begin(Lifecycle.DISABLE)

    def _finished_enable(self) -> None:
        self._enabled = True

    def _enable_then_fresh(self, feedback: JointFeedback) -> Steps:
        """The backend's ENABLE steps, ending with the pose the joints are held at in
        ``feedback`` (core holds exactly there, never a stale pose: a joint may have sagged while
        torque was off). An ENABLE done in one step (a blocking ``_enable_hook``) writes it into
        ``feedback`` itself; one stepped over cycles ends in a later cycle whose read succeeded
        (its sample is core's), trying ENABLE_FRESH_READ_CYCLES reads (a loaded host may miss
        one reply: not a FAULT for one late byte); none: BackendError. Nothing here touches the
        bus: the cycle reads it."""
        inner = self._enable_steps(feedback)
        stepped = False
        try:
            for _ in inner:
                stepped = True
                yield
        finally:
            inner.close()
        if not stepped:
            return
        for _ in range(ENABLE_FRESH_READ_CYCLES):
            yield
            if self._read_fault is None:
                return
        raise BackendError(f"{self.robot}: no fresh position after torque on: {self._read_fault.message}")

    def transition_timeout_s(self, kind: Lifecycle) -> float:
        """The backend's time limit (s) for transition ``kind`` (may depend on the profile)."""
        return self.transition_timeouts_s.get(kind, DEFAULT_TRANSITION_TIMEOUTS_S[kind])

    @property
    def native_homing(self) -> bool:
        """True when the backend homes itself (``_home_steps`` implemented)."""
        return type(self)._home_steps is not Actuator._home_steps

    def enable(self, feedback: JointFeedback) -> None:
        """The ENABLE transition run to its end, cycle by cycle (:func:`~crtk_bridge.core.cycle.run_transition`:
        wait, read, step, write, as in the loop). Blocks. Raises BackendError."""
        run_transition(self, self.begin(Lifecycle.ENABLE, feedback))

    def disable(self) -> None:
        """The DISABLE transition run to its end, cycle by cycle. Blocks. Raises BackendError if
        a joint did not confirm torque off."""
        run_transition(self, self.begin(Lifecycle.DISABLE))

    # ---- calibration (docs/calibration.md): joints moved by hand while DISABLED ----
    def calibration_begin(self) -> Steps:
        """Steps (lifecycle path, one bus step per cycle) that start a calibration sweep from the
        pose the joints are in now, the middle pose; from then on every read follows how far each
        joint travels. Legal only while DISABLED (core checks). Raises BackendError when the
        backend has no calibration procedure (the default)."""
        raise BackendError(f"{self.robot}: the {self.profile.backend_type} backend has no calibration procedure")
        yield  # pragma: no cover

    def calibration_seen(self) -> dict[str, list[float]]:
        """joint -> [lowest, highest, now] in rad from the middle pose (in the joint's direction)
        during a sweep. Never touches the bus. Raises BackendError without a sweep."""
        raise BackendError(f"{self.robot}: no calibration sweep under way")

    def calibration_result(self, grippers: Sequence[str]) -> dict[str, dict[str, Any]]:
        """End the sweep: joint -> the backend's own ``calibration`` keys for the profile
        (``grippers``: joints whose closed end is where they are now). Never touches the bus.
        Raises BackendError naming the joints that cannot be calibrated from what was seen."""
        raise BackendError(f"{self.robot}: no calibration sweep under way")

    def calibration_cancel(self) -> None:
        """Forget a sweep under way (none: nothing to do)."""

    def calibration_import(self, fmt: str, data: Any, grippers: Sequence[str]) -> dict[str, dict[str, Any]]:
        """Another tool's calibration file ``data`` (format ``fmt``, e.g. "lerobot") converted to
        joint -> the backend's ``calibration`` keys. Never touches the bus. Raises BackendError."""
        raise BackendError(f"{self.robot}: the {self.profile.backend_type} backend cannot import {fmt} calibrations")

    # ---- device status (backend -> core) ----
    def report_status(self, status: DeviceStatus, cause: Fault | None = None) -> None:
        """Called by the backend (from ``_read`` or a step) when the device's status changes.
        Core takes the latest report once per cycle; a report of the current status is ignored."""
        if status is not self.device_status or status is DeviceStatus.FAULT_CLEARED:
            self.device_status = DeviceStatus.OK if status is DeviceStatus.FAULT_CLEARED else status
            self._status_news = (status, cause)

    def take_status(self) -> tuple[DeviceStatus, Fault | None] | None:
        """The status reported since the last call (and its cause), or None. Core calls it once
        per cycle after ``read``."""
        news = self._status_news
        if news is not None:
            self._status_news = None
        return news

    # ---- pacing ----
    def cycle_period_s(self) -> float | None:
        """The hardware's cycle period (s) when it paces the loop, else None (the profile's
        ``loop.rate_hz`` rules). Default: ``1 / capabilities.native_rate_hz`` when
        ``paces_cycle``."""
        rate = self.capabilities.native_rate_hz
        return 1.0 / rate if self.paces_cycle and rate else None

    def wait_cycle(self, deadline: float) -> bool:
        """The start of the cycle scheduled at ``deadline`` (``time.perf_counter``; the cycle
        runner's schedule, core/cycle.py), called first thing in every cycle. On the loop's clock
        the runner has slept to ``deadline`` already: a backend does what starts its cycle (a
        CANopen SYNC). On the device's clock (``paces_cycle``) it blocks until the device's next
        packet, giving up one period after ``deadline``. Returns False when nothing came (the
        read that follows reports the cause). Default: nothing to do (True)."""
        return True

    # ---- simulator wiring ----
    @classmethod
    def sim_profile(cls, profile: Profile, endpoint: str) -> Profile:
        """``profile`` wired to a running simulator at ``endpoint`` (see :class:`SimWiring`), with
        :attr:`SIM_DEFAULTS` where it gives no value of its own."""
        if cls.simulator is None:
            raise BackendError(f"{profile.name}: backend {profile.backend_type!r} has no simulator")
        backend = {**profile.backend, cls.simulator.endpoint_key: endpoint}
        for key, value in cls.SIM_DEFAULTS.items():
            if backend.get(key) is None:
                backend[key] = value
        return msgspec.structs.replace(profile, backend=backend)

    # ---- real-time path (bounded, returns a Fault instead of raising) ----
    def read(self, feedback: JointFeedback) -> Fault | None:
        """Fill ``feedback`` in place from one bus transaction. Never raises."""
        try:
            fault = self._read(feedback)
        except Exception as exc:  # a backend bug must fault the robot, not kill the loop
            fault = Fault("backend_exception", f"{self.robot}: read failed: {exc!r}", transient=False)
        self._read_fault = fault
        return fault

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

    def deceleration_limit(self, i: int) -> float:
        """rad/s^2: the most joint ``i``'s hardware decelerates at as configured (a servo's own
        acceleration register), bounding the default stop deceleration
        (:func:`~crtk_bridge.profile.stop_deceleration`). Default: unbounded (inf)."""
        return float("inf")

    def capabilities_of(self, joints: Sequence[int]) -> Capabilities:
        """What the joints ``joints`` (indices) can do together, e.g. one namespace's."""
        return combine_capabilities([self.joint_capabilities(i) for i in joints])

    def cartesian_namespaces(self) -> list[str]:
        """The namespaces this backend controls in cartesian space itself, in the order of the
        rows of :class:`CartesianCommand` / :class:`CartesianFeedback`. Default: with
        ``capabilities.native_cartesian``, every namespace with a ``kinematics`` section."""
        if not self.capabilities.native_cartesian:
            return []
        return [ns.name for ns in self.profile.namespaces if ns.kinematics is not None]

    def goal_check_steps(self, ns: str, cmd: str, goal: np.ndarray) -> Steps | None:
        """Steps that ask the device whether a move goal is within ITS OWN limits (a UR's safety
        limits) before core starts the move; core runs them as a GOAL_CHECK transition (the cycle
        goes on) and starts the move once they end. ``goal``: the namespace's joint positions
        (``move_jp``) or the pose ``[x, y, z, qx, qy, qz, qw]`` (``move_cp`` on a native cartesian
        namespace). They raise :class:`~crtk_bridge.errors.CommandError` (``out_of_limits``, the
        message naming the joint or pose) to refuse the move. None (the default): no such check."""
        return None

    def new_feedback(self) -> JointFeedback:
        z = np.zeros(self.n)
        k = len(self.cartesian_namespaces())
        cart = CartesianFeedback(np.zeros((k, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (k, 1)),
                                 np.zeros(k, dtype=np.int64), 0.0, np.zeros((k, 6))) if k else None
        return JointFeedback(z.copy(), z.copy(), z.copy(), 0.0, cart)

    def new_command(self) -> JointCommand:
        z = np.zeros(self.n)
        k = len(self.cartesian_namespaces())
        cart = CartesianCommand(np.zeros(k, dtype=np.uint8), np.zeros((k, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (k, 1)),
                                np.zeros((k, 3)), np.zeros((k, 3)), np.zeros(k, dtype=np.uint8),
                                np.zeros(k, dtype=np.int64)) if k else None
        return JointCommand(np.zeros(self.n, dtype=np.uint8), z.copy(), z.copy(), z.copy(), cart)

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

    def _enable_steps(self, feedback: JointFeedback) -> Steps:
        """Steps of ENABLE. Default: the blocking :meth:`_enable_hook` in one step."""
        self._enable_hook(feedback)
        yield from ()

    def _disable_steps(self) -> Steps:
        """Steps of DISABLE (torque off on every joint). Default: :meth:`_disable_hook` in one
        step."""
        self._disable_hook()
        yield from ()

    def _pause_steps(self) -> Steps:
        """Steps of PAUSE (core already holds every joint). Default: nothing to do."""
        yield from ()

    def _resume_steps(self) -> Steps:
        """Steps of RESUME. Default: nothing to do."""
        yield from ()

    def _fault_reset_steps(self) -> Steps:
        """Steps that clear a device fault, run before ENABLE when leaving FAULT. Default: none."""
        yield from ()

    def _home_steps(self) -> Steps:
        """Steps of native homing (incremental encoders). Not implemented = core homes by moving
        to the profile's ``home`` positions."""
        raise NotImplementedError
        yield  # pragma: no cover

    def _enable_hook(self, feedback: JointFeedback) -> None:
        """Blocking enable, for backends without ``_enable_steps`` of their own; leaves the pose
        the joints are held at in ``feedback``."""
        raise NotImplementedError(f"{type(self).__name__} implements neither _enable_steps nor _enable_hook")

    def _disable_hook(self) -> None:
        """Blocking torque off, for backends without ``_disable_steps`` of their own."""
        raise NotImplementedError(f"{type(self).__name__} implements neither _disable_steps nor _disable_hook")

    @abc.abstractmethod
    def _close_hook(self) -> None: ...

    @abc.abstractmethod
    def _read(self, feedback: JointFeedback) -> Fault | None: ...

    @abc.abstractmethod
    def _write(self, command: JointCommand) -> Fault | None: ...


from .cycle import run_transition  # noqa: E402 - the runner needs nothing of this module at import

# ---------------------------------------------------------------- ruckig, for the motion layer and
# backends that plan on their own (a UR's move_cp)
#: position offsets a failed ruckig plan is retried from, in order (see ruckig_update)
_NUDGES = (1e-9, -1e-9, 1e-7, -1e-7)


def ruckig_update(otg: Ruckig, inp: InputParameter, out: OutputParameter) -> Result | None:
    """One ruckig cycle (``otg.update``). Ruckig 0.19 raises RuckigError on a few bit-exact inputs
    (a rest-to-rest move of 0.3000000000000002 rad at 4 rad/s, 15 rad/s^2, 150 rad/s^3 fails its
    step-1 profile search; 0.3 and 0.30000000000000004 do not; a rate-limited servo setpoint makes
    such sums): the plan is then made from the current position moved by a nanoradian or so (far
    below any encoder's resolution). None when every such plan fails too (``inp`` as it was)."""
    try:
        return otg.update(inp, out)
    except RuckigError:
        pass
    here = np.array(inp.current_position)
    for nudge in _NUDGES:
        inp.current_position = here + nudge
        try:
            return otg.update(inp, out)
        except RuckigError:
            continue
    inp.current_position = here
    return None

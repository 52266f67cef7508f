"""The actuator interface: the one seam every backend implements.

A backend turns its bus into joint-space SI quantities (rad, rad/s, N*m) and back. Raw device
units (ticks, counts, RTDE vectors) never leave it; calibration from the profile is applied inside.

Three paths, as in ros2_control hardware components:

* Start-up path -- ``open()`` -> ``configure()``, before the loop runs; ``close()`` after it.
  May block on the bus, raises :class:`~crtk_bridge.errors.BackendError`; idempotent.
* Lifecycle transitions -- enable, disable (also the torque-off of a fault), pause, resume,
  fault reset, where the backend homes natively home, and the operating-mode switches a command
  needs (:meth:`Actuator.mode_switch_steps`, prepared off the bus, performed on the cycle: core
  runs them as a MODE_SWITCH transition). They take as long as the hardware
  needs but never block the cycle: :meth:`Actuator.begin` returns a :class:`Transition` that the
  cycle runner (core/cycle.py: the loop, start-up and shutdown alike) advances with ONE
  :meth:`Transition.step` per cycle, after that cycle's ``read``, until it reports done (or
  raises, or exceeds the backend's time limit, ``traits.transition_timeouts_s``). A step may do a
  bounded bus exchange (a sync write, an acknowledged write or two); waiting for the device is
  done across cycles.
  Meanwhile the loop keeps reading and publishing, the CRTK state stays as it was and ``is_busy``
  is true. A backend writes a transition as a generator (``_enable_steps`` ...): each ``yield``
  hands the cycle back and resumes one cycle later, so a CiA 402 controlword walk or "torque on,
  then wait until the servo confirms" interleaves with the cycle's own bus traffic on the same
  thread (a serial bus is used by one thread at a time). Blocking vendor calls that cannot be
  split go to :func:`on_worker`, a step generator that runs them on a thread and yields until
  they return.
* Real-time path -- ``read(feedback)`` and ``write(command)``. Bounded time, never sleeps on
  purpose, never raises: they return ``None`` when all went well, else a :class:`Fault` naming the
  cause. Backends implement the hooks ``_read`` / ``_write``; the public methods turn any exception
  a hook lets escape into a Fault, so a backend bug faults the robot instead of killing the loop.
  ``write`` is also the one finiteness gate: a non-finite setpoint never reaches ``_write``
  (:meth:`Actuator.write`), and core's motion output is already within the profile's limits, so
  a backend clamps only to its device's ranges (docs/architecture.md, Limits).
  ``write`` is called only while ENABLED or PAUSED unless the backend declares ``cyclic_write``
  (a CiA 402 chain needs SYNC, RPDOs and the controlword every cycle in every state); then it is
  called every cycle, with every joint in :attr:`CommandMode.NONE` outside ENABLED / PAUSED.

What a backend declares about itself is ONE immutable :class:`Traits` (per-joint capabilities and
what each joint measures, clock, write policy, pause behaviour, goal check, native homing, speed
scaling, the shortest period its bus keeps, transition time limits), returned by its ``_traits_hook`` when it opens and read by core
as :attr:`Actuator.traits` only; a robot on several buses combines its buses' traits with one
function (backends/composite.py). When the robot enters FAULT, core runs the DISABLE transition
(torque off; a UR stops, powers off and applies its brakes).

* Device status (:class:`DeviceStatus`): a backend reports what the device says about itself
  (paused by the device, powered off by the device, fault with cause, fault cleared) with
  :meth:`Actuator.report_status` from its ``_read``; core takes it once per cycle
  (:meth:`Actuator.take_status`) and maps it onto the CRTK states with ONE table
  (``core/state.py``, ``DEVICE_STATUS``). A non-transient :class:`Fault` from ``read`` is a
  device FAULT too. WARNING and NOTICE are news, not a status (:data:`DEVICE_NEWS`): each report
  is passed on, in order, without changing the state.
* Pacing: every cycle starts with :meth:`Actuator.wait_cycle` (``deadline``: the cycle
  runner's, core/cycle.py). With ``traits.clock`` Clock.DEVICE the device's clock paces the loop
  (a UR's next packet); on Clock.LOOP the runner sleeps to its own clock's deadline and
  ``wait_cycle`` does what starts the backend's cycle (a CANopen SYNC).
  :func:`effective_period_s` is the ONE period the loop, motion, the server's rates and the
  statistics use, computed once at start-up.
* ``simulator`` (:class:`SimWiring`): how ``--sim`` wires the backend to its wire-level
  simulator (which backend key takes the simulator's endpoint; which simulator is the registry's).
* Native cartesian control (``Capabilities.native_cartesian`` of the joints): a controller with its own
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
import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import cached_property
from types import MappingProxyType
from typing import Any, ClassVar, Mapping, Sequence

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
    native_cartesian: bool = False  # follows cartesian setpoints and measures the tip pose itself
    measures_wrench: bool = False  # native cartesian: also measures the tip wrench (CartesianFeedback.wrench)


def combine_capabilities(caps: Sequence[Capabilities]) -> Capabilities:
    """What a group of joints (a namespace, a robot) can do together: a command is offered only
    if every joint can follow it, and the group needs homing if any joint does."""
    if not caps:
        return Capabilities()
    return Capabilities(
        position=all(c.position for c in caps), velocity=all(c.velocity for c in caps),
        effort=all(c.effort for c in caps), measures_velocity=all(c.measures_velocity for c in caps),
        measures_effort=all(c.measures_effort for c in caps), needs_homing=any(c.needs_homing for c in caps),
        can_free=all(c.can_free for c in caps),
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
    details: dict[str, Any] = field(default_factory=dict)  # model numbers, firmware, port...


class Lifecycle(str, enum.Enum):
    """The lifecycle transitions a backend may take cycles over (see the module docstring)."""

    ENABLE = "enable"
    DISABLE = "disable"  # also the torque-off of a fault (core's fault reaction)
    PAUSE = "pause"
    RESUME = "resume"
    FAULT_RESET = "fault_reset"  # before ENABLE when leaving FAULT
    HOME = "home"  # only where the backend homes natively (``native_homing``)
    GOAL_CHECK = "goal_check"  # a move goal asked of the device's own limits (:meth:`Actuator.goal_check_steps`)
    CALIBRATE = "calibrate"  # start a calibration sweep (:meth:`Actuator.calibration_begin`)
    MODE_SWITCH = "mode_switch"  # the device's operating modes changed for a command (:meth:`Actuator.mode_switch_steps`)


class DeviceStatus(str, enum.Enum):
    """What the device reports about itself; core maps it onto CRTK states (state.DEVICE_STATUS)."""

    OK = "ok"
    PAUSED = "paused"  # the device paused itself (UR safeguard stop)
    POWERED_OFF = "powered_off"  # the device removed power itself (e-stop, power button)
    FAULT = "fault"  # with a cause (a Fault)
    FAULT_CLEARED = "fault_cleared"  # the cause of a reported fault went away
    # news, not a state of the device (:attr:`Actuator.device_status` stays): each one reported is
    # passed on, one per cycle, in order
    WARNING = "warning"  # a condition the device works on through (a gripper's minor fault: heat)
    NOTICE = "notice"  # news of its work that is no fault (a gripper's fingers stopped on an object)


#: device reports that are news (passed on one by one), not a state the device is in
DEVICE_NEWS = frozenset({DeviceStatus.WARNING, DeviceStatus.NOTICE})


@dataclass(frozen=True)
class SimWiring:
    """How ``--sim`` wires a backend to its simulator (no port patching in the entry layer).

    Which simulator is the registry's (:mod:`crtk_bridge.registry`, one registration names the
    backend and its simulator); the simulator prints or links an endpoint (a pty path, an address)
    that :meth:`Actuator.sim_profile` writes into the backend key ``endpoint_key`` of the profile
    the backend is then built from.
    """

    endpoint_key: str = "port"
    #: a simulator that serves fixed TCP ports (a UR controller's) instead of a pty: ``--sim``
    #: picks a loopback address 127.0.0.x where these ports are free, passes it as ``--host`` and
    #: waits until the first one accepts; that address is the endpoint. Empty: a pty link.
    host_ports: tuple[int, ...] = ()
    #: a TCP port of the device that carries a serial line behind it (a UR's tool flange RS-485,
    #: UR's tool communication on 54321). Under ``--sim``, another bus of the robot whose endpoint
    #: is ``socket://<this bus's endpoint>:<port>`` gets its simulator on a pty that this bus's
    #: simulator relays the port to (``crtk-sim <device> --tool-link PTY``). None: no such port.
    tool_port: int | None = None


#: cycles an ENABLE stepped over cycles waits, after its steps, for a read with torque on
ENABLE_FRESH_READ_CYCLES = 3

#: default time limits (s) of lifecycle transitions; a backend's :class:`Traits` names its own
DEFAULT_TRANSITION_TIMEOUTS_S: Mapping[Lifecycle, float] = MappingProxyType({
    Lifecycle.ENABLE: 5.0, Lifecycle.DISABLE: 2.0, Lifecycle.PAUSE: 2.0, Lifecycle.RESUME: 2.0,
    Lifecycle.FAULT_RESET: 5.0, Lifecycle.HOME: 60.0, Lifecycle.CALIBRATE: 5.0,
    Lifecycle.GOAL_CHECK: 2.0, Lifecycle.MODE_SWITCH: 2.0,
})


class Clock(str, enum.Enum):
    """Who says when a cycle starts (:attr:`Traits.clock`)."""

    #: the cycle runner sleeps to its own clock (the profile's ``loop.rate_hz``), then
    #: :meth:`Actuator.wait_cycle` starts the backend's cycle (a CiA 402 master's SYNC)
    LOOP = "loop"
    #: the device paces the loop: the runner waits in :meth:`Actuator.wait_cycle` (a UR's next RTDE
    #: package), at :meth:`Actuator.cycle_period_s`
    DEVICE = "device"


@dataclass(frozen=True)
class Traits:
    """What a backend declares about itself: ONE immutable declaration, final once the backend is
    open (:attr:`Actuator.traits`, from the backend's :meth:`Actuator._traits_hook`, which
    :meth:`Actuator.open` calls after ``_open_hook``: a backend that learns its joints'
    capabilities from the devices, a CiA 402 drive's supported modes, knows them then). Core reads
    every one of these from here and nowhere else; a robot on several buses combines its buses'
    with one function, one rule per field (backends/composite.py ``combine_traits``).

    Fields given per joint accept one value for every joint (it is repeated)."""

    #: per joint: what it can do and what it measures (velocity, effort, the tip's wrench), whether
    #: it needs homing (incremental encoders: ``is_homed`` starts False)
    joints: tuple[Capabilities, ...]
    #: who starts the cycle: the loop's clock, or the device's (:class:`Clock`)
    clock: Clock = Clock.LOOP
    #: write policy. True: ``write`` every cycle in every state (a CiA 402 chain: SYNC, RPDOs,
    #: controlword), every joint in CommandMode.NONE outside ENABLED / PAUSED. False: only while
    #: ENABLED / PAUSED (serial servos: nothing goes on the bus while disabled)
    cyclic_write: bool = False
    #: per joint: PAUSE stops the device by itself (a CiA 402 quick stop ramp, a UR safeguard stop)
    #: and it holds where its own stop ended, not where core's braking ramp did; core takes the
    #: measured position on RESUME for the namespaces of these joints
    stops_itself_on_pause: tuple[bool, ...] | bool = False
    #: the device checks move goals against its own limits (:meth:`Actuator.goal_check_steps`,
    #: run by core as a GOAL_CHECK transition before the move starts)
    goal_check: bool = False
    #: the backend homes its joints itself (the HOME transition, :meth:`Actuator._home_steps`);
    #: False: core homes by moving to the profile's ``home`` pose
    native_homing: bool = False
    #: the device has an operator's speed scaling (a UR's speed slider): :attr:`Actuator.speed_fraction`
    #: (0..1) is reported to clients in ``operating_state``
    speed_scaling: bool = False
    #: the shortest cycle period (s) the bus keeps: one read and one write on its wire (a Robotiq
    #: gripper's Modbus RTU at 115200 baud takes several ms). 0: any period the loop runs at. In a
    #: robot on several buses, a bus slower than the robot's cycle is served at its own rate, on
    #: its own thread, and never stretches the cycle (backends/composite.py)
    min_period_s: float = 0.0
    #: time limit (s) of each lifecycle transition (exceeding it faults the robot); kinds not
    #: given keep :data:`DEFAULT_TRANSITION_TIMEOUTS_S`
    transition_timeouts_s: Mapping[Lifecycle, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        joints = tuple(self.joints)
        if not joints or not all(isinstance(c, Capabilities) for c in joints):
            raise ValueError("Traits.joints: one Capabilities per joint")
        object.__setattr__(self, "joints", joints)
        pause = self.stops_itself_on_pause
        pause = (bool(pause),) * len(joints) if isinstance(pause, bool) else tuple(bool(p) for p in pause)
        if len(pause) != len(joints):
            raise ValueError(f"Traits.stops_itself_on_pause: {len(pause)} values for {len(joints)} joints")
        object.__setattr__(self, "stops_itself_on_pause", pause)
        object.__setattr__(self, "clock", Clock(self.clock))
        if not (math.isfinite(self.min_period_s) and self.min_period_s >= 0):
            raise ValueError(f"Traits.min_period_s: {self.min_period_s!r} is not a period (s, >= 0)")
        object.__setattr__(self, "min_period_s", float(self.min_period_s))
        timeouts = {**DEFAULT_TRANSITION_TIMEOUTS_S, **self.transition_timeouts_s}
        object.__setattr__(self, "transition_timeouts_s", MappingProxyType(timeouts))

    @property
    def n(self) -> int:
        return len(self.joints)

    @cached_property
    def capabilities(self) -> Capabilities:
        """What every joint can do together (the robot's)."""
        return combine_capabilities(self.joints)

    def capabilities_of(self, joints: Sequence[int]) -> Capabilities:
        """What the joints ``joints`` (indices) can do together, e.g. one namespace's."""
        return combine_capabilities([self.joints[i] for i in joints])

    def timeout_s(self, kind: Lifecycle) -> float:
        """The time limit (s) of transition ``kind``."""
        return self.transition_timeouts_s[kind]


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


class Actuator(abc.ABC):
    """Base class of every backend. Subclasses fill the ``_hooks``; see the module docstring.

    Order: open -> configure -> (ENABLE <-> DISABLE transitions, PAUSE / RESUME while enabled)*
    -> close. ``close`` is legal at any time and idempotent; the backend is also a context manager.
    """

    #: how ``--sim`` wires this backend to its simulator; None: no simulator. A fact of the backend
    #: TYPE (``--sim`` needs it before any backend is built), so a class attribute, not a trait
    simulator: ClassVar[SimWiring | None] = None
    #: backend keys ``--sim`` sets where the profile gives no value (absent or null): limits that
    #: the simulator, a Python process on the daemon's own (possibly loaded) PC, needs wider than
    #: the real device (a serial reply margin, a CAN TPDO deadline, an RTDE link timeout)
    SIM_DEFAULTS: ClassVar[dict[str, Any]] = {}
    #: the device's speed scaling (0..1) set by its operator (a UR's speed slider), where
    #: ``traits.speed_scaling``: updated by the backend's ``_read``; NaN: not known (yet)
    speed_fraction: float = float("nan")

    def __init__(self, profile: Profile, *, source: str = "<profile>"):
        self.profile = profile
        self.robot = profile.name
        self.joint_names = profile.joint_names
        self.n = len(self.joint_names)
        self._open = False
        self._enabled = False
        self._traits: Traits | None = None
        #: the device's last reported status (see :meth:`report_status`)
        self.device_status = DeviceStatus.OK
        self._status_news: tuple[DeviceStatus, Fault | None] | None = None
        self._news_queue: list[tuple[DeviceStatus, Fault | None]] = []  # WARNING / NOTICE reports, oldest first
        self._read_fault: Fault | None = None  # the last read's fault (None: it succeeded)

    # ---- start-up path (may block, raises BackendError) ----
    def open(self) -> None:
        """Open the bus and check every device answers. Blocks. Raises BackendError."""
        if not self._open:
            self._open_hook()
            if self._traits is None:  # final: a second open (after close) declares nothing new
                try:
                    traits = self._traits_hook()
                except BaseException:
                    self._close_hook()
                    raise
                if traits.n != self.n:
                    self._close_hook()
                    raise BackendError(f"{self.robot}: {type(self).__name__} declared traits for {traits.n} "
                                       f"joints, the profile has {self.n}")
                self._traits = traits
            self._open = True

    @property
    def traits(self) -> Traits:
        """What the backend declares about itself (:class:`Traits`): immutable, final once open.
        Raises BackendError before the first :meth:`open` (a CiA 402 drive's capabilities are
        read from the drive)."""
        traits = self._traits
        if traits is None:
            raise BackendError(f"{self.robot}: the {type(self).__name__} traits were read before open(); "
                               f"they are final only once the backend is open")
        return traits

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
        when ``traits.native_homing``. Does not touch the bus itself; the first step does.
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
            if not self.traits.native_homing:
                raise BackendError(f"{self.robot}: the backend does not home natively")
            steps = self._home_steps()
        else:  # pragma: no cover - Lifecycle is closed
            raise ValueError(kind)
        return Transition(self.robot, kind, steps, self._timeout_s(kind), on_finish)

    def _timeout_s(self, kind: Lifecycle) -> float:
        # close() may run the DISABLE of a backend whose open failed before it declared its traits
        return self._traits.timeout_s(kind) if self._traits is not None else DEFAULT_TRANSITION_TIMEOUTS_S[kind]

    def _finished_enable(self) -> None:
        self._enabled = True

    def _enable_then_fresh(self, feedback: JointFeedback) -> Steps:
        """The backend's ENABLE steps, ending with the pose the joints are held at in
        ``feedback`` (core holds exactly there, never a stale pose: a joint may have sagged while
        torque was off). An ENABLE done in one step writes it into ``feedback`` itself; one
        stepped over cycles ends in a later cycle whose read succeeded (its sample is core's),
        trying ENABLE_FRESH_READ_CYCLES reads (a loaded host may miss one reply: not a FAULT for
        one late byte); none: BackendError. Nothing here touches the bus: the cycle reads it."""
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

    def lerobot_maps(self) -> list[dict[str, list[float]] | None]:
        """Per joint: ``{mode: [scale, bias]}``, LeRobot's number in each of its norm modes
        (``degrees``, ``range_m100_100``, ``range_0_100``) as ``scale * value + bias`` of the
        joint's SI value, from the joint's calibration, or None where LeRobot has no such number
        (docs/protocol.md, "LeRobot units"; ``list`` carries them). Default: None for every joint."""
        return [None] * self.n

    # ---- device status (backend -> core) ----
    def report_status(self, status: DeviceStatus, cause: Fault | None = None) -> None:
        """Called by the backend (from ``_read`` or a step) when the device's status changes.
        Core takes the latest report once per cycle; a report of the current status is ignored.
        WARNING and NOTICE are news, not a status: each is kept (the 16 latest) and taken after
        any status change, one per cycle."""
        if status in DEVICE_NEWS:
            news = self._news_queue
            if len(news) >= 16:
                del news[0]
            news.append((status, cause))
            return
        if status is not self.device_status or status is DeviceStatus.FAULT_CLEARED:
            self.device_status = DeviceStatus.OK if status is DeviceStatus.FAULT_CLEARED else status
            self._status_news = (status, cause)

    def take_status(self) -> tuple[DeviceStatus, Fault | None] | None:
        """The status reported since the last call (and its cause), or None. Core calls it once
        per cycle after ``read``."""
        news = self._status_news
        if news is not None:
            self._status_news = None
        elif self._news_queue:
            news = self._news_queue.pop(0)
        return news

    # ---- pacing (``traits.clock`` is Clock.DEVICE) ----
    def cycle_period_s(self) -> float | None:
        """The device's cycle period (s) when it paces the loop (``traits.clock`` is
        Clock.DEVICE), else None (the profile's ``loop.rate_hz`` rules). Default: None. Known from
        the profile, before open (docs/protocol.md's stopping table is computed from it)."""
        return None

    def wait_cycle(self, deadline: float) -> bool:
        """The start of the cycle scheduled at ``deadline`` (``time.perf_counter``; the cycle
        runner's schedule, core/cycle.py), called first thing in every cycle. On the loop's clock
        the runner has slept to ``deadline`` already: a backend does what starts its cycle (a
        CANopen SYNC). On the device's clock (``traits.clock`` Clock.DEVICE) it blocks until the
        device's next packet, giving up one period after ``deadline``. Returns False when
        nothing came (the read that follows reports the cause). Default: nothing to do (True)."""
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
        """Send ``command`` in one bus transaction. Never raises.

        The one finiteness gate of every backend: a joint whose setpoint (the field its mode
        follows, and a position's velocity feed-forward) or a cartesian row whose pose or twist
        is not finite is handed to ``_write`` in :attr:`CommandMode.NONE` (its joints keep their
        last goal; the others are sent) and the write returns a non-transient ``invalid_command``
        Fault naming the robot and joint, so core faults the robot. No backend checks NaN itself."""
        refused = None if _all_finite(command) else self._refuse_non_finite(command)
        try:
            fault = self._write(command)
        except Exception as exc:
            fault = Fault("backend_exception", f"{self.robot}: write failed: {exc!r}", transient=False)
        if refused is None:
            return fault
        fault_out, modes, cart_modes = refused
        command.mode[:] = modes  # the caller's buffer as it was
        if cart_modes is not None:
            command.cartesian.mode[:] = cart_modes
        return fault_out

    def _refuse_non_finite(self, command: JointCommand) -> tuple[Fault, np.ndarray, np.ndarray | None] | None:
        """Set every joint (cartesian row) with a non-finite setpoint to NONE for this write; ->
        (the Fault naming the first, the modes to restore), or None when all is finite after all
        (a sum that overflowed)."""
        first = None
        modes = command.mode.copy()
        for i in range(self.n):
            m = modes[i]
            if m == _POSITION:
                fields = ("position", command.position[i]), ("velocity", command.velocity[i])
            elif m == _VELOCITY:
                fields = (("velocity", command.velocity[i]),)
            elif m == _EFFORT:
                fields = (("effort", command.effort[i]),)
            else:
                continue
            bad = next(((f, v) for f, v in fields if not np.isfinite(v)), None)
            if bad is not None:
                command.mode[i] = _NONE_MODE
                if first is None:
                    name = self.joint_names[i]
                    first = Fault("invalid_command", f"{self.robot}: joint {name!r}: {bad[0]} setpoint {bad[1]} "
                                  "is not finite; not sent (the joint keeps its last goal)", joint=name,
                                  transient=False)
        cart, cart_modes = command.cartesian, None
        if cart is not None:
            rows = self.cartesian_namespaces()
            cart_modes = cart.mode.copy()
            for k in range(len(cart_modes)):
                m = cart_modes[k]
                if m == CartesianMode.TWIST:
                    ok = np.isfinite(cart.linear[k]).all() and np.isfinite(cart.angular[k]).all()
                    what = "twist"
                elif m in (CartesianMode.POSE, CartesianMode.MOVE):
                    ok = np.isfinite(cart.position[k]).all() and np.isfinite(cart.orientation[k]).all()
                    what = "pose"
                else:
                    continue
                if not ok:
                    cart.mode[k] = CartesianMode.NONE
                    if first is None:
                        first = Fault("invalid_command", f"{self.robot}: namespace {rows[k]!r}: cartesian {what} "
                                      "setpoint is not finite; not sent (the arm keeps its last goal)",
                                      transient=False)
        if first is None:
            return None
        return first, modes, cart_modes

    def deceleration_limit(self, i: int) -> float:
        """rad/s^2: the most joint ``i``'s hardware decelerates at as configured (a servo's own
        acceleration register), bounding the default stop deceleration
        (:func:`~crtk_bridge.profile.stop_deceleration`). Default: unbounded (inf)."""
        return float("inf")

    def cartesian_namespaces(self) -> list[str]:
        """The namespaces this backend controls in cartesian space itself, in the order of the
        rows of :class:`CartesianCommand` / :class:`CartesianFeedback`. Default: with
        ``traits.capabilities.native_cartesian``, every namespace with a ``kinematics`` section."""
        if not self.traits.capabilities.native_cartesian:
            return []
        return [ns.name for ns in self.profile.namespaces if ns.kinematics is not None]

    def goal_check_steps(self, ns: str, cmd: str, goal: np.ndarray) -> Steps | None:
        """Steps that ask the device whether a move goal is within ITS OWN limits (a UR's safety
        limits) before core starts the move; core runs them as a GOAL_CHECK transition (the cycle
        goes on) and starts the move once they end. ``goal``: the namespace's joint positions
        (``move_jp``) or the pose ``[x, y, z, qx, qy, qz, qw]`` (``move_cp`` on a native cartesian
        namespace). They raise :class:`~crtk_bridge.errors.CommandError` (``out_of_limits``, the
        message naming the joint or pose) to refuse the move. None (the default): no such check.
        Called only when ``traits.goal_check``."""
        return None

    def mode_switch_steps(self, modes: np.ndarray) -> Steps | None:
        """The operating-mode change the device needs to follow the per-joint
        :class:`CommandMode` ``modes`` (ros2_control's prepare / perform): this call, the
        prepare, decides off the bus; the steps it returns perform the change on the cycle,
        stepped (one joint's acknowledged transactions per step), and hold the joints meanwhile;
        ``_write`` leaves a joint alone until its device mode is the one its command needs.
        Core calls it when the command's modes changed (before the cycle's write) and runs the
        steps as a MODE_SWITCH transition; a failure faults the robot (the joint may be
        unpowered). None (the default): the device follows every mode as it is."""
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
        return ActuatorInfo(list(self.joint_names))

    @staticmethod
    def now() -> float:
        return time.time()

    # ---- hooks for subclasses ----
    @abc.abstractmethod
    def _open_hook(self) -> None: ...

    @abc.abstractmethod
    def _traits_hook(self) -> Traits:
        """The backend's :class:`Traits`, called once by :meth:`open` right after ``_open_hook``
        (so what the devices said is known); final from then on."""

    def _configure_hook(self) -> None:
        pass

    @abc.abstractmethod
    def _enable_steps(self, feedback: JointFeedback) -> Steps:
        """Steps of ENABLE: torque on, holding where the joints are. Steps that end without
        yielding (all done in the first step) leave the pose they hold in ``feedback``; stepped
        over cycles, the cycle's read after the last step gives it (:meth:`_enable_then_fresh`)."""

    @abc.abstractmethod
    def _disable_steps(self) -> Steps:
        """Steps of DISABLE (torque off on every joint; also core's reaction to a FAULT)."""

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
        """Steps of native homing (incremental encoders), where ``traits.native_homing``; else
        core homes by moving to the profile's ``home`` positions."""
        raise NotImplementedError
        yield  # pragma: no cover

    @abc.abstractmethod
    def _close_hook(self) -> None: ...

    @abc.abstractmethod
    def _read(self, feedback: JointFeedback) -> Fault | None: ...

    @abc.abstractmethod
    def _write(self, command: JointCommand) -> Fault | None: ...


_POSITION, _VELOCITY, _EFFORT, _NONE_MODE = (int(CommandMode.POSITION), int(CommandMode.VELOCITY),
                                             int(CommandMode.EFFORT), int(CommandMode.NONE))


def _all_finite(command: JointCommand) -> bool:
    """True when every number of ``command`` is finite (the cycle's fast path: a sum is finite
    only if every term is; False may also mean a finite sum that overflowed, checked joint by joint)."""
    # Python floats: an overflow is inf, never a warning; a third of numpy's cost on a few joints
    total = sum(command.position.tolist()) + sum(command.velocity.tolist()) + sum(command.effort.tolist())
    cart = command.cartesian
    if cart is not None:
        total += (sum(cart.position.ravel().tolist()) + sum(cart.orientation.ravel().tolist())
                  + sum(cart.linear.ravel().tolist()) + sum(cart.angular.ravel().tolist()))
    return math.isfinite(total)


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

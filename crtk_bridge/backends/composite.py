"""Several buses in one robot: one actuator made of one backend per bus.

A profile with ``backends:`` (by name) describes a robot on several buses -- two arms on two serial
buses, a UR arm with a servo gripper. Each namespace's joints live on one bus; each bus gets its
own backend, built from a one-bus profile (:meth:`Profile.bus_profile`) that knows only its joints.
:class:`CompositeActuator` puts them behind the one actuator interface, so core sees one robot:
one loop, one operating state, one sample per cycle with one stamp.

Real-time path: ``read`` and ``write`` fan out to one persistent worker thread per bus (the first
bus is served by the calling thread itself, which saves a hand-off) and join, so independent buses'
I/O overlaps: serial I/O waits in ``select`` / ``os.read`` with the GIL released. The hand-off is
two pre-allocated locks per worker (no allocation, no Condition per cycle); the per-bus buffers
are pre-allocated and gathered / scattered with index arrays. The cycle's stamp is the earliest
bus's read in the cycle (the sample is at least that old). A fault on any bus is the robot's, its message naming
the bus (and the bus's backend names the joint).

A bus slower than the robot's cycle (``traits.min_period_s`` longer than the effective period: a
Robotiq gripper's Modbus RTU beside a UR's 500 Hz) is served at its own rate and never joined
(:class:`_OwnRateWorker`): its thread runs the bus's own cycles (core/cycle.py
``CycleRunner.own_rate``) and publishes each completed read with its own stamp (the robot's
sample keeps the stamp of the buses read in the cycle: :meth:`CompositeActuator.bus_stamps` has
that bus's); the cycle takes the newest sample, posts the newest setpoint (newest wins: a stop never queues behind stale
setpoints) and hands the bus's lifecycle transitions to it, seeing at each read how they went (the
robot's DISABLE ends only once that bus's did). Its failures are counted at its own rate against
``safety.bus_errors_max`` and reach the loop as a FAULT naming bus and joint
(docs/architecture.md, "Several buses: the composite").

Start-up: ``open`` / ``configure`` / ``close`` run bus by bus (``open`` closes the buses already
opened when one fails). Lifecycle transitions (enable, disable, pause, resume, fault reset) run on
every bus together: each cycle steps every bus's :class:`~crtk_bridge.core.actuator.Transition`
once, so a bus that takes many cycles (a CiA 402 controlword walk) never holds the others back,
and the robot's transition ends when the last bus's does. Enable is all or none (a bus that fails
gets every bus disabled again, the error naming the bus); disable goes on on every bus and names
those that did not confirm.

What the buses declare (their :class:`~crtk_bridge.core.actuator.Traits`, final once each is open)
becomes the robot's through ONE function, :func:`combine_traits`, with one rule per field
(:data:`TRAIT_RULES`; tests/test_composite.py fails on a field without one):

* per joint (capabilities, what each joint measures, pause behaviour): each joint keeps its own
  bus's, so a UR arm's namespace resumes from where the arm's own stop left it while its servo
  gripper resumes from core's braking ramp;
* the clock: the one bus whose device paces the loop (two such buses are refused);
* write policy: written every cycle if any bus needs it (the others only while enabled);
* goal check: if any bus checks goals, each namespace's goal is checked by its own bus;
* homing: if any bus homes natively, the robot does, HOME running on those buses (a bus that
  needs homing but cannot home itself beside one that can is refused: core's move-home and a
  native HOME cannot share one ``home``);
* speed scaling: the bus that has a speed slider reports it (the slowest, if several do);
* the shortest period: the longest of the buses served in every cycle (a slower one is served
  at its own rate and bounds nothing);
* transition time limits: the buses' added up (their steps share the loop's thread), plus the
  rollback of a failed enable.

Device status is the most severe bus's, its cause naming the bus; native cartesian namespaces
are each bus's rows of the cartesian setpoints and measured poses, bus after bus. When the robot
enters FAULT, core's DISABLE switches torque off on every bus. A failed enable is undone in steps
too: every bus that may have torque on (finished or partly enabled) runs its own DISABLE steps,
together, one per cycle, within the disable time limits, before the error naming the failed bus
is raised.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ..core.actuator import (
    DEVICE_NEWS,
    Actuator,
    ActuatorInfo,
    Clock,
    CommandMode,
    DeviceStatus,
    Fault,
    JointCommand,
    JointFeedback,
    Lifecycle,
    Steps,
    Traits,
    Transition,
)
from ..core.cycle import CycleRunner
from ..errors import BackendError, ProfileError
from ..profile import Profile

_READ, _WRITE, _STOP = 1, 2, 3
_SEVERITY = {DeviceStatus.OK: 0, DeviceStatus.PAUSED: 1, DeviceStatus.POWERED_OFF: 2, DeviceStatus.FAULT: 3}


class _BusWorker:
    """One persistent thread doing one bus's ``read`` / ``write`` when told, then signalling.

    ``start(op)`` releases ``_go``; the thread runs the op and releases ``_done``; ``join()``
    acquires ``_done``. Plain locks may be released by another thread than the one that acquired
    them: two locks make a hand-off with no allocation (a Condition allocates a waiter lock per wait).
    """

    def __init__(self, name: str, actuator: Actuator, feedback: JointFeedback, command: JointCommand):
        self.actuator = actuator
        self.feedback = feedback
        self.command = command
        self.result: Fault | None = None
        self._op = 0
        self._go = threading.Lock()
        self._go.acquire()
        self._done = threading.Lock()
        self._done.acquire()
        self._thread = threading.Thread(target=self._run, name=f"crtk-bus-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        act = self.actuator
        while True:
            self._go.acquire()
            op = self._op
            if op == _STOP:
                self._done.release()
                return
            # read / write never raise (Actuator turns a backend's exception into a Fault)
            self.result = act.read(self.feedback) if op == _READ else act.write(self.command)
            self._done.release()

    def start(self, op: int) -> None:
        self._op = op
        self._go.release()

    def join(self) -> Fault | None:
        self._done.acquire()
        return self.result

    def stop(self) -> None:
        if self._thread.is_alive():
            self.start(_STOP)
            self._done.acquire()
            self._thread.join(1.0)


#: an own-rate bus with no new sample for this many of its periods (at least OWN_RATE_STALE_S) is
#: lost: its worker is stuck (its own read failures are counted by the worker itself)
OWN_RATE_STALE_PERIODS = 50
OWN_RATE_STALE_S = 2.0
#: close() waits this long (at least 4 of the bus's periods) for an own-rate worker to end; one
#: still inside a call on the bus then keeps the bus (it closes it itself once the call returns)
OWN_RATE_STOP_S = 1.0


def _copy_feedback(dst: JointFeedback, src: JointFeedback) -> None:
    np.copyto(dst.position, src.position)
    np.copyto(dst.velocity, src.velocity)
    np.copyto(dst.effort, src.effort)
    dst.stamp = src.stamp
    if dst.cartesian is not None and src.cartesian is not None:
        dst.cartesian.copy_from(src.cartesian)


def _copy_command(dst: JointCommand, src: JointCommand) -> None:
    np.copyto(dst.mode, src.mode)
    np.copyto(dst.position, src.position)
    np.copyto(dst.velocity, src.velocity)
    np.copyto(dst.effort, src.effort)
    a, b = dst.cartesian, src.cartesian
    if a is not None and b is not None:
        for name in ("mode", "position", "orientation", "linear", "angular", "frame", "seq"):
            np.copyto(getattr(a, name), getattr(b, name))


class _OwnRateWorker:
    """A bus served at its own rate (its ``traits.min_period_s`` is longer than the robot's
    cycle): one thread runs the bus's own cycle on its own schedule (core/cycle.py
    ``CycleRunner.own_rate``: wait, read, one step of the transition handed to it, write the
    newest setpoint) and publishes each completed read with its own stamp. The loop's cycle never
    waits for it: it takes the newest published sample (:meth:`take`), hands the newest setpoint
    over (:meth:`post`: newest wins, so a stop never queues behind stale setpoints) and hands
    lifecycle transitions over (:meth:`hand`), seeing how they went at its reads. One lock guards
    the hand-overs (copies of a few numbers). Failed reads / writes are counted here against
    ``safety.bus_errors_max`` (core counts the loop's cycles, not the bus's): the loop hears of a
    failure once it is a FAULT (non-transient), in the cycle that sees it."""

    def __init__(self, name: str, actuator: Actuator, period_s: float, errors_max: int,
                 first: JointFeedback | None = None):
        """``first``: the bus's sample read at open (the loop's first cycles take it until the
        worker's own first read); None: none (a transient "no sample yet" until then)."""
        self.actuator = actuator
        self.period_s = period_s
        self.errors_max = max(1, int(errors_max))
        self.stale_s = max(OWN_RATE_STALE_S, OWN_RATE_STALE_PERIODS * period_s)
        self.runner = CycleRunner(actuator, period_s)  # the bus's own schedule
        self._lock = threading.Lock()
        self._stop = False
        # loop -> worker (under _lock)
        self._cmd = actuator.new_command()  # the newest setpoint (every joint NONE: none yet)
        self._handed: _Handed | None = None  # the transition to step (begun on the worker's thread)
        self._aborts: list[_Handed] = []  # replaced or abandoned: closed on the worker's thread
        self._orphaned = False  # stop() gave up waiting: the worker closes the bus itself
        self._exited = False
        # worker -> loop (under _lock)
        self._sample = actuator.new_feedback()
        self._sample_fault: Fault | None = Fault(
            "bus_timeout", f"{actuator.robot}: no sample yet (served at its own rate)", transient=True)
        if first is not None:
            _copy_feedback(self._sample, first)
            self._sample_fault = None
        self._write_fault: Fault | None = None
        self._news: tuple[DeviceStatus, Fault | None] | None = None
        self._device_news: list[tuple[DeviceStatus, Fault | None]] = []  # WARNING / NOTICE reports
        self._result: tuple[_Handed, bool, BaseException | None] | None = None
        self._published = time.monotonic()
        self.cycles = 0  # the bus's own cycles run
        # the worker's own
        self._mine = actuator.new_command()
        self._streak = {"read": 0, "write": 0}
        self._stepping: _Handed | None = None  # the transition this cycle stepped
        # the loop's own: what the last take() saw
        self.seen: tuple[_Handed, bool, BaseException | None] | None = None
        self.news: tuple[DeviceStatus, Fault | None] | None = None
        self.device_news: list[tuple[DeviceStatus, Fault | None]] = []  # the news reported since
        #: the feedback an ENABLE handed to this bus holds (the worker's, not the loop's buffer)
        self.enable_feedback = actuator.new_feedback()
        self._thread = threading.Thread(target=self._run, name=f"crtk-bus-{name}", daemon=True)
        self._thread.start()

    # ---- the worker's thread
    def _run(self) -> None:
        act, runner = self.actuator, self.runner
        runner.restart()
        try:
            while not self._stop:
                self._stepping = None
                read_fault, write_fault, done, error = runner.own_rate(self._fetch, self._newest)
                h = self._stepping
                read_fault = self._count("read", read_fault)
                write_fault = self._count("write", write_fault)
                reports = []
                while (report := act.take_status()) is not None:  # its status, then its news
                    reports.append(report)
                with self._lock:
                    _copy_feedback(self._sample, runner.feedback)
                    self._sample_fault = read_fault
                    if write_fault is not None:
                        self._write_fault = write_fault
                    for report in reports:
                        if report[0] in DEVICE_NEWS:
                            self._device_news.append(report)
                        else:
                            self._news = report
                    if h is not None and self._handed is h:
                        self._result = (h, done, error)
                        if done:
                            self._handed = None
                    self._published = time.monotonic()
                    self.cycles += 1
        finally:
            with self._lock:
                left = [*self._aborts, self._handed]
                self._aborts, self._handed = [], None
            for a in left:
                if a is not None:
                    a.close()
            with self._lock:
                self._exited = True
                orphaned = self._orphaned
            if orphaned:  # close() gave the bus up to this thread: its torque off and release
                act.close()

    def _fetch(self) -> Transition | None:
        """The transition to step in this cycle, asked after its read (``CycleRunner.own_rate``):
        the ones the loop replaced or abandoned meanwhile are closed first, a newly handed one is
        begun here (``Actuator.begin``: its bookkeeping, e.g. ``is_enabled``, is this thread's
        alone, as the bus is), and it is stepped only if it is still the one handed."""
        with self._lock:
            h = self._handed
            aborts = self._aborts
            if aborts:
                self._aborts = []
        for a in aborts:  # replaced or abandoned by the loop: closed on this thread
            a.close()
        if h is None:
            return None
        self._stepping = h  # (what make() raises is its result)
        if h.transition is None:
            h.transition = h.make()
        with self._lock:
            if self._handed is not h:  # abandoned while it began: closed at the next cycle
                self._stepping = None
                return None
        return h.transition

    def _newest(self) -> JointCommand:
        """The newest setpoint the loop posted, taken just before the bus's write; none (every
        joint NONE) once a DISABLE is handed, even before it began here (a stop is at once)."""
        mine = self._mine
        with self._lock:
            h = self._handed
            if h is not None and h.quiet:
                mine.mode[:] = CommandMode.NONE
                if mine.cartesian is not None:
                    mine.cartesian.mode[:] = 0
            else:
                _copy_command(mine, self._cmd)
        return mine

    def _count(self, what: str, fault: Fault | None) -> Fault | None:
        """The bus's failed reads (writes) in a row: a transient failure is the loop's only from
        ``errors_max`` in a row on (then non-transient: the robot's FAULT)."""
        if fault is None:
            self._streak[what] = 0
            return None
        n = self._streak[what] = self._streak[what] + 1
        if not fault.transient:
            return fault
        if n < self.errors_max:
            return None
        return dataclasses.replace(fault, message=f"{fault.message} ({n} failed {what}s in a row)", transient=False)

    # ---- the loop's thread
    def take(self, feedback: JointFeedback) -> Fault | None:
        """The newest completed read into ``feedback`` (its own stamp), the transition's progress
        into :attr:`seen`, the device status reported since into :attr:`news` and its news
        (WARNING / NOTICE) into :attr:`device_news`; -> the read's
        fault (a FAULT), or a non-transient ``bus_timeout`` when nothing was published for
        ``stale_s`` (a stuck worker)."""
        with self._lock:
            _copy_feedback(feedback, self._sample)
            fault = self._sample_fault
            self.seen = self._result
            self.news, self._news = self._news, None
            self.device_news, self._device_news = self._device_news, []
            published = self._published
        if fault is None and time.monotonic() - published > self.stale_s:
            return Fault("bus_timeout", f"{self.actuator.robot}: no sample for {self.stale_s:g} s "
                         f"(served at its own rate every {self.period_s * 1e3:.3g} ms)", transient=False)
        return fault

    def post(self, command: JointCommand) -> Fault | None:
        """``command`` becomes the newest setpoint (the last one posted wins); -> the write fault
        (a FAULT) the bus reported since the last post, once."""
        with self._lock:
            _copy_command(self._cmd, command)
            fault, self._write_fault = self._write_fault, None
        return fault

    def clear_command(self) -> None:
        """No setpoint (every joint NONE) until the loop posts one: an ENABLE must not send a
        setpoint from before it."""
        with self._lock:
            self._cmd.mode[:] = CommandMode.NONE
            if self._cmd.cartesian is not None:
                self._cmd.cartesian.mode[:] = 0

    def hand(self, handed: "_Handed") -> None:
        """``handed`` is begun and stepped on the bus's own cycles from now on, replacing
        (aborting) any other."""
        with self._lock:
            if self._handed is not None:
                self._aborts.append(self._handed)
            self._handed = handed
            self._result = None

    def abort(self, handed: "_Handed") -> None:
        """Stop stepping ``handed``; it is closed on the worker's thread (a no-op if it ended)."""
        with self._lock:
            if self._handed is handed:
                self._handed = None
            self._aborts.append(handed)

    def stop(self) -> bool:
        """End the worker. True once it ended; False when it is still inside a call on the bus
        after OWN_RATE_STOP_S (at least 4 periods): then the bus stays its alone (no second
        thread on it) and it closes the bus itself (torque off, release) once the call returns."""
        self._stop = True
        if self._thread.is_alive():
            self._thread.join(max(OWN_RATE_STOP_S, 4 * self.period_s))
        with self._lock:
            if not self._exited:
                self._orphaned = True
            return self._exited


class _Handed:
    """A bus's lifecycle transition stepped on its own-rate worker (:class:`_OwnRateWorker`), as
    the composite's steps see it: each loop cycle's step tells how it went as of that cycle's
    read (so an ENABLE ends with the bus's fresh sample already taken). ``make()`` begins it
    (the part's ``begin``), on the worker's thread at its first step: the bus and the part's
    state are that thread's alone, so an ENABLE the loop abandoned is closed there before the
    DISABLE that replaced it begins, never stepped after it."""

    __slots__ = ("worker", "make", "quiet", "transition", "done")

    def __init__(self, worker: _OwnRateWorker, make: Callable[[], Transition], quiet: bool = False):
        """``quiet``: no setpoint is written from now on (a DISABLE)."""
        self.worker, self.make, self.quiet, self.done = worker, make, quiet, False
        self.transition: Transition | None = None  # the worker's own, once begun
        worker.hand(self)

    def step(self) -> bool:
        if self.done:
            return True
        seen = self.worker.seen
        if seen is not None and seen[0] is self:
            if seen[2] is not None:
                self.done = True
                raise seen[2]
            if seen[1]:
                self.done = True
                return True
        return False

    def abort(self) -> None:
        if not self.done:
            self.done = True
            self.worker.abort(self)

    def close(self) -> None:
        """On the worker's thread: the transition, if begun, is closed (its ``finally`` runs)."""
        if self.transition is not None:
            self.transition.abort()


class _Buses:
    """What a combining rule may need beside the buses' traits: joint ``i`` of the robot is joint
    ``owner[i][1]`` of bus ``owner[i][0]``; ``names`` are the buses'; ``where`` names the robot;
    ``period_s`` is the robot's cycle period (None: not known)."""

    def __init__(self, owner: Sequence[tuple[int, int]], names: Sequence[str], where: str,
                 period_s: float | None = None):
        self.owner, self.names, self.where, self.period_s = owner, names, where, period_s

    def named(self, buses: Sequence[int]) -> str:
        return ", ".join(repr(self.names[b]) for b in buses)


def _per_joint(values: list, parts: list[Traits], buses: _Buses) -> tuple:
    """Each robot joint keeps its own bus's value."""
    return tuple(values[b][k] for b, k in buses.owner)


def _any(values: list, parts: list[Traits], buses: _Buses) -> bool:
    return any(values)


def _one_clock(values: list, parts: list[Traits], buses: _Buses) -> Clock:
    """The device's clock if one bus's device paces the loop; two cannot."""
    pacing = [b for b, c in enumerate(values) if c is Clock.DEVICE]
    if len(pacing) > 1:
        raise ProfileError(f"{buses.where}: backends: buses {buses.named(pacing)} both pace the control loop "
                           f"(each has its device's clock); at most one bus of a robot may")
    return Clock.DEVICE if pacing else Clock.LOOP


def _homing(values: list, parts: list[Traits], buses: _Buses) -> bool:
    """Native if any bus homes itself; then every bus that needs homing must home itself too."""
    if not any(values):
        return False
    unhomed = [b for b, t in enumerate(parts) if not t.native_homing and t.capabilities.needs_homing]
    if unhomed:
        raise ProfileError(f"{buses.where}: backends: bus {buses.named(unhomed)} needs homing but does not home "
                           f"itself, beside bus {buses.named([b for b, v in enumerate(values) if v])} that does; "
                           f"the robot's `home` cannot be both (put those joints on one kind of bus)")
    return True


def _timeouts(values: list, parts: list[Traits], buses: _Buses) -> dict[Lifecycle, float]:
    """Added up: the buses' steps share the loop's thread, so in the worst case their times add up
    (HOME: the buses that home natively); an enable may end in a rollback (every bus's disable)."""
    out = {}
    for kind in Lifecycle:
        homing = [t for t in parts if t.native_homing]
        of = homing if kind is Lifecycle.HOME and homing else parts
        out[kind] = sum(t.timeout_s(kind) for t in of)
    out[Lifecycle.ENABLE] += out[Lifecycle.DISABLE]
    return out


def _joined_period(values: list, parts: list[Traits], buses: _Buses) -> float:
    """The longest of the buses the robot's cycle serves in every cycle: a bus slower than the
    robot's cycle period is served at its own rate (CompositeActuator) and bounds nothing."""
    period = buses.period_s
    return max((v for v in values if period is None or v <= period), default=0.0)


#: how the robot's traits come from its buses': one rule per :class:`Traits` field, called with
#: (each bus's value, each bus's traits, the buses); tests/test_composite.py checks every field has one
TRAIT_RULES: dict[str, Callable[[list, list[Traits], _Buses], Any]] = {
    "joints": _per_joint,
    "clock": _one_clock,
    "cyclic_write": _any,
    "stops_itself_on_pause": _per_joint,
    "goal_check": _any,  # delegated per namespace to its bus (CompositeActuator.goal_check_steps)
    "native_homing": _homing,
    "speed_scaling": _any,  # the bus's slider (CompositeActuator.speed_fraction)
    "min_period_s": _joined_period,
    "transition_timeouts_s": _timeouts,
}


def combine_traits(parts: Sequence[Traits], owner: Sequence[tuple[int, int]], names: Sequence[str],
                   where: str, period_s: float | None = None) -> Traits:
    """The traits of a robot made of buses with traits ``parts`` (see the module docstring):
    every field of :class:`Traits` by its rule in :data:`TRAIT_RULES` (``period_s``: the robot's
    cycle period, which decides which buses are served at their own rate). Raises ProfileError when
    the buses cannot be one robot, naming them; a field without a rule is a bug (KeyError)."""
    parts = list(parts)
    buses = _Buses(owner, names, where, period_s)
    return Traits(**{f.name: TRAIT_RULES[f.name]([getattr(t, f.name) for t in parts], parts, buses)
                     for f in dataclasses.fields(Traits)})


class CompositeActuator(Actuator):
    """One robot on several buses: ``buses`` maps bus name -> (backend built on that bus's
    one-bus profile). Joint ``i`` of the robot is joint ``k`` of exactly one bus."""

    def __init__(self, profile: Profile, buses: dict[str, Actuator], *, source: str = "<profile>"):
        super().__init__(profile, source=source)
        self.bus_names = list(buses)
        self.parts = list(buses.values())
        index = {name: i for i, name in enumerate(self.joint_names)}
        #: robot joint indices of each bus's joints, in the bus's order
        self._idx = [np.array([index[n] for n in part.joint_names], dtype=np.intp) for part in self.parts]
        self._owner = np.empty(self.n, dtype=np.intp)  # robot joint -> (bus, joint on the bus)
        self._local = np.empty(self.n, dtype=np.intp)
        for b, idx in enumerate(self._idx):
            self._owner[idx] = b
            self._local[idx] = np.arange(len(idx))
        #: namespace -> its bus
        self._ns_bus = {ns.name: self.bus_names.index(profile.namespace_bus(ns)) for ns in profile.namespaces}
        # known once the buses are open (their traits, their cartesian rows): _open_hook
        self._fb: list[JointFeedback] = []
        self._cmd: list[JointCommand] = []
        self._cart_rows: list[tuple[int, int, int]] = []
        self._cyclic: list[bool] = []
        self._pacer: Actuator | None = None
        self._scaled: list[Actuator] = []  # the buses with a speed slider
        self._combined: Traits | None = None
        self._workers: list[_BusWorker | _OwnRateWorker] | None = None  # started at the first cycle (_start_workers)
        #: per bus: its worker (None: the bus served on the calling thread), once started
        self._bw: list[_BusWorker | _OwnRateWorker | None] = []
        #: bus -> its own period (s), for the buses served at their own rate (known once open)
        self.own_rate: dict[str, float] = {}
        self._own_b: list[int] = []  # the buses served at their own rate
        self._joined_b: list[int] = []  # the buses joined every cycle on a worker of theirs
        self._first = -1  # the bus joined every cycle on the calling thread (-1: none)
        self._first_sample: dict[int, JointFeedback] = {}  # own-rate bus -> its sample read at open
        self._stamped: list[bool] = []  # per bus: its stamp is one the robot's sample takes
        self._stops_itself = [False] * len(self.parts)  # per bus: a joint of it stops itself on pause (known once open)
        #: per bus: not written (it holds where its own RESUME left it) until the robot's RESUME ends
        self._held = [False] * len(self.parts)
        nb = len(self.parts)
        self._read_res: list[Fault | None] = [None] * nb  # this cycle's result per bus
        self._write_res: list[Fault | None] = [None] * nb
        self._read_streak = [0] * nb  # failed cycles in a row per bus
        self._write_streak = [0] * nb
        self._where = [f"bus {name!r}" for name in self.bus_names]
        #: per bus: an ENABLE took a step and neither finished nor was undone (some torque may be on)
        self._partial = [False] * nb
        self._source = source

    def _bus_of(self, parts: list[Actuator]) -> list[str]:
        return [repr(name) for name, p in zip(self.bus_names, self.parts) if p in parts]

    # ---------------------------------------------------------------- traits
    def _traits_hook(self) -> Traits:
        return self._combined

    def _combine(self) -> None:
        """The robot's traits and what follows from them, once every bus is open."""
        owner = [(int(self._owner[i]), int(self._local[i])) for i in range(self.n)]
        self._pacer = next((p for p in self.parts if p.traits.clock is Clock.DEVICE), None)
        hw = self._pacer.cycle_period_s() if self._pacer is not None else None
        period = float(hw) if hw is not None else 1.0 / self.profile.loop.rate_hz  # (effective_period_s)
        self._combined = combine_traits([p.traits for p in self.parts], owner, self.bus_names, self._source, period)
        # a bus slower than the robot's cycle is served at its own rate, never joined by the cycle
        self._own_b = [b for b, p in enumerate(self.parts) if p.traits.min_period_s > period]
        self.own_rate = {self.bus_names[b]: self.parts[b].traits.min_period_s for b in self._own_b}
        joined = [b for b in range(len(self.parts)) if b not in self._own_b]
        self._first = joined[0] if joined else -1
        self._joined_b = joined[1:]
        # the sample's one stamp: the earliest of the buses read in the cycle (an own-rate bus's
        # newest read is older by up to its period: stamping the robot's sample with it would
        # freeze the stamp of a 500 Hz arm for cycles while its joints move); every bus's if
        # every bus runs at its own rate
        self._stamped = [b in joined or not joined for b in range(len(self.parts))]
        self._fb = [p.new_feedback() for p in self.parts]
        self._cmd = [p.new_command() for p in self.parts]
        # native cartesian rows (a UR arm beside a servo gripper): bus b's rows are the robot's lo:hi
        self._cart_rows = []
        lo = 0
        for b, p in enumerate(self.parts):
            k = len(p.cartesian_namespaces())
            if k:
                self._cart_rows.append((b, lo, lo + k))
                lo += k
        # written every cycle if its bus needs it; the others only while enabled
        self._cyclic = [p.traits.cyclic_write for p in self.parts]
        self._stops_itself = [any(p.traits.stops_itself_on_pause) for p in self.parts]
        self._scaled = [p for p in self.parts if p.traits.speed_scaling]

    # ---------------------------------------------------------------- pacing
    def cycle_period_s(self) -> float | None:
        return self._pacer.cycle_period_s() if self._pacer is not None else None

    def wait_cycle(self, deadline: float) -> bool:
        """The pacing bus's wait (the device's clock) first, if any; then every other joined
        bus's start of the cycle (a CANopen SYNC), in bus order (a bus served at its own rate
        starts its own cycles)."""
        pacer = self._pacer
        ok = pacer.wait_cycle(deadline) if pacer is not None else True
        own = self._own_b
        for b, p in enumerate(self.parts):
            if p is not pacer and b not in own:
                p.wait_cycle(deadline)
        return ok

    @property
    def speed_fraction(self) -> float:  # type: ignore[override]
        """The speed slider of the bus that has one (the slowest, if several do); NaN: none known."""
        known = [v for v in (p.speed_fraction for p in self._scaled) if v == v]
        return min(known) if known else math.nan

    def goal_check_steps(self, ns: str, cmd: str, goal: np.ndarray) -> Steps | None:
        """The goal check of namespace ``ns``'s own bus (None where that bus has none)."""
        b = self._ns_bus[ns]
        part = self.parts[b]
        if not part.traits.goal_check:
            return None
        steps = part.goal_check_steps(ns, cmd, goal)
        return None if steps is None else self._named_steps(b, self._bus_steps(b, Lifecycle.GOAL_CHECK, steps))

    def mode_switch_steps(self, modes: np.ndarray) -> Steps | None:
        """Each bus's own operating-mode switch for its joints' ``modes``, stepped together (one
        step of each per cycle, as :meth:`_together`); None when no bus needs one."""
        todo = []
        for b, idx in enumerate(self._idx):
            steps = self.parts[b].mode_switch_steps(modes[idx])
            if steps is not None:
                todo.append(self._named_steps(b, self._bus_steps(b, Lifecycle.MODE_SWITCH, steps)))
        return self._switch_together(todo) if todo else None

    @staticmethod
    def _switch_together(todo: list[Steps]) -> Steps:
        pending = todo
        try:
            while pending:
                running = []
                for steps in pending:
                    try:
                        next(steps)
                        running.append(steps)
                    except StopIteration:
                        pass
                pending = running
                if pending:
                    yield
        finally:
            for steps in todo:
                steps.close()

    def _bus_steps(self, b: int, kind: Lifecycle, steps: Steps) -> Steps:
        """Bus ``b``'s own steps: as they are for a bus joined every cycle (the caller steps them
        on the loop's thread, after its read); stepped on its own cycles for a bus served at its
        own rate (its bus is its worker's alone), the caller's step seeing how they went."""
        if b not in self._own_b:
            return steps
        return self._handed_steps(b, Transition(self.robot, kind, steps, math.inf))

    def _handed_steps(self, b: int, transition: Transition) -> Steps:
        self._ensure_workers()
        handed = _Handed(self._bw[b], lambda: transition)
        try:
            while not handed.step():
                yield
        finally:
            handed.abort()

    def _named_steps(self, b: int, steps: Steps) -> Steps:
        """A bus's steps whose BackendError names the bus (a refusal, CommandError, passes as is)."""
        try:
            yield from steps
        except BackendError as exc:
            raise self._named(b, exc) from exc

    def deceleration_limit(self, i: int) -> float:
        return self.parts[self._owner[i]].deceleration_limit(int(self._local[i]))

    def lerobot_maps(self) -> list[dict[str, list[float]] | None]:
        maps = [p.lerobot_maps() for p in self.parts]
        return [maps[self._owner[i]][self._local[i]] for i in range(self.n)]

    def cartesian_namespaces(self) -> list[str]:
        """Every bus's natively cartesian namespaces, bus after bus (the rows of the robot's
        CartesianCommand / CartesianFeedback)."""
        return [ns for p in self.parts for ns in p.cartesian_namespaces()]

    def info(self) -> ActuatorInfo:
        details: dict[str, Any] = {name: p.info().details for name, p in zip(self.bus_names, self.parts)}
        return ActuatorInfo(list(self.joint_names), {"buses": details, "own_rate_period_s": dict(self.own_rate)})

    # ---------------------------------------------------------------- lifecycle
    def _open_hook(self) -> None:
        opened = []
        try:
            for b, p in enumerate(self.parts):
                self._on_bus(b, p.open)
                opened.append(p)
            self._combine()
            # a first sample of each bus served at its own rate, read now (open may block), so
            # the loop's first cycle has it: its worker starts with the first cycle
            self._first_sample = {b: self.parts[b].new_feedback() for b in self._own_b}
            for b, fb in list(self._first_sample.items()):
                if self.parts[b].read(fb) is not None:
                    del self._first_sample[b]
        except BaseException:
            for p in opened:
                p.close()
            raise

    def _configure_hook(self) -> None:
        for b, p in enumerate(self.parts):
            self._on_bus(b, p.configure)

    # ---- lifecycle transitions: every bus's, stepped together ----
    def _enable_then_fresh(self, feedback: JointFeedback) -> Steps:
        """The buses' ENABLE steps: each bus's own ends on a fresh read of it (Actuator's)."""
        return self._enable_steps(feedback)

    def _enable_steps(self, feedback: JointFeedback) -> Steps:
        return self._together(Lifecycle.ENABLE, feedback)

    def _disable_steps(self) -> Steps:
        return self._together(Lifecycle.DISABLE)

    def _pause_steps(self) -> Steps:
        return self._together(Lifecycle.PAUSE)

    def _resume_steps(self) -> Steps:
        return self._together(Lifecycle.RESUME)

    def _fault_reset_steps(self) -> Steps:
        return self._together(Lifecycle.FAULT_RESET)

    def _home_steps(self) -> Steps:
        """HOME on the buses that home natively, together (the others need no homing:
        :func:`combine_traits` refuses a robot where they would)."""
        return self._together(Lifecycle.HOME, buses=[b for b, p in enumerate(self.parts) if p.traits.native_homing])

    def _together(self, kind: Lifecycle, feedback: JointFeedback | None = None,
                  buses: list[int] | None = None) -> Steps:
        """Steps of transition ``kind`` on every bus (or on ``buses``) at once: each cycle steps
        every unfinished bus transition once, until all are done. A failure names its bus.
        ENABLE is all or none: when one bus fails, the others' enables are stopped and every bus
        that may have any torque on is disabled again, in steps (:meth:`_rollback`), before the
        error is raised. DISABLE goes on on every bus when one fails, then names every bus that
        did not confirm."""
        buses = list(range(len(self.parts))) if buses is None else buses
        transitions: list[tuple[int, Transition | _Handed]] = []
        if any(b in self._own_b for b in buses):
            self._ensure_workers()
        for b in buses:
            own = b in self._own_b
            fb = None
            if feedback is not None:
                fb = self._bw[b].enable_feedback if own else self._fb[b]
                np.take(feedback.position, self._idx[b], out=fb.position)
                np.take(feedback.velocity, self._idx[b], out=fb.velocity)
                np.take(feedback.effort, self._idx[b], out=fb.effort)
            if own:  # stepped on the bus's own cycles; an ENABLE sends no setpoint from before it
                if kind is Lifecycle.ENABLE:
                    self._bw[b].clear_command()
                # begun on the bus's own thread (its begin() never races the worker's steps)
                transitions.append((b, _Handed(self._bw[b], functools.partial(self.parts[b].begin, kind, fb),
                                               quiet=kind is Lifecycle.DISABLE)))
            else:
                transitions.append((b, self.parts[b].begin(kind, fb)))
        failed: list[str] = []
        error: BackendError | None = None
        try:
            pending = transitions
            while pending:
                running = []
                for b, t in pending:
                    if kind is Lifecycle.ENABLE:
                        self._partial[b] = True
                    try:
                        if not t.step():
                            running.append((b, t))
                        elif kind in (Lifecycle.ENABLE, Lifecycle.DISABLE):
                            self._partial[b] = False  # enabled (is_enabled says so) or off
                        elif kind is Lifecycle.RESUME and self._stops_itself[b]:
                            # resumed before the others: it holds where it resumed (it is not
                            # written) until the robot's RESUME ends, when core takes its measured
                            # pose; core's command until then is where its braking ramp ended
                            self._held[b] = True
                    except Exception as exc:
                        if kind is Lifecycle.DISABLE:
                            failed.append(str(self._named(b, exc)).removeprefix(f"{self.robot}: "))
                        elif kind is Lifecycle.ENABLE:
                            error = self._named(b, exc)
                            error.__cause__ = exc
                            break
                        else:
                            raise self._named(b, exc) from exc
                if error is not None:
                    break
                pending = running
                if pending:
                    yield
        finally:
            for _, t in transitions:
                t.abort()  # a no-op on finished ones; stops the others (failed or abandoned)
            if kind is Lifecycle.RESUME:
                self._held[:] = [False] * len(self._held)
        if error is not None:  # no bus stays powered unsaid
            yield from self._rollback([b for b in buses if self._partial[b] or self.parts[b].is_enabled], error)
        if failed:
            raise BackendError(f"{self.robot}: " + "; ".join(failed))

    def _rollback(self, buses: list[int], error: BackendError) -> Steps:
        """A failed ENABLE undone: the DISABLE steps of every bus in ``buses`` (finished or partly
        enabled), stepped together one per cycle like any transition, within the buses' disable
        time limits; then ``error`` (the bus that failed) is raised, saying if torque off was not
        confirmed."""
        limit = sum(self.parts[b].traits.timeout_s(Lifecycle.DISABLE) for b in buses)
        deadline = time.monotonic() + limit
        steps = self._together(Lifecycle.DISABLE, buses=buses)
        try:
            while True:
                try:
                    next(steps)
                except StopIteration:
                    break
                except BackendError as exc:
                    error = BackendError(f"{error}; undoing the enable: {str(exc).removeprefix(f'{self.robot}: ')}")
                    break
                if time.monotonic() > deadline:
                    error = BackendError(f"{error}; undoing the enable: torque off not confirmed on "
                                         f"{', '.join(self._bus_of([self.parts[b] for b in buses]))} "
                                         f"within {limit:g} s")
                    break
                yield
        finally:
            steps.close()
        raise error

    def _named(self, b: int, exc: BaseException) -> BackendError:
        """A bus's lifecycle error, re-raised naming the bus."""
        message = _robot_key_paths(str(exc).removeprefix(f"{self.robot}: "), self.profile, self.bus_names[b])
        return BackendError(f"{self.robot}: bus {self.bus_names[b]!r}: {message}")

    # ---------------------------------------------------------------- calibration (each bus's joints)
    def calibration_begin(self) -> Steps:
        for b, p in enumerate(self.parts):
            try:
                yield from self._bus_steps(b, Lifecycle.CALIBRATE, p.calibration_begin())
            except BackendError as exc:
                raise self._named(b, exc) from exc

    def calibration_seen(self) -> dict[str, list[float]]:
        return {name: seen for p in self.parts for name, seen in p.calibration_seen().items()}

    def calibration_result(self, grippers) -> dict[str, dict[str, Any]]:
        return {name: keys for p in self.parts for name, keys in p.calibration_result(grippers).items()}

    def calibration_cancel(self) -> None:
        for p in self.parts:
            p.calibration_cancel()

    def _close_hook(self) -> None:
        kept: list[int] = []  # own-rate buses whose worker is still inside a call on the bus
        if self._workers is not None:
            for b, w in enumerate(self._bw):
                if w is not None and w.stop() is False:
                    kept.append(b)
            self._workers = None
        for b, p in enumerate(self.parts):
            if b not in kept:  # a kept bus is its worker's alone: no second thread on it
                p.close()
        if kept:
            w = self._bw[kept[0]]
            waited = max(OWN_RATE_STOP_S, 4 * w.period_s)
            self.report_status(DeviceStatus.FAULT, Fault(
                "torque_off_unconfirmed",
                f"{self.robot}: close: torque off not confirmed on bus {', '.join(self._where[b][4:] for b in kept)}: "
                f"its worker was still inside a call on the bus after {waited:g} s (the bus closes itself "
                f"once the call returns: one thread per bus); check it and switch its power off",
                transient=False))

    def _on_bus(self, b: int, fn) -> None:
        """Run a bus's start-up call; its BackendError is re-raised naming the bus."""
        try:
            fn()
        except BackendError as exc:
            raise self._named(b, exc) from exc

    # ---------------------------------------------------------------- real-time path
    def _start_workers(self) -> list[_BusWorker | _OwnRateWorker]:
        """One thread per bus but the first joined one, created once, in the control process
        (after the fork) and after it asked for its real-time scheduling, which the threads
        inherit: a joined bus's does its read / write when told; a bus served at its own rate runs
        its own cycles (:class:`_OwnRateWorker`)."""
        bw: list[_BusWorker | _OwnRateWorker | None] = [None] * len(self.parts)
        errors_max = self.profile.safety.bus_errors_max
        for b, (name, p) in enumerate(zip(self.bus_names, self.parts)):
            if b in self._own_b:
                bw[b] = _OwnRateWorker(name, p, self.own_rate[name], errors_max, self._first_sample.pop(b, None))
            elif b != self._first:
                bw[b] = _BusWorker(name, p, self._fb[b], self._cmd[b])
        self._bw = bw
        self._workers = [w for w in bw if w is not None]
        return self._workers

    def _ensure_workers(self) -> None:
        if self._workers is None:
            self._start_workers()

    def bus_stamps(self) -> dict[str, float]:
        """bus -> the stamp of its sample the last read took (a bus at its own rate: its newest
        read's own time, older than the robot's stamp by up to its period)."""
        return {name: fb.stamp for name, fb in zip(self.bus_names, self._fb)}

    def own_rate_cycles(self) -> dict[str, int]:
        """bus -> the cycles its own-rate worker has run (bench/, tests)."""
        return {self.bus_names[b]: self._bw[b].cycles for b in self._own_b} if self._workers is not None else {}

    def _closed(self, what: str) -> Fault:
        return Fault("bus_timeout", f"{self.robot}: {what} on closed buses", transient=False)

    def _read(self, feedback: JointFeedback) -> Fault | None:
        if self._workers is None:
            if not self._open:
                return self._closed("read")
            self._start_workers()
        bw, parts, res = self._bw, self.parts, self._read_res
        for b in self._joined_b:
            bw[b].start(_READ)
        first = self._first
        if first >= 0:
            res[first] = parts[first].read(self._fb[first])
        for b in self._joined_b:
            res[b] = bw[b].join()
        for b in self._own_b:  # the newest sample of a bus at its own rate: never waited for
            res[b] = bw[b].take(self._fb[b])
        failed = self._count(res, self._read_streak)
        news = None
        own = self._own_b
        for b, p in enumerate(parts):  # device status: the robot's is the most severe bus's
            if b in own:
                for n in bw[b].device_news:  # news (DEVICE_NEWS) passed on as they are, in order
                    self._forward_news(b, n)
                n = bw[b].news
            else:
                n = p.take_status()
                if n is not None and n[0] in DEVICE_NEWS:
                    self._forward_news(b, n)
                    n = None
            if n is not None:
                news = (b, n)
        if news is not None:
            self._forward_status(*news)
        if failed:
            return self._bus_fault(res, self._read_streak)
        stamp = math.inf
        stamped = self._stamped
        for b, idx in enumerate(self._idx):
            fb = self._fb[b]
            feedback.position[idx] = fb.position
            feedback.velocity[idx] = fb.velocity
            feedback.effort[idx] = fb.effort
            if fb.stamp < stamp and stamped[b]:
                stamp = fb.stamp
        feedback.stamp = stamp
        if self._cart_rows:
            self._gather_cartesian(feedback.cartesian)
        return None

    def _gather_cartesian(self, dst) -> None:
        stamp = None
        for b, lo, hi in self._cart_rows:
            src = self._fb[b].cartesian
            dst.position[lo:hi] = src.position
            dst.orientation[lo:hi] = src.orientation
            dst.done_seq[lo:hi] = src.done_seq
            if stamp is None or src.stamp < stamp:
                stamp = src.stamp  # 0 (no valid pose) on any bus makes the whole 0
        dst.stamp = stamp

    def _scatter_cartesian(self, src) -> None:
        for b, lo, hi in self._cart_rows:
            dst = self._cmd[b].cartesian
            dst.mode[:] = src.mode[lo:hi]
            dst.position[:] = src.position[lo:hi]
            dst.orientation[:] = src.orientation[lo:hi]
            dst.linear[:] = src.linear[lo:hi]
            dst.angular[:] = src.angular[lo:hi]
            dst.frame[:] = src.frame[lo:hi]
            dst.seq[:] = src.seq[lo:hi]

    def _write(self, command: JointCommand) -> Fault | None:
        if self._workers is None:
            if not self._open:
                return self._closed("write")
            self._start_workers()
        for b, idx in enumerate(self._idx):
            c = self._cmd[b]
            np.take(command.mode, idx, out=c.mode)
            np.take(command.position, idx, out=c.position)
            np.take(command.velocity, idx, out=c.velocity)
            np.take(command.effort, idx, out=c.effort)
        if self._cart_rows:
            self._scatter_cartesian(command.cartesian)
        parts, cyclic, res, bw, held = self.parts, self._cyclic, self._write_res, self._bw, self._held
        if any(held):  # held where its RESUME left it: no setpoint (a cyclic bus gets every joint NONE)
            for b, h in enumerate(held):
                if h:
                    self._cmd[b].mode[:] = CommandMode.NONE
                    if self._cmd[b].cartesian is not None:
                        self._cmd[b].cartesian.mode[:] = 0
        joined = self._joined_b
        for b in joined:  # a bus that is not written outside ENABLED / PAUSED is skipped
            if cyclic[b] or (parts[b].is_enabled and not held[b]):
                bw[b].start(_WRITE)
        first = self._first
        if first >= 0:
            res[first] = parts[first].write(self._cmd[first]) if (
                cyclic[first] or (parts[first].is_enabled and not held[first])) else None
        for b in self._own_b:  # the newest setpoint, written on the bus's own next cycle
            res[b] = bw[b].post(self._cmd[b]) if not held[b] or cyclic[b] else None
        for b in joined:
            res[b] = bw[b].join() if cyclic[b] or (parts[b].is_enabled and not held[b]) else None
        if self._count(res, self._write_streak):
            return self._bus_fault(res, self._write_streak)
        return None

    @staticmethod
    def _count(res: list[Fault | None], streak: list[int]) -> bool:
        """Count each bus's failed cycles in a row; True if any bus failed this cycle."""
        failed = False
        for b, f in enumerate(res):
            if f is None:
                streak[b] = 0
            else:
                streak[b] += 1
                failed = True
        return failed

    def _forward_news(self, b: int, news: tuple[DeviceStatus, Fault | None]) -> None:
        """A bus's news (a WARNING / NOTICE: no status of the robot's) reported as it is, its
        cause naming the bus."""
        cause = news[1]
        if cause is not None:
            cause = self._bus_fault([cause if k == b else None for k in range(len(self.parts))])
        self.report_status(news[0], cause)

    def _forward_status(self, b: int, news: tuple[DeviceStatus, Fault | None]) -> None:
        """A bus reported a device status: report the robot's, the most severe of all buses'
        (a fault cleared on one bus is the robot's only when no other bus is in fault)."""
        worst = max((p.device_status for p in self.parts), key=_SEVERITY.__getitem__)
        cause = news[1]
        if cause is not None:
            cause = self._bus_fault([cause if k == b else None for k in range(len(self.parts))])
        if worst is DeviceStatus.OK and self.device_status is DeviceStatus.FAULT:
            self.report_status(DeviceStatus.FAULT_CLEARED, cause)
        else:
            self.report_status(worst, cause)

    def _bus_fault(self, res: list[Fault | None], streak: list[int] | None = None) -> Fault:
        """The robot's fault from the buses' results ``res``: a non-transient one leads, else the
        bus failing for the most cycles in a row (the likely cause, not a bus that missed one
        reply in the same cycle); its message names the bus and says what the other failing buses
        said. Allocates, but only on a failed cycle."""
        faults = [(b, f) for b, f in enumerate(res) if f is not None]
        faults.sort(key=lambda bf: (bf[1].transient, -(streak[bf[0]] if streak else 0)))
        b, f = faults[0]
        prefix = f"{self.robot}: "
        parts = [f"{self._where[k]}: {g.message.removeprefix(prefix)}" for k, g in faults]
        return Fault(f.code, prefix + "; ".join(parts), joint=f.joint, register=f.register, value=f.value,
                     transient=all(g.transient for _, g in faults))


def create_composite(profile: Profile, make_bus: Any, source: str = "<profile>") -> CompositeActuator:
    """The composite actuator of a several-bus profile. ``make_bus(bus_profile, source)`` builds one
    bus's backend; its ProfileError's key paths are rewritten to the robot profile's
    (``backends.<bus>.port``, the joint's index among the robot's joints)."""
    buses = {}
    for name in profile.bus_names:
        sub = profile.bus_profile(name)
        try:
            buses[name] = make_bus(sub, source)
        except ProfileError as exc:
            raise ProfileError(_robot_key_paths(str(exc), profile, name)) from exc
    return CompositeActuator(profile, buses, source=source)


def _robot_key_paths(message: str, profile: Profile, bus: str) -> str:
    """``backend.port`` -> ``backends.<bus>.port``; ``joints[k] (name)`` -> the robot's index."""
    message = re.sub(r"(^|: |; )backend\.", lambda m: f"{m.group(1)}backends.{bus}.", message)

    def robot_index(m: re.Match) -> str:
        name = m.group(1)
        return f"joints[{profile.joint_index(name)}] ({name})" if name in profile.joint_names else m.group(0)

    return re.sub(r"joints\[\d+\] \(([^)]*)\)", robot_index, message)


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
bus's (the sample is at least that old). A fault on any bus is the robot's, its message naming
the bus (and the bus's backend names the joint).

Start-up: ``open`` / ``configure`` / ``close`` run bus by bus (``open`` closes the buses already
opened when one fails). Lifecycle transitions (enable, disable, pause, resume, fault reset) run on
every bus together: each cycle steps every bus's :class:`~crtk_bridge.core.actuator.Transition`
once, so a bus that takes many cycles (a CiA 402 controlword walk) never holds the others back,
and the robot's transition ends when the last bus's does. Enable is all or none (a bus that fails
gets every bus disabled again, the error naming the bus); disable goes on on every bus and names
those that did not confirm.

What the buses declare becomes the robot's: device status (the most severe bus's, its cause
naming the bus), ``cyclic_write`` (if any bus needs it; the others are written only while
enabled), native cartesian namespaces (each bus's rows of the cartesian setpoints and measured
poses, bus after bus), pacing (by the one bus that paces; two pacing buses are refused), and the fault
reaction, per bus: the robot declares TORQUE_OFF if any bus does, and its fault transition
(:meth:`CompositeActuator.begin_fault_reaction`) switches torque off only on the buses that declare
TORQUE_OFF (and on a bus an abandoned enable left partly on); a HOLD or NONE bus is left as it is
(a UR arm that stopped itself keeps its pose beside a servo gripper switched off). A failed enable
is undone in steps too: every bus that may have torque on (finished or partly enabled) runs its
own DISABLE steps, together, one per cycle, within the disable time limits, before the error
naming the failed bus is raised. Native homing on one bus is not offered through the composite yet.
"""

from __future__ import annotations

import re
import threading
import time
from typing import Any

import numpy as np

from ..core.actuator import (
    Actuator,
    ActuatorInfo,
    Capabilities,
    DeviceStatus,
    Fault,
    FaultReaction,
    JointCommand,
    JointFeedback,
    Lifecycle,
    Steps,
    Transition,
    combine_capabilities,
)
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
        self._joint_caps = [self.parts[self._owner[i]].joint_capabilities(int(self._local[i]))
                            for i in range(self.n)]
        self.capabilities = combine_capabilities(self._joint_caps)
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
        self._workers: list[_BusWorker] | None = None  # started at the first cycle (see _start_workers)
        nb = len(self.parts)
        self._read_res: list[Fault | None] = [None] * nb  # this cycle's result per bus
        self._write_res: list[Fault | None] = [None] * nb
        self._read_streak = [0] * nb  # failed cycles in a row per bus
        self._write_streak = [0] * nb
        self._where = [f"bus {name!r}" for name in self.bus_names]
        #: per bus: an ENABLE took a step and neither finished nor was undone (some torque may be on)
        self._partial = [False] * nb
        # what the buses declare, for the robot: written every cycle if any bus needs it (the
        # others are then skipped while not enabled); paced by the one bus that paces, if any;
        # the fault reaction that leaves nothing powered that needs switching off
        self.cyclic_write = any(p.cyclic_write for p in self.parts)
        self._cyclic = [p.cyclic_write for p in self.parts]
        pacers = [p for p in self.parts if p.paces_cycle]
        if len(pacers) > 1:
            raise ProfileError(f"{source}: backends: buses {', '.join(self._bus_of(pacers))} both pace the "
                               f"control loop; at most one bus of a robot may")
        self._pacer = pacers[0] if pacers else None
        self.paces_cycle = self._pacer is not None
        # core runs the fault reaction's transition if any bus needs torque off; it then applies
        # each bus's own reaction (begin_fault_reaction)
        reactions = {p.fault_reaction for p in self.parts}
        self.fault_reaction = next(r for r in (FaultReaction.TORQUE_OFF, FaultReaction.HOLD, FaultReaction.NONE)
                                   if r in reactions)

    def _bus_of(self, parts: list[Actuator]) -> list[str]:
        return [repr(name) for name, p in zip(self.bus_names, self.parts) if p in parts]

    # ---------------------------------------------------------------- pacing
    def cycle_period_s(self) -> float | None:
        return self._pacer.cycle_period_s() if self._pacer is not None else None

    def wait_cycle(self, deadline: float) -> bool:
        """The pacing bus's wait (the device's clock) first, if any; then every other bus's
        start of the cycle (a CANopen SYNC), in bus order."""
        pacer = self._pacer
        ok = pacer.wait_cycle(deadline) if pacer is not None else True
        for p in self.parts:
            if p is not pacer:
                p.wait_cycle(deadline)
        return ok

    # ---------------------------------------------------------------- capabilities
    def joint_capabilities(self, i: int) -> Capabilities:
        return self._joint_caps[i]

    def deceleration_limit(self, i: int) -> float:
        return self.parts[self._owner[i]].deceleration_limit(int(self._local[i]))

    def cartesian_namespaces(self) -> list[str]:
        """Every bus's natively cartesian namespaces, bus after bus (the rows of the robot's
        CartesianCommand / CartesianFeedback)."""
        return [ns for p in self.parts for ns in p.cartesian_namespaces()]

    def info(self) -> ActuatorInfo:
        details: dict[str, Any] = {name: p.info().details for name, p in zip(self.bus_names, self.parts)}
        return ActuatorInfo(list(self.joint_names), self.capabilities, {"buses": details})

    # ---------------------------------------------------------------- lifecycle
    def _open_hook(self) -> None:
        opened = []
        try:
            for b, p in enumerate(self.parts):
                self._on_bus(b, p.open)
                opened.append(p)
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

    def transition_timeout_s(self, kind: Lifecycle) -> float:
        # the buses' steps share the loop's thread, so in the worst case their times add up; an
        # enable may end in a rollback (every bus's disable)
        limit = sum(p.transition_timeout_s(kind) for p in self.parts)
        if kind is Lifecycle.ENABLE:
            limit += self.transition_timeout_s(Lifecycle.DISABLE)
        return limit

    def _together(self, kind: Lifecycle, feedback: JointFeedback | None = None,
                  buses: list[int] | None = None) -> Steps:
        """Steps of transition ``kind`` on every bus (or on ``buses``) at once: each cycle steps
        every unfinished bus transition once, until all are done. A failure names its bus.
        ENABLE is all or none: when one bus fails, the others' enables are stopped and every bus
        that may have any torque on is disabled again, in steps (:meth:`_rollback`), before the
        error is raised. DISABLE goes on on every bus when one fails, then names every bus that
        did not confirm."""
        buses = list(range(len(self.parts))) if buses is None else buses
        transitions = []
        for b in buses:
            fb = None
            if feedback is not None:
                fb = self._fb[b]
                np.take(feedback.position, self._idx[b], out=fb.position)
                np.take(feedback.velocity, self._idx[b], out=fb.velocity)
                np.take(feedback.effort, self._idx[b], out=fb.effort)
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
        if error is not None:  # no bus stays powered unsaid
            yield from self._rollback([b for b in buses if self._partial[b] or self.parts[b].is_enabled], error)
        if failed:
            raise BackendError(f"{self.robot}: " + "; ".join(failed))

    def _rollback(self, buses: list[int], error: BackendError) -> Steps:
        """A failed ENABLE undone: the DISABLE steps of every bus in ``buses`` (finished or partly
        enabled), stepped together one per cycle like any transition, within the buses' disable
        time limits; then ``error`` (the bus that failed) is raised, saying if torque off was not
        confirmed."""
        limit = sum(self.parts[b].transition_timeout_s(Lifecycle.DISABLE) for b in buses)
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

    def begin_fault_reaction(self) -> Transition:
        """Each bus's own fault reaction, in one transition stepping the buses together: torque
        off (the DISABLE steps) on the buses that declare TORQUE_OFF and on any bus left partly
        enabled by an abandoned enable; the HOLD and NONE buses are left as they are (a UR arm
        that stopped itself keeps its pose beside a servo gripper switched off)."""
        self._enabled = False  # the robot is not enabled from now on
        buses = [b for b, p in enumerate(self.parts)
                 if p.fault_reaction is FaultReaction.TORQUE_OFF or self._partial[b]]
        return Transition(self.robot, Lifecycle.DISABLE, self._together(Lifecycle.DISABLE, buses=buses),
                          self.transition_timeout_s(Lifecycle.DISABLE))

    def _named(self, b: int, exc: BaseException) -> BackendError:
        """A bus's lifecycle error, re-raised naming the bus."""
        message = _robot_key_paths(str(exc).removeprefix(f"{self.robot}: "), self.profile, self.bus_names[b])
        return BackendError(f"{self.robot}: bus {self.bus_names[b]!r}: {message}")

    # ---------------------------------------------------------------- calibration (each bus's joints)
    def calibration_begin(self) -> Steps:
        for b, p in enumerate(self.parts):
            try:
                yield from p.calibration_begin()
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
        if self._workers is not None:
            for w in self._workers:
                w.stop()
            self._workers = None
        for p in self.parts:
            p.close()

    def _on_bus(self, b: int, fn) -> None:
        """Run a bus's start-up call; its BackendError is re-raised naming the bus."""
        try:
            fn()
        except BackendError as exc:
            raise self._named(b, exc) from exc

    # ---------------------------------------------------------------- real-time path
    def _start_workers(self) -> list[_BusWorker]:
        """One thread per bus but the first, created once, in the control process (after the
        fork) and after it asked for its real-time scheduling, which the threads inherit."""
        self._workers = [_BusWorker(name, p, self._fb[b], self._cmd[b])
                         for b, (name, p) in enumerate(zip(self.bus_names, self.parts)) if b > 0]
        return self._workers

    def _closed(self, what: str) -> Fault:
        return Fault("bus_timeout", f"{self.robot}: {what} on closed buses", transient=False)

    def _read(self, feedback: JointFeedback) -> Fault | None:
        workers = self._workers
        if workers is None:
            if not self._open:
                return self._closed("read")
            workers = self._start_workers()
        for w in workers:
            w.start(_READ)
        res = self._read_res
        res[0] = self.parts[0].read(self._fb[0])
        for b, w in enumerate(workers, 1):
            res[b] = w.join()
        failed = self._count(res, self._read_streak)
        news = None
        for b, p in enumerate(self.parts):  # device status: the robot's is the most severe bus's
            n = p.take_status()
            if n is not None:
                news = (b, n)
        if news is not None:
            self._forward_status(*news)
        if failed:
            return self._bus_fault(res, self._read_streak)
        stamp = self._fb[0].stamp
        for b, idx in enumerate(self._idx):
            fb = self._fb[b]
            feedback.position[idx] = fb.position
            feedback.velocity[idx] = fb.velocity
            feedback.effort[idx] = fb.effort
            if fb.stamp < stamp:
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
        for b, idx in enumerate(self._idx):
            c = self._cmd[b]
            np.take(command.mode, idx, out=c.mode)
            np.take(command.position, idx, out=c.position)
            np.take(command.velocity, idx, out=c.velocity)
            np.take(command.effort, idx, out=c.effort)
        if self._cart_rows:
            self._scatter_cartesian(command.cartesian)
        workers = self._workers
        if workers is None:
            if not self._open:
                return self._closed("write")
            workers = self._start_workers()
        parts, cyclic, res = self.parts, self._cyclic, self._write_res
        for b, w in enumerate(workers, 1):  # a bus that is not written outside ENABLED / PAUSED is skipped
            if cyclic[b] or parts[b].is_enabled:
                w.start(_WRITE)
        res[0] = parts[0].write(self._cmd[0]) if cyclic[0] or parts[0].is_enabled else None
        for b, w in enumerate(workers, 1):
            res[b] = w.join() if cyclic[b] or parts[b].is_enabled else None
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


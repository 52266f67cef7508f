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

Lifecycle: ``open`` / ``configure`` / ``close`` run bus by bus (``open`` closes the buses already
opened when one fails). ``enable`` enables every bus; if one fails, the buses already enabled are
disabled again and the error names the bus. ``disable`` tries every bus and names those that did
not confirm.
"""

from __future__ import annotations

import re
import threading
from typing import Any

import numpy as np

from ..core.actuator import (
    Actuator,
    ActuatorInfo,
    Capabilities,
    Fault,
    JointCommand,
    JointFeedback,
    combine_capabilities,
)
from ..errors import BackendError, ProfileError
from ..profile import Profile

_READ, _WRITE, _STOP = 1, 2, 3


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
        self._workers: list[_BusWorker] | None = None  # started at the first cycle (see _start_workers)
        self._where = [f"bus {name!r}" for name in self.bus_names]

    # ---------------------------------------------------------------- capabilities
    def joint_capabilities(self, i: int) -> Capabilities:
        return self._joint_caps[i]

    def info(self) -> ActuatorInfo:
        details: dict[str, Any] = {name: p.info().details for name, p in zip(self.bus_names, self.parts)}
        return ActuatorInfo(list(self.joint_names), self.capabilities, {"buses": details})

    # ---------------------------------------------------------------- lifecycle
    def _open_hook(self) -> None:
        opened = []
        try:
            for name, p in zip(self.bus_names, self.parts):
                self._on_bus(name, p.open)
                opened.append(p)
        except BaseException:
            for p in opened:
                p.close()
            raise

    def _configure_hook(self) -> None:
        for name, p in zip(self.bus_names, self.parts):
            self._on_bus(name, p.configure)

    def _enable_hook(self, feedback: JointFeedback) -> None:
        """Enable every bus, each holding its joints where they are; all or none."""
        enabled = []
        try:
            for b, (name, p) in enumerate(zip(self.bus_names, self.parts)):
                fb = self._fb[b]
                np.take(feedback.position, self._idx[b], out=fb.position)
                self._on_bus(name, lambda: p.enable(fb))
                enabled.append(p)
        except BaseException:
            for p in enabled:
                try:
                    p.disable()
                except Exception:  # best effort: the error raised names the bus that failed
                    pass
            raise

    def _disable_hook(self) -> None:
        """Torque off on every bus; raises naming every bus that did not confirm."""
        failed = []
        for name, p in zip(self.bus_names, self.parts):
            try:
                self._on_bus(name, p.disable)
            except BackendError as exc:
                failed.append(str(exc).removeprefix(f"{self.robot}: "))
        if failed:
            raise BackendError(f"{self.robot}: " + "; ".join(failed))

    def _close_hook(self) -> None:
        if self._workers is not None:
            for w in self._workers:
                w.stop()
            self._workers = None
        for p in self.parts:
            p.close()

    def _on_bus(self, name: str, fn) -> None:
        """Run a bus's lifecycle call; its BackendError is re-raised naming the bus."""
        try:
            fn()
        except BackendError as exc:
            raise BackendError(f"{self.robot}: bus {name!r}: {str(exc).removeprefix(f'{self.robot}: ')}") from exc

    # ---------------------------------------------------------------- real-time path
    def _start_workers(self) -> list[_BusWorker]:
        """One thread per bus but the first, created once, in the control process (after the
        fork) and after it asked for its real-time scheduling, which the threads inherit."""
        self._workers = [_BusWorker(name, p, self._fb[b], self._cmd[b])
                         for b, (name, p) in enumerate(zip(self.bus_names, self.parts)) if b > 0]
        return self._workers

    def _read(self, feedback: JointFeedback) -> Fault | None:
        workers = self._workers if self._workers is not None else self._start_workers()
        for w in workers:
            w.start(_READ)
        fault = self.parts[0].read(self._fb[0])
        faults = None
        if fault is not None:
            faults = [(0, fault)]
        for b, w in enumerate(workers, 1):
            f = w.join()
            if f is not None:
                faults = (faults or []) + [(b, f)]
        if faults is not None:
            return self._bus_fault(faults)
        stamp = self._fb[0].stamp
        for b, idx in enumerate(self._idx):
            fb = self._fb[b]
            feedback.position[idx] = fb.position
            feedback.velocity[idx] = fb.velocity
            feedback.effort[idx] = fb.effort
            if fb.stamp < stamp:
                stamp = fb.stamp
        feedback.stamp = stamp
        return None

    def _write(self, command: JointCommand) -> Fault | None:
        for b, idx in enumerate(self._idx):
            c = self._cmd[b]
            np.take(command.mode, idx, out=c.mode)
            np.take(command.position, idx, out=c.position)
            np.take(command.velocity, idx, out=c.velocity)
            np.take(command.effort, idx, out=c.effort)
        workers = self._workers if self._workers is not None else self._start_workers()
        for w in workers:
            w.start(_WRITE)
        fault = self.parts[0].write(self._cmd[0])
        faults = [(0, fault)] if fault is not None else None
        for b, w in enumerate(workers, 1):
            f = w.join()
            if f is not None:
                faults = (faults or []) + [(b, f)]
        return self._bus_fault(faults) if faults is not None else None

    def _bus_fault(self, faults: list[tuple[int, Fault]]) -> Fault:
        """The robot's fault for this cycle: a non-transient one first, its message naming the bus
        (and what the other buses said). Allocates, but only on a failed cycle."""
        faults.sort(key=lambda bf: bf[1].transient)
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


"""Lifecycle transitions of the controller: the state commands and the transition runner.

A transition (enable, disable, the torque-off of a fault, pause, resume, native home, a goal
check, a calibration start) is the backend's :class:`~crtk_bridge.core.actuator.Transition`,
run here one step per cycle (:meth:`TransitionsMixin._advance` from ``Controller.step``, the
first step at once): the state stays as it was and ``is_busy`` is true until it ends, its
requests get their one reply then, and one that outlives the backend's time limit faults the
robot naming it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from ...errors import BackendError
from ..actuator import Fault, Lifecycle, Steps, Transition
from ..motion import Mode
from ..state import OperatingState, StateCommand, transition
from .common import DEFERRED, Refused

_DEFERRED = DEFERRED


@dataclass
class _Running:
    """A lifecycle transition in progress and who waits for it."""

    transition: Transition
    deadline: float  # controller clock
    on_done: Callable[[], Any]  # -> reply data; may raise Refused
    on_fail: Callable[[Exception], "Refused"]  # handles the failure; -> the waiting requests' error
    rids: list = field(default_factory=list)  # requests answered when it ends
    stepped: int = -1  # cycle of the last step (one step per cycle)
    then: list = field(default_factory=list)  # enable requests handled when it ends


class TransitionsMixin:
    """State commands and the lifecycle transition runner of :class:`~.controller.Controller`
    (whose state it shares)."""

    def _state_command(self, cmd: StateCommand) -> Any:
        t = transition(self.state, cmd)
        if t.target is None:
            raise Refused("invalid_state", f"{self.robot}: {cmd.value} is not valid in state {self.state.value}")
        run = self._running
        # the torque off of a fault (no request waits on it), still confirming servos
        fault_torque_off = run is not None and run.transition.kind is Lifecycle.DISABLE and not run.rids
        if cmd in (StateCommand.DISABLE, StateCommand.PAUSE):  # a stop is never refused
            if run is not None and run.transition.kind is Lifecycle.DISABLE:
                if cmd is StateCommand.PAUSE:
                    return self.operating_state()  # torque is going off: more than a pause
                if run.rids:
                    run.rids.append(self._rid)  # a disable is already under way: the same reply
                    return _DEFERRED
            if run is not None:
                self._abort_running(f"{run.transition.kind.value} aborted by {cmd.value}")
        elif run is not None and cmd is not StateCommand.UNHOME:
            if cmd is StateCommand.ENABLE and fault_torque_off:
                # the torque off of a fault (no request waits on it) confirms one servo per
                # cycle: the enable is handled when it ends, never raced with it
                run.then.append(self._rid)
                return _DEFERRED
            if cmd.value == run.transition.kind.value and run.rids:
                run.rids.append(self._rid)  # the same transition under way: the same reply
                return _DEFERRED
            raise Refused("invalid_state", f"{self.robot}: {cmd.value} refused: "
                          f"{run.transition.kind.value} in progress")
        if cmd is StateCommand.ENABLE:
            if self.state is not OperatingState.ENABLED:
                return self._enable()
        elif cmd is StateCommand.DISABLE:
            return self._disable(retry=t.retry, replaces_torque_off=fault_torque_off)
        elif cmd is StateCommand.PAUSE:
            if self.state is OperatingState.ENABLED:
                self._stop_all()
                self.homing = False
                return self._start(self.actuator.begin(Lifecycle.PAUSE), self._paused, self._failed("pause"))
            self._stop_all()  # PAUSED: whatever moves (a shutdown park) stops too
        elif cmd is StateCommand.RESUME:
            return self._start(self.actuator.begin(Lifecycle.RESUME), self._resumed, self._failed("resume"))
        elif cmd is StateCommand.HOME:
            return self._home()
        elif cmd is StateCommand.UNHOME:
            if self.is_homed:
                self.is_homed = False
                self.push_state()
        return self.operating_state()

    def _start(self, t: Transition, on_done: Callable[[], Any], on_fail: Callable[[Exception], Refused],
               reply: bool = True) -> Any:
        """Run transition ``t``: its first step now (a quick one ends in this cycle, as the
        blocking calls used to), the rest one per cycle in :meth:`step`. Returns _DEFERRED: the
        reply to the request being handled is sent when ``t`` ends."""
        run = _Running(t, self.clock() + t.timeout_s, on_done, on_fail, [self._rid] if reply else [])
        self._running = run
        if not self._advance(run) and t.kind is not Lifecycle.MODE_SWITCH:  # (never busy: is_busy)
            self.busy_seq += 1
            self.push_state()  # is_busy edge: the state stays until the transition ends
            if t.kind is Lifecycle.GOAL_CHECK:
                self._checked_seq = self.busy_seq  # the move it starts keeps this busy_seq
        return _DEFERRED

    def _advance(self, run: _Running) -> bool:
        """One step of ``run``; True once it ended (replies and events are out)."""
        run.stepped = self._cycle
        try:
            finished = run.transition.step()
        except Exception as exc:  # BackendError, or an SDK surprise: a failed transition
            self._running = None
            self._ended(run, exc)
            return True
        if finished:
            self._running = None
            self._ended(run, None)
            return True
        if self.clock() > run.deadline:
            run.transition.abort()
            self._running = None
            kind = run.transition.kind.value
            self._ended(run, BackendError(
                f"{self.robot}: {kind} did not finish within {run.transition.timeout_s:g} s "
                f"(the {self.profile.backend_type} backend's limit for {kind})"))
            return True
        return False

    def _ended(self, run: _Running, exc: Exception | None) -> None:
        try:
            if exc is not None:
                raise run.on_fail(exc)
            data = run.on_done()
        except Refused as refused:
            for rid in run.rids:
                self.outbox.append({"id": rid, "ok": False, "error": {"code": refused.code, "message": str(refused)}})
        else:
            for rid in run.rids:
                self.outbox.append({"id": rid, "ok": True, "data": data})
        if self._busy_reported and not self.is_busy:
            self.push_state()  # is_busy false edge (when no state change carried it)
        if run.then:
            outer = self._rid
            for rid in run.then:
                self.handle({"id": rid, "cmd": StateCommand.ENABLE.value})
            self._rid = outer

    def _abort_running(self, why: str) -> None:
        run = self._running
        if run is None:
            return
        run.transition.abort()
        self._running = None
        for rid in run.rids + run.then:
            self.outbox.append({"id": rid, "ok": False, "error": {"code": "aborted", "message": f"{self.robot}: {why}"}})

    def abort_transition(self) -> None:
        """Abandon the running transition (shutdown): its requests get an ``aborted`` error."""
        self._abort_running("aborted by shutdown")

    def _sequence(self, kinds: tuple[Lifecycle, ...]) -> Steps:
        """The backend's transitions ``kinds`` one after the other (FAULT_RESET, then ENABLE)."""
        for kind in kinds:
            t = self.actuator.begin(kind, self.feedback if kind is Lifecycle.ENABLE else None)
            try:
                while not t.step():
                    yield
            finally:
                t.abort()

    def _switch_modes(self, modes: Any, reply: Any, request: bool = True) -> Any:
        """The backend's operating-mode change for the command modes ``modes``
        (:meth:`~crtk_bridge.core.actuator.Actuator.mode_switch_steps`), run as a MODE_SWITCH
        transition (it does not raise ``is_busy``: servo commands never do): while it runs the backend holds the switching joints, motion commands are
        refused (a stop is not: ``hold``, ``pause``, ``disable``), and the request that asked for
        it gets ``reply`` (its reply data) when it ends (``request`` False: none asked, a stop, a
        watchdog or a park changed the mode). A failure faults the robot (a joint may be unpowered).
        Returns the reply data, or _DEFERRED."""
        steps = self.actuator.mode_switch_steps(modes)
        if steps is None:
            self._modes_ok = modes.tobytes()
            return reply
        self._modes_ok = b""  # asked again once it ended (a stop meanwhile may want the old modes)
        t = Transition(self.robot, Lifecycle.MODE_SWITCH, steps, self.traits.timeout_s(Lifecycle.MODE_SWITCH))
        return self._start(t, lambda: reply, self._failed("mode_switch"), reply=request)

    def _enable(self) -> Any:
        kinds = (Lifecycle.FAULT_RESET, Lifecycle.ENABLE) if self.state is OperatingState.FAULT else (Lifecycle.ENABLE,)
        timeout = sum(self.traits.timeout_s(k) for k in kinds)
        t = Transition(self.robot, Lifecycle.ENABLE, self._sequence(kinds), timeout)
        return self._start(t, self._enabled, self._failed("enable"))

    def _enabled(self) -> dict:
        # hold exactly where the joints are NOW: the backend's ENABLE ends in a cycle whose read
        # measured them with torque on (Actuator._enable_then_fresh), the sample on_read took in
        # this cycle; nothing here touches the bus
        for m in self.namespaces.values():
            m.reset(self.feedback.position[m.idx])
        self.fault_cause = None
        self._modes_ok = b""  # the device's modes as enabling left them: asked again
        self._consecutive_bus_errors = 0
        self._tracking_cycles = 0
        self._written = False
        self._set_state(OperatingState.ENABLED)
        return self.operating_state()

    def _failed(self, kind: str) -> Callable[[Exception], Refused]:
        """What a failed ``kind`` transition (enable, pause, resume, home) does: FAULT with code
        ``<kind>_failed`` and the backend's fault reaction (never leave torque on unsaid), and the
        request's ``fault`` refusal."""
        def failed(exc: Exception) -> Refused:
            self.enter_fault(Fault(f"{kind}_failed", str(exc), transient=False))
            return Refused("fault", f"{self.robot}: {kind} failed: {exc}")
        return failed

    def _disable(self, retry: bool, replaces_torque_off: bool = False) -> Any:
        """DISABLE for a request. ``replaces_torque_off``: it aborted a fault's own torque off,
        whose work it takes over: if it fails, torque off is unconfirmed (said, and retried)."""
        self._abort_motion()

        def failed(exc: Exception) -> Refused:
            if retry:  # FAULT -> DISABLED (retry) failed: stay in FAULT
                if replaces_torque_off and not self._torque_unconfirmed:
                    self._torque_unconfirmed = True  # on_read retries it once the bus answers
                    self.event("error", "torque_off_unconfirmed", f"{self.robot}: torque off not confirmed "
                               f"({exc}); retrying when the bus answers")
                return Refused("fault", f"{self.robot}: disable failed, still FAULT: {exc}")
            self.enter_fault(Fault("disable_failed", str(exc), transient=False))
            return Refused("fault", f"{self.robot}: disable failed: {exc}")

        return self._start(self.actuator.begin(Lifecycle.DISABLE), self._disabled, failed)

    def _disabled(self) -> dict:
        self.fault_cause = None
        self._torque_unconfirmed = False
        self._set_state(OperatingState.DISABLED)
        return self.operating_state()

    def _paused(self) -> dict:
        self._set_state(OperatingState.PAUSED)
        return self.operating_state()

    def _resumed(self) -> dict:
        stopped_itself = self.traits.stops_itself_on_pause
        for m in self.namespaces.values():  # a device that stops itself holds where its own stop ended
            if any(stopped_itself[i] for i in m.idx):
                m.reset(self.feedback.position[m.idx])
        self._set_state(OperatingState.ENABLED)
        return self.operating_state()

    def _home(self) -> Any:
        if self.traits.native_homing:
            def homed() -> dict:
                self.is_homed = True
                for m in self.namespaces.values():
                    m.reset(self.feedback.position[m.idx])
                self.push_state()
                return self.operating_state()

            self._stop_all()
            return self._start(self.actuator.begin(Lifecycle.HOME), homed, self._failed("home"))
        if not all(c.position for c in self.ns_caps.values()):
            raise Refused("unsupported", f"{self.robot}: home unsupported without position control")
        missing = [name for m in self.namespaces.values() for name in m.no_home]
        if missing:  # a joint's zero is not always a safe pose (a UR's is the arm stretched out)
            raise Refused("unsupported", f"{self.robot}: home refused: no home pose in the profile for joint"
                          f"{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))} (key `home`, "
                          f"rad, beside the joint's limits); add a safe pose, or move_jp there")
        now = self.clock()
        for m in self.namespaces.values():
            if m.mode is Mode.FREE:
                m.reset(self.feedback.position[m.idx])
            m.start_move(m.home.copy(), now)
        self.homing = True
        self.busy_seq += 1
        self.push_state()
        return self.operating_state()

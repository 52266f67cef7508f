"""The ONE cycle runner: wait -> read -> step -> write, on one schedule.

Everything that drives a backend cycle by cycle goes through :class:`CycleRunner`: the control
loop (core/loop.py, around the controller), the start-up and shutdown paths that run a lifecycle
transition to its end without a controller (:func:`run_transition`: ``Actuator.enable`` /
``disable`` / ``close``, a backend's configure), and the test rigs. So a backend sees the same
sequence of calls everywhere, the one production runs.

The cycle's start (:meth:`CycleRunner.wait`) has one meaning: the cycle scheduled at
``deadline`` begins. On the loop's clock (``traits.clock`` Clock.LOOP) the runner sleeps to the
deadline of an absolute schedule (after an overrun it skips ahead instead of bursting); then the
backend's :meth:`~crtk_bridge.core.actuator.Actuator.wait_cycle` runs (CANopen sends its SYNC
there). On the device's clock (Clock.DEVICE: a UR's packages) the backend's ``wait_cycle``
blocks until the device's next packet, and the next deadline is one period after the cycle
began. Either way the deadline is the runner's, passed in, never rebuilt by the backend.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, Callable

from ..errors import BackendError

if TYPE_CHECKING:  # core/actuator.py imports this module
    from .actuator import Actuator, Fault, JointCommand, JointFeedback, Transition

#: what :meth:`CycleRunner.cycle` drives: core's Controller (``on_read`` / ``step`` / ``command`` /
#: ``on_write``); the runner is part of the seam, beside core/actuator.py, and imports no more
Stepper = Any


class CycleRunner:
    """Runs ``actuator``'s cycles at ``period_s`` (the effective period). ``clock`` / ``sleep``
    default to the monotonic performance counter and ``time.sleep`` (a test on a fake clock
    passes its own; a backend on the device's clock needs the real ones)."""

    def __init__(self, actuator: "Actuator", period_s: float, *,
                 clock: Callable[[], float] = time.perf_counter, sleep: Callable[[float], None] = time.sleep):
        self.actuator = actuator
        self.period = float(period_s)
        from .actuator import Clock  # (core/actuator.py imports this module)
        self.device_clock = actuator.traits.clock is Clock.DEVICE
        self.clock = clock
        self._sleep = sleep
        self.feedback: "JointFeedback" = actuator.new_feedback()
        self._idle = actuator.new_command()  # every joint in CommandMode.NONE: no controller
        self.next_t = clock() + self.period  # the scheduled start of the next cycle
        self.t0 = self.next_t  # the start of the current cycle
        self.late = 0.0  # how late the current cycle started (s)
        self.overruns = 0  # cycles that ended after the next one's start

    # ------------------------------------------------------------------ the schedule
    def restart(self) -> None:
        """The schedule starts again: the next cycle one period from now (after start-up work
        that took its time: the loop's first cycle is not an overrun)."""
        self.next_t = self.clock() + self.period
        self.overruns = 0

    def wait(self) -> None:
        """Until the next cycle starts (see the module docstring); sets ``t0`` and ``late``."""
        deadline = self.next_t
        if not self.device_clock:
            delay = deadline - self.clock()
            if delay > 0:
                self._sleep(delay)
        self.actuator.wait_cycle(deadline)
        self.t0 = self.clock()
        self.late = self.t0 - deadline

    def schedule(self) -> None:
        """After the cycle's work: the next cycle's start. An overrun (the work ended after it)
        is counted; on the loop's clock the schedule then skips the missed starts."""
        period = self.period
        self.next_t = (self.t0 if self.device_clock else self.next_t) + period
        now = self.clock()
        if now > self.next_t:
            self.overruns += 1
            if not self.device_clock:
                self.next_t += (int((now - self.next_t) / period) + 1) * period

    # ------------------------------------------------------------------ one cycle
    def cycle(self, controller: Stepper, between: Callable[[], None] | None = None) -> None:
        """One cycle around ``controller``: wait, read, ``between`` (the loop takes the
        requests that arrived), step (lifecycle transition + motion), write what it says."""
        self.wait()
        self.work(controller, between)
        self.schedule()

    def work(self, controller: Stepper, between: Callable[[], None] | None = None) -> None:
        """The cycle's work (between :meth:`wait` and :meth:`schedule`): read -> requests ->
        step -> write."""
        act, fb = self.actuator, self.feedback
        controller.on_read(fb, act.read(fb))
        if between is not None:
            between()
        if controller.step():  # also advances a lifecycle transition by one step
            controller.on_write(act.write(controller.command))

    def step_transition(self, transition: "Transition") -> tuple[bool, "Fault | None"]:
        """One cycle without a controller: wait, read, one step of ``transition``, and the
        write of a backend that is written every cycle (``cyclic_write``: every joint in
        CommandMode.NONE, as the controller writes while a transition runs outside ENABLED).
        Returns (the transition ended, the read's fault). Raises what the step raises."""
        return self._bare(transition, None)

    def idle(self, command: "JointCommand | None" = None) -> "Fault | None":
        """One cycle without a controller and without a transition: wait, read, then the write
        of ``command`` (None: of every joint in CommandMode.NONE, for a ``cyclic_write`` backend
        only). Returns the read's fault."""
        return self._bare(None, command)[1]

    def own_rate(self, transition: Callable[[], "Transition | None"], command: Callable[[], "JointCommand"]
                 ) -> tuple["Fault | None", "Fault | None", bool, BaseException | None]:
        """One cycle of a part served at its own rate (a slow bus beside a fast one, on its own
        thread: backends/composite.py): wait on this runner's own schedule, read, one step of
        the transition ``transition()`` returns (None: none; asked AFTER the read, so a
        transition the caller replaced or abandoned while the wait and the read took their time
        is never stepped), then the write of ``command()`` (the newest setpoint, taken now) while
        the backend is enabled (of every joint in CommandMode.NONE outside it, with
        ``cyclic_write``). Never raises: returns
        (the read's fault, the write's fault, the transition ended, what ``transition()`` or its
        step raised)."""
        self.wait()
        act = self.actuator
        read_fault = act.read(self.feedback)
        done, error = False, None
        try:
            t = transition()
            if t is not None:
                done = t.step()
        except BaseException as exc:  # carried to the loop's thread, which names the bus
            done, error = True, exc
        write_fault = None
        if act.is_enabled:
            write_fault = act.write(command())
        elif act.traits.cyclic_write:
            write_fault = act.write(self._idle)
        self.schedule()
        return read_fault, write_fault, done, error

    def _bare(self, transition: "Transition | None", command: "JointCommand | None") -> tuple[bool, "Fault | None"]:
        self.wait()
        act = self.actuator
        fault = act.read(self.feedback)
        try:
            done = transition.step() if transition is not None else True
        finally:
            if command is not None:
                act.write(command)
            elif act.traits.cyclic_write:
                act.write(self._idle)
            self.schedule()
        return done, fault


def run_transition(actuator: "Actuator", transition: "Transition", period_s: float | None = None) -> None:
    """Run ``transition`` to its end outside the control loop (start-up, shutdown, tests), one
    step per cycle of a :class:`CycleRunner` (wait, read, step, write: what the loop does).
    Blocks. Raises what a step raises, or BackendError after the transition's time limit (the
    transition is aborted). ``period_s`` defaults to the backend's effective period."""
    if period_s is None:
        from .actuator import effective_period_s
        period_s = effective_period_s(actuator.profile, actuator)
    runner = CycleRunner(actuator, period_s)
    deadline = time.monotonic() + transition.timeout_s
    while True:
        done, _ = runner.step_transition(transition)
        if done:
            return
        if time.monotonic() > deadline:
            transition.abort()
            raise BackendError(f"{actuator.robot}: {transition.kind.value} did not finish within "
                               f"{transition.timeout_s:g} s")

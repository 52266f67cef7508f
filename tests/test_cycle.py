"""The ONE cycle runner (core/cycle.py): the loop, start-up / shutdown and the test rigs drive a
backend the same way -- wait, read, step, write -- on one schedule."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from crtk_bridge.core.actuator import Clock as Beat, Lifecycle
from crtk_bridge.core.cycle import CycleRunner, run_transition

from .test_controller import PROFILE, Clock, FakeActuator
from .test_transitions import SlowActuator

ROOT = Path(__file__).resolve().parents[1]


class Recording(SlowActuator):
    """Written every cycle (as a CiA 402 chain); logs the cycle's calls in order."""

    def __init__(self, profile, enable_cycles=3):
        self.calls: list[str] = []
        super().__init__(profile, enable_cycles, cyclic_write=True)

    def wait_cycle(self, deadline):
        self.calls.append("wait")
        return True

    def _read(self, fb):
        self.calls.append("read")
        return super()._read(fb)

    def _write(self, cmd):
        self.calls.append("write")
        return super()._write(cmd)

    def _enable_steps(self, feedback):
        for k in range(self.enable_cycles):
            self.calls.append("step")
            yield
        self.torque = True

    def _disable_steps(self):
        self.calls.append("step")
        self.torque = False
        yield from ()


def _cycles(calls: list[str]) -> list[str]:
    """The calls cut into cycles, each starting at a wait."""
    cycles: list[list[str]] = []
    for call in calls:
        if call == "wait" or not cycles:
            cycles.append([])
        cycles[-1].append(call)
    return [" ".join(c) for c in cycles]


def test_start_up_and_shutdown_run_whole_cycles_not_bare_steps():
    """Enable, disable and close outside the loop (start-up, shutdown, the UR configure hook) run
    the loop's cycle: every step between the cycle's wait + read and its write, never a step
    alone with a sleep (the bus saw no SYNC, no read of the statusword it produced)."""
    act = Recording(PROFILE)
    act.open()
    act.enable(act.new_feedback())
    assert act.torque and act.is_enabled
    act.close()  # torque off on the way out, cycle by cycle too
    assert not act.torque
    # enable: its three steps, the step that ends them (torque on), the cycle whose read is the
    # pose it holds; then close's torque off; each a whole cycle (a step logs "step" here only
    # where the backend's own steps do)
    assert _cycles(act.calls) == ["wait read step write"] * 3 + ["wait read write"] * 2 + ["wait read step write"]


def test_run_transition_gives_up_at_the_transitions_time_limit():
    act = Recording(PROFILE, enable_cycles=10_000)
    act.open()
    t = act.begin(Lifecycle.ENABLE, act.new_feedback())
    t.timeout_s = 0.05
    with pytest.raises(Exception, match="enable did not finish within 0.05 s"):
        run_transition(act, t, period_s=0.005)
    assert t.done  # aborted


def test_the_loops_clock_keeps_an_absolute_schedule_and_skips_after_an_overrun():
    clock = Clock()
    act = FakeActuator(PROFILE)
    runner = CycleRunner(act, 0.01, clock=clock, sleep=clock.sleep)
    start = clock()
    starts = []
    for _ in range(3):
        runner.wait()
        starts.append(runner.t0 - start)
        clock.t += 0.003  # the cycle's work
        runner.schedule()
    assert starts == pytest.approx([0.01, 0.02, 0.03]) and runner.overruns == 0
    runner.wait()
    clock.t += 0.025  # an overrun: the work took two and a half periods
    runner.schedule()
    assert runner.overruns == 1
    runner.wait()  # the missed starts are skipped, not run in a burst: the grid is kept
    assert runner.t0 - start == pytest.approx(0.07) and runner.late == pytest.approx(0.0)


def test_the_devices_clock_sets_each_cycle_one_period_after_the_last_began():
    """On the device's clock the backend's wait_cycle returns when its packet came; the next
    deadline handed to it is one period after that cycle began (never rebuilt by the backend)."""
    clock = Clock()

    class Device(FakeActuator):
        def __init__(self, profile):
            self.deadlines = []
            super().__init__(profile, clock=Beat.DEVICE)

        def wait_cycle(self, deadline):
            self.deadlines.append(deadline)
            clock.t = deadline + 0.004  # the packet comes 4 ms after it was expected
            return True

    act = Device(PROFILE)
    runner = CycleRunner(act, 0.01, clock=clock, sleep=clock.sleep)
    start = clock()
    for _ in range(3):
        runner.wait()
        runner.schedule()
    assert [d - start for d in act.deadlines] == pytest.approx([0.01, 0.024, 0.038])


def test_no_cycle_body_outside_the_runner():
    """Only core/cycle.py calls a backend's wait_cycle or feeds a controller a write's result
    (a composite hands its buses' wait_cycle on): the loop, start-up and shutdown, the test rigs
    and the benches all run the one cycle."""
    allowed = {ROOT / "crtk_bridge" / "core" / "cycle.py", ROOT / "crtk_bridge" / "backends" / "composite.py",
               # the unit test of the UR backend's own wait_cycle (how many receives one wake-up
               # costs), not a cycle body
               ROOT / "tests" / "test_ur_worker.py"}
    body = re.compile(r"\.(?:wait_cycle|on_write)\(")
    found = []
    for top in ("crtk_bridge", "tests", "bench"):
        for path in sorted((ROOT / top).rglob("*.py")):
            if path in allowed or path == Path(__file__).resolve():
                continue
            found += [f"{path.relative_to(ROOT)}:{n}" for n, line in enumerate(path.read_text().splitlines(), 1)
                      if body.search(line)]
    assert found == []

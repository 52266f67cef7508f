"""Hardware pacing: a backend that paces the cycle sets the loop's one period and is waited on
instead of the loop's own clock (core/actuator.py, core/loop.py)."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from crtk_bridge.core.actuator import Clock
from crtk_bridge.core.loop import ControlLoop
from crtk_bridge.core.snapshot import Layout, SnapshotBuffer

from .conftest import wait_until
from .test_transitions import PROFILE, SlowActuator


class PacedActuator(SlowActuator):
    """Hardware at 100 Hz (the profile asks 200 Hz): each cycle waits for its next 'packet'."""

    def __init__(self, profile):
        super().__init__(profile, clock=Clock.DEVICE)
        self.waits = 0
        self.calls: list[str] = []  # "w" per wait_cycle, "r" per read, in order
        self.next_packet = time.perf_counter()

    def cycle_period_s(self):
        return 0.01

    def wait_cycle(self, deadline):
        self.waits += 1
        self.calls.append("w")
        self.next_packet += 0.01
        delay = min(self.next_packet, deadline + 0.01) - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        return True

    def _read(self, fb):
        self.calls.append("r")
        return super()._read(fb)


def test_a_pacing_backend_sets_the_period_and_paces_every_cycle():
    act = PacedActuator(PROFILE)
    front, back = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    snap = SnapshotBuffer(Layout(len(PROFILE.joints), len(PROFILE.namespaces)), create=True)
    try:
        loop = ControlLoop(PROFILE, act, back, snap, realtime=False)
        assert PROFILE.loop.rate_hz == 200
        assert loop.period == pytest.approx(0.01) and loop.controller.dt == pytest.approx(0.01)
        t = threading.Thread(target=loop.run, daemon=True)
        t.start()
        cycles = snap.views["cycles"]
        wait_until(lambda: cycles[0] >= 30, 10, what="30 paced cycles")
        loop.running = False
        t.join(5)
        assert not t.is_alive()
        # one wait for the hardware per cycle: the loop's own clock never ran it; every read, the
        # loop's and those of start-up (the first sample) and shutdown (torque off), follows one
        calls = "".join(act.calls)
        assert act.waits >= int(cycles[0]) and calls == "wr" * act.waits, calls
    finally:
        front.close()
        back.close()
        snap.close(unlink=True)


REALTIME_PROBE = """
import os, threading
from crtk_bridge.core.loop import request_realtime
started, done = threading.Event(), threading.Event()
tid = []
def receive():  # a bus's receive thread, started before the loop asks for real time
    tid.append(threading.get_native_id()); started.set(); done.wait()
threading.Thread(target=receive, daemon=True).start()
started.wait()
problems = request_realtime(10, None)
print(int(any(p.startswith("SCHED_FIFO") for p in problems)), os.sched_getscheduler(0) == os.SCHED_FIFO,
      os.sched_getscheduler(tid[0]) == os.SCHED_FIFO, os.sched_getparam(0).sched_priority,
      os.sched_getparam(tid[0]).sched_priority, end=" ")
from crtk_bridge.core.actuator import background_thread
seen = []
def work():  # blocking work started by the loop's thread later (a transition, a reconnect)
    seen.append((os.sched_getscheduler(0), os.sched_getparam(0).sched_priority))
plain = threading.Thread(target=work)  # what a thread inherits from the loop's thread
plain.start(); plain.join()
worker = background_thread(work, "probe")
worker.start(); worker.join()
print(seen[0] == (os.SCHED_FIFO, 10), seen[1] == (os.SCHED_OTHER, 0))
done.set()
"""


def test_realtime_reaches_the_threads_a_backend_started_before_the_loop():
    """A backend's threads started at open (python-can's notifier: the TPDOs) get the loop's
    SCHED_FIFO too: left at the normal class, a loaded host starved them and the drives'
    answers went unheard (tpdo_missing FAULTs). They sit one priority below the loop, and blocking
    work started later (actuator.background_thread) runs at the normal class, so nothing that
    spins on the loop's pinned CPU starves the loop. In a child process: it changes scheduling."""
    import subprocess
    import sys

    from .conftest import ROOT

    out = subprocess.run([sys.executable, "-c", REALTIME_PROBE], cwd=ROOT, capture_output=True, text=True,
                         timeout=30)
    assert out.returncode == 0, out.stderr
    refused, main, other, main_prio, other_prio, inherited, background = out.stdout.split()
    if refused == "1":
        pytest.skip("SCHED_FIFO is not permitted on this host")
    assert (main, other) == ("True", "True")
    # the loop preempts a thread of the backend's that spins: one priority below it
    assert (main_prio, other_prio) == ("10", "9")
    # a plain thread the loop starts inherits its class and priority (why the next is needed);
    # blocking work (a worker that may spin on a dead link) runs at the normal class instead
    assert (inherited, background) == ("True", "True")

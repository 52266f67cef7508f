"""A control process that ABORTS while the UR arm moves (what ur_rtde 1.6.5 can do to the process
it runs in after a link breaks: C++ exceptions reaching std::terminate, a heap corrupted by its
own reconnect thread; see tests/in_child.py) leaves no speedJ running: the control script's RTDE
watchdog (backend.watchdog_hz, set at every enable) stops the program, and with it the arm,
within 1 / watchdog_hz of the last input. The daemon's front then reports FAULT and exits
non-zero (tests/test_e2e_processes.py); here the backend runs in a child that aborts itself."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

from crtk_bridge.backends.ur.backend import UrBackend
from crtk_bridge.profile import load_profile
from crtk_bridge.sim import simulator_class

from .conftest import ROOT, wait_until

UR5E = ROOT / "profiles" / "ur5e.yaml"

CHILD = textwrap.dedent("""
    import os, sys, time
    import numpy as np
    from crtk_bridge.backends.ur.backend import UrBackend
    from crtk_bridge.core.actuator import CommandMode
    from crtk_bridge.profile import load_profile

    b = UrBackend(UrBackend.sim_profile(load_profile(sys.argv[1]), sys.argv[2]))
    b.open()
    b.configure()
    fb, cmd = b.new_feedback(), b.new_command()
    assert b.read(fb) is None
    b.enable(fb)
    cmd.mode[:] = int(CommandMode.VELOCITY)
    cmd.velocity[0] = 0.3  # speedJ: the base turns until something stops it
    cmd.position[:] = fb.position
    end = time.monotonic() + 0.3
    while time.monotonic() < end:
        b.wait_cycle(2 * b.dt)
        b.read(fb)
        b.write(cmd)
    print("moving", flush=True)
    sys.stdin.readline()  # the parent saw the arm turn
    os.abort()  # as std::terminate does
""")


def test_an_aborted_control_process_leaves_the_arm_stopped_by_the_scripts_watchdog():
    profile = load_profile(UR5E)
    watchdog_s = 1.0 / UrBackend.SIM_DEFAULTS["watchdog_hz"]  # the backend's own on --sim: 0.5 s
    sim = simulator_class("ur").from_profile(profile, power_on_s=0.1, brake_release_s=0.1)
    sim.start()
    try:
        child = subprocess.Popen([sys.executable, "-c", CHILD, str(UR5E), sim.port], cwd=ROOT, text=True,
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        try:
            line = child.stdout.readline()
            assert line.strip() == "moving", line + child.stdout.read()
            wait_until(lambda: abs(sim.state()["qd"][0]) > 0.2, 2, what="the arm turning under speedJ")
            child.stdin.write("\n")
            child.stdin.flush()
            assert child.wait(10) == -6  # SIGABRT: nothing stopped the arm on the way out
            died = time.monotonic()
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
        wait_until(lambda: sim.state()["qd"] == [0.0] * 6, watchdog_s + 1.0, interval=0.005,
                   what="the arm stopped by the script's watchdog")
        took = time.monotonic() - died
        st = sim.state()
        assert st["runtime_state"] != "PLAYING" and "watchdog" in st["last_error"], st
        print(f"arm stopped {took * 1e3:.0f} ms after the control process aborted (watchdog {watchdog_s:g} s)")
    finally:
        sim.stop()


class _Recorder:
    """A stand-in ur_rtde interface recording the calls made on it."""

    def __init__(self, log: list, name: str, connected: bool, running: bool = True):
        self.log, self.name, self.connected, self.running = log, name, connected, running

    def isConnected(self):  # noqa: N802 - ur_rtde's names
        return self.connected

    def isProgramRunning(self):  # noqa: N802
        return self.running

    def __getattr__(self, attr):
        def call(*args):
            self.log.append(f"{self.name}.{attr}")
            return True
        return call


def test_the_receive_interface_is_joined_before_it_reconnects():
    """Its own receive thread ended the link: ``disconnect`` (which joins that thread) comes
    before ``reconnect`` starts another, so two never share its socket (the heap corruption)."""
    b = UrBackend(UrBackend.sim_profile(load_profile(UR5E), "127.0.0.1"))
    log: list[str] = []
    b._rcv = _Recorder(log, "rcv", connected=False)
    b._maybe_reconnect()
    b._reconnect_thread.join(5)
    assert log == ["rcv.disconnect", "rcv.reconnect"]


def test_a_control_interface_that_lived_through_a_link_loss_is_never_called_again(monkeypatch):
    """Enable after a link loss builds a NEW control interface (ur_rtde's own receive thread of
    the old one raced calls made on it: heap corruption); the old one is not reconnected,
    stopped, disconnected or freed, and a disable in between does not call it either."""
    import crtk_bridge.backends.ur.backend as ur

    b = UrBackend(UrBackend.sim_profile(load_profile(UR5E), "127.0.0.1"))
    log: list[str] = []
    old = _Recorder(log, "old", connected=True)  # even one that says it is connected again
    b._ctl, b._ctl_link_lost = old, True
    b._dash = _Recorder(log, "dash", connected=True)
    b._link, b.runtime_state, b.robot_mode = True, int(ur.RuntimeState.PLAYING), int(ur.RobotMode.POWER_OFF)
    monkeypatch.setattr(b, "_refresh", lambda: True)
    for _ in b._disable_steps():  # the fault reaction once the link is back
        pass
    assert not [c for c in log if c.startswith("old.")], log
    made = []
    monkeypatch.setattr(ur.rtde_control, "RTDEControlInterface",
                        lambda host, rate: made.append((host, rate)) or _Recorder(log, "new", connected=True))
    b._start_script()
    assert made == [("127.0.0.1", 500.0)] and b._ctl is not old and not b._ctl_link_lost
    assert not [c for c in log if c.startswith("old.")], log
    assert sys.getrefcount(old) > 2  # abandoned: an extra reference keeps it from ever being freed

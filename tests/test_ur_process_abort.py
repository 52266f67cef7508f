"""A control process that ABORTS while the UR arm moves (a bug, the OOM killer; no longer ur_rtde,
which runs in the backend's worker process) leaves no speedJ running: its ur_rtde worker ends
with it (it sees the backend's socket close), and the control script's RTDE watchdog
(backend.watchdog_hz, set at every enable) stops the program, and with it the arm, within
1 / watchdog_hz of the last input. The daemon's front then reports FAULT and exits non-zero
(tests/test_e2e_processes.py); here the backend runs in a child that aborts itself. The child
also shows that the process running the backend never loads ur_rtde."""

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
    from crtk_bridge.core.cycle import CycleRunner
    from crtk_bridge.profile import load_profile

    b = UrBackend(UrBackend.sim_profile(load_profile(sys.argv[1]), sys.argv[2]))
    b.open()
    b.configure()
    runner = CycleRunner(b, b.dt)  # the loop's cycle, paced by the controller's packages
    fb, cmd = runner.feedback, b.new_command()
    assert runner.idle() is None
    b.enable(fb)
    cmd.mode[:] = int(CommandMode.VELOCITY)
    cmd.velocity[0] = 0.3  # speedJ: the base turns until something stops it
    cmd.position[:] = fb.position
    end = time.monotonic() + 0.3
    while time.monotonic() < end:
        runner.idle(cmd)
    maps = open("/proc/self/maps").read()
    print("moving", b.worker_pid, "rtde_control" in sys.modules or "rtde_receive" in sys.modules,
          "rtde_control" in maps or "rtde_receive" in maps, flush=True)
    sys.stdin.readline()  # the parent saw the arm turn
    os.abort()  # as std::terminate does
""")


def worker_alive(pid: int) -> bool:
    """Alive and not a zombie (an orphan is reaped by init; a zombie has ended)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


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
            assert line.startswith("moving"), line + child.stdout.read()
            _, worker, imported, mapped = line.split()
            assert worker_alive(int(worker)), "no ur_rtde worker"
            # ur_rtde is the worker's, never the control process's
            assert (imported, mapped) == ("False", "False"), line
            wmaps = open(f"/proc/{worker}/maps").read()
            assert "rtde_control" in wmaps and "rtde_receive" in wmaps  # (the extension modules, linked statically)
            wait_until(lambda: abs(sim.state()["qd"][0]) > 0.2, 2, what="the arm turning under speedJ")
            child.stdin.write("\n")
            child.stdin.flush()
            assert child.wait(10) == -6  # SIGABRT: nothing stopped the arm on the way out
            died = time.monotonic()
            # its worker ends with it: no orphan keeps talking to the controller
            wait_until(lambda: not worker_alive(int(worker)), 2, interval=0.005, what="the worker gone")
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

"""A simulator subprocess ends when the process that started it dies (``crtk-sim --parent-pid``),
even when nothing signals it: here its spawner sets no PR_SET_PDEATHSIG (as a spawner killed
before the child's prctl, or a test starting ``crtk-sim`` itself) and is killed with SIGKILL.
Nine ``crtk-sim ur`` were once found orphaned (parent pid 1, still using CPU) after killed runs."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from .conftest import wait_until

ROOT = Path(__file__).resolve().parents[1]

# the spawner: starts crtk-sim ur with --parent-pid (no preexec_fn, a session of its own as the
# real spawners do), prints the simulator's pid once it is ready, then waits to be killed
SPAWNER = """
import os, subprocess, sys, time
sim = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", "ur", "--profile", sys.argv[1],
                        "--host", "auto", "--parent-pid", str(os.getpid())],
                       stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, start_new_session=True)
line = sim.stdout.readline()
print(sim.pid if line.startswith(b"crtk-sim: ur controller ready") else -1, flush=True)
time.sleep(120)
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


def test_ur_simulator_ends_when_its_spawner_is_killed():
    spawner = subprocess.Popen([sys.executable, "-c", SPAWNER, str(ROOT / "profiles" / "ur5e.yaml")],
                               cwd=ROOT, stdout=subprocess.PIPE, start_new_session=True)
    sim_pid = None
    try:
        sim_pid = int(spawner.stdout.readline() or -1)
        assert sim_pid > 0, "crtk-sim ur did not start under the spawner"
        assert _alive(sim_pid)
        spawner.kill()  # SIGKILL: no cleanup, no signal reaches the simulator
        spawner.wait()
        wait_until(lambda: not _alive(sim_pid), timeout=10.0, what="the orphaned crtk-sim ur to end by itself")
    finally:
        if spawner.poll() is None:
            spawner.kill()
            spawner.wait()
        if sim_pid and sim_pid > 0 and _alive(sim_pid):
            os.kill(sim_pid, signal.SIGKILL)

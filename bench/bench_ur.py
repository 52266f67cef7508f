#!/usr/bin/env python3
"""UR over RTDE: the daemon's cycle rate paced by the controller, missed packets, and servo latency
through the daemon beside ur_rtde's ``servoJ`` called directly, same run.

One simulated UR5e controller (``crtk-sim ur``, e-Series: a data package every 2 ms) on a free
127.0.0.N serves both:

* **Cycle rate and missed packets**: the daemon (``crtk-bridge`` on profiles/ur5e.yaml with
  ``backend.host`` set to the simulator) runs ENABLED, holding; over ``--seconds`` the bench reads
  ``period_statistics``' cycle count and the simulator's tick count (packages sent): achieved
  rate = cycles / s, missed = packages sent - cycles run (a cycle per package is the target).
* **Servo latency**, alternating in ``--rounds`` rounds so both see the same host load:
  - through the daemon: a client sends ``servo_jp`` (a 0.01 rad step of wrist 3) on the socket;
    the time until the simulated arm's wrist 3 starts to move (the controller acted on the
    commanded joint), polled on the simulator's control socket;
  - direct: the same step sent with ur_rtde's ``RTDEControlInterface.servoJ`` from this process
    to a second simulated controller of the same kind (the daemon's control connection owns the
    first one's RTDE input registers), timed the same way.
  Both include the same polling delay of the simulator's state, so their difference is what the
  daemon adds (socket, front process, control process, one cycle, and the hop from the control
  process to the backend's ur_rtde worker process, which makes the servoJ call).

``--old DIR`` runs another checkout's daemon (``git worktree add --detach /tmp/old <commit>``) the
same way on a third simulated controller, its latency rounds alternating with this one's and the
direct path's, for a before/after from one run (the simulators and the client are this tree's).

Figures only; nothing is asserted. Usage:

    python bench/bench_ur.py [--seconds 5] [--rounds 3] [--steps 30] [--old /tmp/old]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from crtk_bridge.client import connect  # noqa: E402
from crtk_bridge.profile import load_profile  # noqa: E402
from crtk_bridge.sim import simulator_class  # noqa: E402

PROFILE = ROOT / "profiles" / "ur5e.yaml"
READY = [0.0, -1.57, 1.57, -1.57, -1.57, 0.0]
STEP = 0.01  # rad, wrist 3
MOVED = 1e-5  # rad: the arm has started to follow


def wait(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise SystemExit(f"bench: timed out waiting for {what}")
        time.sleep(0.01)


def onset(sim, before: dict, send) -> tuple[float, int]:
    """(seconds, controller ticks) from ``send()`` until the simulated wrist 3 leaves where it
    was in the state ``before`` (the ticks count from that state's). The poll sleeps 0.1 ms
    between reads: the simulator runs in this process, and a poll that never let go of the GIL
    held its tick thread for up to the interpreter's switch interval (5 ms), late ticks that
    both paths then paid for in the latency."""
    t0 = time.perf_counter()
    send()
    while True:
        st = sim.state()
        if abs(st["q"][5] - before["q"][5]) >= MOVED:
            return time.perf_counter() - t0, st["ticks"] - before["ticks"]
        if time.perf_counter() - t0 > 2.0:
            raise SystemExit("bench: the arm did not follow within 2 s")
        time.sleep(0.0001)


def daemon_latency(sim, arm, steps: int) -> list[tuple[float, int]]:
    out = []
    q = list(arm.measured_jp()[0])
    for _ in range(steps):
        time.sleep(0.1)  # the arm at rest between steps
        before = sim.state()
        q[5] += STEP
        out.append(onset(sim, before, lambda: arm.servo_jp(q)))
    return out


def direct_latency(sim, host: str, steps: int) -> list[float]:
    import rtde_control

    ctl = rtde_control.RTDEControlInterface(host, 500.0)
    ctl.moveJ(READY)
    try:
        q = list(sim.state()["q"])
        out = []
        for _ in range(steps):
            t_end = time.monotonic() + 0.1  # the arm at rest between steps, target streamed at 500 Hz
            while time.monotonic() < t_end:
                ctl.servoJ(q, 0.0, 0.0, 0.002, 0.05, 600.0)
                time.sleep(0.002)
            before = sim.state()
            q[5] += STEP
            out.append(onset(sim, before, lambda: ctl.servoJ(q, 0.0, 0.0, 0.002, 0.05, 600.0)))
    finally:
        ctl.servoStop(4.0)
        ctl.stopScript()
        ctl.disconnect()
    return out


def bare_receive(host: str, seconds: float) -> tuple[int, int]:
    """The baseline: an RTDEReceiveInterface polled for new packages (timestamp changes) with
    0.1 ms sleeps, as the backend's ur_rtde worker process does, for ``seconds``. (packages seen,
    missed)"""
    import rtde_receive

    r = rtde_receive.RTDEReceiveInterface(host, 500.0, ["timestamp"])
    seen = missed = 0
    last = r.getTimestamp()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        ts = r.getTimestamp()
        if ts != last:
            seen += 1
            missed += max(int(round((ts - last) / 0.002)) - 1, 0)
            last = ts
        else:
            time.sleep(0.0001)
    r.disconnect()
    return seen, missed


def power_on(sim) -> None:
    """Power on and release the brakes over the dashboard, as a user would before servoJ."""
    import dashboard_client

    dash = dashboard_client.DashboardClient(sim.port)
    dash.connect()
    dash.powerOn()
    wait(lambda: sim.state()["robot_mode"] == "IDLE", 5, "IDLE")
    dash.brakeRelease()
    wait(lambda: sim.state()["robot_mode"] == "RUNNING", 5, "RUNNING")
    dash.disconnect()


def start_daemon(tree: Path, sim, workdir: str, name: str):
    """``crtk-bridge`` of checkout ``tree`` on profiles/ur5e.yaml against ``sim``, ENABLED at
    READY. Returns (process, connection, arm)."""
    data = yaml.safe_load(PROFILE.read_text())
    data["backend"]["host"] = sim.port
    # the simulator shares this PC with the daemon, unscheduled: its --sim link timeout and
    # watchdog (UrBackend.SIM_DEFAULTS), or a loaded host's hiccup is a link_lost FAULT mid-run
    for key, value in {"link_timeout_s": 0.5, "watchdog_hz": 2.0}.items():
        data["backend"].setdefault(key, value)
    data["namespaces"][0]["kinematics"]["urdf"] = str(PROFILE.parent / data["namespaces"][0]["kinematics"]["urdf"])
    profile_path = os.path.join(workdir, f"{name}.yaml")
    with open(profile_path, "w") as f:
        yaml.safe_dump(data, f)
    sock = os.path.join(workdir, f"{name}.sock")
    env = dict(os.environ, PYTHONPATH=str(tree))
    daemon = subprocess.Popen([sys.executable, "-m", "crtk_bridge.cli", "--profile", profile_path,
                               "--socket", sock], cwd=tree, env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    try:
        wait(lambda: os.path.exists(sock), 30, f"the {name} daemon's socket")
        robot = connect(socket=sock)
        arm = robot.device("ur5e")
        assert arm.enable(10.0), "enable failed"
        arm.move_jp(READY).wait(timeout=15)
    except BaseException:
        daemon.terminate()
        daemon.wait(15)
        raise
    return daemon, robot, arm


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=5.0, help="cycle-rate window (default 5)")
    ap.add_argument("--rounds", type=int, default=3, help="latency rounds, daemon and direct alternating")
    ap.add_argument("--steps", type=int, default=30, help="servo steps per round and path")
    ap.add_argument("--old", type=Path, help="another checkout whose daemon is measured the same way, same run")
    args = ap.parse_args()

    sims = [simulator_class("ur").from_profile(load_profile(PROFILE), power_on_s=0.1, brake_release_s=0.1)
            for _ in range(3 if args.old else 2)]
    for s in sims:
        s.start()
    sim, sim2 = sims[0], sims[1]
    power_on(sim2)
    workdir = tempfile.mkdtemp(prefix="crtk-bench-ur-")
    daemons = []
    try:
        daemon, robot, arm = start_daemon(ROOT, sim, workdir, "new")
        daemons.append(daemon)
        old = None
        if args.old:
            old_daemon, old_robot, old_arm = start_daemon(args.old.resolve(), sims[2], workdir, "old")
            daemons.append(old_daemon)
            old = (old_robot, old_arm, sims[2])

        # -- cycle rate and missed packets, ENABLED and holding --
        c0, t0 = robot.connection.request("period_statistics")["cycles"], sim.state()["ticks"]
        w0 = time.monotonic()
        bare_seen, bare_missed = bare_receive(sim.port, args.seconds)
        stats = robot.connection.request("period_statistics")
        c1, t1 = stats["cycles"], sim.state()["ticks"]
        took = time.monotonic() - w0
        cycles, packets = c1 - c0, t1 - t0
        print(f"RTDE cycle rate: {cycles / took:.1f} Hz over {took:.1f} s (target 500 Hz; simulator sent "
              f"{packets / took:.1f} packages/s); missed packets: {max(packets - cycles, 0)} of {packets} "
              f"({100.0 * max(packets - cycles, 0) / max(packets, 1):.2f} %)")
        print(f"baseline, a bare ur_rtde receive loop in this process over the same window: "
              f"{bare_seen / args.seconds:.1f} packages/s seen, {bare_missed} missed "
              f"({100.0 * bare_missed / max(bare_seen + bare_missed, 1):.2f} %)")
        print(f"  period_statistics: {({k: v for k, v in stats.items() if k != 'cycles'})}")

        # -- servo latency, daemon(s) and direct alternating --
        through, direct, before = [], [], []
        for r in range(args.rounds):
            through += daemon_latency(sim, arm, args.steps)
            if old is not None:
                before += daemon_latency(old[2], old[1], args.steps)
            direct += direct_latency(sim2, sim2.port, args.steps)
            print(f"round {r + 1}: servo latency median through the daemon "
                  f"{1e3 * statistics.median(s for s, _ in through[-args.steps:]):.2f} ms"
                  + (f", old daemon {1e3 * statistics.median(s for s, _ in before[-args.steps:]):.2f} ms"
                     if before else "")
                  + f", direct servoJ {1e3 * statistics.median(s for s, _ in direct[-args.steps:]):.2f} ms")
        mx = statistics.median(s for s, _ in direct)
        kx = statistics.median(k for _, k in direct)
        for label, runs in (("the daemon", through), ("the OLD daemon", before)):
            if not runs:
                continue
            md = statistics.median(s for s, _ in runs)
            print(f"servo latency (request -> simulated joint moving), median of {len(runs)}: through {label} "
                  f"{1e3 * md:.2f} ms, ur_rtde servoJ direct {1e3 * mx:.2f} ms; ratio {md / mx:.2f}, {label} adds "
                  f"{1e3 * (md - mx):.2f} ms (target: one controller cycle, 2 ms)")
            kd = statistics.median(k for _, k in runs)
            print(f"  in controller ticks (the simulator's own clock: robust to a loaded host), median: through "
                  f"{label} {kd:g}, direct {kx:g}; it adds {kd - kx:g} tick(s) (target <= 1)")
        robot.close()
        if old is not None:
            old[0].close()
    finally:
        for d in daemons:
            d.terminate()
            d.wait(15)
        for s in sims:
            s.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())

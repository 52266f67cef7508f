#!/usr/bin/env python3
"""Several buses in one robot: the two-bus cycle rate beside the one-bus rate, same run.

profiles/bimanual_so101.yaml is two SO-101 arms, each six STS3215 on its own bus. Two simulator
processes (``crtk-sim feetech --bus left|right --emulate-baud``: each reply leaves no earlier than
the request and reply would take on a real wire at the profile's baud) serve the two buses. The
bench then runs, alternating in rounds so both see the same host load:

* one bus: the left arm's FeetechBackend alone (its one-bus profile), and
* two buses: the whole robot's CompositeActuator (one worker thread per bus, I/O concurrent),

each for ``--cycles`` real-time cycles back to back (one ``read`` + one ``write`` of position
goals, goals changing so the writes are real), and prints each round's rate, the medians and the
ratio two-bus / one-bus (DESIGN.md target: >= 90 %). A sequential composite (the same two buses
served one after the other, ``--sequential``) shows what the concurrency buys.

Figures only; nothing is asserted. Usage:

    python bench/bench_multibus.py [--cycles 1000] [--rounds 5] [--baud 1000000]
"""

from __future__ import annotations

import argparse
import copy
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

from crtk_bridge.backends import create_backend  # noqa: E402
from crtk_bridge.core.actuator import CommandMode  # noqa: E402
from crtk_bridge.profile import parse_profile  # noqa: E402

PROFILE = ROOT / "profiles" / "bimanual_so101.yaml"


def start_sims(workdir: str, profile_file: Path) -> tuple[list[subprocess.Popen], dict[str, str]]:
    procs, ports = [], {}
    for bus in ("left", "right"):
        link = os.path.join(workdir, f"tty-{bus}")
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "crtk_bridge.sim.cli", "feetech", "--profile", str(profile_file),
             "--bus", bus, "--link", link, "--emulate-baud"],
            stdout=subprocess.DEVNULL, stdin=subprocess.DEVNULL, cwd=ROOT))
        ports[bus] = link
    deadline = time.monotonic() + 20
    while not all(os.path.exists(p) for p in ports.values()):
        if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
            raise SystemExit("the simulators did not start")
        time.sleep(0.05)
    return procs, ports


def cycle_rate(actuator, cycles: int) -> tuple[float, int]:
    """Open, enable, run ``cycles`` read + write cycles back to back; (cycles/s, faults)."""
    actuator.open()
    try:
        actuator.configure()
        fb, cmd = actuator.new_feedback(), actuator.new_command()
        actuator.enable(fb)
        cmd.mode[:] = CommandMode.POSITION
        for _ in range(50):  # warm up (and start the composite's worker threads)
            actuator.read(fb)
            actuator.write(cmd)
        faults = []
        t0 = time.perf_counter()
        for k in range(cycles):
            f = actuator.read(fb)
            if f is not None:
                faults.append(f)
            cmd.position[:] = 0.05 * ((k // 100) % 2)
            f = actuator.write(cmd)
            if f is not None:
                faults.append(f)
        rate = cycles / (time.perf_counter() - t0)
        for f in faults[:2]:
            print(f"  fault: {f.message}", file=sys.stderr)
        return rate, len(faults)
    finally:
        actuator.close()
        time.sleep(0.1)  # replies the simulator still sends to the closed port must not meet the next open


class Sequential:
    """The composite's buses served one after the other (the baseline concurrency beats)."""

    def __init__(self, composite):
        self.c = composite

    def __getattr__(self, name):
        return getattr(self.c, name)

    def read(self, fb):
        faults = [p.read(self.c._fb[b]) for b, p in enumerate(self.c.parts)]
        for b, idx in enumerate(self.c._idx):
            fb.position[idx] = self.c._fb[b].position
        return next((f for f in faults if f is not None), None)

    def write(self, cmd):
        faults = []
        for b, (p, idx) in enumerate(zip(self.c.parts, self.c._idx)):
            c = self.c._cmd[b]
            c.mode[:] = cmd.mode[idx]
            c.position[:] = cmd.position[idx]
            faults.append(p.write(c))
        return next((f for f in faults if f is not None), None)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cycles", type=int, default=1000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--baud", type=int, default=1_000_000)
    ap.add_argument("--sequential", action="store_true", help="also time the buses served one after the other")
    ap.add_argument("--switch-interval", type=float, default=None,
                    help="sys.setswitchinterval (s) for this process (default: Python's 0.005)")
    args = ap.parse_args(argv)
    if args.switch_interval:
        sys.setswitchinterval(args.switch_interval)
    data = yaml.safe_load(PROFILE.read_text())
    for section in data["backends"].values():
        section["baudrate"] = args.baud
    with tempfile.TemporaryDirectory(prefix="crtk-bench-") as workdir:
        profile_file = Path(workdir) / "bimanual.yaml"
        profile_file.write_text(yaml.safe_dump(data))
        procs, ports = start_sims(workdir, profile_file)
        try:
            wired = copy.deepcopy(data)
            for bus, port in ports.items():
                wired["backends"][bus]["port"] = port
            robot = parse_profile(wired)
            one = robot.bus_profile("left")
            rows: dict[str, list[float]] = {"one bus (6 servos)": [], "two buses (2 x 6), concurrent": []}
            if args.sequential:
                rows["two buses, sequential"] = []
            faults = {k: 0 for k in rows}
            for _ in range(args.rounds):
                rate, f = cycle_rate(create_backend(one), args.cycles)
                rows["one bus (6 servos)"].append(rate)
                faults["one bus (6 servos)"] += f
                rate, f = cycle_rate(create_backend(robot), args.cycles)
                rows["two buses (2 x 6), concurrent"].append(rate)
                faults["two buses (2 x 6), concurrent"] += f
                if args.sequential:
                    rate, f = cycle_rate(Sequential(create_backend(robot)), args.cycles)
                    rows["two buses, sequential"].append(rate)
                    faults["two buses, sequential"] += f
        finally:
            for p in procs:
                p.terminate()
                p.wait(5)
    print(f"emulated baud {args.baud}, {args.rounds} alternating rounds of {args.cycles} cycles "
          f"(read + write of position goals), simulators in their own processes")
    base = statistics.median(rows["one bus (6 servos)"])
    print(f"{'configuration':34s} {'median Hz':>9s} {'vs one bus':>10s} {'faults':>6s}   rounds (Hz)")
    for label, rates in rows.items():
        med = statistics.median(rates)
        print(f"{label:34s} {med:9.0f} {med / base:10.1%} {faults[label]:6d}   "
              f"{' '.join(f'{r:.0f}' for r in rates)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

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
ratio two-bus / one-bus (docs/architecture.md, "Performance targets": >= 90 %). A sequential composite (the same two buses
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


def cycle_rate(actuator, fb, cmd, cycles: int) -> tuple[float, int]:
    """``cycles`` real-time cycles (read + write) back to back: (cycles/s, faults)."""
    faults = []
    t0 = time.perf_counter()
    for k in range(cycles):
        f = actuator.read(fb)
        if f is not None:
            faults.append(f)
        cmd.position[:] = 0.05 * ((k // 100) % 2)  # goals change: the writes are real
        f = actuator.write(cmd)
        if f is not None:
            faults.append(f)
    rate = cycles / (time.perf_counter() - t0)
    return rate, len(faults)


def sequential(composite):
    """The composite's buses served one after the other (what the concurrency beats)."""

    class Sequential:
        def read(self, fb):
            faults = [p.read(composite._fb[b]) for b, p in enumerate(composite.parts)]
            for b, idx in enumerate(composite._idx):
                fb.position[idx] = composite._fb[b].position
            return next((f for f in faults if f is not None), None)

        def write(self, cmd):
            faults = []
            for b, (p, idx) in enumerate(zip(composite.parts, composite._idx)):
                c = composite._cmd[b]
                c.mode[:] = cmd.mode[idx]
                c.position[:] = cmd.position[idx]
                faults.append(p.write(c))
            return next((f for f in faults if f is not None), None)

    return Sequential()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cycles", type=int, default=1000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--baud", type=int, default=1_000_000)
    ap.add_argument("--sequential", action="store_true", help="also time the buses served one after the other")
    ap.add_argument("--nice", type=int, default=0,
                    help="nice increment for this process and the simulators, e.g. -10 (root): on a "
                         "shared host, other processes then take less CPU from the measured buses")
    args = ap.parse_args(argv)
    if args.nice:
        os.nice(args.nice)  # inherited by the simulators started below
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
            robot = create_backend(parse_profile(wired))  # the composite: both buses
            robot.open()
            robot.configure()
            robot.enable(robot.new_feedback())
            # one bus = the composite's left bus alone (the same open FeetechBackend), so nothing
            # is reopened between rounds and both configurations share the same ports
            left = robot.parts[0]
            configs = {"one bus (6 servos)": (left, left.new_feedback(), left.new_command()),
                       "two buses (2 x 6), concurrent": (robot, robot.new_feedback(), robot.new_command())}
            if args.sequential:
                configs["two buses, sequential"] = (sequential(robot), robot.new_feedback(), robot.new_command())
            rows: dict[str, list[float]] = {k: [] for k in configs}
            faults = {k: 0 for k in configs}
            for _, fb, cmd in configs.values():
                cmd.mode[:] = CommandMode.POSITION
            for act, fb, cmd in configs.values():  # warm up (and start the composite's workers)
                cycle_rate(act, fb, cmd, 50)
            for _ in range(args.rounds):
                for label, (act, fb, cmd) in configs.items():
                    rate, f = cycle_rate(act, fb, cmd, args.cycles)
                    rows[label].append(rate)
                    faults[label] += f
            robot.close()
        finally:
            for p in procs:
                p.terminate()
                p.wait(5)
    print(f"emulated baud {args.baud}, {args.rounds} alternating rounds of {args.cycles} cycles "
          f"(read + write of position goals), simulators in their own processes"
          f"{f', nice {args.nice}' if args.nice else ''}; load average {os.getloadavg()[0]:.1f}")
    base = statistics.median(rows["one bus (6 servos)"])
    print(f"{'configuration':34s} {'median Hz':>9s} {'vs one bus':>10s} {'faults':>6s}   rounds (Hz)")
    for label, rates in rows.items():
        med = statistics.median(rates)
        print(f"{label:34s} {med:9.0f} {med / base:10.1%} {faults[label]:6d}   "
              f"{' '.join(f'{r:.0f}' for r in rates)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Recording's cost on the simulated SO-101 at 1 kHz, recording on against off in the same run.

One daemon (``crtk-bridge --sim``, the loop at 1 kHz), ENABLED and streaming a servo_jp sine so
every topic changes. Windows alternate: recording off, recording on (every namespace, every
cycle, into a bag in a temporary folder), off, on, ... Per window: the loop's lateness p99 (from
``period_statistics``, sampled once a second: each sample covers the last 1024 cycles) and the
front process's CPU time (/proc). Per recording: bytes per second of the bag, its ``lost`` cycles
and the largest single write (``max_write_s``: a batch of cycles, or a flush) seen by the writer.

Prints medians over the windows, the on/off lateness ratio (the issue's target: within 1.1x) and
the recorder's CPU share (front CPU on minus off, as a share of one core). Figures only; nothing
is asserted. Usage:

    python bench/bench_record.py [--rounds 2] [--window 4]
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from sim_daemon import start  # noqa: E402

from crtk_bridge.client import connect  # noqa: E402

RATE_HZ = 1000.0


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (all its threads)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def window(robot, pid: int, seconds: float) -> tuple[list[float], float]:
    """(lateness p99 samples, front CPU share of one core) over ``seconds``."""
    p99 = []
    c0, t0 = cpu_s(pid), time.monotonic()
    end = t0 + seconds
    while time.monotonic() < end:
        time.sleep(1.05)  # a little more than the 1024-cycle statistics ring: samples do not overlap
        p99.append(robot.period_statistics()["lateness_p99_s"])
    return p99, (cpu_s(pid) - c0) / (time.monotonic() - t0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--window", type=float, default=4.0, help="seconds per window")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="crtk-bench-rec-"))
    daemon, sock = start(RATE_HZ, tmp)
    stop = threading.Event()
    try:
        robot = connect(socket=str(sock), timeout=10.0)  # observes and records; takes no control
        enabled = threading.Event()

        def sine() -> None:  # enable, then servo_jp at 100 Hz, from its own connection
            r = connect(socket=str(sock), timeout=10.0)
            d = r.device("so101")
            r.enable()
            home = np.array(d.measured_jp()[0])
            enabled.set()
            t0 = time.monotonic()
            while not stop.is_set():
                t = time.monotonic() - t0
                d.servo_jp(home + 0.2 * math.sin(2 * math.pi * 0.5 * t))
                time.sleep(0.01)
            r.disable()
            r.close()

        streamer = threading.Thread(target=sine, daemon=True)
        streamer.start()
        if not enabled.wait(20.0):
            raise RuntimeError("the robot did not enable")
        time.sleep(1.0)
        off_p99, on_p99, off_cpu, on_cpu, results = [], [], [], [], []
        for k in range(args.rounds):
            p, c = window(robot, daemon.pid, args.window)
            off_p99 += p
            off_cpu.append(c)
            started = robot.record(str(tmp / f"bench{k}.mcap"))
            p, c = window(robot, daemon.pid, args.window)
            on_p99 += p
            on_cpu.append(c)
            results.append(robot.record_stop(started["recording"], timeout=60.0))
        stop.set()
        streamer.join(5.0)
        stats = robot.period_statistics()
        robot.close()
    finally:
        stop.set()
        daemon.send_signal(signal.SIGTERM)
        daemon.wait(30)
        shutil.rmtree(tmp, ignore_errors=True)
    off, on = float(np.median(off_p99)), float(np.median(on_p99))
    span = [(r["last_cycle"] - r["first_cycle"] + 1) / RATE_HZ for r in results]
    rate = [r["bytes"] / s for r, s in zip(results, span)]
    print(f"loop at {RATE_HZ:g} Hz, {args.rounds} rounds of {args.window:g} s windows, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}, overruns {stats['overruns']} of {stats['cycles']} cycles")
    print(f"lateness p99, median of windows: recording off {off * 1e6:.0f} us, on {on * 1e6:.0f} us "
          f"(ratio {on / off:.2f}; target <= 1.1)")
    print(f"front process CPU (share of one core): off {np.median(off_cpu):.1%}, on {np.median(on_cpu):.1%} "
          f"-> recorder {np.median(on_cpu) - np.median(off_cpu):.1%}")
    print(f"bag: {np.median(rate) / 1e3:.0f} kB/s (zstd chunks), "
          f"{np.median([r['messages'] for r in results]) / np.median(span):.0f} messages/s, "
          f"lost cycles {sum(r['lost'] for r in results)}, "
          f"largest write stall {max(r['max_write_s'] for r in results) * 1e3:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())

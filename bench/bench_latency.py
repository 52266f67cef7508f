#!/usr/bin/env python3
"""A command acts in the next cycle (issue 23, item 3): ``servo_jp`` request -> bus write on the
simulated serial-servo buses, against the loop period, same run.

``crtk-bridge --profile <profile> --sim`` runs ENABLED. A client sends ``servo_jp`` (the held
position with one joint moved by +/- ``--step`` rad, alternately, at a random phase of the loop's
cycle), then polls the simulated servo's ``Goal_Position`` register over the simulator's control
socket (one persistent connection) until it changes: request -> bus write. A ``servo_jp`` that
arrives during cycle k is written in cycle k's write or k+1's, so the target is at most two
periods. Beside it, the same poll's own round trip (what the figure includes on top: the
resolution). The UR's figure (request -> the simulated joint moving, through the daemon and with
ur_rtde's ``servoJ`` direct) is bench/bench_ur.py's.

Figures only; nothing is asserted. Usage:

    python bench/bench_latency.py [--profiles so101 koch] [--steps 200]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import socket
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


class Control:
    """The simulator's control socket, one connection, one request line at a time."""

    def __init__(self, path: str):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(path)
        self.file = self.sock.makefile("rb")

    def req(self, **request) -> dict:
        self.sock.sendall(json.dumps(request).encode() + b"\n")
        return json.loads(self.file.readline())


def pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))]


def run(profile: str, steps: int, step: float, tmp: Path) -> dict:
    data = yaml.safe_load((ROOT / "profiles" / f"{profile}.yaml").read_text())
    rate = float(data["loop"]["rate_hz"])
    joint = data["joints"][-2]  # a wrist: a small step moves nothing else
    sid, name = int(joint["id"]), joint["name"]
    sock = tmp / f"{profile}.sock"
    log = tmp / f"{profile}.log"
    with open(log, "w") as err:
        daemon = subprocess.Popen([sys.executable, "-m", "crtk_bridge.cli", "--profile", f"profiles/{profile}.yaml",
                                   "--sim", "--socket", str(sock)], cwd=ROOT, stdout=err, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while not sock.exists():
            if daemon.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"{profile}: the daemon did not start: {log.read_text()[-500:]}")
            time.sleep(0.05)
        m = re.search(r"simulator control socket (\S+?)\)", log.read_text())
        if not m:
            raise RuntimeError(f"{profile}: no simulator control socket in the daemon's log")
        ctl = Control(m.group(1))
        lat, poll = [], []
        with connect(socket=str(sock), timeout=10.0) as robot:
            dev = robot.device()
            if not dev.enable(20.0):
                raise RuntimeError(f"{profile}: not ENABLED")
            names = dev.joint_names
            k = names.index(name)
            held = list(dev.measured_js()[0])
            time.sleep(0.2)
            for n in range(steps):
                goal = ctl.req(cmd="read", id=sid, register="Goal_Position")["value"]
                target = list(held)
                target[k] += step if n % 2 == 0 else 0.0
                time.sleep(random.uniform(0.5, 1.5) / rate)  # a random phase of the cycle
                t0 = time.perf_counter()
                dev.servo_jp(target)
                while True:
                    t1 = time.perf_counter()
                    now = ctl.req(cmd="read", id=sid, register="Goal_Position")["value"]
                    t2 = time.perf_counter()
                    if now != goal:
                        break
                    if t2 - t0 > 1.0:
                        raise RuntimeError(f"{profile}: servo_jp never reached the bus")
                lat.append(t2 - t0)
                poll.append(t2 - t1)
                time.sleep(4 / rate)  # the goal settles before the next step
            dev.disable(10.0)
    finally:
        daemon.terminate()
        daemon.wait(30)
    return {"rate": rate, "lat": lat, "poll": poll}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profiles", nargs="+", default=["so101", "koch"])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--step", type=float, default=0.02, help="rad (default 0.02)")
    args = ap.parse_args()
    load = [os.getloadavg()[0]]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-lat-") as tmp:
        for profile in args.profiles:
            rows.append((profile, run(profile, args.steps, args.step, Path(tmp))))
            load.append(os.getloadavg()[0])
    print("servo_jp request -> Goal_Position written on the simulated bus")
    print(f"{'profile':<16} {'period':>8} {'p50':>9} {'p99':>9} {'max':>9} {'p50/period':>11} {'p99/period':>11} "
          f"{'poll p50':>9}")
    for profile, r in rows:
        period = 1.0 / r["rate"]
        lat = r["lat"]
        label = f"{profile} {r['rate']:g}Hz"
        print(f"{label:<16} {period * 1e3:6.2f}ms {pct(lat, .5) * 1e3:7.2f}ms "
              f"{pct(lat, .99) * 1e3:7.2f}ms {max(lat) * 1e3:7.2f}ms {pct(lat, .5) / period:11.2f} "
              f"{pct(lat, .99) / period:11.2f} {statistics.median(r['poll']) * 1e3:7.2f}ms")
    print(f"load average (1 min) from {min(load):.2f} to {max(load):.2f} on {os.cpu_count()} cores; "
          "target: p99 <= 2 periods (on the bus in cycle k+1)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

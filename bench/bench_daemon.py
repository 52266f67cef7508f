#!/usr/bin/env python3
"""Daemon performance on the simulated SO-101, each figure beside a baseline measured in the same run.

1. Loop lateness: the daemon's control loop at 1 kHz on the simulated bus while 8 clients stream
   ``measured_js`` at 1 kHz and one client sends ``servo_jp`` at 500 Hz, against a bare SCHED_FIFO
   sleep loop at 1 kHz. Windows alternate (baseline, daemon, baseline, daemon, ...).
2. Socket round trip: ``measured_js`` request -> reply, against a bare asyncio Unix-socket echo
   server answering the same request line, alternating, same client code.

Prints medians / p99 and the ratios (docs/architecture.md, "Performance targets": loop p99 within
2x of the bare loop's, socket p50 within 2x of the echo's). Figures only; nothing is asserted. Usage:

    python bench/bench_daemon.py [--rounds 3] [--window 3]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import sim_daemon  # noqa: E402  (bench/, beside this script)
from crtk_bridge.client import connect  # noqa: E402


def bare_loop(rate_hz: float, seconds: float) -> np.ndarray:
    """A SCHED_FIFO sleep loop in a child process; returns its lateness samples (s)."""
    code = f"""
import os, time, json
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
except OSError:
    pass
period = 1.0 / {rate_hz}
n = int({seconds} * {rate_hz})
late = []
nxt = time.perf_counter() + period
for _ in range(n):
    d = nxt - time.perf_counter()
    if d > 0:
        time.sleep(d)
    late.append(time.perf_counter() - nxt)
    nxt += period
    if time.perf_counter() > nxt:
        nxt = time.perf_counter() + period
print(json.dumps(late))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return np.array(json.loads(out))


def echo_server(path: str) -> subprocess.Popen:
    code = f"""
import asyncio
async def handle(r, w):
    while line := await r.readline():
        w.write(b'{{"id":1,"ok":true,"data":{{"stamp":1.0,"position":[0,0,0,0,0]}}}}\\n')
async def main():
    s = await asyncio.start_unix_server(handle, path={path!r})
    async with s:
        await s.serve_forever()
asyncio.run(main())
"""
    p = subprocess.Popen([sys.executable, "-c", code])
    deadline = time.monotonic() + 10
    while not os.path.exists(path):
        if time.monotonic() > deadline:
            raise RuntimeError("echo server did not start")
        time.sleep(0.01)
    return p


def round_trips(path: str, n: int) -> np.ndarray:
    """Blocking request/reply of measured_js over a plain socket; returns round-trip times (s)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(path)
    f = s.makefile("rb")
    req = b'{"id":1,"cmd":"measured_js","ns":"so101"}\n'
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        s.sendall(req)
        while True:  # skip pushed events; stop at the reply
            line = f.readline()
            if b'"id"' in line:
                break
        out[i] = time.perf_counter() - t0
    s.close()
    return out


class Load:
    """8 subscribers of measured_js at 1 kHz + one servo_jp client at 500 Hz."""

    def __init__(self, path: str, arm_start: np.ndarray, cartesian: bool = False):
        self.cartesian = cartesian
        self.stop = threading.Event()
        self.frames = [0] * 8
        self.threads = [threading.Thread(target=self._sub, args=(path, i), daemon=True) for i in range(8)]
        self.threads.append(threading.Thread(target=self._servo, args=(path, arm_start), daemon=True))
        self.sent = 0

    def _sub(self, path: str, i: int) -> None:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(path)
        s.sendall(b'{"id":1,"cmd":"subscribe","ns":"so101","data":{"topic":"measured_js","rate_hz":1000}}\n')
        f = s.makefile("rb")
        while not self.stop.is_set():
            if f.readline().startswith(b'{"topic"'):
                self.frames[i] += 1
        s.close()

    def _servo(self, path: str, start: np.ndarray) -> None:
        robot = self.robot
        arm = robot.device("so101")
        conn = robot.connection
        period = 1 / 500
        nxt = time.perf_counter()
        k = 0
        if self.cartesian:  # a 2 cm circle in the arm's vertical plane, one servo_cp (IK) per command
            cp = conn.request("measured_cp", "so101")
            centre, quat = np.array(cp["position"]), cp["orientation"]
            radial = np.array([1.0, 0.0, 0.0])
        while not self.stop.is_set():
            k += 1
            try:
                if self.cartesian:
                    a = k * period * 2 * np.pi
                    goal = centre + 0.02 * ((np.cos(a) - 1) * radial + np.sin(a) * np.array([0, 0, 1.0]))
                    conn.request("servo_cp", "so101", {"position": goal.tolist(), "orientation": quat})
                else:
                    arm.servo_jp(start + np.array([0.2 * np.sin(k * period), 0, 0, 0, 0]))
                self.sent += 1
            except Exception:
                pass
            nxt += period
            d = nxt - time.perf_counter()
            if d > 0:
                time.sleep(d)

    def start(self, robot) -> None:
        self.robot = robot
        for t in self.threads:
            t.start()

    def finish(self) -> None:
        self.stop.set()


def pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--window", type=float, default=3.0, help="seconds per measurement window")
    ap.add_argument("--rtt", type=int, default=2000, help="round trips per window")
    ap.add_argument("--cartesian", action="store_true", help="stream servo_cp (IK per command) instead of servo_jp")
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="crtk-bench-"))
    daemon, sock = sim_daemon.start(1000, tmp)
    echo_path = str(tmp / "echo.sock")
    echo = echo_server(echo_path)
    try:
        robot = connect(socket=str(sock))
        arm = robot.device("so101")
        assert arm.enable(5.0), "enable failed"
        start = arm.measured_jp()[0]

        # -- socket round trip, idle daemon (loop running), alternating with the echo baseline --
        rtt_d, rtt_e = [], []
        for _ in range(args.rounds):
            rtt_e.append(round_trips(echo_path, args.rtt))
            rtt_d.append(round_trips(str(sock), args.rtt))
        rtt_d, rtt_e = np.concatenate(rtt_d), np.concatenate(rtt_e)

        # -- loop lateness under load, alternating with the bare loop --
        bare, loaded, compute, overruns = [], [], [], []
        stats_start = robot.connection.request("period_statistics")
        load = Load(str(sock), start, cartesian=args.cartesian)
        load.start(robot)
        load_t0 = time.monotonic()
        time.sleep(0.5)  # let subscriptions start
        for _ in range(args.rounds):
            bare.append(bare_loop(1000, args.window))
            t_end = time.monotonic() + args.window
            window = []
            while time.monotonic() < t_end:
                time.sleep(min(0.9, args.window))  # the daemon's ring holds the last 1024 cycles
                window.append(robot.connection.request("period_statistics"))
            loaded.append(np.array([w["lateness_p99_s"] for w in window]))
            compute.append(np.array([w["compute_p99_s"] for w in window]))
            overruns.append(window[-1]["overruns"])
        stats_end = robot.connection.request("period_statistics")
        elapsed = time.monotonic() - load_t0
        frames = sum(load.frames)
        sent = load.sent
        load.finish()
        arm.disable(5.0)
        robot.close()
    finally:
        for p in (daemon, echo):
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()

    bare_all = np.concatenate(bare)
    loaded_p99 = float(np.median(np.concatenate(loaded)))
    bare_p99 = pct(bare_all, 99)
    print(f"loop @1kHz under load (8x measured_js@1kHz subscribers, {'servo_cp' if args.cartesian else 'servo_jp'}@500Hz; {frames} frames, "
          f"{sent} {'servo_cp' if args.cartesian else 'servo_jp'} sent; overruns so far {overruns[-1]}):")
    print(f"  daemon lateness p99 (median of ~1 s windows): {loaded_p99 * 1e3:.3f} ms")
    print(f"  bare SCHED_FIFO loop lateness p50 {pct(bare_all, 50) * 1e3:.3f} ms, p99 {bare_p99 * 1e3:.3f} ms")
    cyc = stats_end["cycles"] - stats_start["cycles"]
    ovr = stats_end["overruns"] - stats_start["overruns"]
    print(f"  daemon compute p99 (median of windows): {float(np.median(np.concatenate(compute))) * 1e3:.3f} ms; "
          f"overruns {ovr} of {cyc} cycles ({100.0 * ovr / max(cyc, 1):.2f} %)")
    print(f"  subscriber frames received: {frames / (8 * elapsed):.0f} Hz per subscriber (asked 1000)")
    print(f"  ratio daemon p99 / bare p99: {loaded_p99 / bare_p99:.2f}  (target <= 2)")
    print("measured_js round trip:")
    print(f"  daemon p50 {pct(rtt_d, 50) * 1e6:.0f} us, p99 {pct(rtt_d, 99) * 1e6:.0f} us")
    print(f"  bare asyncio echo p50 {pct(rtt_e, 50) * 1e6:.0f} us, p99 {pct(rtt_e, 99) * 1e6:.0f} us")
    print(f"  ratio p50 daemon / echo: {pct(rtt_d, 50) / pct(rtt_e, 50):.2f}  (target <= 2)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Daemon performance on the simulated SO-101, each figure beside a baseline measured in the same run.

1. Loop lateness and overruns: the daemon's control loop at 1 kHz on the simulated bus while 8
   clients stream ``measured_js`` at 1 kHz and one client sends ``servo_jp`` at 500 Hz, against
   a bare SCHED_FIFO sleep loop at 1 kHz (lateness), and a bare SCHED_FIFO loop doing the same
   read + write round trip with the servo SDK alone (issue 23, item 2): each cycle one
   GroupSyncRead of the block the backend reads and one GroupSyncWrite of Goal_Position, to a
   simulator of its own of the same kind, profile and priority as the daemon's, counting overruns
   as the daemon's loop does (the cycle ended after the next one's start). Windows alternate
   (baselines, daemon, baselines, daemon, ...), all under the same load.
2. Socket round trip: ``measured_js`` request -> reply, against a bare asyncio Unix-socket echo
   server answering the same request line, alternating, same client code.

Prints medians / p99 and the ratios (docs/architecture.md, "Performance targets": loop p99 within
2x of the bare loop's, socket p50 within 2x of the echo's). Figures only; nothing is asserted. Usage:

    python bench/bench_daemon.py [--rounds 3] [--window 3] [--old /tmp/old]
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
import yaml

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


BARE_BUS = """
import json, os, sys, time, yaml
from scservo_sdk import GroupSyncRead, GroupSyncWrite, PacketHandler, PortHandler
from crtk_bridge.backends.feetech import tables
profile, link, rate, seconds, prio = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), int(sys.argv[5])
note = ""
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
except OSError as exc:
    note = f"SCHED_FIFO refused ({exc.strerror}): the bare loop ran at SCHED_OTHER"
data = yaml.safe_load(open(profile))
ids = [int(j["id"]) for j in data["joints"]]
port = PortHandler(link)
port.openPort()
port.setBaudRate(int(data["backend"]["baudrate"]))
ph = PacketHandler(0)
gsr = GroupSyncRead(port, ph, tables.PRESENT_BLOCK_START, tables.PRESENT_BLOCK_LEN)
gsw = GroupSyncWrite(port, ph, tables.STS_CONTROL_TABLE["Goal_Position"].address, 2)
for sid in ids:
    gsr.addParam(sid)
    gsw.addParam(sid, [0, 8])
period = 1.0 / rate
clock = time.perf_counter
late, overruns, cycles, failed = [], 0, 0, 0
next_t = clock() + period
end = clock() + seconds
while clock() < end:
    d = next_t - clock()
    if d > 0:
        time.sleep(d)
    t0 = clock()
    late.append(t0 - next_t)
    if gsr.txRxPacket() != 0:
        failed += 1
    for sid in ids:
        p = gsr.getData(sid, tables.PRESENT_BLOCK_START, 2)
        gsw.changeParam(sid, [p & 0xFF, p >> 8])
    gsw.txPacket()
    cycles += 1
    next_t += period
    if clock() > next_t:  # as the daemon's loop counts an overrun, and skips ahead
        overruns += 1
        next_t += (int((clock() - next_t) / period) + 1) * period
print(json.dumps({"late": late, "overruns": overruns, "cycles": cycles, "failed": failed, "note": note}))
"""


class BareBus:
    """A feetech simulator of its own (the daemon's profile, at the priority the daemon gives its
    own: daemon.SIM_NICE where permitted) for the bare bus loop."""

    def __init__(self, profile: Path, tmp: Path):
        from crtk_bridge.daemon import SIM_NICE

        self.profile = profile
        self.link = tmp / "bare.tty"

        def nice() -> None:
            try:
                os.setpriority(os.PRIO_PROCESS, 0, SIM_NICE)
            except OSError:
                pass
        self.sim = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", "feetech", "--profile", str(profile),
                                     "--link", str(self.link)], cwd=ROOT, stdout=subprocess.PIPE,
                                    stderr=subprocess.DEVNULL, text=True, preexec_fn=nice)
        line = self.sim.stdout.readline()
        if "ready" not in line:
            self.sim.kill()
            raise RuntimeError(f"the bare loop's simulator did not start: {line!r}")

    def window(self, rate_hz: float, seconds: float, priority: int) -> dict:
        out = subprocess.run([sys.executable, "-c", BARE_BUS, str(self.profile), str(self.link), str(rate_hz),
                              str(seconds), str(priority)], capture_output=True, text=True, check=True, cwd=ROOT).stdout
        return json.loads(out)

    def close(self) -> None:
        self.sim.terminate()
        try:
            self.sim.wait(10)
        except subprocess.TimeoutExpired:
            self.sim.kill()


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
    ap.add_argument("--old", type=Path, help="another checkout, measured after this one the same way (its own "
                                             "baselines in its own windows)")
    args = ap.parse_args()
    print(f"load average (1 min) at start {os.getloadavg()[0]:.2f}")
    for name, tree in [("this checkout", ROOT)] + ([(f"OLD {args.old}", args.old.resolve())] if args.old else []):
        print(f"== {name}")
        run(tree, args)
    print(f"load average (1 min) at end {os.getloadavg()[0]:.2f} (this script's own processes included)")
    return 0


def cpu_s(pid: int) -> float:
    """utime + stime of process ``pid`` (its own threads, not its children), in seconds."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(tree: Path, args) -> None:
    tmp = Path(tempfile.mkdtemp(prefix="crtk-bench-"))
    daemon, sock = sim_daemon.start(1000, tmp, tree=tree)
    echo_path = str(tmp / "echo.sock")
    echo = echo_server(echo_path)
    profile = tmp / "so101-1000hz.yaml"  # sim_daemon's: the daemon's own profile at 1 kHz
    priority = int((yaml.safe_load(profile.read_text()).get("loop") or {}).get("realtime_priority", 80))
    bus = BareBus(profile, tmp)
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
        bus_runs, daemon_ovr, daemon_cyc, front_cpu = [], 0, 0, []
        stats_start = robot.connection.request("period_statistics")
        load = Load(str(sock), start, cartesian=args.cartesian)
        load.start(robot)
        load_t0 = time.monotonic()
        time.sleep(0.5)  # let subscriptions start
        for _ in range(args.rounds):
            bare.append(bare_loop(1000, args.window))
            bus_runs.append(bus.window(1000, args.window, priority))
            t_end = time.monotonic() + args.window
            window = []
            first = robot.connection.request("period_statistics")
            cpu0, t0 = cpu_s(daemon.pid), time.monotonic()
            while time.monotonic() < t_end:
                time.sleep(min(0.9, args.window))  # the daemon's ring holds the last 1024 cycles
                window.append(robot.connection.request("period_statistics"))
            front_cpu.append((cpu_s(daemon.pid) - cpu0) / (time.monotonic() - t0))
            daemon_ovr += window[-1]["overruns"] - first["overruns"]
            daemon_cyc += window[-1]["cycles"] - first["cycles"]
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
        bus.close()
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
    print(f"  subscriber frames received: {frames / (8 * elapsed):.0f} Hz per subscriber (asked 1000); "
          f"front process CPU {100 * float(np.median(front_cpu)):.0f} % of a core")
    print(f"  ratio daemon p99 / bare p99: {loaded_p99 / bare_p99:.2f}  (target <= 2)")
    bus_late = np.concatenate([np.array(r["late"]) for r in bus_runs])
    bus_ovr, bus_cyc = sum(r["overruns"] for r in bus_runs), sum(r["cycles"] for r in bus_runs)
    notes = {r["note"] for r in bus_runs if r["note"]}
    d_rate, b_rate = daemon_ovr / max(daemon_cyc, 1), bus_ovr / max(bus_cyc, 1)
    print(f"  bare SCHED_FIFO bus loop (servo SDK alone, sync read + sync write to its own simulator, 1 kHz): "
          f"overruns {bus_ovr} of {bus_cyc} cycles ({100 * b_rate:.2f} %), lateness p99 {pct(bus_late, 99) * 1e3:.3f} ms, "
          f"failed reads {sum(r['failed'] for r in bus_runs)}" + (f"; NOTE: {'; '.join(notes)}" if notes else ""))
    print(f"  daemon in the same windows: overruns {daemon_ovr} of {daemon_cyc} cycles ({100 * d_rate:.2f} %)")
    print(f"  ratio overruns per cycle daemon / bare bus loop: "
          f"{d_rate / b_rate if b_rate else float('inf') if d_rate else 1.0:.2f}  (target <= 1.5)")
    print("measured_js round trip:")
    print(f"  daemon p50 {pct(rtt_d, 50) * 1e6:.0f} us, p99 {pct(rtt_d, 99) * 1e6:.0f} us")
    print(f"  bare asyncio echo p50 {pct(rtt_e, 50) * 1e6:.0f} us, p99 {pct(rtt_e, 99) * 1e6:.0f} us")
    print(f"  ratio p50 daemon / echo: {pct(rtt_d, 50) / pct(rtt_e, 50):.2f}  (target <= 2)")


if __name__ == "__main__":
    sys.exit(main())

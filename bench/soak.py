#!/usr/bin/env python3
"""Soak: the daemon at 1 kHz on the simulated SO-101 for N minutes under client churn.

While it runs, clients connect, stream and disconnect in a loop:
- ``--subscribers`` threads, each: connect, subscribe to ``measured_js`` (and sometimes
  ``setpoint_js`` / ``operating_state``) at 100-1000 Hz, read for 0.5-3 s, a few queries,
  disconnect (sometimes without unsubscribing, sometimes by closing the socket mid-stream);
- one controller thread: connect, enable (if needed), stream ``servo_jp`` at 500 Hz for 1-4 s
  (a slow sine on shoulder_pan), sometimes a ``move_jr`` to finish, disconnect (the daemon holds on
  client loss); every 10th round it disables before leaving, so enable runs again.

Once a minute it prints, for the front (daemon) process, the control process and the simulator:
RSS (kB) and open file descriptors; and for the loop: cycles and overruns in that minute, and the
lateness p99 (the daemon keeps the last 1024 cycles, so it is sampled every ~0.9 s; the minute's
median and max of those p99s are printed), plus clients served, frames and servo_jp sent, client
request errors, and the robot's FAULTs (error events, with their codes: at 1 kHz on a loaded host,
a simulator that misses ``safety.bus_errors_max`` cycles in a row is a ``bus_timeout``; the
controller thread enables again). The goal is no growth: the last line compares the last minute
with the first. Figures only, nothing asserted.

    python bench/soak.py --minutes 10 [--subscribers 6]
"""

from __future__ import annotations

import argparse
import json
import os
import random
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
from crtk_bridge.client import CommandError, connect  # noqa: E402


def children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def cmdline(pid: int) -> str:
    return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")


class Churn:
    """Clients connecting, streaming and disconnecting until ``stop`` is set."""

    def __init__(self, path: str, subscribers: int, seed: int):
        self.path = path
        self.stop = threading.Event()
        self.lock = threading.Lock()
        self.sessions = 0
        self.frames = 0
        self.servo_sent = 0
        self.errors: list[str] = []  # the first ones, for the report
        self.error_count = 0
        self.threads = [threading.Thread(target=self._subscriber, args=(random.Random(seed + i),), daemon=True)
                        for i in range(subscribers)]
        self.threads.append(threading.Thread(target=self._controller, args=(random.Random(seed - 1),), daemon=True))

    def _count(self, sessions=0, frames=0, sent=0) -> None:
        with self.lock:
            self.sessions += sessions
            self.frames += frames
            self.servo_sent += sent

    def _error(self, what: str) -> None:
        with self.lock:
            self.error_count += 1
            if len(self.errors) < 20:
                self.errors.append(what)

    def _subscriber(self, rnd: random.Random) -> None:
        while not self.stop.is_set():
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                s.connect(self.path)
                s.settimeout(2.0)
                topics = ["measured_js"] + rnd.sample(["setpoint_js", "operating_state", "period_statistics"], rnd.randint(0, 2))
                for i, topic in enumerate(topics):
                    ns = None if topic in ("operating_state", "period_statistics") else "so101"
                    req = {"id": i + 1, "cmd": "subscribe", "ns": ns,
                           "data": {"topic": topic, "rate_hz": rnd.choice([100, 500, 1000])}}
                    s.sendall((json.dumps(req) + "\n").encode())
                f = s.makefile("rb")
                end = time.monotonic() + rnd.uniform(0.5, 3.0)
                n = 0
                while time.monotonic() < end and not self.stop.is_set():
                    line = f.readline()
                    if not line:
                        self._error("subscriber: connection closed by the daemon")
                        break
                    if line.startswith(b'{"topic"'):
                        n += 1
                    elif b'"ok":false' in line:
                        self._error(f"subscriber: {line[:200]!r}")
                if rnd.random() < 0.5:  # a query or two before leaving, on the same session
                    s.sendall(b'{"id":99,"cmd":"measured_js","ns":"so101"}\n')
                self._count(sessions=1, frames=n)
            except OSError as exc:
                self._error(f"subscriber: {exc}")
            finally:
                if rnd.random() < 0.3:
                    try:
                        s.shutdown(socket.SHUT_RDWR)  # abrupt
                    except OSError:
                        pass
                s.close()

    def _controller(self, rnd: random.Random) -> None:
        k = 0
        rounds = 0
        while not self.stop.is_set():
            rounds += 1
            try:
                robot = connect(socket=self.path)
            except Exception as exc:
                self._error(f"controller connect: {exc}")
                time.sleep(0.5)
                continue
            try:
                arm = robot.device("so101")
                if not arm.is_enabled():
                    arm.enable(5.0)
                start = arm.setpoint_jp()[0] if arm.setpoint_jp()[1] else arm.measured_jp()[0]
                centre = start.copy()
                centre[0] = 0.0
                period = 1 / 500
                end = time.monotonic() + rnd.uniform(1.0, 4.0)
                nxt = time.perf_counter()
                sent = 0
                # ease from where the arm is into a slow sine around 0 (within velocity_max)
                phase0 = k * period
                while time.monotonic() < end and not self.stop.is_set():
                    k += 1
                    goal = centre.copy()
                    goal[0] = 0.3 * np.sin(k * period)
                    blend = min(1.0, (k * period - phase0) / 0.5)
                    goal[0] = (1 - blend) * start[0] + blend * goal[0]
                    try:
                        arm.servo_jp(goal)
                        sent += 1
                    except CommandError as exc:
                        self._error(f"servo_jp: {exc}")
                    nxt += period
                    d = nxt - time.perf_counter()
                    if d > 0:
                        time.sleep(d)
                if rnd.random() < 0.3:
                    arm.move_jr([0.02, 0, 0, 0, 0]).wait(timeout=5.0)
                if rounds % 10 == 0:
                    arm.disable(5.0)
                self._count(sessions=1, sent=sent)
            except Exception as exc:
                self._error(f"controller: {exc!r}")
            finally:
                robot.close()

    def start(self) -> None:
        for t in self.threads:
            t.start()

    def finish(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(10)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0, help="how long to soak (default 10)")
    ap.add_argument("--subscribers", type=int, default=6, help="churning subscriber threads (default 6)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="crtk-soak-"))
    daemon, sock = sim_daemon.start(1000, tmp)
    churn = None
    try:
        kids = children(daemon.pid)
        procs = {"front": daemon.pid}
        for pid in kids:
            procs["sim" if "crtk_bridge.sim" in cmdline(pid) else "control"] = pid
        print(f"soak: {args.minutes:g} min at 1 kHz, {args.subscribers} churning subscribers + 1 servo_jp@500Hz "
              f"controller; pids {procs}", flush=True)
        watch = connect(socket=str(sock))
        churn = Churn(str(sock), args.subscribers, args.seed)
        churn.start()
        names = list(procs)
        print("min  " + "  ".join(f"{n}_rss_kB {n}_fds" for n in names)
              + "  cycles overruns late_p99_med_ms late_p99_max_ms sessions frames servo_jp errors faults", flush=True)
        first = last = None
        prev = watch.period_statistics()
        prev_counts = (0, 0, 0, 0)
        prev_events = watch.connection.event_count
        t_end = time.monotonic() + args.minutes * 60
        minute = 0
        while time.monotonic() < t_end:
            minute += 1
            p99s = []
            m_end = min(time.monotonic() + 60, t_end)
            while time.monotonic() < m_end:
                time.sleep(0.9)  # the daemon's ring holds the last 1024 cycles (~1 s at 1 kHz)
                st = watch.period_statistics()
                if "lateness_p99_s" in st:
                    p99s.append(st["lateness_p99_s"])
            st = watch.period_statistics()
            mem = {n: (rss_kb(pid), fds(pid)) for n, pid in procs.items()}
            with churn.lock:
                counts = (churn.sessions, churn.frames, churn.servo_sent, churn.error_count)
            d = [c - p for c, p in zip(counts, prev_counts)]
            faults = [e.data.get("code") for e in watch.connection.events_since(prev_events) if e.kind == "error"]
            prev_events = watch.connection.event_count
            row = {"mem": mem, "cycles": st["cycles"] - prev["cycles"], "overruns": st["overruns"] - prev["overruns"],
                   "p99_med": float(np.median(p99s)) * 1e3, "p99_max": float(np.max(p99s)) * 1e3, "d": d}
            print(f"{minute:3d}  " + "  ".join(f"{mem[n][0]:>8d} {mem[n][1]:>4d}" for n in names)
                  + f"  {row['cycles']:6d} {row['overruns']:8d} {row['p99_med']:14.3f} {row['p99_max']:14.3f}"
                  + f" {d[0]:8d} {d[1]:6d} {d[2]:9d} {d[3]:6d} {len(faults):6d}"
                  + (f"  ({', '.join(sorted(set(faults)))})" if faults else ""), flush=True)
            first = first or row
            last = row
            prev, prev_counts = st, counts
        churn.finish()
        errors, error_count = list(churn.errors), churn.error_count
        watch.close()
        if first and last:
            growth = "  ".join(f"{n}: RSS {last['mem'][n][0] - first['mem'][n][0]:+d} kB, fds {last['mem'][n][1] - first['mem'][n][1]:+d}"
                               for n in names)
            print(f"growth, last minute vs first: {growth}")
        if errors:
            print(f"{error_count} client-side errors (commands refused while the robot was in FAULT count here); "
                  "first ones:")
            for e in errors[:5]:
                print("  " + e)
        print(f"daemon alive at the end: {daemon.poll() is None}")
    finally:
        if churn is not None:
            churn.stop.set()
        daemon.send_signal(signal.SIGTERM)
        try:
            daemon.wait(15)
        except subprocess.TimeoutExpired:
            daemon.kill()
    return 0


if __name__ == "__main__":
    sys.exit(main())

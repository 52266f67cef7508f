#!/usr/bin/env python3
"""The ROS 2 graph over Zenoh on the simulated SO-101 at 1 kHz, each figure beside a baseline
measured in the same run (docs/architecture.md, "Performance targets": Zenoh ``measured_js``
latency within 2x of a bare Zenoh pub/sub of the same bytes; the loop's lateness unchanged with
the transport publishing at 1 kHz).

1. Latency of ``measured_js`` over Zenoh on loopback: the daemon publishes at the loop rate
   (1 kHz); a subscriber in this process takes (receive time - the attachment's source timestamp)
   per sample, and (receive time - the header stamp, the bus read) for the data's age. Baseline: a
   bare Zenoh publisher in its own process putting the same bytes at 1 kHz, each with its send
   time, to the same kind of subscriber. Windows alternate.
2. The control loop's lateness and overruns (``period_statistics``, ~1 s windows) with the daemon
   publishing at 1 kHz every ROS topic to a subscriber of all of them while ``--clients`` remote
   clients (eclipse-zenoh alone, as docs/zenoh.md's key layout) stream measured_js, setpoint_js,
   goal_js and measured_cp at 1 kHz each, then only measured_js to a ROS subscriber, against the
   same daemon without the Zenoh transport. Daemons alternate, enabled and idle. ``--old DIR``
   also runs another checkout (``git worktree add /tmp/old <commit>``) with every topic and without
   Zenoh, in the same rounds: a before / after in one run.

Figures only; nothing is asserted. Usage:

    python bench/bench_zenoh.py [--rounds 3] [--window 3] [--clients 4] [--old /tmp/old]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import sim_daemon  # noqa: E402  (bench/, beside this script)
from crtk_bridge.client import connect  # noqa: E402
from crtk_bridge.transport.ros import types as T  # noqa: E402

MEASURED_JS = "0/so101/measured_js/**"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def session(connect_to: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([connect_to]))
    return zenoh.open(conf)


class Receiver:
    """Collects (receive - source timestamp) and (receive - header stamp) of every sample."""

    def __init__(self, s: zenoh.Session, key: str, decode: bool = True):
        self.lock = threading.Lock()
        self.transit: list[int] = []
        self.age: list[float] = []
        self.payload: bytes | None = None
        self.decode = decode
        self.on = False
        self.sub = s.declare_subscriber(key, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        now = time.time_ns()
        if not self.on:
            return
        att = sample.attachment.to_bytes()
        _, ts = struct.unpack_from("<qq", att)
        payload = sample.payload.to_bytes()
        with self.lock:
            self.transit.append(now - ts)
            if self.decode:
                msg = T.decode(payload, T.JOINT_STATE)
                self.age.append(now * 1e-9 - T.seconds(msg.header.stamp))
                self.payload = payload

    def window(self, seconds: float) -> tuple[np.ndarray, np.ndarray]:
        with self.lock:
            self.transit.clear()
            self.age.clear()
        self.on = True
        time.sleep(seconds)
        self.on = False
        with self.lock:
            return np.array(self.transit) * 1e-9, np.array(self.age)


def bare_publisher(endpoint: str, payload: bytes, rate_hz: float) -> subprocess.Popen:
    """A plain Zenoh publisher of ``payload`` at ``rate_hz`` (attachment: seq, send time ns),
    listening on ``endpoint``, in its own process as the daemon's front is."""
    code = f"""
import json, struct, time, zenoh
conf = zenoh.Config()
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("listen/endpoints", json.dumps([{endpoint!r}]))
s = zenoh.open(conf)
pub = s.declare_publisher("0/bare/measured_js", congestion_control=zenoh.CongestionControl.DROP)
payload = bytes.fromhex({payload.hex()!r})
gid = bytes(16)
period = 1.0 / {rate_hz}
nxt = time.perf_counter()
seq = 0
while True:
    seq += 1
    pub.put(payload, attachment=struct.pack("<qqB16s", seq, time.time_ns(), 16, gid))
    nxt += period
    d = nxt - time.perf_counter()
    if d > 0:
        time.sleep(d)
    else:
        nxt = time.perf_counter()
"""
    return subprocess.Popen([sys.executable, "-c", code])


def stop(p: subprocess.Popen) -> None:
    p.send_signal(signal.SIGTERM)
    try:
        p.wait(15)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()


def loop_window(sock: Path, seconds: float) -> tuple[list[float], list[float], int, int]:
    """Enable, then sample period_statistics every ~0.9 s (the ring holds 1024 cycles) for
    ``seconds``: (lateness p99s, lateness p50s, overruns, cycles) of the window."""
    robot = connect(socket=str(sock))
    try:
        arm = robot.device("so101")
        assert arm.enable(5.0), "enable failed"
        time.sleep(1.1)  # the ring now holds only enabled cycles
        first = robot.connection.request("period_statistics")
        p99, p50 = [], []
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            time.sleep(0.9)
            st = robot.connection.request("period_statistics")
            p99.append(st["lateness_p99_s"])
            p50.append(st["lateness_p50_s"])
        last = robot.connection.request("period_statistics")
        arm.disable(5.0)
        return p99, p50, last["overruns"] - first["overruns"], last["cycles"] - first["cycles"]
    finally:
        robot.close()


REMOTE_TOPICS = ("measured_js", "setpoint_js", "goal_js", "measured_cp")


class RemoteClients:
    """``n`` remote clients of the daemon's tunnel spoken with eclipse-zenoh alone (docs/zenoh.md's
    key layout), each streaming REMOTE_TOPICS at 1 kHz; counts the frame lines they receive."""

    def __init__(self, s: zenoh.Session, n: int):
        import uuid

        self.lines = 0
        self.lock = threading.Lock()
        self.entities = []
        for _ in range(n):
            cid = uuid.uuid4().hex
            self.entities.append(s.declare_subscriber(f"crtk_bridge/so101/out/{cid}", self._on))
            self.entities.append(s.liveliness().declare_token(f"crtk_bridge/so101/client/{cid}"))
            time.sleep(0.3)  # the daemon opens the session on the token
            s.put(f"crtk_bridge/so101/in/{cid}", b"".join(
                b'{"id": %d, "cmd": "subscribe", "ns": "so101", "data": {"topic": "%s", "rate_hz": 1000}}\n'
                % (i, t.encode()) for i, t in enumerate(REMOTE_TOPICS)))

    def _on(self, sample: zenoh.Sample) -> None:
        n = sample.payload.to_bytes().count(b'{"topic"')
        with self.lock:
            self.lines += n

    def close(self) -> None:
        for e in reversed(self.entities):
            e.undeclare()


def cpu_s(pid: int) -> float:
    """utime + stime of process ``pid`` (its own threads, not its children), in seconds."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def loop_round(tmp: Path, zen: str | None, window: float, tree: Path = ROOT, clients: int = 0) -> tuple:
    """One daemon of checkout ``tree`` (without the Zenoh transport, or with it, a subscriber of the
    ROS key ``zen`` and ``clients`` remote clients) and one loop_window: (p99s, p50s, overruns,
    cycles, ROS samples received, remote frames received, frames_dropped)."""
    extra = ["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"] if zen else []
    d, sock = sim_daemon.start(1000, tmp, args=extra, tree=tree)
    listener = remote = None
    got = [0]
    try:
        if zen:  # a subscriber of every topic, so the samples really leave the process
            listener = session(extra[1])
            listener.declare_subscriber(zen, lambda s: got.__setitem__(0, got[0] + 1))
            if clients:
                remote = RemoteClients(listener, clients)
        rx0, t_rx = (got[0], remote.lines if remote else 0), time.monotonic()
        time.sleep(0.5)  # the streams run
        cpu0, t0 = cpu_s(d.pid), time.monotonic()
        p99, p50, ovr, cyc = loop_window(sock, window)
        front = (cpu_s(d.pid) - cpu0) / (time.monotonic() - t0)
        span = time.monotonic() - t_rx
        ros_rate, remote_rate = (got[0] - rx0[0]) / span, ((remote.lines if remote else 0) - rx0[1]) / span
        robot = connect(socket=str(sock))
        dropped = robot.connection.request("period_statistics").get("frames_dropped", float("nan"))
        robot.close()
        return p99, p50, ovr, cyc, ros_rate, remote_rate, dropped, front
    finally:
        if remote is not None:
            remote.close()
        if listener is not None:
            listener.close()
        stop(d)


def ms(values) -> str:
    return f"{float(np.median(values)) * 1e3:.3f} ms"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--window", type=float, default=3.0, help="seconds per measurement window")
    ap.add_argument("--clients", type=int, default=4, help="remote clients streaming 4 topics at 1 kHz each")
    ap.add_argument("--old", type=Path, help="another checkout: every topic and without Zenoh, same rounds")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="crtk-bench-zenoh-"))
    load_before = os.getloadavg()[0]  # the host is shared: figures from a loaded one say little

    # -- 1. latency: daemon's measured_js vs a bare publisher of the same bytes, alternating --
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    daemon, sock = sim_daemon.start(1000, tmp, args=["--zenoh-listen", endpoint])
    bare_endpoint = f"tcp/127.0.0.1:{free_port()}"
    ros = session(endpoint)
    rx = Receiver(ros, MEASURED_JS)
    bare = None
    try:
        rx.window(1.0)  # warm up; captures a payload for the bare publisher
        assert rx.payload is not None, "no measured_js received from the daemon"
        bare = bare_publisher(bare_endpoint, rx.payload, 1000)
        bare_s = session(bare_endpoint)
        bare_rx = Receiver(bare_s, "0/bare/measured_js", decode=False)
        bare_rx.window(1.0)
        d_transit, d_age, b_transit, rates = [], [], [], []
        for _ in range(args.rounds):
            tr, age = rx.window(args.window)
            d_transit.append(tr)
            d_age.append(age)
            rates.append(len(tr) / args.window)
            b_transit.append(bare_rx.window(args.window)[0])
        bare_s.close()
    finally:
        ros.close()
        if bare is not None:
            stop(bare)
        stop(daemon)
    d_transit, d_age, b_transit = (np.concatenate(x) for x in (d_transit, d_age, b_transit))

    # -- 2. loop lateness with / without the Zenoh transport, daemons alternating --
    # every topic subscribed (the worst case: every ROS topic, and remote clients streaming), only
    # measured_js (a typical client), or no transport
    every = f"every topic + {args.clients} remote clients"
    variants = {f"with Zenoh, {every}": ("0/**", ROOT, args.clients),
                "with Zenoh, measured_js subscribed": (MEASURED_JS, ROOT, 0), "without Zenoh": (None, ROOT, 0)}
    if args.old:
        variants[f"OLD with Zenoh, {every}"] = ("0/**", args.old.resolve(), args.clients)
        variants["OLD without Zenoh"] = (None, args.old.resolve(), 0)
    rows: dict[str, list] = {name: [] for name in variants}
    for r in range(args.rounds):
        for name, (key, tree, clients) in variants.items():
            for attempt in range(3):  # a loaded host can starve the 1 kHz simulator at start-up
                try:
                    rows[name].append(loop_round(tmp, key, args.window, tree, clients))
                    break
                except Exception as exc:  # noqa: BLE001 (a starved simulator, a refused transition)
                    print(f"  (a '{name}' window failed, retrying: {exc})", flush=True)
    def col(rows, i):
        return [v for row in rows for v in (row[i] if isinstance(row[i], list) else [row[i]])]

    print("measured_js over Zenoh on loopback (1 kHz loop; latency = receive - source timestamp):")
    print(f"  daemon:    p50 {np.percentile(d_transit, 50) * 1e6:.0f} us, p99 {np.percentile(d_transit, 99) * 1e6:.0f} us "
          f"({len(d_transit)} samples, {np.median(rates):.0f} Hz received)")
    print(f"  bare pub:  p50 {np.percentile(b_transit, 50) * 1e6:.0f} us, p99 {np.percentile(b_transit, 99) * 1e6:.0f} us "
          f"({len(b_transit)} samples)")
    print(f"  ratio p50 daemon / bare: {np.percentile(d_transit, 50) / np.percentile(b_transit, 50):.2f}  (target <= 2)")
    print(f"  data age at the subscriber (receive - header stamp = bus read): p50 "
          f"{np.percentile(d_age, 50) * 1e3:.2f} ms, p99 {np.percentile(d_age, 99) * 1e3:.2f} ms")
    print("control loop lateness @1 kHz, enabled, idle (median of ~1 s windows' p50 / p99):")
    for name, rs in rows.items():
        ovr, cyc = sum(col(rs, 2)), sum(col(rs, 3))
        extra = f"; {float(np.median(col(rs, 4))):.0f} ROS samples/s" if variants[name][0] else ""
        if variants[name][2]:
            extra += (f", {float(np.median(col(rs, 5))):.0f} remote frames/s (asked {1000 * len(REMOTE_TOPICS) * args.clients}),"
                      f" frames_dropped {sum(col(rs, 6))}")
        print(f"  {name:50s}: p50 {ms(col(rs, 1))}, p99 {ms(col(rs, 0))}; overruns {ovr} of {cyc} cycles; "
              f"front process CPU {100 * float(np.median(col(rs, 7))):.0f} % of a core{extra}")
    for tag in ("", "OLD ") if args.old else ("",):
        base_rows = rows[f"{tag}without Zenoh"]
        base = float(np.median(col(base_rows, 0)))
        base_ovr = sum(col(base_rows, 2)) / max(1, sum(col(base_rows, 3)))
        for name in [n for n in variants if n.startswith(tag + "with Zenoh")]:
            ovr = sum(col(rows[name], 2)) / max(1, sum(col(rows[name], 3)))
            print(f"  ratio p99 {name} / {tag}without: {float(np.median(col(rows[name], 0))) / base:.2f}  "
                  f"(target <= 1.2); overruns per cycle: {ovr / base_ovr if base_ovr else float('nan'):.2f}x")
    print(f"load average (1 min) at start {load_before:.2f}, at end {os.getloadavg()[0]:.2f} (this script's "
          "own processes included)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Does IK hold up the front process? ``measured_js`` round trips from one session while another
session keeps the daemon busy with cold IK (``inverse_kinematics`` of a pose a 5-joint arm cannot
reach, solved from zero with restarts, as a ``move_cp`` would), against the same round trips with
nobody solving IK, windows alternating, same run.

The daemon runs IK on a worker thread per namespace (server/cartesian.py), so the event loop keeps
answering; what is left is the GIL the worker holds between its numpy / pinocchio calls. Prints
p50 / p99 / max of the round trip in both conditions and the ratios, and the IK solve time seen by
its client. Figures only; nothing is asserted. Usage:

    python bench/bench_ik_front.py [--rounds 3] [--window 2]
"""

from __future__ import annotations

import argparse
import json
import signal
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import sim_daemon  # noqa: E402  (bench/, beside this script)
from crtk_bridge.core.kinematics import Kinematics, matrix_from_quaternion, quaternion_from_matrix  # noqa: E402

ARM = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]


def hard_target() -> dict:
    kin = Kinematics(ROOT / "profiles" / "urdf" / "so101.urdf", "base_link", "gripper_frame_link", ARM)
    p, quat = kin.fk(np.array([0.3, 0.4, -0.3, 0.2, 0.1]))
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # sideways: out of reach
    return {"position": p.tolist(), "orientation": quaternion_from_matrix(Rz @ matrix_from_quaternion(quat)).tolist(),
            "jp": [0.0] * 5}


def session(path: str):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(path)
    return s, s.makefile("rb")


def ask(s, f, line: bytes) -> None:
    s.sendall(line)
    while b'"id"' not in f.readline():  # skip pushed events
        pass


def round_trips(path: str, seconds: float) -> np.ndarray:
    s, f = session(path)
    line = b'{"id":1,"cmd":"measured_js","ns":"so101"}\n'
    out = []
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        t0 = time.perf_counter()
        ask(s, f, line)
        out.append(time.perf_counter() - t0)
    s.close()
    return np.array(out)


class ColdIk(threading.Thread):
    """Back-to-back cold IK requests from another session until stopped."""

    def __init__(self, path: str):
        super().__init__(daemon=True)
        self.path = path
        self.stop = threading.Event()
        self.times: list[float] = []
        self.line = json.dumps({"id": 2, "cmd": "inverse_kinematics", "ns": "so101", "data": hard_target()}).encode() + b"\n"

    def run(self) -> None:
        s, f = session(self.path)
        while not self.stop.is_set():
            t0 = time.perf_counter()
            ask(s, f, self.line)
            self.times.append(time.perf_counter() - t0)
        s.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--window", type=float, default=2.0, help="seconds per window")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="crtk-bench-") as tmp:
        daemon, sock = sim_daemon.start(200.0, Path(tmp))
        try:
            idle, busy, ik = [], [], []
            round_trips(str(sock), 0.3)  # warm up
            for _ in range(args.rounds):
                idle.append(round_trips(str(sock), args.window))
                load = ColdIk(str(sock))
                load.start()
                time.sleep(0.1)
                busy.append(round_trips(str(sock), args.window))
                load.stop.set()
                load.join(10)
                ik.extend(load.times)
        finally:
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(20)
    a, b, t = np.concatenate(idle), np.concatenate(busy), np.array(ik)

    def fig(x: np.ndarray) -> str:
        return (f"p50 {np.median(x) * 1e3:7.3f} ms  p99 {np.percentile(x, 99) * 1e3:7.3f} ms  "
                f"max {x.max() * 1e3:7.2f} ms  ({len(x)} round trips)")

    print(f"measured_js round trip, another session idle:        {fig(a)}")
    print(f"measured_js round trip, another session solving IK:  {fig(b)}")
    print(f"ratio busy / idle: p50 {np.median(b) / np.median(a):.2f}x, p99 "
          f"{np.percentile(b, 99) / np.percentile(a, 99):.2f}x")
    print(f"cold IK as its client sees it: p50 {np.median(t) * 1e3:.1f} ms, max {t.max() * 1e3:.1f} ms "
          f"({len(t)} solves); a round trip blocked behind one would take that long")
    return 0


if __name__ == "__main__":
    sys.exit(main())

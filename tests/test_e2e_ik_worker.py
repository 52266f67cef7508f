"""IK never blocks the front's event loop (issue 8 item 7): while one session's cold IK solves
run, another session's measured_js queries are answered."""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np

from crtk_bridge.core.kinematics import Kinematics, matrix_from_quaternion, quaternion_from_matrix
from crtk_bridge.profile import load_profile

from .conftest import SO101, only_on

K = 4  # pipelined IK requests: ~40 ms each here, solved one after the other on the worker


def hard_target() -> dict:
    """A reachable position with an orientation a 5-joint arm cannot reach (turned 90 degrees
    about the base z axis): IK runs every restart to the end and fails, cold, from zero."""
    ns = load_profile(SO101).namespace("so101")
    kin = Kinematics(ns.kinematics.urdf, ns.kinematics.base_frame, ns.kinematics.tip_frame, list(ns.joints))
    p, quat = kin.fk(np.array([0.3, 0.4, -0.3, 0.2, 0.1]))
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    turned = quaternion_from_matrix(Rz @ matrix_from_quaternion(quat))
    return {"position": p.tolist(), "orientation": turned.tolist(), "jp": [0.0] * 5}


class Lines:
    """A plain JSON-lines session: send requests, read replies (events skipped)."""

    def __init__(self, path: str):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(path)
        self.file = self.sock.makefile("rb")

    def send(self, *requests: dict) -> None:
        self.sock.sendall(b"".join(json.dumps(r).encode() + b"\n" for r in requests))

    def reply(self) -> dict:
        while True:
            msg = json.loads(self.file.readline())
            if "id" in msg:
                return msg

    def close(self) -> None:
        self.sock.close()


@only_on("so101-feetech")
def test_measured_js_is_answered_while_another_session_runs_cold_ik(sim_daemon):
    path = str(sim_daemon.socket_path)
    solver, watcher = Lines(path), Lines(path)
    try:
        watcher.send({"id": 0, "cmd": "measured_js", "ns": "so101"})
        assert watcher.reply()["ok"]
        target = hard_target()
        ik_replies: list[tuple[float, dict]] = []

        def read_ik():
            for _ in range(K):
                msg = solver.reply()
                ik_replies.append((time.monotonic(), msg))

        reader = threading.Thread(target=read_ik, daemon=True)
        reader.start()
        t_sent = time.monotonic()
        solver.send(*({"id": i, "cmd": "inverse_kinematics", "ns": "so101", "data": target} for i in range(1, K + 1)))
        answered: list[tuple[float, float]] = []  # (sent, answered) of each measured_js
        rid = 100
        deadline = time.monotonic() + 60
        while reader.is_alive() and time.monotonic() < deadline:
            rid += 1
            t0 = time.monotonic()
            watcher.send({"id": rid, "cmd": "measured_js", "ns": "so101"})
            reply = watcher.reply()
            assert reply["id"] == rid and reply["ok"] and reply["data"]["stamp"] > 0
            answered.append((t0, time.monotonic()))
        reader.join(5)
        assert len(ik_replies) == K, "the IK requests were not all answered"

        # the IK replies: each one, in the order sent (one worker per namespace keeps order)
        assert [m["id"] for _, m in ik_replies] == list(range(1, K + 1))
        assert all(m["ok"] and m["data"]["result"] is False for _, m in ik_replies)
        t_done = ik_replies[-1][0]
        window = t_done - t_sent
        during = [(a, b) for a, b in answered if a > t_sent and b < t_done]
        # IK on the event loop would have run the K pipelined solves back to back and answered
        # no query in between; off the loop, the other session is served throughout
        assert len(during) >= 5, f"{len(during)} measured_js answered during {window * 1e3:.0f} ms of IK"
        worst = max(b - a for a, b in during)
        assert worst < window / 2, f"a measured_js took {worst * 1e3:.1f} ms during {window * 1e3:.0f} ms of IK"
    finally:
        solver.close()
        watcher.close()

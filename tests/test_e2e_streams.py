"""Subscriptions: frames at the requested rate; a slow subscriber loses frames, never slows others."""

from __future__ import annotations

import json
import socket
import time

import pytest

from crtk_bridge.client import connect

from .conftest import wait_until

pytestmark = pytest.mark.requires()  # every simulated robot


def test_subscription_rate_and_slow_subscriber(sim_daemon):
    ns = sim_daemon.robot.arm
    path = str(sim_daemon.socket_path)
    robot = connect(socket=path)
    try:
        # a normal subscriber gets frames at about the requested rate, each fresh
        sub = robot.device(ns).subscribe("measured_js", 50)
        # the frames that carry a valid sample (stamp 0 marks an invalid one: a simulated bus that
        # a loaded host starved for safety.bus_errors_max cycles); every tenth may be invalid
        frames, seen = [], 0
        while len(frames) < 51:
            f = sub.get(timeout=2)
            seen += 1
            assert seen <= 56, f"{seen - len(frames)} of {seen} measured_js frames invalid"
            if (f["stamp"] if "stamp" in f else f["data"]["stamp"]) > 0:
                frames.append(f)
        stamps = [f["stamp"] if "stamp" in f else f["data"]["stamp"] for f in frames]
        assert all(b >= a for a, b in zip(stamps, stamps[1:])) and stamps[-1] > stamps[0]
        # the rate, by the frames' own stamps (the sample each frame carried, so a client thread
        # that reads late cannot make frames look bunched): 50 Hz asked, generous bounds for a
        # loaded host (a stream that falls behind skips frames, it never bursts; a stream at the
        # loop's 200 Hz, or at 1 Hz, fails)
        rate = 50 / (stamps[-1] - stamps[0])
        assert 25 < rate < 70, rate
        sub.close()

        # a slow client: 10 streams at the loop rate that it never reads
        slow = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        slow.connect(path)
        for i in range(10):
            req = {"id": i + 1, "cmd": "subscribe", "ns": ns, "data": {"topic": "measured_js", "rate_hz": 1000}}
            slow.sendall((json.dumps(req) + "\n").encode())
        t0 = time.monotonic()
        answered = 0
        while time.monotonic() - t0 < 3.0:  # meanwhile another session is served as usual
            pos, ts = robot.device(ns).measured_jp()
            assert ts > 0
            answered += 1
            time.sleep(0.005)  # paces this client at ~200 Hz (a 2-core host also runs the simulator)
        assert answered > 50
        # what the slow client can read now is a fraction of what was produced: frames were dropped
        slow.settimeout(0.05)
        received = b""
        t_read = time.monotonic()
        while time.monotonic() - t_read < 0.3:  # bounded: the streams never stop by themselves
            try:
                chunk = slow.recv(1 << 20)
            except socket.timeout:
                continue
            if not chunk:
                break
            received += chunk
        produced = 10 * 200 * (time.monotonic() - t0)  # 10 streams capped at the 200 Hz loop rate
        got = received.count(b'"topic"')
        assert 0 < got < produced / 2, (got, produced)
        stats = robot.period_statistics()
        assert stats["cycles"] > 0
        slow.close()
        # the daemon is still healthy
        wait_until(lambda: robot.device(ns).measured_jp()[1] > 0, 2, what="daemon still serving")
    finally:
        robot.close()

"""The socket protocol over Zenoh, end to end: a Zenoh router (a Python process, router mode,
loopback, multicast off) and two daemons (SO-101 and Koch on their simulators) joined to it; the
Python client and crtk-ctl reach both through the router with the same API as over the socket,
under the same control rules (one controller across transports, stops from anyone, client loss)."""

from __future__ import annotations

import contextlib
import json
import re
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from crtk_bridge.client import CommandError, DaemonConnectionError, connect, list_robots

from .conftest import KOCH, ROOT, SO101, DaemonProcess, free_port, wait_until

ROUTER = """
import json, sys, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"router"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
session = zenoh.open(conf)
print("ready", flush=True)
sys.stdin.read()  # until the test closes our stdin
session.close()
"""


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A router on a free loopback port and the two daemons joined to it: (endpoint, so101, koch).
    The Koch daemon also listens on its own loopback port (``koch.listen``), for peers and clients
    that reach it directly."""
    tmp = tmp_path_factory.mktemp("zenoh")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    koch_listen = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen([sys.executable, "-c", ROUTER, endpoint], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=ROOT)
    daemons = []
    try:
        assert router.stdout.readline().strip() == b"ready"
        for name, profile, more in (("so101", SO101, []), ("koch", KOCH, ["--zenoh-listen", koch_listen])):
            daemons.append(DaemonProcess(["--profile", str(profile), "--sim", "--zenoh-connect", endpoint, *more],
                                         tmp / f"{name}.sock", tmp / f"{name}.log"))
        daemons[1].listen = koch_listen
        yield endpoint, daemons[0], daemons[1]
    finally:
        for d in daemons:
            d.stop()
        router.stdin.close()
        try:
            router.wait(10)
        except subprocess.TimeoutExpired:
            router.kill()
            router.wait()


def test_lists_both_robots(lab):
    endpoint, so101, koch = lab
    assert list_robots(zenoh_connect=endpoint) == ["koch", "so101"]
    assert "serving CRTK on" in so101.output() and f"Zenoh (connected to {endpoint}" in so101.output()
    # --zenoh-connect alone listens on loopback port 0: the banner tells the port the system gave
    port = int(re.search(r"listening on tcp/127\.0\.0\.1:(\d+)", so101.output())[1])
    assert port != 0, so101.output()
    with socket.create_connection(("127.0.0.1", port), timeout=5):
        pass
    done = subprocess.run([sys.executable, "-m", "crtk_bridge.client.cli", "--zenoh-connect", endpoint, "--json",
                           "robots"], cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert (done.returncode, json.loads(done.stdout)) == (0, {"robots": ["koch", "so101"]})


def test_streams_enables_and_moves_over_zenoh(lab):
    endpoint, so101, _ = lab
    with connect(robot="so101", zenoh_connect=endpoint) as robot:
        assert robot.name == "so101" and robot.namespaces == ["so101", "so101/gripper"]
        arm = robot.device("so101")
        with arm.subscribe("measured_js", 50.0) as stream:
            frames = [stream.get(timeout=5.0) for _ in range(5)]
        stamps = [f["stamp"] for f in frames]
        # in order and live (a stream that fell behind under load may repeat a sample, never go back)
        assert all(b >= a for a, b in zip(stamps, stamps[1:])) and stamps[-1] > stamps[0] > 0
        assert len(frames[0]["position"]) == 5
        assert arm.enable(5.0) and arm.is_enabled()
        goal = np.array([0.1, 0.2, 0.3, 0.0, 0.0])
        assert arm.move_jp(goal).wait(timeout=15.0)
        p, ts = arm.measured_jp()
        assert ts > 0 and np.max(np.abs(p - goal)) < 0.02
        assert arm.disable(5.0)
    # the socket sees what the Zenoh client did: one robot, one state
    with connect(socket=str(so101.socket_path)) as local:
        assert local.device("so101").operating_state() == "DISABLED"
        assert np.max(np.abs(local.device("so101").measured_jp()[0] - goal)) < 0.02


def test_several_requests_in_one_put_over_zenoh(lab):
    """Connection.request_all writes several request lines at once (the LeRobot plugin's arm and
    gripper): over Zenoh they travel in one put and each gets its reply, in order."""
    endpoint, _, _ = lab
    with connect(robot="so101", zenoh_connect=endpoint) as robot:
        arm, grip, state = robot.connection.request_all(
            [("measured_js", "so101", None), ("measured_js", "so101/gripper", None), ("operating_state", None, None)])
    assert len(arm["position"]) == 5 and len(grip["position"]) == 1 and arm["stamp"] > 0
    assert state["state"] in ("DISABLED", "ENABLED")


def test_one_controller_across_transports_and_stops_from_anyone(lab):
    endpoint, _, koch = lab
    with connect(robot="koch", zenoh_connect=endpoint) as holder, \
            connect(robot="koch", zenoh_connect=endpoint) as other, \
            connect(socket=str(koch.socket_path)) as local:
        arm = holder.device("koch")
        assert arm.enable(5.0)
        here = arm.measured_jp()[0]
        for robot in (other, local):  # a second Zenoh client, and a socket client: both refused
            with pytest.raises(CommandError) as refused:
                robot.device("koch").move_jp(here + 0.05)
            assert refused.value.code == "read_only"
            assert "Zenoh client" in refused.value.message  # names the holder's session
        assert other.device("koch").disable(5.0)  # a stop is never refused
        wait_until(arm.is_disabled, 5.0, what="the holder seeing DISABLED")
        assert arm.enable(5.0)  # the holder kept control
        assert local.device("koch").pause(5.0)  # stops from the socket too
        assert arm.disable(5.0)


def test_client_loss_over_zenoh_stops_the_robot(lab):
    endpoint, so101, _ = lab
    with connect(socket=str(so101.socket_path)) as watcher:
        speed = lambda: abs(watcher.device("so101").measured_jv()[0][0])  # noqa: E731 - shoulder_pan, rad/s
        remote = connect(robot="so101", zenoh_connect=endpoint)
        try:
            arm = remote.device("so101")
            assert arm.enable(5.0)
            count = watcher.connection.event_count
            arm.servo_jv([0.2, 0.0, 0.0, 0.0, 0.0])
            wait_until(lambda: speed() > 0.05, 5.0, what="the joint moving")
            remote.connection._sock._session.close()  # gone as far as Zenoh knows: its token goes away
            warned = wait_until(lambda: [e for e in watcher.connection.events_since(count)
                                         if e.data.get("code") == "control_released"], 5.0,
                                what="a control_released warning after the Zenoh client left")
            assert warned[0].kind == "warning" and "so101" in warned[0].data["message"]
            wait_until(lambda: speed() < 0.01, 5.0, what="the joint stopped")
            watcher.acquire()  # control is free again
            assert watcher.device("so101").disable(5.0)
            with pytest.raises(DaemonConnectionError):
                remote.list()
        finally:
            remote.close()


def test_unreachable_router_from_the_client():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "crtk_bridge.client.cli", "--zenoh-connect", endpoint,
                           "--timeout", "0.5", "state"], cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"crtk-ctl: crtk-bridge client: cannot reach the Zenoh router or peer at {endpoint} within 0.5 s: "
        f"start a router there (e.g. `zenohd -l tcp/127.0.0.1:{endpoint.rsplit(':', 1)[1]}`) or check the "
        "address (--zenoh-connect)"]
    assert time.monotonic() - started < 20


def test_a_client_reaches_a_daemon_listening_without_a_router(lab):
    _, _, koch = lab
    with connect(robot="koch", zenoh_connect=koch.listen) as robot:
        assert robot.name == "koch" and robot.device("koch").operating_state() in ("DISABLED", "ENABLED", "PAUSED")
        assert robot.measured_js()[3] > 0


def test_no_such_robot_on_the_network(lab):
    endpoint, _, _ = lab
    with pytest.raises(DaemonConnectionError, match=r"no crtk-bridge daemon for robot 'ur5e' on the Zenoh "
                                                    r"network at .* \(robots there: koch, so101\)"):
        connect(robot="ur5e", zenoh_connect=endpoint)
    with pytest.raises(DaemonConnectionError, match="several robots on the Zenoh network .*: koch, so101"):
        connect(zenoh_connect=endpoint)


@contextlib.contextmanager
def plain_zenoh_client(endpoint: str, robot: str = "so101"):
    """The documented key layout spoken with eclipse-zenoh alone (no project client): a client
    session through the router, subscribed to its own out key, its liveliness token declared (the
    daemon opens a session for it and greets it). Yields (put, got): ``put(bytes)`` sends request
    lines to its in key; ``got`` collects every message received, in order."""
    import uuid

    import zenoh

    conf = zenoh.Config()
    for key, value in (("mode", '"client"'), ("scouting/multicast/enabled", "false"),
                       ("connect/endpoints", json.dumps([endpoint]))):
        conf.insert_json5(key, value)
    session = zenoh.open(conf)
    cid = uuid.uuid4().hex
    got: list[dict] = []
    sub = session.declare_subscriber(
        f"crtk_bridge/{robot}/out/{cid}",
        zenoh.handlers.Callback(lambda s: got.extend(json.loads(x) for x in s.payload.to_bytes().splitlines()),
                                indirect=False))
    token = session.liveliness().declare_token(f"crtk_bridge/{robot}/client/{cid}")
    try:
        yield (lambda payload: session.put(f"crtk_bridge/{robot}/in/{cid}", payload)), got
    finally:
        token.undeclare()
        sub.undeclare()
        session.close()


def test_a_plain_zenoh_client_and_a_flood_of_requests(lab):
    """The documented key layout, spoken with eclipse-zenoh alone (no project client): the token
    opens a session greeted with operating_state; a flood beyond the pending-request bound is
    refused line by line with each request's id, and a stop in it is still served."""
    from crtk_bridge.transport.tunnel import MAX_PENDING

    endpoint, _, _ = lab
    with plain_zenoh_client(endpoint) as (put, got):
        wait_until(lambda: got, 5.0, what="the greeting")
        assert got[0]["event"] == "operating_state" and got[0]["data"]["state"] in ("DISABLED", "ENABLED", "PAUSED")
        n = MAX_PENDING + 100
        flood = b"".join(b'{"id": %d, "cmd": "operating_state"}\n' % i for i in range(n))
        put(flood + b'{"id": -1, "cmd": "hold", "ns": "so101"}\n')
        replies = lambda: {m["id"]: m for m in list(got) if "id" in m}  # noqa: E731
        wait_until(lambda: -1 in replies() and len(replies()) == n + 1, 30.0, what="every reply")
        discarded = [m for m in replies().values() if not m["ok"] and "request discarded" in m["error"]["message"]]
        assert len(discarded) == n - MAX_PENDING  # each refused with its own id, none silently dropped
        assert {m["id"] for m in discarded} == set(range(MAX_PENDING, n))
        stop = replies()[-1]
        assert "request discarded" not in json.dumps(stop)  # a stop is never refused for the flood


def test_a_plain_zenoh_subscriber_at_a_low_rate_gets_every_frame(lab):
    """Spoken with eclipse-zenoh alone: two subscriptions of measured_js at 20 Hz on one session
    (the topic read and encoded once a tick, the frames put together) arrive whole, each with its
    own subscription id, in order of their bus reads, and the daemon drops none of them
    (period_statistics' frames_dropped does not move)."""
    endpoint, so101, _ = lab
    with connect(socket=str(so101.socket_path)) as robot, plain_zenoh_client(endpoint) as (put, got):
        wait_until(lambda: got, 5.0, what="the greeting")
        dropped_before = robot.period_statistics()["frames_dropped"]
        put(b"".join(
            b'{"id": %d, "cmd": "subscribe", "ns": "so101", "data": {"topic": "measured_js", "rate_hz": 20}}\n' % i
            for i in (1, 2)))
        replies = lambda: {m["id"]: m["data"]["sub"] for m in list(got) if m.get("id") in (1, 2)}  # noqa: E731
        wait_until(lambda: len(replies()) == 2, 10.0, what="both subscriptions")
        subs = set(replies().values())
        frames = lambda sid: [m for m in list(got) if m.get("sub") == sid]  # noqa: E731
        wait_until(lambda: all(len(frames(sid)) >= 20 for sid in subs), 30.0, what="20 frames of each subscription")
        for sid in subs:
            stamps = [m["data"]["stamp"] for m in frames(sid)]
            assert all(m["topic"] == "measured_js" and m["ns"] == "so101" and len(m["data"]["position"]) == 5
                       for m in frames(sid))
            assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
        assert robot.period_statistics()["frames_dropped"] == dropped_before


def test_a_second_daemon_for_the_same_robot_is_refused(lab, short_tmp):
    endpoint, so101, _ = lab
    done = subprocess.run([sys.executable, "-m", "crtk_bridge.cli", "--profile", str(SO101), "--sim",
                           "--socket", str(short_tmp / "twin.sock"), "--zenoh-connect", endpoint],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        "crtk-bridge: so101: another crtk-bridge daemon already serves robot 'so101' on this Zenoh network "
        "(crtk_bridge/so101/daemon): stop it, or give this robot another name"]
    assert not (short_tmp / "twin.sock").exists()
    assert list_robots(zenoh_connect=endpoint) == ["koch", "so101"]  # the first one still serves
    with connect(robot="so101", zenoh_connect=endpoint) as robot:
        assert robot.measured_js()[3] > 0


def test_a_frozen_client_behind_the_router_gives_control_up_within_its_lease(lab):
    """The lab's layout: the client reaches the daemon through the router. Frozen (SIGSTOP), it
    is dropped by the router after the lease it announced (the library's 2 s), which withdraws its
    token; for the daemon that is client loss, and control is free again (docs/zenoh.md, Lease)."""
    import os
    import signal

    from crtk_bridge.profile import ZENOH_LEASE_MS_DEFAULT

    from .test_zenoh_lease import MARGIN_S, remote_client

    endpoint, _, koch = lab

    def control_free() -> bool:
        try:
            local.acquire()
        except CommandError as exc:
            assert exc.code == "read_only", exc
            return False
        return True

    with connect(socket=str(koch.socket_path), timeout=15.0) as local, \
            remote_client(endpoint, "koch", "hold") as client:
        assert not control_free()  # the remote client holds it
        frozen_at = time.monotonic()
        os.kill(client.pid, signal.SIGSTOP)
        wait_until(control_free, ZENOH_LEASE_MS_DEFAULT / 1000 + MARGIN_S, interval=0.02,
                   what=f"control free within the frozen client's lease + {MARGIN_S} s")
        print(f"frozen client behind the router lost after {time.monotonic() - frozen_at:.2f} s")
        assert client.poll() is None  # frozen, not gone: only the lease could find it
        local.release()

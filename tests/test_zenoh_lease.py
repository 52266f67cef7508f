"""The Zenoh link lease (docs/zenoh.md, "Lease"): ``transport.zenoh.lease_ms`` on the daemon's
session and ``--zenoh-lease-ms`` / ``zenoh_lease_ms`` on the client library's, both with a short
default (2 s, against Zenoh's own 10 s), validated in one line naming the key or option. Zenoh
expires a link when the peer sends nothing for the lease THE PEER announced at link open, so it is
the client's own lease that bounds how long a frozen remote client keeps control: a client process
frozen (SIGSTOP) while its velocity stream runs is lost, its stream stops and control is free,
within its lease plus a margin."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
import yaml

from crtk_bridge.client import connect, list_robots
from crtk_bridge.errors import CrtkBridgeError, ProfileError
from crtk_bridge.profile import (ZENOH_KEEP_ALIVE_PER_LEASE, ZENOH_LEASE_MS_DEFAULT, ZENOH_LEASE_MS_MAX,
                                 ZENOH_LEASE_MS_MIN, load_profile)
from crtk_bridge.transport.zenoh_session import ZenohConfig, session_config, zenoh_config
from crtk_client.zenoh_session import HANDSHAKE_MS_MAX, SessionConfig

from .conftest import ROOT, DaemonProcess, free_port, so101_data, wait_until

#: the daemon's reaction after the client's lease ran out (link closed, token gone, session ended,
#: control process told, event back on the socket): generous, for a loaded 2-core PC
MARGIN_S = 2.0
#: the frozen client's stream: shoulder_pan at this speed (rad/s) until the daemon stops it
SPEED = 0.15

REMOTE_CLIENT = """
import sys, threading, time
from crtk_bridge.client import connect
endpoint, robot, how = sys.argv[1:4]
remote = connect(robot=robot, zenoh_connect=endpoint, timeout=15.0)   # the library's default lease
arm = remote.device(robot)
if how == "stream":   # enable, then shoulder_pan at argv[4] rad/s, streamed at 20 Hz until frozen
    assert arm.enable(15.0)
    velocity = [float(sys.argv[4])] + [0.0] * (len(arm.joint_names) - 1)
    arm.servo_jv(velocity)

    def stream():
        while True:
            time.sleep(0.05)
            arm.servo_jv(velocity)
    threading.Thread(target=stream, daemon=True).start()
else:                 # only hold control
    remote.acquire()
print("ready", flush=True)
sys.stdin.read()   # until frozen, then killed
"""


@contextlib.contextmanager
def remote_client(endpoint: str, robot: str, *how: str):
    """A process holding control of ``robot`` over Zenoh (``how``: ``hold``, or ``stream SPEED``),
    ready when entered; on the way out it is continued (if stopped) and killed."""
    proc = subprocess.Popen([sys.executable, "-c", REMOTE_CLIENT, endpoint, robot, *how], cwd=ROOT,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        started = proc.stdout.readline().strip()
        if started != b"ready":
            raise AssertionError(f"the remote client did not start: {started + proc.stdout.read()!r}")
        yield proc
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGCONT)
            proc.kill()
        proc.wait(10)
        proc.stdin.close()
        proc.stdout.close()


def _lease_keys(conf) -> tuple[int, int]:
    """(lease, keep_alive) of a zenoh.Config, as Zenoh will use them."""
    return tuple(json.loads(conf.get_json(f"transport/link/tx/{key}")) for key in ("lease", "keep_alive"))


def _write(tmp_path, lease):
    data = so101_data()
    data["transport"] = {"zenoh": {"lease_ms": lease}}
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("lease", [0, -1000, ZENOH_LEASE_MS_MIN - 1, ZENOH_LEASE_MS_MAX + 1, 1500.5, True, "2s"])
def test_profile_refuses_a_lease_out_of_range_naming_the_key(tmp_path, lease):
    with pytest.raises(ProfileError) as refused:
        load_profile(_write(tmp_path, lease))
    text = str(refused.value)
    assert len(text.splitlines()) == 1 and "transport.zenoh.lease_ms" in text, text


def test_profile_lease_reaches_the_daemons_session_with_keep_alive_a_quarter(tmp_path):
    assert load_profile(_write(tmp_path, ZENOH_LEASE_MS_MIN)).transport.zenoh.lease_ms == ZENOH_LEASE_MS_MIN
    profile = load_profile(_write(tmp_path, 3000))
    conf = session_config(zenoh_config(profile))
    assert _lease_keys(conf) == (3000, 4)
    # no section, --zenoh-connect alone: the short default, not Zenoh's 10 s
    plain = zenoh_config(load_profile(_write(tmp_path, ZENOH_LEASE_MS_MAX)), connect=["tcp/127.0.0.1:1"])
    assert plain.lease_ms == ZENOH_LEASE_MS_MAX
    assert _lease_keys(session_config(ZenohConfig())) == (ZENOH_LEASE_MS_DEFAULT, 4) == (2000, 4)
    assert ZENOH_KEEP_ALIVE_PER_LEASE == 4


def test_a_sessions_handshake_is_bounded_by_its_start_up_timeout_and_two_seconds(tmp_path):
    """Zenoh waits 10 s by default for a session handshake, and closing a session waits for one
    under way: a client whose daemon froze retries, the frozen daemon's kernel accepts the TCP
    connection, and close() hung 10 s. The handshake limit is the start-up timeout, at most 2 s."""
    def open_timeout(timeout_s: float) -> int:
        conf = session_config(SessionConfig(mode="client", connect=["tcp/127.0.0.1:1"], connect_timeout_s=timeout_s))
        return json.loads(conf.get_json("transport/unicast/open_timeout"))

    assert open_timeout(5.0) == open_timeout(60.0) == HANDSHAKE_MS_MAX == 2000
    assert open_timeout(1.5) == 1500
    assert open_timeout(0.01) == 100
    data = so101_data()
    data["transport"] = {"zenoh": {"connect_timeout_s": 0.75}}
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(data))
    daemon_side = session_config(zenoh_config(load_profile(tmp_path / "p.yaml")))
    assert json.loads(daemon_side.get_json("transport/unicast/open_timeout")) == 750


def test_lease_is_set_over_a_zenoh_configuration_file(tmp_path):
    base = tmp_path / "z.json5"
    base.write_text('{ transport: { link: { tx: { lease: 10000, keep_alive: 1 } } } }')
    conf = session_config(ZenohConfig(mode="client", listen=[]), base=str(base))
    assert _lease_keys(conf) == (2000, 4)


def test_client_lease_out_of_range_is_refused_naming_the_option():
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # never reached: refused before any session opens
    for bad in (0, ZENOH_LEASE_MS_MIN - 1, ZENOH_LEASE_MS_MAX + 1, 1000.0):
        with pytest.raises(CrtkBridgeError, match=r"^crtk-bridge client: --zenoh-lease-ms \(zenoh_lease_ms\): "
                                                  r"must be an integer from 500 to 60000 \(ms\), got "):
            connect(robot="so101", zenoh_connect=endpoint, zenoh_lease_ms=bad)
        with pytest.raises(CrtkBridgeError, match="--zenoh-lease-ms"):
            list_robots(zenoh_connect=endpoint, zenoh_lease_ms=bad)
    for bad in ("0", "-5", "499", "60001", "nan", "1e3"):
        done = subprocess.run([sys.executable, "-m", "crtk_bridge.client.cli", "--zenoh-connect", endpoint,
                               "--zenoh-lease-ms", bad, "state"], cwd=ROOT, capture_output=True, text=True,
                              timeout=30)
        assert done.returncode == 2
        assert done.stderr.strip().splitlines()[-1].startswith("crtk-ctl: error: argument --zenoh-lease-ms: "), bad


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    """An SO-101 daemon on its simulator listening for Zenoh clients on a free loopback port, with
    a servo watchdog (10 s) far longer than lease + margin: only client loss can stop the frozen
    client's stream within the test's bound. The simulated bus is given room (100 ms per reply, 50
    failed cycles before FAULT): on a 2-core PC at load 10 a starved simulator faulted the robot
    mid-test (bus_timeout), which stops the stream before any client loss; this test is about
    the link, not the bus. Its own lease is the longest allowed (60 s): a frozen client is
    expired after the lease the CLIENT announced, so the daemon's own must not delay it. Yields
    (endpoint, daemon)."""
    tmp = tmp_path_factory.mktemp("lease")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    data = so101_data()
    data["safety"]["servo_timeout_s"] = 10.0
    data["safety"]["bus_errors_max"] = 50
    data["backend"]["timeout_ms"] = 100
    data["transport"] = {"zenoh": {"listen": [endpoint], "lease_ms": ZENOH_LEASE_MS_MAX}}
    profile = tmp / "so101-lease.yaml"
    profile.write_text(yaml.safe_dump(data))
    d = DaemonProcess(["--profile", str(profile), "--sim"], tmp / "d.sock", tmp / "d.log")
    try:
        yield endpoint, d
    finally:
        d.stop()


def test_a_frozen_remote_client_is_lost_within_its_lease(daemon):
    endpoint, d = daemon
    with connect(socket=str(d.socket_path), timeout=15.0) as watcher, \
            remote_client(endpoint, "so101", "stream", str(SPEED)) as client:
        arm = watcher.device("so101")
        speed = lambda: abs(arm.measured_jv()[0][0])  # noqa: E731 - shoulder_pan, rad/s
        count = watcher.connection.event_count
        wait_until(lambda: speed() > SPEED / 2, 15.0, what="the remote client's stream moving the joint")
        with pytest.raises(CrtkBridgeError) as held:  # the remote client holds control
            watcher.acquire()
        assert "Zenoh client" in str(held.value)

        frozen_at = time.monotonic()
        os.kill(client.pid, signal.SIGSTOP)  # frozen: no close, no keep-alive, the TCP link stays up
        bound = ZENOH_LEASE_MS_DEFAULT / 1000 + MARGIN_S
        seen = lambda: watcher.connection.events_since(count)  # noqa: E731
        try:
            released = wait_until(lambda: [e for e in seen() if e.data.get("code") == "control_released"],
                                  bound, interval=0.005, what=f"client loss within the lease + {MARGIN_S} s")
        except AssertionError as exc:
            raise AssertionError(f"{exc}; events meanwhile: {[(e.kind, e.data.get('code')) for e in seen()]}") from None
        lost_after = time.monotonic() - frozen_at
        assert released[0].kind == "warning" and "so101" in released[0].data["message"]
        wait_until(lambda: speed() < 0.01, 5.0, what="the stream stopped at client loss")
        watcher.acquire()  # control is free: the frozen client no longer holds it
        assert client.poll() is None  # still there, only frozen: the lease found it, nothing else
        print(f"frozen client lost after {lost_after:.2f} s (lease {ZENOH_LEASE_MS_DEFAULT} ms)")
        assert arm.disable(15.0)


def test_a_frozen_daemon_is_lost_by_its_remote_clients_within_the_daemons_lease(tmp_path):
    """The other direction: the daemon's front frozen (SIGSTOP), a remote client's connection ends
    (DaemonConnectionError) after the lease the DAEMON announced (transport.zenoh.lease_ms, 1 s
    here), though the client's own is 60 s, instead of hanging until its requests time out."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    data = so101_data()
    data["transport"] = {"zenoh": {"listen": [endpoint], "lease_ms": 1000}}
    profile = tmp_path / "so101-short-lease.yaml"
    profile.write_text(yaml.safe_dump(data))
    d = DaemonProcess(["--profile", str(profile), "--sim"], tmp_path / "d.sock", tmp_path / "d.log")
    frozen = False
    try:
        with connect(robot="so101", zenoh_connect=endpoint, timeout=15.0, zenoh_lease_ms=ZENOH_LEASE_MS_MAX) as robot:
            assert robot.measured_js()[3] > 0
            frozen_at = time.monotonic()
            os.kill(d.proc.pid, signal.SIGSTOP)  # the front: its Zenoh session with it
            frozen = True
            wait_until(lambda: robot.connection.closed, 1.0 + MARGIN_S, interval=0.005,
                       what=f"the client losing the frozen daemon within its 1 s lease + {MARGIN_S} s")
            lost_after = time.monotonic() - frozen_at
            with pytest.raises(ConnectionError):
                robot.measured_js()
            print(f"frozen daemon lost after {lost_after:.2f} s (daemon lease 1000 ms)")
            # closing while the daemon is still frozen: the session's reconnect handshake hangs
            # on the frozen peer and close() waits for it, 10 s with Zenoh's default; bounded by
            # HANDSHAKE_MS_MAX now
            closer = threading.Thread(target=robot.close, daemon=True)
            closer.start()
            wait_until(lambda: not closer.is_alive(), HANDSHAKE_MS_MAX / 1000 + MARGIN_S, interval=0.01,
                       what=f"the client closing with its daemon frozen within the {HANDSHAKE_MS_MAX} ms "
                            f"handshake limit + {MARGIN_S} s")
    finally:
        if frozen:
            os.kill(d.proc.pid, signal.SIGCONT)
        d.stop()

"""sd_notify verbs against a real AF_UNIX datagram socket, as systemd would receive them."""

from __future__ import annotations

import logging
import os
import shutil
import socket
import tempfile
import uuid

import pytest

from crtk_bridge import systemd


@pytest.fixture
def short_dir():
    # AF_UNIX paths are limited to ~107 bytes; pytest's tmp_path can be longer than that.
    d = tempfile.mkdtemp(prefix="crtk-sd-")
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def notify_socket(short_dir, monkeypatch):
    path = os.path.join(short_dir, "notify")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    yield sock
    sock.close()


def recv(sock: socket.socket) -> str:
    return sock.recv(4096).decode()


def assert_nothing_pending(sock: socket.socket) -> None:
    sock.setblocking(False)
    with pytest.raises(BlockingIOError):
        sock.recv(4096)


@pytest.mark.parametrize(
    "verb, args, expected",
    [
        (systemd.ready, (), "READY=1"),
        (systemd.ready, ("listening on /run/crtk-bridge/so101.sock",),
         "READY=1\nSTATUS=listening on /run/crtk-bridge/so101.sock"),
        (systemd.stopping, (), "STOPPING=1"),
        (systemd.watchdog_ping, (), "WATCHDOG=1"),
        (systemd.status, ("so101: DISABLED, 200 Hz",), "STATUS=so101: DISABLED, 200 Hz"),
    ],
)
def test_messages_arrive(notify_socket, verb, args, expected):
    assert verb(*args) is True
    assert recv(notify_socket) == expected
    assert_nothing_pending(notify_socket)


def test_status_is_kept_on_one_line(notify_socket):
    assert systemd.status("line one\nline two\nWATCHDOG=1") is True
    assert recv(notify_socket) == "STATUS=line one line two WATCHDOG=1"


def test_several_messages_in_order(notify_socket):
    systemd.ready()
    systemd.watchdog_ping()
    systemd.stopping()
    assert [recv(notify_socket) for _ in range(3)] == ["READY=1", "WATCHDOG=1", "STOPPING=1"]


def test_abstract_socket_name(monkeypatch):
    name = f"crtk-bridge-test-{uuid.uuid4().hex}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        sock.settimeout(2.0)
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        assert systemd.ready() is True
        assert recv(sock) == "READY=1"


@pytest.mark.parametrize("value", [None, ""])
def test_noop_outside_systemd(monkeypatch, value):
    if value is None:
        monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    else:
        monkeypatch.setenv("NOTIFY_SOCKET", value)
    assert systemd.ready() is False
    assert systemd.ready("status") is False
    assert systemd.stopping() is False
    assert systemd.status("x") is False
    assert systemd.watchdog_ping() is False


def test_send_error_never_raises(short_dir, monkeypatch, caplog):
    # The socket path names nothing: sendto fails with ENOENT, logged at debug only.
    monkeypatch.setenv("NOTIFY_SOCKET", os.path.join(short_dir, "gone"))
    with caplog.at_level(logging.DEBUG, logger="crtk_bridge.systemd"):
        assert systemd.ready() is False
        assert systemd.watchdog_ping() is False
    assert caplog.records and all(r.levelno == logging.DEBUG for r in caplog.records)


def test_unsupported_address_is_noop(monkeypatch):
    monkeypatch.setenv("NOTIFY_SOCKET", "vsock:2:1234")
    assert systemd.ready() is False


def test_watchdog_period(monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    assert systemd.watchdog_period() == pytest.approx(2.0)
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert systemd.watchdog_period() == pytest.approx(2.0)
    monkeypatch.setenv("WATCHDOG_USEC", "500")
    assert systemd.watchdog_period() == pytest.approx(0.0005)


def test_watchdog_period_for_another_pid(monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert systemd.watchdog_period() is None


@pytest.mark.parametrize("usec, pid", [(None, None), ("", None), ("0", None), ("-5", None),
                                       ("abc", None), ("2000000", "not-a-pid")])
def test_watchdog_period_absent_or_invalid(monkeypatch, usec, pid):
    for key, value in (("WATCHDOG_USEC", usec), ("WATCHDOG_PID", pid)):
        if value is None:
            monkeypatch.delenv(key, raising=False)
        else:
            monkeypatch.setenv(key, value)
    assert systemd.watchdog_period() is None

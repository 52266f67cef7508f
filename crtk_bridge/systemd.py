"""systemd service notifications (``sd_notify``) without libsystemd.

The verbs here speak the notify protocol of ``systemd.service(5)`` / ``sd_notify(3)`` directly:
one datagram of newline-separated ``KEY=VALUE`` lines sent to the AF_UNIX socket named by
``$NOTIFY_SOCKET`` (a path, or an abstract name written with a leading ``@``).

Outside systemd (``NOTIFY_SOCKET`` unset or empty) every verb is a no-op that returns ``False``,
so the daemon calls them unconditionally. A failed send is logged at debug level and returns
``False``; it never raises, because a missing notification must not take the robot down (systemd
itself acts on the silence: a start timeout, or the watchdog).

Who calls what (see ``systemd/crtk-bridge@.service``, which sets ``NotifyAccess=main``, so only
the daemon's main process, the front process, may notify):

* :func:`ready` once the profile is loaded, the control process runs and the socket listens;
* :func:`watchdog_ping` from the front process whenever the control loop's latest snapshot shows
  it alive and cycling, at least every ``watchdog_period() / 2`` seconds; never from a side
  thread that would keep pinging while the loop is stuck;
* :func:`status` for a one-line human summary shown by ``systemctl status``;
* :func:`stopping` when shutdown begins.

Every call opens, uses and closes its own socket: a handful of syscalls at the watchdog rate (about
once a second), with no descriptor to leak across the fork of the control process.
"""

from __future__ import annotations

import logging
import os
import socket

__all__ = ["notify", "ready", "status", "stopping", "watchdog_period", "watchdog_ping"]

log = logging.getLogger(__name__)


def _address() -> str | None:
    """The notify socket address from the environment, abstract names as ``\\0name``."""
    addr = os.environ.get("NOTIFY_SOCKET", "")
    if not addr:
        return None
    if addr.startswith("@"):
        return "\0" + addr[1:]
    if addr.startswith("/"):
        return addr
    # Other forms (vsock:..., relative paths) are not used by a service manager on our targets.
    log.debug("NOTIFY_SOCKET=%r is not an AF_UNIX path or abstract name; not notifying", addr)
    return None


def notify(*fields: str) -> bool:
    """Send one notify message made of ``KEY=VALUE`` fields (e.g. ``"READY=1"``).

    Non-blocking in practice (one datagram to a local socket). Returns True when the message was
    sent, False outside systemd or on any send error (logged at debug; never raises).
    """
    addr = _address()
    if addr is None:
        return False
    message = "\n".join(fields).encode("utf-8", "replace")
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.sendto(message, addr)
    except OSError as exc:
        log.debug("sd_notify %r to %r failed: %s", message, addr, exc)
        return False
    return True


def _one_line(text: str) -> str:
    # A newline would start a new KEY=VALUE field; the status must stay one line.
    return " ".join(str(text).splitlines())


def ready(status: str | None = None) -> bool:
    """Tell systemd start-up is complete (``READY=1``), optionally with a status line."""
    if status is None:
        return notify("READY=1")
    return notify("READY=1", f"STATUS={_one_line(status)}")


def stopping() -> bool:
    """Tell systemd the service is shutting down (``STOPPING=1``)."""
    return notify("STOPPING=1")


def status(text: str) -> bool:
    """Set the one-line status that ``systemctl status`` shows (``STATUS=...``)."""
    return notify(f"STATUS={_one_line(text)}")


def watchdog_ping() -> bool:
    """Reset the service watchdog (``WATCHDOG=1``). Call only when the control loop is healthy."""
    return notify("WATCHDOG=1")


def watchdog_period() -> float | None:
    """The watchdog timeout in seconds, or None when no watchdog applies to this process.

    Read from ``WATCHDOG_USEC`` (microseconds); None when it is unset, not a positive integer, or
    when ``WATCHDOG_PID`` is set and names another process (the variables were inherited by a
    child, e.g. the control process). Ping at least every half of this period.
    """
    usec = os.environ.get("WATCHDOG_USEC", "")
    try:
        value = int(usec)
    except ValueError:
        return None
    if value <= 0:
        return None
    pid = os.environ.get("WATCHDOG_PID", "")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            return None
    return value / 1_000_000

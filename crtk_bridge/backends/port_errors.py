"""Hints for a serial port that will not open or a bus where no device answers.

A new user's three usual causes, each told with the next thing to do: the port path is wrong or
the adapter is unplugged (list ``/dev/serial/by-id``), another process holds the port (name it, as
``fuser`` would: the holder of the ``flock`` that pyserial's ``exclusive=True`` takes, from
``/proc/locks``, else any process with the device open, from ``/proc/*/fd``), or the user may not
open it (group ``dialout``). Linux ``/proc`` only; elsewhere the hints are shorter. Lifecycle path
only (reads ``/proc``: a few ms).
"""

from __future__ import annotations

import errno
import os

BY_ID = "/dev/serial/by-id"


def _adapters() -> str:
    try:
        names = sorted(os.listdir(BY_ID))
    except OSError:
        return f"no USB serial adapter found: {BY_ID} does not exist"
    if not names:
        return f"no USB serial adapter found: {BY_ID} is empty"
    return (f"adapters plugged in (ls {BY_ID}): {', '.join(names)}; set backend.port to "
            f"{BY_ID}/<one of these>")


def _process(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        cmd = ""
    return f"pid {pid} ({cmd[:80]})" if cmd else f"pid {pid}"


def port_holders(path: str) -> list[int]:
    """Pids holding ``path``: the owner of its flock (``/proc/locks``), else every process with
    it open that this user may inspect (``/proc/<pid>/fd``). Empty when none is visible."""
    try:
        st = os.stat(path)
        real = os.path.realpath(path)
    except OSError:
        return []
    dev = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    pids: list[int] = []
    try:
        with open("/proc/locks") as f:
            for line in f:
                fields = line.split()
                # "1: FLOCK  ADVISORY  WRITE 1234 00:05:321 0 EOF" (a "->" marks a waiter)
                if "->" not in fields and len(fields) >= 6 and fields[5] == dev:
                    pids.append(int(fields[4]))
    except (OSError, ValueError):
        pass
    if pids:
        return sorted(set(pids))
    me = os.getpid()
    for entry in os.listdir("/proc") if os.path.isdir("/proc") else ():
        if not entry.isdigit() or int(entry) == me:
            continue
        fd_dir = f"/proc/{entry}/fd"
        try:
            fds = os.listdir(fd_dir)
        except OSError:
            continue
        for fd in fds:
            try:
                if os.readlink(f"{fd_dir}/{fd}") == real:
                    pids.append(int(entry))
                    break
            except OSError:
                continue
    return pids


def open_error_reason(path: str, exc: BaseException) -> str:
    """Why serial port ``path`` did not open, with what to do about it: one clause. Falls back
    to the exception's own text for a cause not recognised here."""
    text = " ".join(str(exc).split())
    code = getattr(exc, "errno", None)
    if code == errno.ENOENT:
        return f"no such device (is the adapter plugged in? {_adapters()})"
    if code in (errno.EACCES, errno.EPERM):
        return ("permission denied (add the user to the port's group, usually dialout: "
                "sudo usermod -aG dialout $USER, then log in again)")
    if code in (errno.EAGAIN, errno.EBUSY):
        holders = [p for p in port_holders(path) if p != os.getpid()]
        if holders:
            return f"the port is in use by {', '.join(_process(p) for p in holders)}"
        return f"the port is in use by another process (not visible to this user; try: fuser -v {path})"
    return text


def silent_bus_hint(baudrate: int, ids: list[int]) -> str:
    """Why no device answered at all: one clause naming what to check."""
    return (f"no servo answered: check that the servos are powered (their own supply, not USB), that "
            f"backend.baudrate ({baudrate}) is the servos' baud rate, and that the joints' ids "
            f"({', '.join(map(str, ids))}) are the servos' ids")

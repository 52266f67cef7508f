"""A raw pseudo-terminal pair standing in for a serial port, with an optional stable symlink.

The simulator owns the master side; clients (pyserial, vendor SDKs) open the slave path, or the
symlink to it. The simulator also keeps one slave fd open for its whole life: without it, the
master reads EIO whenever no client has the slave open (between a client's close and reopen).

A USB adapter unplugged and plugged back is :meth:`PtyPort.unplug` (the pair is closed, so a
client's open fd reads EIO, and the link goes away, as a ``/dev/serial/by-id`` link does) then
:meth:`PtyPort.plug` (a new pair under a NEW device name, the same link re-pointed at it, as udev
does when the adapter comes back as another ``ttyACM`` number).
"""

from __future__ import annotations

import array
import fcntl
import os
import stat
import termios
import tty
from pathlib import Path

from . import SimulatorError


def _make_raw(fd: int) -> None:
    """Binary-clean line discipline: no echo, no CR/LF translation, no signals, 8N1."""
    tty.setraw(fd, termios.TCSANOW)
    attrs = termios.tcgetattr(fd)
    attrs[0] &= ~(termios.IXON | termios.IXOFF | termios.ICRNL | termios.INLCR | termios.IGNCR)
    attrs[1] &= ~termios.OPOST
    attrs[3] &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
    attrs[6][termios.VMIN] = 1
    attrs[6][termios.VTIME] = 0
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


# Linux termios2 (any baud rate, as pyserial sets non-standard ones): struct termios2 is four
# 32-bit flag words, c_line, c_cc[19], then c_ispeed and c_ospeed (32-bit words 9 and 10).
_TCGETS2 = 0x802C542A
_TCSETS2 = 0x402C542B
_BOTHER = 0o010000
_CBAUD = 0o010017


def line_baud(fd: int) -> int | None:
    """The baud rate the client last set on the pty (either side's fd; Linux keeps one termios for
    the pair), or None where the OS will not say. A real servo hears only its own rate."""
    buf = array.array("I", [0] * 16)
    try:
        fcntl.ioctl(fd, _TCGETS2, buf)
    except OSError:
        return None
    return int(buf[10]) or None


def set_line_baud(fd: int, baud: int) -> None:
    """Set the pty's baud rate (the rate a client that sets none talks at). Best effort."""
    buf = array.array("I", [0] * 16)
    try:
        fcntl.ioctl(fd, _TCGETS2, buf)
        buf[2] = (buf[2] & ~_CBAUD) | _BOTHER
        buf[9] = buf[10] = int(baud)
        fcntl.ioctl(fd, _TCSETS2, buf)
    except OSError:
        pass


def _set_nonblocking(fd: int) -> None:
    fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) | os.O_NONBLOCK)


class PtyPort:
    """A pty pair in raw mode. ``open()`` creates it, ``close()`` releases it (idempotent).

    ``master_fd`` is non-blocking: the simulator waits with poll() and must never block on a write
    when a client stops reading (a real bus would lose those bytes too).
    ``baudrate``: the line's rate until a client sets its own (:func:`line_baud` reads it).
    ``link``: if given, a symlink ``link -> slave path`` is created (a stale symlink is replaced;
    an existing regular file, directory or other non-symlink raises :class:`SimulatorError`) and
    removed on close.
    """

    def __init__(self, link: str | os.PathLike | None = None, baudrate: int | None = None):
        self.link = Path(link) if link is not None else None
        self.baudrate = baudrate  # the line's rate until a client sets its own
        self.master_fd: int | None = None
        self._slave_fd: int | None = None
        self.slave_path: str | None = None
        self._link_made = False

    @property
    def path(self) -> str:
        """The path clients should open: the link if any, else the slave device."""
        if self.slave_path is None:
            raise SimulatorError("pty is not open")
        return str(self.link) if self.link is not None else self.slave_path

    def open(self) -> None:
        if self.master_fd is not None:
            return
        if self.link is not None:
            self._check_link_free()
        master, slave = os.openpty()
        try:
            _make_raw(slave)
            if self.baudrate:
                set_line_baud(slave, self.baudrate)
            _set_nonblocking(master)
            self.slave_path = os.ttyname(slave)
            self.master_fd, self._slave_fd = master, slave
            if self.link is not None:
                self._make_link()
        except BaseException:
            os.close(master)
            os.close(slave)
            self.master_fd = self._slave_fd = None
            raise

    def _check_link_free(self) -> None:
        assert self.link is not None
        try:
            st = os.lstat(self.link)
        except FileNotFoundError:
            return
        if not stat.S_ISLNK(st.st_mode):
            raise SimulatorError(f"{self.link}: exists and is not a symlink; refusing to replace it")

    def _make_link(self) -> None:
        assert self.link is not None and self.slave_path is not None
        self._check_link_free()
        tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
        try:
            tmp.unlink(missing_ok=True)
            os.symlink(self.slave_path, tmp)
            os.replace(tmp, self.link)  # atomic: a waiting client never sees the link missing
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise SimulatorError(f"{self.link}: cannot create symlink: {exc.strerror or exc}") from exc
        self._link_made = True

    def unplug(self) -> None:
        """The adapter is pulled out: the link goes away and the pair is closed (a client's open
        fd reads EIO from now on). :meth:`plug` brings it back. Idempotent."""
        self.close()

    def plug(self) -> None:
        """The adapter is plugged back in: a new pair whose slave has another device name than
        before, behind the same link. No-op while plugged in."""
        if self.master_fd is not None:
            return
        old = self.slave_path
        held = []  # pairs holding the old name: the kernel hands out the lowest free pts number
        try:
            while True:
                self.open()
                if self.slave_path != old or len(held) >= 4:
                    break
                held.append((self.master_fd, self._slave_fd))
                self.master_fd = self._slave_fd = None
                self._link_made = False
        finally:
            for fds in held:
                for fd in fds:
                    os.close(fd)

    def close(self) -> None:
        if self._link_made and self.link is not None:
            # Remove only our own link: another simulator may have replaced it since.
            try:
                if os.readlink(self.link) == self.slave_path:
                    self.link.unlink()
            except OSError:
                pass
            self._link_made = False
        for fd in (self.master_fd, self._slave_fd):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master_fd = self._slave_fd = None

    def __enter__(self) -> PtyPort:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

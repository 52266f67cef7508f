"""Control socket of a running simulator: newline-delimited JSON over a Unix stream socket.

Tests and users inspect and change simulated device state from outside the bus, e.g. with
``socat - UNIX-CONNECT:/tmp/sim.ctl`` or :func:`control_request`. Each request line gets exactly
one reply line: ``{"ok": true, ...}`` or ``{"ok": false, "error": "..."}``.

This module is device-agnostic: :class:`ControlServer` parses lines and calls a handler
``handler(request: dict) -> dict`` supplied by the simulator (see ``FeetechSimulator.control``
for the Feetech commands: dump, read, write, fault, clear_faults, unplug).
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import selectors
import socket
import stat
import threading
from collections.abc import Callable
from pathlib import Path

from . import SimulatorError

log = logging.getLogger(__name__)

Handler = Callable[[dict], dict]
_MAX_LINE = 1 << 16


_PENDING = itertools.count()  # the temporary names of sockets being set up in this process


class ControlServer:
    """Serves ``handler`` on a Unix socket at ``path`` from one background thread.

    ``start()`` returns once the socket is listening. A stale socket file (nobody listening) is
    replaced; a live one, or a path that is not a socket, raises :class:`SimulatorError`.
    ``stop()`` is idempotent, joins the thread and removes the socket file.
    """

    def __init__(self, path: str | os.PathLike, handler: Handler):
        self.path = Path(path)
        self._handler = handler
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._wake_r = self._wake_w = -1
        self._stopping = False

    def start(self) -> None:
        if self._sock is not None:
            return
        pending = self.path.with_name(f".{os.getpid()}-{next(_PENDING)}~")  # bound here first (see below)
        if max(len(os.fsencode(self.path)), len(os.fsencode(pending))) >= 108:
            raise SimulatorError(f"{self.path}: Unix socket path too long (must be < 108 bytes)")
        self._remove_stale()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        # bound and listening under a temporary name, then renamed into place: whoever sees the
        # path (--sim and the tests wait for it to exist) can connect at once; bind() alone makes
        # the file before listen(), and a connect in between is refused
        try:
            pending.unlink(missing_ok=True)
            sock.bind(os.fspath(pending))
            os.chmod(pending, 0o660)
            sock.listen(8)
            sock.setblocking(False)
            os.replace(pending, self.path)
        except OSError as exc:
            sock.close()
            pending.unlink(missing_ok=True)
            raise SimulatorError(f"{self.path}: cannot listen: {exc.strerror or exc}") from exc
        self._sock = sock
        self._wake_r, self._wake_w = os.pipe()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="sim-control", daemon=True)
        self._thread.start()

    def _remove_stale(self) -> None:
        try:
            st = os.lstat(self.path)
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(st.st_mode):
            raise SimulatorError(f"{self.path}: exists and is not a socket; refusing to replace it")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(os.fspath(self.path))
        except OSError:
            self.path.unlink(missing_ok=True)  # stale: nobody listens
            return
        finally:
            probe.close()
        raise SimulatorError(f"{self.path}: another process is listening on this control socket")

    def stop(self) -> None:
        if self._sock is None:
            return
        self._stopping = True
        os.write(self._wake_w, b"x")
        if self._thread is not None:
            self._thread.join()
        self._thread = None
        self._sock.close()
        self._sock = None
        os.close(self._wake_r)
        os.close(self._wake_w)
        self._wake_r = self._wake_w = -1
        self.path.unlink(missing_ok=True)

    # --- serving thread ---
    def _run(self) -> None:
        assert self._sock is not None
        sel = selectors.DefaultSelector()
        sel.register(self._sock, selectors.EVENT_READ, None)
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        buffers: dict[socket.socket, bytearray] = {}
        try:
            while not self._stopping:
                for key, _ in sel.select():
                    if key.data == "wake":
                        continue
                    if key.fileobj is self._sock:
                        try:
                            conn, _ = self._sock.accept()
                        except OSError:
                            continue
                        conn.setblocking(True)
                        conn.settimeout(2.0)  # a client that never reads must not wedge us
                        buffers[conn] = bytearray()
                        sel.register(conn, selectors.EVENT_READ, "conn")
                        continue
                    conn = key.fileobj  # type: ignore[assignment]
                    if not self._serve(conn, buffers[conn]):
                        sel.unregister(conn)
                        del buffers[conn]
                        conn.close()
        finally:
            for conn in buffers:
                conn.close()
            sel.close()

    def _serve(self, conn: socket.socket, buf: bytearray) -> bool:
        """Read what is there, answer every complete line. False when the client is gone."""
        try:
            data = conn.recv(65536)
        except OSError:
            return False
        if not data:
            return False
        buf += data
        while True:
            nl = buf.find(b"\n")
            if nl < 0:
                if len(buf) > _MAX_LINE:
                    return self._send(conn, {"ok": False, "error": "request line too long"}) and False
                return True
            line = bytes(buf[:nl]).strip()
            del buf[: nl + 1]
            if not line:
                continue
            if not self._send(conn, self._answer(line)):
                return False

    def _answer(self, line: bytes) -> dict:
        try:
            request = json.loads(line)
        except ValueError as exc:
            return {"ok": False, "error": f"not valid JSON: {exc}"}
        if not isinstance(request, dict):
            return {"ok": False, "error": "a request must be a JSON object"}
        try:
            return self._handler(request)
        except Exception as exc:  # the control socket must survive any bad request
            log.exception("control request %r failed", request)
            return {"ok": False, "error": f"internal error: {exc}"}

    @staticmethod
    def _send(conn: socket.socket, reply: dict) -> bool:
        try:
            conn.sendall(json.dumps(reply, separators=(",", ":")).encode() + b"\n")
            return True
        except OSError:
            return False


def control_request(path: str | os.PathLike, request: dict, timeout: float = 2.0) -> dict:
    """Send one request to a simulator's control socket and return its reply. Blocks.

    Raises :class:`SimulatorError` if the socket cannot be reached or does not answer within
    ``timeout`` seconds. A refused request is a normal reply with ``ok`` false.
    """
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout)
    try:
        sock.connect(os.fspath(path))
        sock.sendall(json.dumps(request).encode() + b"\n")
        buf = bytearray()
        while b"\n" not in buf:
            chunk = sock.recv(65536)
            if not chunk:
                raise SimulatorError(f"{path}: control socket closed without a reply")
            buf += chunk
    except OSError as exc:
        raise SimulatorError(f"{path}: control request failed: {exc}") from exc
    finally:
        sock.close()
    return json.loads(buf[: buf.index(b"\n")])

"""One session with a crtk-bridge daemon over its Unix socket (docs/protocol.md, version 1).

:class:`Connection` is synchronous for the caller and runs one background reader thread that
routes every incoming line: replies to the request waiting on their ``id``, ``operating_state``
events to :attr:`Connection.operating_state` (with a condition variable to wait on), stream frames
to their subscription, and ``status`` / ``warning`` / ``error`` events to a bounded deque and an
optional callback.

Robust to the orders protocol.md allows: events and frames interleave with replies, and the
``is_busy: true`` event of a move arrives *before* the move's reply. When the daemon goes away every
pending request and every waiter fails at once with :class:`DaemonConnectionError`; nothing hangs.
"""

from __future__ import annotations

import collections
import itertools
import logging
import socket
import threading
import time
from typing import Any, Callable, NamedTuple

import msgspec

from crtk_client.errors import CommandError, CrtkBridgeError
from crtk_client.vocabulary import PROTOCOL_VERSION  # noqa: F401 - re-exported by crtk_bridge.client

log = logging.getLogger(__name__)

_encode = msgspec.json.encode
_decode = msgspec.json.decode


class DaemonConnectionError(CrtkBridgeError, ConnectionError):
    """The daemon is not running, refused the connection, or went away. Names the socket path."""


class Event(NamedTuple):
    """A pushed ``status``, ``warning`` or ``error`` event; ``data`` has stamp, ns, code, message."""

    kind: str
    data: dict


class _Pending:
    __slots__ = ("cmd", "done", "msg", "error", "on_reply")

    def __init__(self, cmd: str, on_reply: Callable[[Any], None] | None):
        self.cmd = cmd
        self.done = threading.Event()
        self.msg: dict | None = None
        self.error: BaseException | None = None
        self.on_reply = on_reply


def encode_vector(values, what: str = "vector") -> list[float]:
    """A list, tuple or numpy array as a list of plain finite floats (the wire wants JSON numbers).

    Raises :class:`CommandError` ``bad_request`` on a non-finite or non-numeric entry, before
    anything is sent (:func:`crtk_bridge.vectors.client_floats`, loaded on first use: a plain
    command needs no numpy).
    """
    from crtk_client.vectors import client_floats
    return client_floats(values, what)


def _open_socket(path: str, timeout: float) -> socket.socket:
    """Connect to the daemon's Unix socket; DaemonConnectionError naming ``path`` if none answers."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.settimeout(timeout)
        sock.connect(path)
        sock.settimeout(None)
    except FileNotFoundError as exc:
        sock.close()
        raise DaemonConnectionError(
            f"crtk-bridge daemon not running: no socket at {path}") from exc
    except ConnectionRefusedError as exc:
        sock.close()
        raise DaemonConnectionError(
            f"crtk-bridge daemon not running: connection refused at {path} "
            "(stale socket file?)") from exc
    except PermissionError as exc:
        sock.close()
        raise DaemonConnectionError(
            f"cannot connect to crtk-bridge at {path}: permission denied "
            "(the socket is mode 0660: join its group)") from exc
    except OSError as exc:
        sock.close()
        raise DaemonConnectionError(
            f"cannot connect to crtk-bridge at {path}: {exc}") from exc
    return sock


class Connection:
    """A session with one crtk-bridge daemon on the Unix socket ``path``, or over ``stream`` (an
    open :class:`~crtk_client.zenoh_link.ZenohStream`; ``path`` then only names it).

    Opening connects at once and raises :class:`DaemonConnectionError` (a ``ConnectionError``)
    naming ``path`` if no daemon listens there. ``timeout`` (s) is the default reply timeout of
    :meth:`request`. Thread-safe: several threads may call :meth:`request` concurrently. A context
    manager; :meth:`close` is idempotent.

    Public state, all updated by the reader thread under :attr:`cond`:

    - :attr:`operating_state`: the latest OperatingState dict (``state``, ``is_homed``,
      ``is_busy``, ``busy_seq``, ``stamp``), ``None`` until the first one arrives;
    - :attr:`state_events`: how many operating_state events have arrived (to wait for a *newer* one);
    - :attr:`idle_seq`: the highest ``busy_seq`` seen in an operating_state with ``is_busy`` false,
      i.e. every move or home numbered ``<= idle_seq`` has ended;
    - :attr:`max_busy_seq`: the highest ``busy_seq`` seen at all (every move or home numbered
      ``<= max_busy_seq`` has started);
    - :attr:`events`: the last ``max_events`` status/warning/error :class:`Event` s;
    - :attr:`event_count`: how many status/warning/error events have arrived in all (take it
      before a command, then :meth:`events_since` gives what came after);
    - :attr:`on_event`: optional ``callable(Event)``, called on the reader thread.
    """

    def __init__(self, path: str, timeout: float = 5.0, max_events: int = 256, stream: Any = None):
        self.path = str(path)
        self.timeout = float(timeout)
        self.cond = threading.Condition()
        self.operating_state: dict | None = None
        self.state_events = 0
        self.idle_seq = -1
        self.max_busy_seq = -1
        self.events: collections.deque[Event] = collections.deque(maxlen=max_events)
        self.event_count = 0
        self.on_event: Callable[[Event], None] | None = None
        self._pending: dict[int, _Pending] = {}
        self._streams: dict[int, Callable[[dict | None, BaseException | None], None]] = {}
        self._ids = itertools.count(1)
        self._send_lock = threading.Lock()
        self._closed_error: DaemonConnectionError | None = None
        self._closing = False

        # the Unix socket at ``path``, or an open ``stream`` with the same methods (sendall, recv,
        # shutdown, close): client/zenoh_link.ZenohStream, the protocol over Zenoh; ``path`` names it
        self._sock = stream if stream is not None else _open_socket(self.path, self.timeout)
        self._reader = threading.Thread(
            target=self._read_loop, name=f"crtk-client-reader:{self.path}", daemon=True)
        self._reader.start()

    # -- lifecycle ---------------------------------------------------------------------------

    def __enter__(self) -> "Connection":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """True once the connection is closed (by :meth:`close` or by the daemon)."""
        return self._closed_error is not None

    def close(self) -> None:
        """Close the session (the daemon releases control if this session held it). Idempotent;
        pending requests and waiters fail with :class:`DaemonConnectionError`."""
        self._closing = True
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        if threading.current_thread() is not self._reader:
            self._reader.join(timeout=2.0)
        self._fail_all(DaemonConnectionError(f"connection to {self.path} closed"))
        try:
            self._sock.close()
        except OSError:
            pass

    # -- requests ----------------------------------------------------------------------------

    def request(self, cmd: str, ns: str | None = None, data: Any = None,
                timeout: float | None = None) -> Any:
        """Send one request and block until its reply; return the reply's ``data``.

        ``timeout`` (s, default the connection's) bounds the wait. Raises :class:`CommandError`
        (``code``, ``message`` from the daemon; ``.cmd`` set) on an error reply, ``TimeoutError``
        when no reply comes in time, :class:`DaemonConnectionError` when the daemon is gone or goes
        away meanwhile. Must not be called from a subscription or event callback (reader thread).
        """
        return self._request(cmd, ns, data, timeout, None)

    def request_all(self, requests: list[tuple[str, str | None, Any]], timeout: float | None = None) -> list[Any]:
        """Send several requests ``(cmd, ns, data)`` at once (one write), then wait for their
        replies: the daemon handles them in order, so the whole costs about one round trip
        instead of one each (a LeRobot action on an arm and its gripper). Returns the replies'
        ``data`` in order; raises like :meth:`request` for the first that failed, after every
        reply came (or the timeout, which bounds the whole wait)."""
        sent = self._send([(cmd, ns, data, None) for cmd, ns, data in requests])
        t = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + t
        errors: list[BaseException] = []
        out = []
        for rid, pending in sent:
            try:
                out.append(self._wait(rid, pending, max(0.0, deadline - time.monotonic()), t))
            except (CommandError, TimeoutError, DaemonConnectionError) as exc:
                errors.append(exc)
                out.append(None)
        if errors:
            raise errors[0]
        return out

    def _request(self, cmd, ns, data, timeout, on_reply):
        ((rid, pending),) = self._send([(cmd, ns, data, on_reply)])
        t = self.timeout if timeout is None else timeout
        return self._wait(rid, pending, t, t)

    def _send(self, requests) -> list[tuple[int, _Pending]]:
        """Register and write the requests ``(cmd, ns, data, on_reply)`` in one write."""
        if threading.current_thread() is self._reader:
            raise RuntimeError(
                "Connection.request() called from a subscription/event callback: it would wait "
                "for a reply that only this thread can read; hand the work to another thread")
        if self._closed_error is not None:
            raise DaemonConnectionError(str(self._closed_error))
        lines, sent = [], []
        for cmd, ns, data, on_reply in requests:
            rid = next(self._ids)
            msg: dict[str, Any] = {"id": rid, "cmd": cmd}
            if ns is not None:
                msg["ns"] = ns
            if data is not None:
                msg["data"] = data
            lines.append(_encode(msg) + b"\n")
            sent.append((rid, _Pending(cmd, on_reply)))
        with self.cond:
            if self._closed_error is not None:
                raise DaemonConnectionError(str(self._closed_error))
            self._pending.update(sent)
        try:
            with self._send_lock:
                self._sock.sendall(b"".join(lines))
        except OSError as exc:
            with self.cond:
                for rid, _ in sent:
                    self._pending.pop(rid, None)
            err = self._closed_error or DaemonConnectionError(
                f"crtk-bridge at {self.path} went away ({exc})")
            raise DaemonConnectionError(str(err)) from exc
        return sent

    def _wait(self, rid: int, pending: _Pending, wait_s: float, timeout_s: float) -> Any:
        """The reply of request ``rid``: its data, or the error it carries."""
        cmd = pending.cmd
        if not pending.done.wait(wait_s):
            with self.cond:
                self._pending.pop(rid, None)
            if not pending.done.is_set():
                raise TimeoutError(f"{cmd}: no reply from crtk-bridge at {self.path} within {timeout_s:g} s")
        if pending.error is not None:
            raise DaemonConnectionError(f"{cmd}: {pending.error}") from pending.error
        reply = pending.msg
        assert reply is not None
        if reply.get("ok"):
            return reply.get("data")
        err = reply.get("error") or {}
        exc = CommandError(str(err.get("code", "internal")), str(err.get("message", "")))
        exc.cmd = cmd  # type: ignore[attr-defined]
        raise exc

    # -- waiting on operating_state ----------------------------------------------------------

    def wait_for(self, predicate: Callable[["Connection"], bool], timeout: float | None) -> bool:
        """Block until ``predicate(self)`` is true (evaluated under :attr:`cond` on every
        operating_state event) or ``timeout`` s pass (``None``: forever). Returns the predicate's
        last value. Raises :class:`DaemonConnectionError` if the connection closes first."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self.cond:
            while True:
                if predicate(self):
                    return True
                if self._closed_error is not None:
                    raise DaemonConnectionError(str(self._closed_error))
                if deadline is None:
                    self.cond.wait()
                else:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return False
                    self.cond.wait(left)

    # -- streams (used by device.Subscription) -----------------------------------------------

    def _open_stream(self, topic: str, rate_hz: float, ns: str | None,
                     sink: Callable[[dict | None, BaseException | None], None],
                     timeout: float | None = None) -> int:
        """Subscribe and route frames to ``sink(data, None)``; on disconnect ``sink(None, exc)``.
        The sink is registered by the reader thread as it reads the reply, so no frame is lost."""

        def register(data):
            with self.cond:
                self._streams[int(data["sub"])] = sink

        data = self._request("subscribe", ns, {"topic": topic, "rate_hz": rate_hz}, timeout,
                             register)
        return int(data["sub"])

    def _close_stream(self, sub: int) -> None:
        with self.cond:
            had = self._streams.pop(sub, None) is not None
        if had and self._closed_error is None:
            try:
                self._request("unsubscribe", None, {"sub": sub}, None, None)
            except (CommandError, TimeoutError, ConnectionError):
                pass  # the stream is gone on our side; the daemon drops it on disconnect anyway

    # -- reader thread -----------------------------------------------------------------------

    def _read_loop(self) -> None:
        buf = b""
        reason = "closed the connection"
        try:
            while True:
                chunk = self._sock.recv(65536)
                if not chunk:
                    break
                buf += chunk
                while True:
                    nl = buf.find(b"\n")
                    if nl < 0:
                        break
                    line, buf = buf[:nl], buf[nl + 1:]
                    if line.strip():
                        self._dispatch(line)
        except OSError as exc:
            reason = f"connection lost ({exc})"
        except Exception as exc:  # a bug here must not leave requests hanging
            log.exception("crtk-bridge client reader failed")
            reason = f"client reader failed ({exc!r})"
        if self._closing:
            err = DaemonConnectionError(f"connection to {self.path} closed")
        else:
            err = DaemonConnectionError(f"crtk-bridge daemon at {self.path} {reason}")
        self._fail_all(err)

    def _fail_all(self, err: DaemonConnectionError) -> None:
        with self.cond:
            if self._closed_error is None:
                self._closed_error = err
            pending = list(self._pending.values())
            self._pending.clear()
            streams = list(self._streams.values())
            self._streams.clear()
            self.cond.notify_all()
        for p in pending:
            p.error = err
            p.done.set()
        for sink in streams:
            try:
                sink(None, err)
            except Exception:
                log.exception("subscription sink failed on disconnect")

    def _dispatch(self, line: bytes) -> None:
        try:
            msg = _decode(line)
        except msgspec.DecodeError:
            log.warning("crtk-bridge sent a line that is not JSON: %.200r", line)
            return
        if not isinstance(msg, dict):
            log.warning("crtk-bridge sent a non-object line: %.200r", line)
            return
        if "id" in msg:
            self._on_reply(msg)
        elif "event" in msg:
            self._on_event(msg)
        elif "sub" in msg:
            self._on_frame(msg)
        else:
            log.warning("crtk-bridge sent an unknown message: %.200r", line)

    def _on_reply(self, msg: dict) -> None:
        rid = msg.get("id")
        if rid is None and msg.get("ok"):
            # not ours: we never send a request without an id (daemons up to 0.1 fan out the
            # control process's reply to its internal "_client_lost" notice to every session)
            log.debug("ignoring a success reply without id: %.200r", msg)
            return
        if rid is None:
            # bad_request for a line the daemon could not parse; we only send valid JSON
            err = msg.get("error") or {}
            log.warning("crtk-bridge rejected an unparseable request: %s", err.get("message"))
            self._record_event(Event("error", {"code": err.get("code"),
                                               "message": err.get("message"), "ns": None,
                                               "stamp": time.time()}))
            return
        with self.cond:
            pending = self._pending.pop(rid, None)
        if pending is None:
            return  # its requester timed out
        if pending.on_reply is not None and msg.get("ok"):
            try:
                pending.on_reply(msg.get("data"))
            except Exception:
                log.exception("reply hook for %s failed", pending.cmd)
        pending.msg = msg
        pending.done.set()

    def _on_event(self, msg: dict) -> None:
        kind = msg.get("event")
        data = msg.get("data")
        if kind == "operating_state" and isinstance(data, dict):
            self._set_operating_state(data)
        else:
            self._record_event(Event(str(kind), data if isinstance(data, dict) else {"data": data}))

    def _set_operating_state(self, data: dict, from_reply: bool = False) -> None:
        with self.cond:
            if from_reply:
                # a reply's OperatingState ("after the command") is adopted so that is_enabled()
                # agrees with enable()'s result at once; never let it roll busy_seq back
                cur = self.operating_state
                if cur is not None and data.get("busy_seq", 0) < cur.get("busy_seq", 0):
                    return
            else:
                self.state_events += 1
            self.operating_state = data
            seq = data.get("busy_seq")
            if isinstance(seq, int):
                self.max_busy_seq = max(self.max_busy_seq, seq)
                if not data.get("is_busy", False):
                    self.idle_seq = max(self.idle_seq, seq)
            self.cond.notify_all()

    def listen_events(self, callback: Callable[[Event], None]) -> None:
        """Hand ``callback`` the events kept since the connection opened (oldest first), then
        every later one (it becomes :attr:`on_event`), atomically: each event reaches it exactly
        once and in order, even one arriving meanwhile; nothing between connect and listening is
        lost (up to ``max_events`` are kept). The backlog is handed over with :attr:`cond` held:
        ``callback`` must not block (``queue.Queue.put`` is fine)."""
        with self.cond:
            for ev in self.events:
                callback(ev)
            self.on_event = callback

    def events_since(self, count: int) -> list[Event]:
        """The events that arrived after :attr:`event_count` was ``count`` (as many as are
        still kept), oldest first."""
        with self.cond:
            n = min(max(0, self.event_count - count), len(self.events))
            return list(self.events)[len(self.events) - n:] if n else []

    def _record_event(self, ev: Event) -> None:
        with self.cond:
            self.events.append(ev)
            self.event_count += 1
            self.cond.notify_all()
            cb = self.on_event  # read under the lock: see listen_events
        if cb is not None:
            try:
                cb(ev)
            except Exception:
                log.exception("on_event callback failed")

    def _on_frame(self, msg: dict) -> None:
        data = msg.get("data")
        # operating_state frames do not update self.operating_state: frames may be dropped and
        # the pushed events (never dropped, in order) are the one source of truth
        with self.cond:
            sink = self._streams.get(msg.get("sub"))
        if sink is None:
            return  # unsubscribed meanwhile
        try:
            sink(data, None)
        except Exception:
            log.exception("subscription callback failed (topic %s)", msg.get("topic"))

"""The socket protocol carried over Zenoh, daemon side (docs/zenoh.md, "Remote clients").

A remote client is a server :class:`~crtk_bridge.server.server.Session` like a socket connection:
the same dispatcher answers its lines, so control ownership (one controller), stops from anyone,
streams and client loss all follow. The daemon announces itself with a liveliness token
(``crtk_bridge/<robot>/daemon``); a client declares its own token
(``crtk_bridge/<robot>/client/<cid>``), which opens its session here (greeted with the operating
state, as a socket connection is), sends request lines on ``.../in/<cid>`` and reads replies,
events and frames on ``.../out/<cid>``. The client's token going away (it closed, its process
died, its link dropped) is its socket closing: the session ends and, if it held control, the
robot stops safely as on any client loss.

Replies and events are published reliably with congestion control BLOCK (never dropped, in
order); stream frames with DROP on a lower priority (Zenoh queues them apart), so a slow remote
client loses frames and never slows the daemon, as on the socket. Stream frames come encoded
(server/streams.py: one encoding per topic a tick, shared by every subscriber). Every put runs on
the session's sender thread, never the event loop: eclipse-zenoh's ``put`` is synchronous (it
releases the GIL), and waits for room in the link's queue (up to ``wait_before_drop`` for DROP,
``wait_before_close`` for BLOCK), so one thread for every session would let a congested client
delay the others; a thread per session wakes once for what the event loop handed it since its last
wake-up and puts it in at most two samples (its replies, in order, then its frames), each one or
more whole lines, as the client reads them. While the thread is behind, a session keeps at most
``FRAME_BACKLOG`` frames: the oldest is dropped for the newest, and counted (the session's
``dropped``, period_statistics' ``frames_dropped``, a log line). Zenoh delivers on its own
threads: every sample is handed to the event loop (``call_soon_threadsafe``), where the server
runs as for the socket.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import threading
from typing import Any

from ..errors import CrtkBridgeError
from ..server.protocol import MAX_LINE, STOP_COMMANDS, ProtocolError, decode_request, encode, error
from ..server.server import Server, Session
from . import tunnel_keys as keys
from .zenoh_session import ZenohConfig

log = logging.getLogger("crtk_bridge.transport.tunnel")

#: how long start-up asks the network whether another daemon already serves this robot's name
DUPLICATE_CHECK_S = 1.0
#: request lines a remote session may have waiting; beyond, new ones are refused (stops never
#: are): Zenoh has no back-pressure towards a client the way a socket's buffer has
MAX_PENDING = 4096
#: stream frames a remote session keeps while its sender thread is behind: beyond, the oldest is
#: dropped for the newest (replies and events never are)
FRAME_BACKLOG = 64


class TunnelSession(Session):
    """A remote client's session: what the server sends goes to its ``out`` key.

    Puts happen on the session's own sender thread: replies and events in the order the server
    sent them; a reply waits for room on a stalled link (congestion control BLOCK, up to Zenoh's
    ``wait_before_close``, after which Zenoh closes the link and the client is lost), and the
    event loop, which serves every other client, never waits with it. Stream frames wait in a
    bounded outbox (``FRAME_BACKLOG``, the oldest dropped and counted when full), as a socket
    drops them when its buffer is full; Zenoh queues them apart, so a frame may lag a reply."""

    def __init__(self, sid: int, cid: str, replies: Any, frames: Any):
        super().__init__(sid, None, peer=f"Zenoh client {cid[:8]}")
        self.cid = cid
        self._replies = replies  # zenoh.Publisher, reliable, congestion control BLOCK
        self._frames = frames  # the same key, congestion control DROP
        self.lines: asyncio.Queue[bytes | None] = asyncio.Queue()
        self.task: asyncio.Task | None = None
        self._wake = threading.Condition()
        self._reply_box: collections.deque[bytes] = collections.deque()  # never dropped
        self._frame_box: collections.deque[bytes] = collections.deque()  # at most FRAME_BACKLOG
        self._ending = False
        self._sender = threading.Thread(target=self._send_all, name=f"zenoh out {cid[:8]}", daemon=True)
        self._sender.start()

    def send(self, msg: Any) -> None:
        if not self.closed:
            data = encode(msg)
            with self._wake:
                self._reply_box.append(data)
                self._wake.notify()

    def send_frame(self, line: bytes) -> None:
        if self.closed:
            return
        with self._wake:
            full = len(self._frame_box) >= FRAME_BACKLOG  # the link is not taking what we send
            if full:
                self._frame_box.popleft()  # the oldest goes: the newest sample is what a client wants
            self._frame_box.append(line)
        if full:
            self.count_dropped()

    def flush(self) -> None:
        """The tick's frames are all handed over: wake the sender thread once for them."""
        with self._wake:
            self._wake.notify()

    def _send_all(self) -> None:
        """Sender thread: put what the server sent (replies and events in order, then the frames
        kept); undeclare once the session closed and everything it sent before is out."""
        while True:
            with self._wake:
                while not (self._reply_box or self._frame_box or self._ending):
                    self._wake.wait()
                replies = b"".join(self._reply_box)
                frames = b"".join(self._frame_box)
                self._reply_box.clear()
                self._frame_box.clear()
                last = self._ending
            for publisher, data in ((self._replies, replies), (self._frames, frames)):
                if data:
                    try:
                        publisher.put(data)
                    except Exception as exc:  # the session is closing under us: the client is gone anyway
                        log.debug("%s: put failed: %s", self.describe(), exc)
            if last:
                break
        for publisher in (self._replies, self._frames):
            try:
                publisher.undeclare()
            except Exception:
                pass

    def close(self) -> None:
        """Stop accepting messages; those already sent still go out (never blocks)."""
        if not self.closed:
            self.closed = True
            with self._wake:
                self._ending = True
                self._wake.notify()


class TunnelServer:
    """Serves the socket protocol on a Zenoh session for ``server``'s robot (a daemon service:
    ``async start()``, ``async close()``; see daemon.zenoh_services)."""

    def __init__(self, server: Server, session: Any, config: ZenohConfig):
        self.server = server
        self.session = session
        self.config = config
        self.robot = server.robot
        self.clients: dict[str, TunnelSession] = {}
        self._declared: list[Any] = []
        self._loop: asyncio.AbstractEventLoop | None = None

    async def start(self) -> None:
        """Announce the daemon and accept clients. Raises CrtkBridgeError when another daemon
        already serves this robot's name on the Zenoh network."""
        import zenoh

        self._zenoh = zenoh
        self._loop = asyncio.get_running_loop()
        if await self._loop.run_in_executor(None, self._another_daemon_named_like_us):
            raise CrtkBridgeError(f"{self.robot}: another crtk-bridge daemon already serves robot {self.robot!r} "
                                  f"on this Zenoh network ({keys.daemon_token(self.robot)}): stop it, or give "
                                  "this robot another name")
        live = self.session.liveliness()
        # on Zenoh's threads (indirect=False): the callbacks only hand the sample to the event loop
        on_request = zenoh.handlers.Callback(self._on_request, indirect=False)
        on_client = zenoh.handlers.Callback(self._on_client, indirect=False)
        self._declared = [
            self.session.declare_subscriber(keys.requests(self.robot, "*"), on_request),
            live.declare_subscriber(keys.client_token(self.robot, "*"), on_client, history=True),
            live.declare_token(keys.daemon_token(self.robot)),  # last: clients come once all is ready
        ]

    def _another_daemon_named_like_us(self) -> bool:
        """Watch this robot's daemon token for DUPLICATE_CHECK_S (blocks): Zenoh peers joined to
        one router open their direct links after the session opened, so a one-shot query made
        at once could miss a daemon that is there."""
        found = threading.Event()

        def seen(sample: Any) -> None:
            if sample.kind == self._zenoh.SampleKind.PUT:
                found.set()

        watch = self.session.liveliness().declare_subscriber(
            keys.daemon_token(self.robot), self._zenoh.handlers.Callback(seen, indirect=False), history=True)
        try:
            return found.wait(DUPLICATE_CHECK_S)
        finally:
            watch.undeclare()

    async def close(self) -> None:
        for entity in reversed(self._declared):
            try:
                entity.undeclare()
            except Exception:
                pass
        self._declared = []
        for cid in list(self.clients):
            self._end(cid, client_lost=False)  # the daemon is stopping: the robot stops already

    # ------------------------------------------------------- Zenoh threads -> event loop
    def _on_client(self, sample: Any) -> None:
        cid = keys.last(str(sample.key_expr))
        if sample.kind == self._zenoh.SampleKind.PUT:
            self._call(self._begin, cid)
        else:
            self._call(self._lost, cid)

    def _on_request(self, sample: Any) -> None:
        self._call(self._lines, keys.last(str(sample.key_expr)), sample.payload.to_bytes())

    def _call(self, fn, *args) -> None:
        try:
            self._loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:
            pass  # the event loop is closed: the daemon is gone

    # ------------------------------------------------------- on the event loop
    def _begin(self, cid: str) -> None:
        if cid in self.clients or not self._declared:
            return
        zenoh = self._zenoh
        key = keys.replies(self.robot, cid)
        replies = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                 reliability=zenoh.Reliability.RELIABLE)
        # frames on a lower priority, so Zenoh queues them apart: they never fill the queue
        # replies and events wait in (a reply is never held up by frames, a frame may lag a reply)
        frames = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP,
                                                reliability=zenoh.Reliability.RELIABLE,
                                                priority=zenoh.Priority.DATA_LOW)
        s = TunnelSession(self.server.new_session_id(), cid, replies, frames)
        self.clients[cid] = s
        self.server.attach(s)  # the greeting: the client's connect returns on it
        s.task = asyncio.get_running_loop().create_task(self._serve(s))
        log.info("%s: %s opened (Zenoh)", self.robot, s.describe())

    def _lines(self, cid: str, payload: bytes) -> None:
        s = self.clients.get(cid)
        if s is None:
            return  # no session: the client's token is not (or no longer) there
        for line in payload.split(b"\n"):
            if not line.strip():
                continue
            if s.lines.qsize() >= MAX_PENDING and not _is_stop(line):
                s.send(error(_request_id(line), "bad_request",
                             f"{self.robot}: request discarded: {MAX_PENDING} requests of this session are "
                             f"waiting (sent faster than they are served); {', '.join(STOP_COMMANDS)} are "
                             "always accepted"))
                continue
            s.lines.put_nowait(line)

    def _lost(self, cid: str) -> None:
        s = self.clients.get(cid)
        if s is not None:
            s.lines.put_nowait(None)  # the lines it sent before leaving are still answered, in order

    async def _serve(self, s: TunnelSession) -> None:
        try:
            while True:
                line = await s.lines.get()
                if line is None:
                    break
                if len(line) > MAX_LINE:
                    s.send(error(None, "bad_request", f"request line longer than {MAX_LINE} bytes; discarded"))
                    continue
                await self.server.handle_line(s, line)
        finally:
            if self.clients.get(s.cid) is s:
                self._end(s.cid, client_lost=True)

    def _end(self, cid: str, client_lost: bool) -> None:
        s = self.clients.pop(cid)
        self.server.detach(s, client_lost=client_lost)
        s.close()
        if s.task is not None and s.task is not asyncio.current_task():
            s.task.cancel()
        log.info("%s: %s closed (Zenoh)", self.robot, s.describe())


def _envelope(line: bytes):
    try:
        return decode_request(line) if len(line) <= MAX_LINE else None
    except ProtocolError:
        return None


def _is_stop(line: bytes) -> bool:
    req = _envelope(line)
    return req is not None and req.cmd in STOP_COMMANDS


def _request_id(line: bytes):
    req = _envelope(line)
    return None if req is None else req.id

"""Stream fan-out: a topic's frames for every subscriber from one read and one encoding a tick.

The server keeps one :class:`TopicStream` per (topic, ns) that somebody subscribes to, whatever the
transport (socket or a remote client over Zenoh). Each tick it takes the topic's data once (the
shared-memory snapshot, a cartesian query), encodes it to JSON once, and hands each subscriber due
at that tick its frame as bytes: the subscriber's own head (``{"topic", "ns", "sub"``, encoded when
it subscribed) + the shared body + ``}``. So the front's cost per tick grows with the number of
topics, not of subscribers (docs/architecture.md, "Streams").

A stream ticks at its fastest subscriber's period; a slower subscriber gets a frame at the first
tick at or after its own next time (tolerance: half a tick), so every subscriber of a topic shares
the same ticks. A subscriber that fell behind (the event loop was held) skips ticks, never bursts.
One task ticks every stream (:func:`tick_all`): streams due together are served in one wake-up of
the event loop, and each session is flushed once for all of them (a remote client's sender thread
wakes once, and puts the tick's frames in one sample).
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Iterable

from .protocol import encode_body, frame_head

log = logging.getLogger("crtk_bridge.server")

TAIL = b"}\n"


class Subscriber:
    """One subscription (``session.subs[sub]``): ``cancel()`` ends it."""

    __slots__ = ("session", "sub", "period", "next_t", "head", "stream")

    def __init__(self, session: Any, sub: int, period: float, head: bytes, stream: TopicStream):
        self.session = session
        self.sub = sub
        self.period = period
        self.next_t = 0.0
        self.head = head
        self.stream = stream

    def cancel(self) -> None:
        self.stream.remove(self)


class TopicStream:
    """The subscribers of one (topic, ns) and its tick. ``produce()`` returns the topic's data
    (called once per tick that has a subscriber due); ``on_empty(stream)`` is called when its
    last subscriber leaves (the server then forgets it)."""

    def __init__(self, topic: str, ns: str | None, produce: Callable[[], Any],
                 on_empty: Callable[[TopicStream], None] = lambda s: None):
        self.topic = topic
        self.ns = ns
        self.produce = produce
        self.on_empty = on_empty
        self.subscribers: list[Subscriber] = []
        self._error_said = -1.0

    def add(self, session: Any, sub: int, period: float, now: float) -> Subscriber:
        """A new subscriber, due at once (its first frame goes out at the stream's next tick)."""
        s = Subscriber(session, sub, period, frame_head(self.topic, self.ns, sub), self)
        s.next_t = now
        self.subscribers.append(s)
        return s

    def remove(self, s: Subscriber) -> None:
        try:
            self.subscribers.remove(s)
        except ValueError:
            return
        if not self.subscribers:
            self.on_empty(self)

    @property
    def period(self) -> float:
        """The tick: the fastest subscriber's period."""
        return min(s.period for s in self.subscribers) if self.subscribers else 1.0

    def tick(self, now: float) -> list[Any]:
        """Send the frame of ``now`` to every subscriber due; returns their sessions (to flush).
        The data is read and encoded once, whatever their number."""
        for s in [s for s in self.subscribers if s.session.closed]:
            self.remove(s)  # its session ended (the server detaches it too: cancel is idempotent)
        if not self.subscribers:
            return []
        half = 0.5 * self.period
        due = [s for s in self.subscribers if s.next_t - half <= now]
        if not due:
            return due
        for s in due:
            s.next_t += s.period
            if s.next_t + half < now:  # behind (the event loop was held): skip, never burst
                s.next_t = now + s.period
        try:
            body = encode_body(self.produce())
        except Exception:  # a bug here must not end the stream silently, nor flood the log
            if now - self._error_said >= 1.0:
                self._error_said = now
                log.exception("stream %s (%s) failed", self.topic, self.ns)
            return []
        for s in due:
            s.session.send_frame(s.head + body + TAIL)
        return [s.session for s in due]

    def next_due(self) -> float:
        """When the next subscriber is due."""
        return min(s.next_t for s in self.subscribers) if self.subscribers else float("inf")


def tick_all(streams: Iterable[TopicStream], now: float) -> float:
    """Tick every stream with a subscriber due at ``now`` (within half its tick), then flush each
    session that got frames once. Returns when the next subscriber is due."""
    touched: dict[int, Any] = {}
    for st in streams:
        for session in st.tick(now):
            touched[id(session)] = session
    for session in touched.values():
        session.flush()
    return min((st.next_due() for st in streams), default=float("inf"))

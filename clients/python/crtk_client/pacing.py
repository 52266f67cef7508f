"""When the samples of a timed command stream go out: on the wall clock, whatever the rate.

A stream of ``duration`` s at ``rate_hz`` has ticks ``k = 0 .. N`` (``N = round(duration *
rate_hz)``, at least 1) at ``k * duration / N`` after the first: the first at once, the last
exactly at ``duration``. Each sample is a request that blocks for its reply (a round trip, about
one control cycle of the daemon), so a rate near the loop rate cannot be kept: a sample whose
reply comes late is followed by the newest tick already due, the ticks missed in between are
skipped, never sent late. So the stream ends at ``duration`` (plus one round trip) on the wall
clock at every rate; sent one after the other, N + 1 samples of 5 ms round trips would stretch a
1 s stream at 1000 Hz to 5 s (issue 18).

A relative stream (``servo_jr``...) must still move by its whole offset: each sample carries the
:attr:`Tick.share` of the offset the ticks it stands for would have carried, so the shares of
the samples sent always add up to exactly 1.

Standard library only; the clock and the sleep are injectable (tests drive them).
"""

from __future__ import annotations

import math
import time
from typing import Callable, Iterator, NamedTuple


class Tick(NamedTuple):
    """One sample of a stream: tick ``index`` of ``0 .. last``. A relative offset has gone out
    up to the fraction ``before`` and reaches ``reached`` with this sample (``(index + 1) /
    (last + 1)``; exactly 1.0 at the end): send ``offset * reached - offset * before``.
    ``final``: the sample at ``duration`` (the stream's end)."""

    index: int
    last: int
    before: float
    reached: float
    final: bool

    @property
    def share(self) -> float:
        """The fraction of a relative offset this sample carries."""
        return self.reached - self.before


class Pacing:
    """The ticks of a stream of ``duration`` s at ``rate_hz`` (both finite and > 0), paced on
    ``clock`` (monotonic, s) with ``sleep``. Iterating yields a :class:`Tick` when each sample is
    due; the caller sends it, then asks for the next one. Iterate once."""

    def __init__(self, duration: float, rate_hz: float,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep):
        for name, value in (("duration", duration), ("rate_hz", rate_hz)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        self.duration = float(duration)
        self.rate_hz = float(rate_hz)
        self.last = max(1, round(self.duration * self.rate_hz))
        self.period = self.duration / self.last
        self._clock = clock
        self._sleep = sleep
        #: samples yielded so far
        self.sent = 0

    def __iter__(self) -> Iterator[Tick]:
        n = self.last + 1
        t0 = self._clock()
        k, before = 0, 0.0  # the tick to send; the fraction of an offset sent before it
        while True:
            self.sent += 1
            reached = (k + 1) / n
            yield Tick(k, self.last, before, reached, k == self.last)
            if k == self.last:
                return
            before = reached
            elapsed = self._clock() - t0
            # the newest tick already due (the end once the duration is over: elapsed / period
            # would overflow for a subnormal duration)
            due = self.last if elapsed >= self.duration else math.floor(elapsed / self.period + 1e-9)
            k = min(self.last, max(k + 1, due))
            wait = t0 + k * self.period - self._clock()
            if wait > 0:
                self._sleep(wait)

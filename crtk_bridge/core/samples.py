"""Every control cycle's sample, handed from the control process to the front through a ring in
shared memory (docs/architecture.md, "Recording: the sample ring"). The snapshot (snapshot.py) is the latest
value only; this ring keeps the last ``capacity`` cycles, so a reader that wakes every few tens of
milliseconds still sees every cycle.

One writer (the control loop, once per cycle, after it published the snapshot): ``push`` copies
the snapshot's state block (everything before the statistics rings, the cycle count included)
into slot ``cycle % capacity`` with the cycle's stamp, into pre-allocated memory; nothing blocks,
nothing is allocated beyond Python's scalars. One reader (the front's drain thread):
:class:`SampleReader` copies the slots written since its last drain and checks each slot's
marker afterwards: a slot the writer overwrote meanwhile (the reader fell more than ``capacity``
cycles behind) is counted as lost, never returned half-written and never silently dropped.

Slot layout (float64): ``marker`` (the cycle number once the slot is complete, -1 while it is
being written) | cycle stamp (s since the Unix epoch, the loop's steady clock) | the snapshot's
state block. Header: ``head`` (the last cycle pushed, -1: none yet).
"""

from __future__ import annotations

from multiprocessing import shared_memory

import numpy as np

from .snapshot import Layout

#: ring length in seconds of cycles: the front may fall this far behind without losing a sample
RING_SECONDS = 2.0
RING_MIN_SLOTS = 1024
HEADER = 8  # float64 slots before the ring (head, and room to grow)
MARKER, STAMP, STATE = 0, 1, 2  # offsets in a slot


def state_size(layout: Layout) -> int:
    """Values of the snapshot copied per cycle: the state, cycle and overrun counts (not the
    statistics rings)."""
    return layout.slices["ring_index"].start


def ring_slots(rate_hz: float) -> int:
    return max(RING_MIN_SLOTS, int(RING_SECONDS * rate_hz) + 1)


class SampleRing:
    """The shared block. ``create=True`` in the daemon before forking the control process."""

    def __init__(self, layout: Layout, capacity: int, name: str | None = None, create: bool = False):
        self.layout = layout
        self.capacity = int(capacity)
        self.state = state_size(layout)
        self.width = STATE + self.state
        nbytes = 8 * (HEADER + self.capacity * self.width)
        self.shm = shared_memory.SharedMemory(name=name, create=create, size=nbytes)
        self.header = np.ndarray((HEADER,), dtype=np.float64, buffer=self.shm.buf, offset=0)
        self.slots = np.ndarray((self.capacity, self.width), dtype=np.float64, buffer=self.shm.buf,
                                offset=8 * HEADER)
        if create:
            self.header[:] = 0.0
            self.header[0] = -1.0
            self.slots[:, MARKER] = -1.0
        # writer side: one pre-made view per slot, so push() makes no array
        self._rows = [self.slots[i, STATE:] for i in range(self.capacity)]
        self._marker = self.slots[:, MARKER]
        self._stamp = self.slots[:, STAMP]

    @property
    def name(self) -> str:
        return self.shm.name

    # ---- writer side (control process) ----
    def push(self, cycle: int, stamp: float, state: np.ndarray) -> None:
        """Cycle ``cycle``'s sample (``state``: the snapshot's state block, a view made once)."""
        j = cycle % self.capacity
        self._marker[j] = -1.0  # being written: a reader copying it now will not trust it
        self._stamp[j] = stamp
        np.copyto(self._rows[j], state)
        self._marker[j] = cycle
        self.header[0] = cycle

    # ---- reader side ----
    def head(self) -> int:
        return int(self.header[0])

    def close(self, unlink: bool = False) -> None:
        self._rows.clear()
        del self.header, self.slots, self._marker, self._stamp
        self.shm.close()
        if unlink:
            try:
                self.shm.unlink()
            except FileNotFoundError:
                pass


class SampleReader:
    """The front's side: :meth:`drain` returns the samples pushed since the previous drain, in
    cycle order, and how many were overwritten before they could be read."""

    def __init__(self, ring: SampleRing):
        self.ring = ring
        self.next = -1  # the next cycle to read; -1: start at whatever the ring holds
        self.lost = 0  # cycles overwritten before they were read, since the reader started

    def drain(self) -> tuple[np.ndarray, int]:
        """(rows, lost now): rows are copies, ``(m, STATE + state)`` with the slot layout, their
        markers the cycle numbers, strictly increasing."""
        ring = self.ring
        head = ring.head()
        cap = ring.capacity
        if head < 0:
            return ring.slots[:0].copy(), 0
        first = self.next if self.next >= 0 else max(0, head - cap + 1)
        if head < first:
            return ring.slots[:0].copy(), 0
        lost = 0
        if head - first >= cap:  # overwritten already, for sure
            lost = head - cap + 1 - first
            first = head - cap + 1
        cycles = np.arange(first, head + 1)
        idx = cycles % cap
        rows = ring.slots[idx]  # fancy indexing: a copy
        # a slot is good when its marker was the expected cycle both in the copy and after it
        # (the writer sets it to -1 before touching a slot, and to the new cycle after)
        good = (rows[:, MARKER] == cycles) & (ring.slots[idx, MARKER] == cycles)
        bad = int(len(cycles) - np.count_nonzero(good))
        if bad:
            rows = rows[good]
        lost += bad
        self.lost += lost
        self.next = head + 1
        return rows, lost

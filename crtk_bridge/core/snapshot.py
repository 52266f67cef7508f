"""The state snapshot the control process publishes every cycle, in shared memory, under a seqlock.

One writer (the control loop), any number of readers (the front process). The writer bumps the
sequence number to odd, writes, bumps it to even; a reader copies the block and retries if the
sequence was odd or changed meanwhile. Nothing is allocated on the writer's side per cycle.

Header (int64): ``seq`` | ``posted``: the front's count of its sends on the pair, which the front
alone writes (two per message, before and after its send: odd while one is under way; -1 until
its link counts them), so the loop skips the receive system call in a cycle where nothing was
sent (core/loop.py :meth:`ControlLoop._receive`).
Layout (float64 unless said), after the header: measured stamp, p[n], v[n], f[n] |
setpoint p[n], v[n], f[n] | goal p[n], v[n], f[n] | per namespace: setpoint stamp, has_p,
has_v, has_f, goal stamp, goal has_p, has_v, has_f | per namespace: native cartesian stamp, p[3], q[4], wrench[6] | per namespace: native
cartesian setpoint stamp, p[3], q[4], twist stamp, twist[6], twist frame, goal stamp, p[3], q[4] | cycle count, overrun count, lateness ring [RING], compute ring [RING].
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from multiprocessing import shared_memory

import numpy as np

RING = 1024  # samples of loop lateness / compute time kept for period_statistics
HEADER_BYTES = 16  # seq, posted (int64 each)


@dataclass
class Layout:
    n: int  # joints
    k: int  # namespaces

    def __post_init__(self) -> None:
        n, k = self.n, self.k
        fields = [
            ("measured_stamp", 1), ("measured_p", n), ("measured_v", n), ("measured_f", n),
            ("setpoint_p", n), ("setpoint_v", n), ("setpoint_f", n), ("goal_p", n), ("goal_v", n), ("goal_f", n),
            ("ns_setpoint_stamp", k), ("ns_has_p", k), ("ns_has_v", k), ("ns_has_f", k), ("ns_goal_stamp", k),
            ("ns_goal_has_p", k), ("ns_goal_has_v", k), ("ns_goal_has_f", k),
            # the tip pose a native cartesian backend measures (its stamp 0 elsewhere)
            ("ns_cart_stamp", k), ("ns_cart_p", 3 * k), ("ns_cart_q", 4 * k), ("ns_cart_f", 6 * k),
            # ...and what it was commanded (core/native_cartesian.py): setpoint_cp, setpoint_cv, goal_cp
            ("ns_cart_sp_stamp", k), ("ns_cart_sp_p", 3 * k), ("ns_cart_sp_q", 4 * k),
            ("ns_cart_tw_stamp", k), ("ns_cart_tw", 6 * k), ("ns_cart_tw_frame", k),
            ("ns_cart_goal_stamp", k), ("ns_cart_goal_p", 3 * k), ("ns_cart_goal_q", 4 * k),
            ("cycles", 1), ("overruns", 1), ("ring_index", 1), ("lateness", RING), ("compute", RING),
        ]
        self.slices: dict[str, slice] = {}
        off = 0
        for name, size in fields:
            self.slices[name] = slice(off, off + size)
            off += size
        self.size = off

    @property
    def nbytes(self) -> int:
        return HEADER_BYTES + 8 * self.size


class SnapshotBuffer:
    """Shared-memory block. ``create=True`` in the daemon before forking the control process."""

    def __init__(self, layout: Layout, name: str | None = None, create: bool = False):
        self.layout = layout
        self.shm = shared_memory.SharedMemory(name=name, create=create, size=layout.nbytes)
        self.seq = np.ndarray((1,), dtype=np.int64, buffer=self.shm.buf, offset=0)
        #: the front's count of its sends on the pair (two per message: odd while one is under way; -1: not counted)
        self.posted = np.ndarray((1,), dtype=np.int64, buffer=self.shm.buf, offset=8)
        self.data = np.ndarray((layout.size,), dtype=np.float64, buffer=self.shm.buf, offset=HEADER_BYTES)
        self.views = {name: self.data[s] for name, s in layout.slices.items()}
        if create:
            self.seq[0] = 0
            self.posted[0] = -1  # until a link counts its sends, the loop receives every cycle
            self.data[:] = 0.0

    @property
    def name(self) -> str:
        return self.shm.name

    # ---- writer side (control process) ----
    def begin(self) -> None:
        self.seq[0] += 1  # odd: write in progress

    def end(self) -> None:
        self.seq[0] += 1  # even: consistent

    # ---- reader side (front process) ----
    def read(self, out: np.ndarray | None = None, timeout_s: float = 0.05,
             upto: int | None = None) -> tuple[np.ndarray, int]:
        """Consistent copy of the data block and its sequence number. Never blocks long.
        ``upto``: copy only the first ``upto`` values (e.g. the state without the statistics rings)."""
        if out is None:
            out = np.empty_like(self.data)
        src, dst = (self.data, out) if upto is None else (self.data[:upto], out[:upto])
        deadline = time.monotonic() + timeout_s
        while True:
            s1 = int(self.seq[0])
            if not s1 & 1:
                np.copyto(dst, src)
                if int(self.seq[0]) == s1:
                    return out, s1
            if time.monotonic() > deadline:  # writer died mid-write: return what is there
                np.copyto(dst, src)
                return out, int(self.seq[0])

    def close(self, unlink: bool = False) -> None:
        self.views.clear()
        del self.seq, self.posted, self.data
        self.shm.close()
        if unlink:
            try:
                self.shm.unlink()
            except FileNotFoundError:
                pass

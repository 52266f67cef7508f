"""An in-process CAN bus for the simulators: python-can's ``BusABC``, frames handed over in the
sender's thread.

python-can's ``virtual`` interface puts a ``deepcopy`` of every frame into a queue per endpoint,
and each endpoint's reader is a thread of its own (a ``Notifier``): every frame is a thread
wake-up and a GIL hand-off per endpoint. Behind the simulated USB-CAN adapter (sim/slcan.py)
the simulated drives (sim/canopen402.py) answer each SYNC with their TPDOs, so a 250 Hz cycle
was ~10 frames through three threads: most of the CANopen simulator's CPU (issue 23, "the
simulators count too": ~750 us per cycle, 19 % of a core). On this bus an endpoint opened with
``on_message`` is called with each frame in the thread that sent it -- the drives' handlers run
in the adapter's thread that parsed the master's SYNC, and their answers go on in the same
pass -- and an endpoint without one is read with ``recv`` like any python-can bus (the adapter's
side).

Bus order: every frame is delivered to every endpoint in the order frames were sent, one at a
time. A frame sent while another thread delivers (a drive's heartbeat thread, the simulator's
tick) is queued and delivered by that thread after the current one; a frame sent from inside a
handler is delivered after the handler returns (no recursion). So a handler may hold its own
lock while it sends (the delivering thread never waits for a sender), and a handler that raises
is logged and does not stop the bus.

A frame is copied when it is sent (the sender may reuse its message), stamped then, as
``virtual`` does: one copy the other endpoints share (``is_rx`` True; handlers and readers
only read it), and the sender's own echo (``is_rx`` False) with ``receive_own_messages``.
"""

from __future__ import annotations

import collections
import logging
import queue
import threading
import time
from typing import Callable, Optional

import can

log = logging.getLogger(__name__)

#: the interface name the simulators use for this bus (not a python-can plugin: built directly)
INTERFACE = "crtk-local"


class _Channel:
    def __init__(self, name: str):
        self.name = name
        self.endpoints: list[LocalBus] = []
        #: (sender, the frame the others get, the sender's own echo or None), in bus order
        self.pending: collections.deque[tuple[LocalBus, can.Message, Optional[can.Message]]] = collections.deque()
        self.delivering = threading.Lock()  # held by the thread handing frames out

    def pump(self) -> None:
        """Deliver what is pending, unless another thread is at it (it delivers ours too)."""
        pending = self.pending
        while pending:
            if not self.delivering.acquire(blocking=False):
                return  # the thread holding it re-checks ``pending`` after releasing it
            try:
                while pending:
                    sender, msg, own = pending.popleft()
                    for bus in tuple(self.endpoints):
                        if bus is not sender:
                            bus._deliver(msg)
                        elif own is not None:
                            bus._deliver(own)
            finally:
                self.delivering.release()


_channels: dict[str, _Channel] = {}
_channels_lock = threading.Lock()


class LocalBus(can.BusABC):
    """One endpoint on the in-process channel ``channel`` (see the module docstring).
    ``on_message``: called with each frame in the delivering thread (then ``recv`` gets
    nothing); without it, frames queue for ``recv``."""

    def __init__(self, channel: str, *, receive_own_messages: bool = False,
                 on_message: Optional[Callable[[can.Message], None]] = None, **kwargs):
        self.channel_info = f"crtk-local channel {channel!r}"
        self.receive_own_messages = receive_own_messages
        self.on_message = on_message
        self._queue: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        with _channels_lock:
            self._channel = _channels.setdefault(channel, _Channel(channel))
            self._channel.endpoints.append(self)
        self.channel_id = channel
        super().__init__(channel=channel, **kwargs)

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        if self._is_shutdown:
            raise can.CanOperationError(f"{self.channel_info} is shut down")
        now = time.time()
        own = _copy(msg, now, False, self.channel_id) if self.receive_own_messages else None
        self._channel.pending.append((self, _copy(msg, now, True, self.channel_id), own))
        self._channel.pump()

    def _deliver(self, msg: can.Message) -> None:
        if self.on_message is None:
            self._queue.put(msg)
            return
        try:
            self.on_message(msg)
        except Exception:  # the bus goes on for the other endpoints and the next frames
            log.exception("%s: a handler raised on frame 0x%03X", self.channel_info, msg.arbitration_id)

    def recv(self, timeout: Optional[float] = None) -> Optional[can.Message]:
        """BusABC.recv without its per-frame debug log and filter pass when no filter is set
        (the adapter's bus thread takes every frame of the cycle through here)."""
        if self._filters is not None:
            return super().recv(timeout)
        return self._recv_internal(timeout)[0]

    def _recv_internal(self, timeout: Optional[float]) -> tuple[Optional[can.Message], bool]:
        try:
            return self._queue.get(timeout=timeout) if timeout != 0 else self._queue.get_nowait(), False
        except queue.Empty:
            return None, False

    def shutdown(self) -> None:
        with _channels_lock:
            if self in self._channel.endpoints:
                self._channel.endpoints.remove(self)
            if not self._channel.endpoints and _channels.get(self._channel.name) is self._channel:
                del _channels[self._channel.name]
        super().shutdown()


def _copy(msg: can.Message, timestamp: float, is_rx: bool, channel: str) -> can.Message:
    """A copy of a frame as sent (what ``virtual``'s deepcopy gives, for a fifth of its cost)."""
    return can.Message(timestamp=timestamp, arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                       is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame,
                       channel=channel, dlc=msg.dlc, data=bytearray(msg.data), is_fd=msg.is_fd,
                       is_rx=is_rx, bitrate_switch=msg.bitrate_switch,
                       error_state_indicator=msg.error_state_indicator, check=False)

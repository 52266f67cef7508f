"""A ``scservo_sdk.PortHandler`` that fixes the SDK's serial-port gaps (reference/servos.md §1).

The pip SDK (feetech-servo-sdk 1.0) has three flaws that matter to a real-time loop:

1. ``clearPort()`` only drains OUTPUT (``ser.flush()``): a late reply from a previous, failed
   transaction stays in the input queue and is taken as the answer to the next request. Here it
   discards stale INPUT bytes (``tcflush(TCIFLUSH)``) before every request.
2. The port is opened with ``timeout=0`` and ``rxPacket`` busy-polls ``readPort`` until its packet
   deadline: a whole core spins while waiting for servos. Here ``readPort(n)`` sleeps in ``select``
   until ``n`` bytes arrived or the packet deadline passed, then returns what it has; the SDK's
   loop (``readPort`` then ``isPacketTimeout``) keeps working unchanged.
3. The packet timeout is wire time + 2 x 16 ms LATENCY_TIMER + 2 ms (~34 ms per attempt). Here it
   is wire time of the expected bytes + ``margin_ms`` (USB and servo turnaround; default 10 ms), so
   one silent servo costs a small, bounded time.

Also: the deadline clock is monotonic (the SDK uses wall-clock time, which NTP can step); the
port is opened ``exclusive`` (an OS lock, where the SDK's ``is_using`` is only an in-process
flag); and OS errors (unplugged adapter, pty closed) are caught, so they become the SDK's
COMM_TX_FAIL / COMM_RX_TIMEOUT results instead of exceptions that would leave ``is_using`` set.
The last such error is kept in :attr:`FastPortHandler.last_os_error` for messages.
"""

from __future__ import annotations

import os
import select
import termios
import time

import serial
from scservo_sdk import PortHandler

DEFAULT_MARGIN_MS = 10.0


class FastPortHandler(PortHandler):
    """PortHandler with input flushing, sleeping reads and short packet timeouts. Not thread-safe.

    ``margin_ms``: time allowed beyond the wire time of the expected reply bytes (USB latency,
    servo return delay, scheduling). Milliseconds, as everywhere in the SDK's port API.
    """

    def __init__(self, port_name: str, margin_ms: float = DEFAULT_MARGIN_MS):
        super().__init__(port_name)
        self.margin_ms = float(margin_ms)
        self.last_os_error: OSError | None = None
        self._fd = -1

    # ---- opening ----
    def setupPort(self, cflag_baud):  # noqa: N802 (SDK name)
        if self.is_open:
            self.closePort()
        # Raises serial.SerialException (an OSError subclass); the backend wraps it.
        self.ser = serial.Serial(
            port=self.port_name,
            baudrate=self.baudrate,
            bytesize=serial.EIGHTBITS,
            timeout=0,
            exclusive=True,
        )
        self.is_open = True
        self._fd = self.ser.fileno()
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0  # ms per byte, 8N1
        self.last_os_error = None
        return True

    def closePort(self):  # noqa: N802
        if self.ser is not None:
            try:
                self.ser.close()
            except (OSError, serial.SerialException):
                pass
        self.is_open = False
        self._fd = -1

    # ---- gap 1: discard stale input ----
    def clearPort(self):  # noqa: N802
        try:
            termios.tcflush(self._fd, termios.TCIFLUSH)
        except (OSError, termios.error) as exc:
            self.last_os_error = exc if isinstance(exc, OSError) else OSError(str(exc))

    # ---- gap 2: sleep until the bytes arrive or the deadline passes ----
    def readPort(self, length):  # noqa: N802
        fd = self._fd
        try:
            data = os.read(fd, length)
        except BlockingIOError:
            data = b""
        except OSError as exc:
            return self._read_failed(exc)
        if len(data) >= length:
            return data
        deadline = self.packet_start_time + self.packet_timeout  # ms, monotonic
        while True:
            remaining = deadline - self.getCurrentTime()
            if remaining <= 0:
                return data
            try:
                ready, _, _ = select.select((fd,), (), (), remaining / 1000.0)
                if not ready:
                    return data
                chunk = os.read(fd, length - len(data))
            except BlockingIOError:
                continue
            except (OSError, ValueError) as exc:
                if not isinstance(exc, OSError):
                    exc = OSError(str(exc))
                return data if data else self._read_failed(exc)
            if not chunk:  # EOF: the other side is gone
                return data if data else self._read_failed(OSError("end of file on serial port"))
            data += chunk
            if len(data) >= length:
                return data

    def _read_failed(self, exc: OSError) -> bytes:
        # Expire the deadline so the SDK's loop gives up now instead of spinning on a dead fd.
        self.last_os_error = exc
        self.packet_timeout = -1.0
        return b""

    def writePort(self, packet):  # noqa: N802
        data = bytes(packet)
        sent = 0
        deadline = time.monotonic() + 0.1  # a full output queue drains in well under this
        try:
            while sent < len(data):
                try:
                    sent += os.write(self._fd, data[sent:])
                except BlockingIOError:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    select.select((), (self._fd,), (), remaining)
        except OSError as exc:
            self.last_os_error = exc
        return sent  # != len(packet) -> the SDK reports COMM_TX_FAIL and releases the port

    def getBytesAvailable(self):  # noqa: N802
        try:
            return self.ser.in_waiting
        except (OSError, serial.SerialException):
            return 0

    # ---- gap 3: short, byte-count-sized packet timeouts on a monotonic clock ----
    def setPacketTimeout(self, packet_length):  # noqa: N802
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.margin_ms

    def getCurrentTime(self):  # noqa: N802
        return time.monotonic() * 1000.0

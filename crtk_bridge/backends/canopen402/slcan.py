"""python-can's ``slcan`` interface, reading the adapter's bytes as they come rather than one by one.

python-can 4.6's ``slcanBus._read`` takes one byte per ``Serial.read(1)`` (a ``select`` and a
``read`` system call each, and the Python around them), and when nothing is waiting it polls at the
serial timeout, 1 ms by default. A CANopen cycle at 250 Hz brings ~100 bytes from the adapter (the
drives' TPDOs, the adapter's ``z`` acknowledgements of the SYNC and RPDOs), so the notifier thread
took ~25 % of a core reading them byte by byte and polling between cycles (issue 23,
bench/bench_cpu.py). python-can's own fix (reading everything waiting at once, hardbyte/python-can
#2028) is not in a release yet; this is the same idea on python-can's pieces: one ``select`` on
the port waits for the adapter (up to the serial timeout, the notifier's cycle, not 1 ms), one
``read`` takes all that is waiting (pyserial opens a tty non-blocking), and the lines are handed
out one at a time from the bus's own buffer. A pyserial URL (``socket://``...) has no descriptor:
it is read with its own ``read``, the first byte then what is waiting.

Sending: python-can's ``_write`` follows every line with ``Serial.flush()``, a ``tcdrain`` that
waits until the port has transmitted it (on a USB adapter, the USB transfer): in the control
cycle, once per SYNC and RPDO. Here a line is written and the cycle goes on; the kernel sends it,
in order, as it would after the wait. And on a tty the line is one ``os.write``: pyserial's
``write`` follows each with a ``select`` for room in the output buffer (with no write timeout,
waiting for it), about a third of the control process's CPU per cycle on a 2-drive 250 Hz bus
(bench/bench_cpu.py); only a line the buffer did not take whole goes through it (it waits for
room, as before).

The cycle's RPDOs in one write: the backend formats its cycle frames itself (:meth:`SlcanBus.line`
/ :meth:`SlcanBus.head`, python-can's bytes) and writes them together with
:meth:`SlcanBus.send_lines`, one writer at a time (a line another thread sends waits for the
whole write, even one the tty's full output buffer splits). Each
write to the adapter is a system call here and, on the adapter's side, a wake-up and an
acknowledgement burst back to the notifier; a 2-drive cycle sends four RPDOs, one write instead
of four (issue 23). A real adapter receives them in one USB transfer and puts them on the bus in
order, as it would four.

Acknowledgements: the adapter answers each transmitted frame with ``z`` / ``Z`` (CR), which
python-can's ``_recv_internal`` parses to no message, one ``recv`` round (and its logging and
filter checks) per transmitted frame. They are dropped where the lines are split, so the
notifier's ``recv`` returns the next frame.

Everything else (opening, bitrate, frame formatting and parsing) is python-can's.
"""

from __future__ import annotations

import binascii
import os
import select
import threading
from typing import Optional

import serial
from can.exceptions import CanOperationError, error_check
from can.interfaces.slcan import slcanBus

#: the serial timeout when the profile's ``backend.options`` name none: how long one read blocks
#: while the bus is silent (the notifier's recv timeout is the same 50 ms; a byte that arrives
#: ends the wait at once)
SERIAL_TIMEOUT_S = 0.05
#: the adapter's acknowledgements of a transmitted standard / extended frame (no message)
_ACKS = (b"z\r", b"Z\r")


class SlcanBus(slcanBus):
    """``slcanBus`` whose receive reads what is waiting in one go (see the module docstring)."""

    def __init__(self, channel, *args, timeout: float = SERIAL_TIMEOUT_S, **kwargs):
        # one writer at a time: send_lines writes outside canopen's send lock, and a write the
        # tty's full output buffer splits (os.write, then port.write for the rest) must not let
        # another thread's line in between: the adapter would send the spliced line as a frame
        self._write_lock = threading.Lock()
        super().__init__(channel, *args, timeout=timeout, **kwargs)

    @staticmethod
    def head(can_id: int, length: int) -> bytes:
        """The start of python-can's line for a standard (11-bit) data frame of ``length`` bytes:
        ``t``, the identifier, the length; the payload in upper-case hex and a CR follow."""
        return b"t%03X%d" % (can_id, length)

    @staticmethod
    def line(can_id: int, data: bytes) -> bytes:
        """The line python-can's ``send`` writes for a standard (11-bit) data frame, CR included."""
        return SlcanBus.head(can_id, len(data)) + binascii.hexlify(data).upper() + b"\r"

    def send_lines(self, data: bytes) -> None:
        """Frames already formatted (:meth:`line`), written as they are, in one write. The backend's cycle (the SYNC, the master's heartbeat, the RPDOs) formats its
        frames here rather than through canopen's ``send_message`` and python-can's ``send`` (a
        ``Message``, a lock and a format per frame: a fifth of the control process's CPU per
        2-drive cycle, issue 23); same bytes, checked by tests/test_canopen_slcan_reads.py."""
        self._send_bytes(data)

    def _write(self, string: str) -> None:
        self._send_bytes(string.encode() + self.LINE_TERMINATOR)

    def _send_bytes(self, data: bytes) -> None:
        port = self.serialPortOrig
        fd = port.fd if isinstance(port, serial.Serial) and port.fd is not None else None
        # what error_check("Could not write to serial device") does, without a generator-based
        # context manager per write (twice a cycle)
        try:
            with self._write_lock:
                if fd is not None:  # a tty: one write, no select after it (see the module docstring)
                    try:
                        n = os.write(fd, data)
                    except BlockingIOError:
                        n = 0
                    if n == len(data):
                        return
                    data = data[n:]
                port.write(data)  # a URL port, or the rest of a line the full output buffer did not take
        except Exception as exc:
            raise CanOperationError("Could not write to serial device") from exc

    def _line(self) -> Optional[str]:
        """The first complete line in the buffer (with its CR or BEL) that is not a transmit
        acknowledgement, taken out of it (with the acknowledgements before it); or None."""
        buf = self._buffer
        while True:
            n = buf.find(self._OK) + 1
            bel = buf.find(self._ERROR) + 1
            if bel and (bel < n or not n):
                n = bel
            if not n:
                return None
            if n == 2 and buf[:2] in _ACKS:
                del buf[:2]
                continue
            line = buf[:n].decode()
            del buf[:n]
            return line

    def _read(self, timeout: Optional[float]) -> Optional[str]:
        line = self._line()
        if line is not None:
            return line
        expiry = serial.Timeout(timeout)
        port = self.serialPortOrig
        fd = port.fd if isinstance(port, serial.Serial) and port.fd is not None else None
        with error_check("Could not read from serial device"):
            while True:
                if fd is not None:  # a tty: one select and one read per wake-up
                    if select.select([fd], [], [], port.timeout)[0]:
                        data = os.read(fd, 4096)  # pyserial opens the port non-blocking
                        if not data:  # what pyserial's read says of a USB adapter pulled out
                            raise serial.SerialException("device reports readiness to read but returned "
                                                         "no data (device disconnected?)")
                        self._buffer += data
                else:  # a pyserial URL (socket://, loop://...): its own read
                    data = port.read(1)  # blocks up to the port's timeout
                    if data:
                        self._buffer += data + port.read(port.in_waiting)
                line = self._line()
                if line is not None:
                    return line
                if expiry.expired():
                    return None

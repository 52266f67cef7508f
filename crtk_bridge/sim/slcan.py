"""A simulated USB-CAN adapter speaking SLCAN (LAWICEL), as CANable-type adapters do, on a pty.

The simulated drives run in the simulator's process and the daemon's control process in another;
this kernel has no CAN (no vcan) and multicast is not allowed, so the two share a bus through this
adapter: the master opens the pty with python-can's ``slcan`` interface (``channel`` = the pty or
its link), exactly as it would open a real CANable on ``/dev/ttyACM0``; the adapter bridges it to
a python-can bus in the simulator's process (a private ``virtual`` channel the drives are on).

Why SLCAN rather than a socketcand server on loopback (measured with python-can's own clients,
``bench/bench_can_adapter.py``): both sustain far more frames per second than a CANopen cycle
needs, but SLCAN keeps the profile keys of a real adapter (``interface: slcan``,
``channel: /dev/ttyACM0``, ``bitrate``), reuses the serial simulators' pty machinery (a stable
``--link``, the daemon's ``--sim`` wiring that waits for the link), and needs no TCP port;
python-can's socketcand client adds ``host`` / ``port`` keys and a fixed 10 s connect retry.

LAWICEL commands answered (CR-terminated; ``\\r`` = OK, ``\\a`` = error):
``Sn`` / ``sxxyy`` bitrate (only while closed), ``O`` open, ``L`` listen only, ``C`` close,
``tiiildd..`` / ``Tiiiiiiiildd..`` / ``riiil`` / ``Riiiiiiiil`` transmit (``z\\r`` / ``Z\\r``),
``F`` status flags, ``V`` / ``v`` version, ``N`` serial number, ``Zn`` timestamps on / off; an
empty line is OK; anything else (CAN FD frames, a malformed frame, a DLC above 8, a transmit
while closed or listen-only) is answered ``\\a`` and dropped. Received frames go to the pty as
``t`` / ``T`` / ``r`` / ``R`` lines (with a 4-hex-digit ms timestamp after ``Z1``) while open.

Fault injection: :attr:`bus_off` (nothing passes either way, transmits are refused, status flags
report it); a bitrate other than the bus's (``S4`` on a 1 Mbit/s bus) behaves the same way, as
a real adapter at the wrong bitrate sees only errors.
"""

from __future__ import annotations

import collections
import logging
import os
import select
import threading
import time

import can

from . import SimulatorError, canbus
from .pty import PtyPort

log = logging.getLogger(__name__)

#: LAWICEL ``Sn`` codes (python-can's slcan table; 9 = 83.3 kbit/s)
BITRATE_CODES = {"0": 10_000, "1": 20_000, "2": 50_000, "3": 100_000, "4": 125_000, "5": 250_000,
                 "6": 500_000, "7": 750_000, "8": 1_000_000, "9": 83_300}
OK, ERROR = b"\r", b"\a"
# status flags (LAWICEL "F"): bit 2 error warning, bit 5 error passive, bit 7 bus error
FLAG_BUS_ERROR = 0x80 | 0x20 | 0x04
_MAX_LINE = 64  # longest valid command is 27 characters; a longer line is noise
_HEX = frozenset(b"0123456789abcdefABCDEF")
#: a USB full-speed frame: what arrives from the bus within it goes to the host in one transfer
USB_FRAME_S = 0.001
USB_BATCH_FRAMES = 32  # lines per write at most (a busy bus still flows)


def parse_frame(line: bytes) -> can.Message | None:
    """A LAWICEL transmit command (``t``, ``T``, ``r``, ``R``, no CR) as a message, or None when
    it is malformed (wrong id length or range, DLC above 8, data not matching the DLC, not hex)."""
    kind = line[:1]
    extended, remote = kind in (b"T", b"R"), kind in (b"r", b"R")
    id_len = 8 if extended else 3
    head = line[1:1 + id_len + 1]
    if len(head) != id_len + 1 or not set(head) <= _HEX or not head[-1:].isdigit():
        return None
    can_id, dlc = int(head[:-1], 16), int(head[-1:])
    if dlc > 8 or can_id > (0x1FFFFFFF if extended else 0x7FF):
        return None
    data = line[2 + id_len:]
    if remote:
        if data:
            return None
        return can.Message(arbitration_id=can_id, is_extended_id=extended, is_remote_frame=True, dlc=dlc)
    if len(data) != 2 * dlc or not set(data) <= _HEX:
        return None
    return can.Message(arbitration_id=can_id, is_extended_id=extended, data=bytes.fromhex(data.decode()))


def format_frame(msg: can.Message) -> bytes:
    """A received frame as the LAWICEL line an adapter sends (no timestamp, no CR)."""
    if msg.is_extended_id:
        head = f"{'R' if msg.is_remote_frame else 'T'}{msg.arbitration_id:08X}{msg.dlc:d}"
    else:
        head = f"{'r' if msg.is_remote_frame else 't'}{msg.arbitration_id:03X}{msg.dlc:d}"
    return head.encode() + (b"" if msg.is_remote_frame else msg.data.hex().upper().encode())


class SlcanAdapter:
    """An SLCAN adapter on a pty (optionally behind the stable symlink ``link``), bridged to the
    python-can bus ``interface`` / ``channel`` whose bitrate is ``bitrate``.

    ``start()`` returns once the pty exists and the bus is open; ``stop()`` is idempotent.
    Two threads: one reads the pty (commands, frames to send), one forwards bus frames to it.
    """

    def __init__(self, interface: str, channel: str, bitrate: int, link: str | os.PathLike | None = None):
        self.bus_interface, self.bus_channel = interface, channel
        self.bitrate = int(bitrate)
        self._pty = PtyPort(link)
        self._bus: can.BusABC | None = None
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        self._wake_r = self._wake_w = -1
        self._write_lock = threading.Lock()
        #: the acknowledgement of each frame sent to the bus, in order, until its echo comes back
        self._acks: collections.deque[bytes] = collections.deque()
        self._pass_t = 0.0  # wall-clock time frames last started to pass (opened, bus-off over)
        self.is_open = False
        self.listen_only = False
        self.selected_bitrate: int | None = None  # what the master chose with S / s
        self.timestamps = False
        self._bus_off = False
        #: bytes from / to the master, frames from / to the master, lines dropped (client not reading)
        self.rx_bytes = self.tx_bytes = 0
        self.rx_frames = self.tx_frames = 0
        self.overruns = 0

    # ------------------------------------------------------------------ lifecycle
    @property
    def port(self) -> str:
        """The path a master opens (``channel`` of python-can's ``slcan`` interface)."""
        return self._pty.path

    @property
    def pty_path(self) -> str | None:
        return self._pty.slave_path

    @property
    def running(self) -> bool:
        return bool(self._threads) and all(t.is_alive() for t in self._threads)

    def start(self) -> None:
        if self._threads:
            return
        try:
            # its own frames come back (is_rx False): each is acknowledged when it is on the bus
            if self.bus_interface == canbus.INTERFACE:  # the simulator's in-process bus
                self._bus = canbus.LocalBus(self.bus_channel, receive_own_messages=True)
            else:
                self._bus = can.Bus(interface=self.bus_interface, channel=self.bus_channel, receive_own_messages=True)
        except Exception as exc:
            raise SimulatorError(f"SLCAN adapter: cannot open {self.bus_interface} channel "
                                 f"{self.bus_channel!r}: {exc}") from exc
        try:
            self._pty.open()
        except BaseException:
            self._bus.shutdown()
            self._bus = None
            raise
        self._wake_r, self._wake_w = os.pipe()
        self._acks.clear()
        self._stopping.clear()
        self._threads = [threading.Thread(target=self._serve_pty, name="sim-slcan-pty", daemon=True),
                         threading.Thread(target=self._serve_bus, name="sim-slcan-bus", daemon=True)]
        for t in self._threads:
            t.start()

    def stop(self) -> None:
        if not self._threads:
            return
        self._stopping.set()
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass
        for t in self._threads:
            t.join()
        self._threads = []
        os.close(self._wake_r)
        os.close(self._wake_w)
        self._wake_r = self._wake_w = -1
        self._pty.close()
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    @property
    def bus_off(self) -> bool:
        return self._bus_off

    @bus_off.setter
    def bus_off(self, on: bool) -> None:
        if self._bus_off and not on:
            self._pass_t = time.time()  # what was on the bus meanwhile never reached the adapter
        self._bus_off = bool(on)

    @property
    def passing(self) -> bool:
        """Frames pass between the master and the bus: open, not bus-off, at the bus's bitrate."""
        return self.is_open and not self.bus_off and self.selected_bitrate in (None, self.bitrate)

    # ------------------------------------------------------------------ pty side
    def _serve_pty(self) -> None:
        master = self._pty.master_fd
        poller = select.poll()
        poller.register(master, select.POLLIN)
        poller.register(self._wake_r, select.POLLIN)
        buf = bytearray()
        try:
            while not self._stopping.is_set():
                poller.poll()
                if self._stopping.is_set():
                    return
                try:
                    data = os.read(master, 4096)
                except BlockingIOError:
                    continue
                except OSError:  # EIO: no client has the pty open; wait for the next one
                    time.sleep(0.01)
                    continue
                self.rx_bytes += len(data)
                buf += data
                replies = []
                while True:
                    cr = buf.find(b"\r")
                    if cr < 0:
                        if len(buf) > _MAX_LINE:
                            buf.clear()  # noise without a CR: drop it, as the firmware's buffer would
                        break
                    line = bytes(buf[:cr]).replace(b"\n", b"")
                    del buf[: cr + 1]
                    replies.append(self._command(line))
                out = b"".join(replies)  # a frame's acknowledgement comes later (_serve_bus)
                if out:
                    self._write(out)
        except Exception:
            log.exception("SLCAN adapter: pty thread died")
            raise

    def _command(self, line: bytes) -> bytes:
        """The adapter's reply to one LAWICEL command line (without its CR)."""
        if not line:
            return OK
        c = line[:1]
        if c in (b"t", b"T", b"r", b"R"):
            msg = parse_frame(line)
            if msg is None or not self.is_open or self.listen_only or not self.passing:
                return ERROR
            self.rx_frames += 1
            self._acks.append(b"Z\r" if c in (b"T", b"R") else b"z\r")
            self._bus.send(msg)
            return b""  # acknowledged when it is on the bus (_serve_bus), with what the bus brings
        if c == b"S" and len(line) == 2 and chr(line[1]) in BITRATE_CODES and not self.is_open:
            self.selected_bitrate = BITRATE_CODES[chr(line[1])]
            return OK
        if c == b"s" and len(line) == 5 and set(line[1:]) <= _HEX and not self.is_open:
            self.selected_bitrate = -1  # a custom bit timing: not the simulated bus's bitrate
            return OK
        if c in (b"O", b"L") and len(line) == 1 and not self.is_open:
            self.is_open, self.listen_only = True, c == b"L"
            self._pass_t = time.time()  # frames on the bus before the channel opened are not received
            return OK
        if c == b"C" and len(line) == 1:
            self.is_open = False
            return OK
        if c == b"F" and len(line) == 1:
            return f"F{FLAG_BUS_ERROR if self.is_open and not self.passing else 0:02X}\r".encode()
        if c == b"V" and len(line) == 1:
            return b"V1013\r"
        if c == b"v" and len(line) == 1:
            return b"v1013\r"
        if c == b"N" and len(line) == 1:
            return b"NSIM0\r"
        if c == b"Z" and line[1:] in (b"0", b"1") and not self.is_open:
            self.timestamps = line[1:] == b"1"
            return OK
        return ERROR

    def _write(self, data: bytes) -> None:
        with self._write_lock:
            try:
                n = os.write(self._pty.master_fd, data)
            except (BlockingIOError, OSError):
                n = 0
            self.tx_bytes += n
            if n < len(data):
                self.overruns += 1  # the client is not reading: an adapter's buffer overflows

    # ------------------------------------------------------------------ bus side
    def _serve_bus(self) -> None:
        """Bus frames to the pty, as a USB adapter sends them, several in one transfer: what
        arrives within one USB frame (:data:`USB_FRAME_S`) of the first goes up in one write, at
        most :data:`USB_BATCH_FRAMES` at a time. The master's own frames come back here once on
        the bus: their acknowledgements (``z`` / ``Z``) go up in the same stream, in bus order.
        So a 250 Hz CANopen cycle wakes the master's reader about once: the SYNC's
        acknowledgement, the TPDOs answering it and the acknowledgements of the RPDOs the master
        sends right after go up together (a SYNC's answers reach the master up to a USB frame
        later, as through a real USB adapter)."""
        bus = self._bus
        try:
            while not self._stopping.is_set():
                msg = bus.recv(0.05)
                if msg is None:
                    continue
                lines = []
                until = time.monotonic() + USB_FRAME_S
                while True:
                    if not msg.is_rx:  # one of ours, on the bus: its acknowledgement
                        if self._acks:
                            lines.append(self._acks.popleft())
                    # passing when the frame was on the bus (its stamp), not only when this
                    # thread gets to it: a frame from while the adapter was closed, at the wrong
                    # bitrate or bus-off is not forwarded after it reopened
                    elif self.passing and msg.timestamp >= self._pass_t and not msg.is_error_frame and not msg.is_fd:
                        line = format_frame(msg)
                        if self.timestamps:
                            line += f"{int(time.monotonic() * 1000) % 60000:04X}".encode()
                        lines.append(line + b"\r")
                    if len(lines) >= USB_BATCH_FRAMES:
                        break
                    msg = bus.recv(max(0.0, until - time.monotonic()))
                    if msg is None:
                        break
                if lines:
                    self.tx_frames += sum(len(line) > 2 for line in lines)  # not the acknowledgements
                    self._write(b"".join(lines))
        except Exception:
            log.exception("SLCAN adapter: bus thread died")
            raise

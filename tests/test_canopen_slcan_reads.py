"""The CANopen backend's slcan bus (backends/canopen402/slcan.py) reads what the adapter sent in one
go (issue 23: python-can 4.6 reads an SLCAN line byte by byte, a ``select`` + ``read`` per byte,
and polls every 1 ms while the bus is silent; at 250 Hz that was a quarter of a core). Asserted as
behaviour: the frames come out whole and in order, and the number of serial reads they took, not
how long they took."""

from __future__ import annotations

import os
import pty
import select
import time
import tty

import can
import pytest

from crtk_bridge.backends.canopen402.slcan import SERIAL_TIMEOUT_S, SlcanBus


def record_writes(monkeypatch, port) -> list[bytes]:
    """The list of what each os.write on the bus's port writes (the write still happens)."""
    writes = []
    real_write = os.write

    def os_write(fd, data):
        if fd == port.fd:
            writes.append(bytes(data))
        return real_write(fd, data)

    monkeypatch.setattr(os, "write", os_write)
    return writes


@pytest.fixture
def bus_and_adapter(monkeypatch):
    """A SlcanBus on one end of a pty; the test writes the adapter's bytes on the other. The
    third item lists the reads of the bus's port (os.read of its descriptor, or Serial.read)."""
    master, slave = pty.openpty()
    tty.setraw(master)
    name = os.ttyname(slave)
    bus = SlcanBus(channel=name, bitrate=1_000_000, sleep_after_open=0)
    sent = b""
    deadline = time.monotonic() + 10
    while b"O\r" not in sent and time.monotonic() < deadline:  # the bitrate and open commands python-can sent
        if select.select([master], [], [], 0.1)[0]:
            sent += os.read(master, 1024)
    assert b"O\r" in sent, sent
    reads = []
    port = bus.serialPortOrig
    real_read, real_os_read = port.read, os.read

    def counted(size=1):
        reads.append(size)
        return real_read(size)

    def os_read(fd, n):
        if fd == port.fd:
            reads.append(n)
        return real_os_read(fd, n)

    port.read = counted
    monkeypatch.setattr(os, "read", os_read)
    yield bus, master, reads
    monkeypatch.undo()
    bus.shutdown()
    os.close(master)
    os.close(slave)


def test_a_burst_of_frames_takes_one_or_two_reads_not_one_per_byte(bus_and_adapter):
    bus, master, reads = bus_and_adapter
    sent = [(0x181, bytes.fromhex("0F012C00000000")), (0x282, bytes.fromhex("1122334455667788")),
            (0x182, bytes.fromhex("0F012D00000000"))]
    # the adapter's acknowledgements of two transmits between the frames, all in one chunk
    frames = b"z\r" + b"z\r".join(f"t{i:03X}{len(d)}{d.hex().upper()}\r".encode() for i, d in sent)
    os.write(master, frames)
    got = [bus.recv(1.0) for _ in range(3)]
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == sent
    # python-can 4.6's slcan: one read per byte, len(frames) of them
    assert 1 <= len(reads) <= 4, reads


def test_a_line_split_across_two_writes_comes_out_whole(bus_and_adapter):
    bus, master, _ = bus_and_adapter
    os.write(master, b"t1812AB")
    assert bus.recv(0.1) is None  # no CR yet: no frame, and no garbage
    os.write(master, b"CD\r")
    msg = bus.recv(1.0)
    assert msg is not None and msg.arbitration_id == 0x181 and bytes(msg.data) == b"\xab\xcd"


def test_a_silent_bus_is_waited_on_not_polled_every_millisecond(bus_and_adapter):
    bus, _, reads = bus_and_adapter
    assert bus.recv(0.5) is None
    # stock python-can: the serial timeout is 1 ms, so ~500 reads in 0.5 s
    assert len(reads) <= 0.5 / SERIAL_TIMEOUT_S + 2, len(reads)


def test_sending_is_python_cans_without_waiting_for_the_port_to_drain(bus_and_adapter):
    """A send writes the line and returns: no tcdrain (Serial.flush) in the control cycle."""
    bus, master, _ = bus_and_adapter
    drains = []
    bus.serialPortOrig.flush = lambda: drains.append(1)
    bus.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
    out = b""
    while not out.endswith(b"\r"):  # a closing CR, or the test's timeout
        out += os.read(master, 64)
    assert out.endswith(b"t0800\r") and drains == []


def test_a_line_is_one_write_of_the_tty_without_pyserials_select_for_room(bus_and_adapter, monkeypatch):
    """pyserial's write follows each write with a ``select`` for room in the output buffer: a
    line on a tty is one os.write of the whole line, pyserial's write not called."""
    bus, master, _ = bus_and_adapter
    port = bus.serialPortOrig
    writes, pyserial = record_writes(monkeypatch, port), []
    port.write = lambda data: pyserial.append(bytes(data))
    bus.send(can.Message(arbitration_id=0x201, data=b"\x0f\x00", is_extended_id=False))
    assert writes == [b"t20120F00\r"] and pyserial == []
    out = b""
    while not out.endswith(b"\r"):
        out += os.read(master, 64)
    assert out == b"t20120F00\r"


def test_the_rest_of_a_line_the_output_buffer_did_not_take_goes_through_pyserial(bus_and_adapter, monkeypatch):
    """A full output buffer (os.write takes part of the line, or none): pyserial's write sends the
    rest (waiting for room), so the line goes out whole and in order."""
    bus, _, _ = bus_and_adapter
    port = bus.serialPortOrig
    taken = iter([3, None])  # 3 bytes of the first line; then a full buffer (EAGAIN)
    rest = []

    def os_write(fd, data):
        n = next(taken)
        if n is None:
            raise BlockingIOError
        return n

    monkeypatch.setattr(os, "write", os_write)
    port.write = lambda data: rest.append(bytes(data))
    bus.send(can.Message(arbitration_id=0x201, data=b"\x0f\x00", is_extended_id=False))
    bus.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
    assert rest == [b"120F00\r", b"t0800\r"]


def test_a_pyserial_url_without_a_descriptor_is_read_with_its_own_read():
    """``loop://`` (pyserial's loopback URL) has no file descriptor: what the bus sends comes
    back through pyserial's own read, a frame whole (after the open commands' echoes)."""
    bus = SlcanBus(channel="loop://", bitrate=1_000_000, sleep_after_open=0)
    try:
        bus.send(can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
        msg = bus.recv(1.0)
        while msg is not None and msg.arbitration_id != 0x123:
            msg = bus.recv(1.0)
        assert msg is not None and bytes(msg.data) == b"\x01\x02"
    finally:
        bus.shutdown()


def test_the_adapters_acknowledgements_are_dropped_not_parsed_one_recv_round_each(bus_and_adapter, monkeypatch):
    """``z`` / ``Z`` (a transmit acknowledged) is no message: the frame after three of them comes
    out of the first parse, not after three empty rounds of python-can's ``_recv_internal``."""
    bus, master, _ = bus_and_adapter
    rounds = []
    real = bus._recv_internal

    def counted(timeout):
        got = real(timeout)
        rounds.append(got[0])
        return got

    monkeypatch.setattr(bus, "_recv_internal", counted)
    os.write(master, b"z\rZ\rz\rt1812ABCD\r")
    msg = bus.recv(1.0)
    assert msg is not None and msg.arbitration_id == 0x181 and bytes(msg.data) == b"\xab\xcd"
    assert rounds == [msg]
    os.write(master, b"V1013\rz\r")  # other lines still come out whole (python-can's own commands)
    assert bus._read(1.0) == "V1013\r"


def test_a_write_of_lines_split_by_a_full_output_buffer_lets_no_other_line_in(bus_and_adapter, monkeypatch):
    """The cycle's lines (``send_lines``) are written outside canopen's send lock; when the tty
    takes only part of them (a full output buffer) and the rest goes through port.write, another
    thread's line waits for the whole write: spliced into it, the adapter would send a frame
    nobody asked for."""
    import threading

    bus, master, _ = bus_and_adapter
    port = bus.serialPortOrig
    real_write, real_port_write = os.write, port.write
    in_rest, release = threading.Event(), threading.Event()

    def os_write(fd, data):
        if fd == port.fd and len(data) > 20:  # the cycle's lines: the tty takes half of them
            return real_write(fd, bytes(data[:len(data) // 2]))
        return real_write(fd, data)

    def port_write(data):  # the rest of them: slow, while another thread sends
        in_rest.set()
        release.wait(5)
        return real_port_write(data)

    monkeypatch.setattr(os, "write", os_write)
    port.write = port_write
    other = threading.Thread(target=lambda: (in_rest.wait(5), bus.send(can.Message(
        arbitration_id=0x601, data=b"\x40", is_extended_id=False)), None))
    other.start()
    releaser = threading.Timer(0.3, release.set)  # the other thread is inside send by then, or blocked
    releaser.start()
    bus.send_lines(b"".join(SlcanBus.line(cob, b"\x0f\x00") for cob in (0x201, 0x301, 0x202)))
    other.join(10)
    releaser.join()
    out = b""
    deadline = time.monotonic() + 10
    while out.count(b"\r") < 4 and time.monotonic() < deadline:
        if select.select([master], [], [], 0.1)[0]:
            out += os.read(master, 256)
    assert out == b"t20120F00\rt30120F00\rt20220F00\rt601140\r", out



def test_the_backends_preformatted_lines_are_python_cans_bytes(bus_and_adapter, monkeypatch):
    """``SlcanBus.line`` / ``head`` / ``send_lines`` (the backend's cycle frames, formatted once
    without a Message each): the same bytes python-can's ``send`` writes for the same frame."""
    bus, master, _ = bus_and_adapter
    writes = record_writes(monkeypatch, bus.serialPortOrig)
    frames = [(0x080, b""), (0x201, b"\x0f\x00\x10\x27\x00\x00\x08"), (0x77F, b"\x05"), (0x7FF, bytes(range(250, 256)) + b"\xab\xcd")]
    for cob, data in frames:
        bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
        bus.send_lines(SlcanBus.line(cob, data))
    assert len(writes) == 2 * len(frames)
    assert writes[0::2] == writes[1::2], writes
    assert all(SlcanBus.line(cob, data).startswith(SlcanBus.head(cob, len(data))) for cob, data in frames)

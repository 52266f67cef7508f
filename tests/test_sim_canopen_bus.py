"""The CANopen simulator's drives on one shared bus endpoint (crtk_bridge/sim/canopen402.py): one
receive thread for all of them, not one per drive woken by every frame (issue 23: the simulator's
CPU counts too), and still a bus: every drive hears the master and the other drives."""

from __future__ import annotations

import os
import threading
import time

import can

from crtk_bridge.sim.canopen402 import CanopenSimulator, DriveOptions

from .conftest import wait_until


def test_the_drives_share_one_receive_thread_and_hear_the_master_and_each_other():
    channel = f"shared-bus-test-{os.getpid()}-{time.monotonic_ns()}"
    before = {t.ident for t in threading.enumerate()}
    ids = (1, 2, 3)
    sim = CanopenSimulator(list(ids), {n: DriveOptions(heartbeat_ms=20) for n in ids},
                           interface="virtual", channel=channel)
    master = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        sim.start()
        receivers = [t for t in threading.enumerate() if t.ident not in before and t.name.startswith("Notifier")]
        assert len(receivers) == 1, [t.name for t in receivers]  # one per drive before
        # each drive hears the others' heartbeats (its own frames come back to the endpoint too)
        wait_until(lambda: all(set(ids) - {n} <= set(sim.drive(n)._heartbeats) for n in ids), 5,
                   what="every drive hearing the other drives' heartbeats")
        # and the master's frames: NMT start all, then SYNCs every drive counts
        master.send(can.Message(arbitration_id=0, data=b"\x01\x00", is_extended_id=False))
        wait_until(lambda: all(sim.drive(n).local.nmt.state == "OPERATIONAL" for n in ids), 5,
                   what="every drive OPERATIONAL")
        for _ in range(3):
            master.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        wait_until(lambda: all(sim.drive(n).sync_count == 3 for n in ids), 5, what="every drive taking 3 SYNCs")
        # a silenced drive hears nothing on the shared endpoint either
        sim.set_fault(2, "silent")
        master.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        wait_until(lambda: sim.drive(1).sync_count == sim.drive(3).sync_count == 4, 5, what="the 4th SYNC")
        assert sim.drive(2).sync_count == 3
    finally:
        master.shutdown()
        sim.stop()
    assert not [t for t in threading.enumerate() if t.ident not in before and t.name.startswith("Notifier")]


def test_a_drive_that_raises_on_a_frame_does_not_deafen_the_others(monkeypatch, caplog):
    """The shared receive thread survives a drive's error (logged, naming the drive), and the
    other drives keep hearing the bus, as each did on its own canopen listener."""
    channel = f"shared-bus-raise-{os.getpid()}-{time.monotonic_ns()}"
    sim = CanopenSimulator([1, 2], interface="virtual", channel=channel)
    master = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        sim.start()
        master.send(can.Message(arbitration_id=0, data=b"\x01\x00", is_extended_id=False))
        wait_until(lambda: all(sim.drive(n).local.nmt.state == "OPERATIONAL" for n in (1, 2)), 5,
                   what="both drives OPERATIONAL")

        def broken(msg):
            raise RuntimeError("broken drive")

        monkeypatch.setattr(sim.drive(1), "hear", broken)
        for _ in range(2):
            master.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        wait_until(lambda: sim.drive(2).sync_count == 2, 5, what="drive 2 taking both SYNCs")
        assert sim.drive(1).sync_count == 0
        assert "drive 1: frame 0x080 dropped" in caplog.text
    finally:
        master.shutdown()
        sim.stop()


def test_behind_the_adapter_a_frame_is_handled_in_the_adapters_thread_with_no_receive_thread(tmp_path):
    """With the simulated USB-CAN adapter (what ``--sim`` runs), the drives sit on the in-process
    bus (sim/canbus.py): a SYNC the master writes to the pty is handled by the drives in the
    adapter's own thread -- no receive thread of theirs, no hand-off per frame (issue 23: the
    simulator's CPU per cycle) -- and the drives still hear each other."""
    before = {t.ident for t in threading.enumerate()}
    sim = CanopenSimulator([1, 2], {n: DriveOptions(heartbeat_ms=20) for n in (1, 2)}, interface="slcan")
    seen = []
    sim.start()
    fd = os.open(sim.port, os.O_RDWR | os.O_NOCTTY)
    try:
        started = [t.name for t in threading.enumerate() if t.ident not in before]
        assert not [n for n in started if n.startswith("Notifier")], started
        wait_until(lambda: {2} <= set(sim.drive(1)._heartbeats) and {1} <= set(sim.drive(2)._heartbeats), 5,
                   what="each drive hearing the other's heartbeat")
        real = sim.drive(2).hear
        sim.drive(2).hear = lambda msg: (seen.append((msg.arbitration_id, threading.current_thread().name)),
                                         real(msg))
        os.write(fd, b"S8\rO\rt00020100\r")  # open, NMT start all; a SYNC once they are OPERATIONAL
        wait_until(lambda: all(sim.drive(n).local.nmt.state == "OPERATIONAL" for n in (1, 2)), 5,
                   what="both drives OPERATIONAL")
        os.write(fd, b"t0800\r")
        wait_until(lambda: sim.drive(1).sync_count == sim.drive(2).sync_count == 1, 5, what="both drives taking the SYNC")
        assert (0x80, "sim-slcan-pty") in seen, seen
    finally:
        os.close(fd)
        sim.stop()


def test_the_in_process_bus_delivers_in_bus_order_without_recursion_or_deadlock(caplog):
    """sim/canbus.py: a frame sent from inside a handler is delivered after the handler returns
    (bus order, no re-entry); a sender holding a lock the delivering handler waits for is not
    blocked (it queues, the delivering thread delivers it: no deadlock, as a drive's tick thread
    sends under its drive's lock); a handler that raises is logged and the others still get the
    frame; each endpoint gets its own copy, the sender's own echo with is_rx False."""
    from crtk_bridge.sim.canbus import LocalBus

    channel = f"local-bus-test-{os.getpid()}-{time.monotonic_ns()}"
    drive_lock = threading.RLock()  # as a simulated drive's
    depth, heard = [0], []
    entered = threading.Event()  # a delivery reached the drive's handler

    def drive(msg):  # answers 0x80 with 0x181, under its lock, as a simulated drive does
        depth[0] += 1
        entered.set()
        try:
            with drive_lock:
                heard.append((msg.arbitration_id, msg.is_rx, depth[0]))
                if msg.arbitration_id == 0x80:
                    drives.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
        finally:
            depth[0] -= 1

    def broken(msg):
        raise RuntimeError("broken endpoint")

    master = LocalBus(channel)
    drives = LocalBus(channel, receive_own_messages=True, on_message=drive)
    other = LocalBus(channel, on_message=broken)
    try:
        sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
        master.send(sync)
        assert heard == [(0x80, True, 1), (0x181, False, 1)]  # its answer after it, not inside it
        got = master.recv(1)
        assert got.arbitration_id == 0x181 and got.is_rx and got.data == b"\x01"
        assert master.recv(0) is None  # no echo of its own without receive_own_messages
        master.set_filters([{"can_id": 0x181, "can_mask": 0x7FF}])  # a filter still filters
        drives.send(can.Message(arbitration_id=0x182, data=b"", is_extended_id=False))
        drives.send(can.Message(arbitration_id=0x181, data=b"\x02", is_extended_id=False))
        assert master.recv(1).data == b"\x02" and master.recv(0) is None
        master.set_filters(None)
        heard.clear()
        assert "broken endpoint" in caplog.text and "0x080" in caplog.text

        # a thread holding the drive's lock sends while this thread delivers to that drive
        heard.clear()
        entered.clear()
        holding, sent = threading.Event(), threading.Event()

        def tick():
            with drive_lock:
                holding.set()
                entered.wait(10)  # the delivering thread is in the handler, waiting for the lock
                drives.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
                sent.set()

        t = threading.Thread(target=tick, daemon=True)
        t.start()
        assert holding.wait(10)
        # (in a thread: a bus that made the sender wait would deadlock it; the test then fails)
        delivering = threading.Thread(target=master.send, daemon=True,
                                      args=(can.Message(arbitration_id=0x700, data=b"\x05", is_extended_id=False),))
        delivering.start()
        t.join(20)
        delivering.join(20)
        assert sent.is_set() and not t.is_alive() and not delivering.is_alive()
        assert [h[0] for h in heard] == [0x700, 0x701]
    finally:
        for bus in (master, drives, other):
            bus.shutdown()

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

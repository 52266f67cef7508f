"""The loop's receive from the front (core/loop.py ``ControlLoop._receive``, issue 23): the front
counts what it sends on the pair in the snapshot's shared memory (``posted``), so a cycle where
nothing was sent makes no receive system call; yet a request is taken in the first cycle after it
was counted, an uncounted sender (-1) is received every cycle, and the front's loss (EOF) is seen
within RECEIVE_AT_LEAST_S. Cycle by cycle, no daemon."""

from __future__ import annotations

import math
import socket

import msgspec
import pytest

from crtk_bridge.core.loop import RECEIVE_AT_LEAST_S, ControlLoop
from crtk_bridge.core.snapshot import Layout, SnapshotBuffer
from crtk_bridge.server.link import ControlLink

from .test_controller import PROFILE, FakeActuator

_encode = msgspec.msgpack.Encoder().encode


class CountingChan:
    """The control process's end of the pair, counting its receives."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.receives = 0

    def recv(self, *args):
        self.receives += 1
        return self.sock.recv(*args)

    def send(self, *args):
        return self.sock.send(*args)


@pytest.fixture
def rig():
    front, back = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    snap = SnapshotBuffer(Layout(len(PROFILE.joints), len(PROFILE.namespaces)), create=True)
    chan = CountingChan(back)
    loop = ControlLoop(PROFILE, FakeActuator(PROFILE), chan, snap, realtime=False)
    try:
        yield loop, chan, front, snap
    finally:
        front.close()
        back.close()
        snap.close(unlink=True)


def replies(loop):
    out = [m for m in loop.controller.outbox if "ok" in m]
    loop.controller.outbox.clear()
    return out


def test_cycles_with_nothing_sent_make_no_receive_yet_one_at_least_every_period_of_grace(rig):
    loop, chan, front, snap = rig
    link = ControlLink(PROFILE, front, snap, lambda msg: None)  # the front counts: 0 sent so far
    assert int(snap.posted[0]) == 0
    every = max(1, int(RECEIVE_AT_LEAST_S / loop.period))  # cycles between receives at the most
    cycles = 20 * every
    for _ in range(cycles):
        loop._receive()
    assert loop.front_alive
    # one receive empties the pair, then one per RECEIVE_AT_LEAST_S (not one per cycle, as before)
    assert chan.receives <= 1 + math.ceil(cycles / every) < cycles
    assert chan.receives >= cycles // every
    del link


def test_a_counted_request_is_taken_in_the_next_cycle(rig):
    loop, chan, front, snap = rig
    link = ControlLink(PROFILE, front, snap, lambda msg: None)
    loop._receive()  # the pair is empty: the count is seen drained
    loop._receive()
    before = chan.receives
    link._post(_encode({"id": 7, "cmd": "hold", "ns": "arm", "data": None}))  # the front's send + count
    assert int(snap.posted[0]) == 2
    loop._receive()
    assert chan.receives > before
    assert [r["id"] for r in replies(loop)] == [7]  # (refused: DISABLED; what matters is it was taken)


def test_a_send_under_way_is_received_in_the_first_cycle_after_it_lands(rig):
    """The front counts before its send (odd: under way) and after it (even): a cycle that looks
    while a send is under way receives, and so does every cycle after it until the count is even
    again, so the message is taken in the first cycle after it is on the pair, whenever the front
    (preempted between its count and its send on a loaded host) gets to send it."""
    loop, chan, front, snap = rig
    snap.posted[0] = 0
    loop._receive()  # the pair emptied at count 0
    snap.posted[0] = 1  # the front counted its send, and has not sent yet
    loop._receive()
    loop._receive()
    assert not replies(loop)
    front.send(_encode({"id": 8, "cmd": "hold", "ns": "arm", "data": None}))  # on the pair now
    loop._receive()
    assert [r["id"] for r in replies(loop)] == [8]
    snap.posted[0] = 2  # the send is done
    loop._receive()  # (the count moved: one receive, which empties the pair at count 2)
    before = chan.receives
    loop._receive()
    assert chan.receives == before  # nothing under way, nothing new: no receive


def test_the_links_count_is_even_after_each_send(rig):
    loop, chan, front, snap = rig
    link = ControlLink(PROFILE, front, snap, lambda msg: None)
    for k in range(3):
        link._post(_encode({"id": k, "cmd": "hold", "ns": "arm", "data": None}))
        assert int(snap.posted[0]) == 2 * (k + 1)


def test_an_uncounted_sender_is_received_every_cycle(rig):
    loop, chan, front, snap = rig
    assert int(snap.posted[0]) == -1  # no link counts (a test rig, a raw pair)
    for k in range(5):
        front.send(_encode({"id": k, "cmd": "hold", "ns": "arm", "data": None}))
        loop._receive()
        assert [r["id"] for r in replies(loop)] == [k]
    assert chan.receives >= 10  # each cycle: the message, then the empty pair


def test_more_than_a_cycles_worth_of_requests_are_taken_over_the_next_cycles(rig):
    from crtk_bridge.core.loop import MAX_REQUESTS_PER_CYCLE

    loop, chan, front, snap = rig
    link = ControlLink(PROFILE, front, snap, lambda msg: None)
    n = MAX_REQUESTS_PER_CYCLE + 5
    for k in range(n):
        link._post(_encode({"id": k, "cmd": "hold", "ns": "arm", "data": None}))
    loop._receive()
    assert len(replies(loop)) == MAX_REQUESTS_PER_CYCLE
    loop._receive()  # the count has not moved, but the pair was not emptied: received anyway
    assert len(replies(loop)) == 5


def test_the_fronts_loss_is_seen_within_the_period_of_grace(rig):
    loop, chan, front, snap = rig
    ControlLink(PROFILE, front, snap, lambda msg: None)
    loop._receive()
    assert loop.front_alive
    front.close()  # the front process died: its count never moves again
    every = max(1, int(RECEIVE_AT_LEAST_S / loop.period))
    for _ in range(every):
        loop._receive()
    assert not loop.front_alive

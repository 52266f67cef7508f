"""The front's Zenoh publishing paths in-process: the ROS graph's (transport/ros: who is
subscribed, the CDR it puts on the wire) and a remote client's (transport/tunnel: a stalled link
never holds the event loop). No daemon: Zenoh sessions on loopback endpoints, multicast off."""

from __future__ import annotations

import itertools
import json
import logging
import threading

import msgspec
import numpy as np
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore

from crtk_bridge.core.snapshot import Layout, SnapshotBuffer
from crtk_bridge.server import streams
from crtk_bridge.server.protocol import encode
from crtk_bridge.server.server import Server
from crtk_bridge.server.streams import TopicStream, tick_all
from crtk_bridge.transport.ros import types as T
from crtk_bridge.transport.ros.periodic import Encoders
from crtk_bridge.transport.ros.rmw import Node
from crtk_bridge.transport.tunnel import FRAME_BACKLOG, TunnelSession
from tests.conftest import free_port, wait_until

# an independent type store (not the project's): the reference serializer
STORE = get_typestore(Stores.ROS2_KILTED)
R = STORE.types
ENCODERS = Encoders()  # one for every example: its templates are reused as on the wire


def _session(listen: list[str] = (), connect: list[str] = ()) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("timestamping/enabled", "true")  # the advanced publishers need it
    return zenoh.open(conf)


@pytest.fixture(scope="module")
def pair():
    """The graph's session (listening) and a peer joined to it (a ROS node's view)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ours = _session(listen=[endpoint])
    theirs = _session(connect=[endpoint])
    yield ours, theirs
    theirs.close()
    ours.close()


def test_a_topic_is_wanted_only_while_somebody_subscribes(pair):
    """A periodic topic nobody subscribes to is not encoded: ``wanted`` is False until a matching
    subscriber appears (an unrelated one does not count) and False again once it leaves."""
    ours, theirs = pair
    node = Node(ours, 0, "wanted_test")
    try:
        pub = node.publisher("/so101/measured_js", T.JOINT_STATE)
        assert pub.wanted is False
        other = theirs.declare_subscriber("0/so101/setpoint_js/**", lambda s: None)
        sub = theirs.declare_subscriber("0/so101/measured_js/**", lambda s: None)
        wait_until(lambda: pub.wanted is True, 5, what="measured_js wanted once subscribed")
        sub.undeclare()
        wait_until(lambda: pub.wanted is False, 5, what="measured_js not wanted once unsubscribed")
        other.undeclare()
    finally:
        node.close()


def _time(stamp: float):
    ns = int(round(stamp * 1e9)) if stamp > 0 else 0
    return R["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(stamp: float, frame: str):
    return R["std_msgs/msg/Header"](stamp=_time(stamp), frame_id=frame)


def _ref(msg, ros_type: str) -> bytes:
    return bytes(STORE.serialize_cdr(msg, ros_type))


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
stamps = st.one_of(st.just(0.0), st.floats(1e9, 2.1e9))  # int32 seconds (to 2038)


@settings(max_examples=60, deadline=None)
@given(stamp=stamps, values=st.lists(finite, min_size=15, max_size=15),
       present=st.tuples(st.booleans(), st.booleans(), st.booleans()), n=st.integers(1, 5))
def test_joint_state_template_encodes_as_rosbags(stamp, values, present, n):
    """The periodic JointState (a CDR template whose numbers are rewritten in place) is byte for
    byte the reference serializer's, for every layout: vectors present or empty, any length."""
    names = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"][:n]
    vec = [np.array(values[5 * i:5 * i + n], dtype=np.float64) if present[i] else np.empty(0) for i in range(3)]
    js = {"stamp": stamp, "frame_id": "so101", "name": names, "position": vec[0].tolist(),
          "velocity": vec[1].tolist(), "effort": vec[2].tolist()}
    ref = R["sensor_msgs/msg/JointState"](header=_header(stamp, "so101"), name=names, position=vec[0],
                                          velocity=vec[1], effort=vec[2])
    assert ENCODERS.joint_state(js) == _ref(ref, "sensor_msgs/msg/JointState")


@settings(max_examples=40, deadline=None)
@given(stamp=stamps, v=st.lists(finite, min_size=14, max_size=14), valid=st.booleans())
def test_cartesian_and_tf_templates_encode_as_rosbags(stamp, v, valid):
    """PoseStamped (an invalid pose: the identity, stamp 0), TwistStamped, WrenchStamped and a
    two-transform TFMessage, byte for byte the reference serializer's."""
    G = "geometry_msgs/msg/"
    pos, q = (v[0:3], v[3:7]) if valid else ([0.0] * 3, [0.0, 0.0, 0.0, 1.0])
    pose = {"stamp": stamp if valid else 0.0, "frame_id": "base_link", "child_frame_id": "tip",
            "position": v[0:3] if valid else [], "orientation": v[3:7] if valid else []}
    ref_pose = R[G + "Pose"](position=R[G + "Point"](x=pos[0], y=pos[1], z=pos[2]),
                             orientation=R[G + "Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
    assert ENCODERS.cartesian(T.POSE_STAMPED, pose) == _ref(
        R[G + "PoseStamped"](header=_header(pose["stamp"], "base_link"), pose=ref_pose), G + "PoseStamped")

    def v3(x):
        return R[G + "Vector3"](x=x[0], y=x[1], z=x[2])
    six = (v[7:10], v[10:13]) if valid else ([0.0] * 3, [0.0] * 3)
    twist = {"stamp": pose["stamp"], "frame_id": "tip", "linear": v[7:10] if valid else [],
             "angular": v[10:13] if valid else []}
    assert ENCODERS.cartesian(T.TWIST_STAMPED, twist) == _ref(R[G + "TwistStamped"](
        header=_header(pose["stamp"], "tip"), twist=R[G + "Twist"](linear=v3(six[0]), angular=v3(six[1]))),
        G + "TwistStamped")
    wrench = {"stamp": pose["stamp"], "frame_id": "base_link", "force": twist["linear"], "torque": twist["angular"]}
    assert ENCODERS.cartesian(T.WRENCH_STAMPED, wrench) == _ref(R[G + "WrenchStamped"](
        header=_header(pose["stamp"], "base_link"), wrench=R[G + "Wrench"](force=v3(six[0]), torque=v3(six[1]))),
        G + "WrenchStamped")

    other = dict(pose, stamp=stamp, frame_id="world", child_frame_id="base_link", position=v[0:3],
                 orientation=v[3:7])
    transforms = [R[G + "TransformStamped"](
        header=_header(p["stamp"], p["frame_id"]), child_frame_id=p["child_frame_id"],
        transform=R[G + "Transform"](translation=v3(a), rotation=R[G + "Quaternion"](x=b[0], y=b[1], z=b[2], w=b[3])))
        for p, (a, b) in ((pose, (pos, q)), (other, (v[0:3], v[3:7])))]
    assert ENCODERS.tf([pose, other]) == _ref(R["tf2_msgs/msg/TFMessage"](transforms=transforms),
                                              "tf2_msgs/msg/TFMessage")


class StalledPublisher:
    """A Zenoh publisher whose link is stalled: ``put`` waits (as congestion control BLOCK does)
    until ``release`` is set. Each put carries one or more whole JSON lines."""

    def __init__(self, log: list, kind: str, release: threading.Event):
        self.log, self.kind, self.release = log, kind, release
        self.waiting = threading.Event()
        self.undeclared = False
        self.puts = 0

    def put(self, data: bytes) -> None:
        self.waiting.set()
        assert self.release.wait(10), "never released"
        self.puts += 1
        self.log.extend((self.kind, msgspec.json.decode(line)) for line in data.splitlines())

    def undeclare(self) -> None:
        self.undeclared = True


def _frame(sub: int, i: int) -> bytes:
    return encode({"topic": "measured_js", "ns": "so101", "sub": sub, "data": i})


def test_a_stalled_remote_link_never_holds_the_event_loop():
    """A remote client's replies wait for room on its link on the session's own thread: sending
    returns at once while the put is stuck; once the link moves, replies and events arrive all
    and in order, the frames kept are the newest (the oldest beyond the backlog dropped and
    counted, never queued without bound), and the publishers are undeclared after the last
    message went out."""
    release = threading.Event()
    log: list = []
    replies, frames = StalledPublisher(log, "reply", release), StalledPublisher(log, "frame", release)
    s = TunnelSession(1, "0123456789abcdef", replies, frames)
    try:
        s.send({"id": 1, "ok": True})
        assert replies.waiting.wait(5)  # the sender thread is stuck in the put
        for i in range(FRAME_BACKLOG + 50):  # all of this returns while the link is stalled
            s.send_frame(_frame(1, i))
            s.flush()
        s.send({"event": "operating_state", "data": {"state": "ENABLED"}})
        s.send({"id": 2, "ok": True})
        assert not release.is_set() and log == []
        assert s.dropped == 50
        s.close()
        release.set()
        wait_until(lambda: replies.undeclared and frames.undeclared, 5, what="publishers undeclared after the last put")
    finally:
        release.set()
    assert [m for k, m in log if k == "reply"] == [{"id": 1, "ok": True},
                                                   {"event": "operating_state", "data": {"state": "ENABLED"}},
                                                   {"id": 2, "ok": True}]
    assert [m["data"] for k, m in log if k == "frame"] == list(range(50, FRAME_BACKLOG + 50))  # the newest kept
    assert replies.puts == 2 and frames.puts == 1  # what waited went out together: one put each


class CountingPublisher:
    """A healthy link: records every line put, each put at once."""

    def __init__(self):
        self.lines: list[dict] = []
        self.lock = threading.Lock()

    def put(self, data: bytes) -> None:
        with self.lock:
            self.lines.extend(msgspec.json.decode(line) for line in data.splitlines())

    def frames(self) -> list[dict]:
        with self.lock:
            return [m for m in self.lines if "topic" in m]

    def undeclare(self) -> None:
        pass


def test_a_slow_remote_subscriber_delays_no_other_and_its_drops_are_counted(caplog):
    """Two remote clients subscribe the same topic; one's link stalls. The other still gets every
    tick's frame while the first is stuck, the stalled one keeps only the newest FRAME_BACKLOG
    frames, and what it lost is counted in its session, in the server's period_statistics
    (``frames_dropped``) and said in the log."""
    release = threading.Event()
    stalled_log: list = []
    slow = TunnelSession(1, "slow0123456789ab", StalledPublisher(stalled_log, "reply", release),
                         StalledPublisher(stalled_log, "frame", release))
    fast_pub = CountingPublisher()
    fast = TunnelSession(2, "fast0123456789ab", CountingPublisher(), fast_pub)
    stream = TopicStream("measured_js", "so101", itertools.count().__next__)
    ticks = FRAME_BACKLOG + 40
    try:
        stream.add(slow, 1, 0.001, 0.0)
        stream.add(fast, 2, 0.001, 0.0)
        with caplog.at_level(logging.WARNING, logger="crtk_bridge.server"):
            for k in range(ticks):
                tick_all([stream], k * 0.001)
                if k == 0:  # the slow client's sender thread is stuck in its first put from now on
                    assert slow._frames.waiting.wait(5)
                # the fast client has each frame while the slow one's thread is stuck
                wait_until(lambda: len(fast_pub.frames()) == k + 1, 5, what=f"the fast client's frame {k}")
        assert [m["data"] for m in fast_pub.frames()] == list(range(ticks))
        assert all(m["sub"] == 2 for m in fast_pub.frames()) and fast.dropped == 0
        assert not release.is_set() and stalled_log == []
        assert slow.dropped == ticks - 1 - FRAME_BACKLOG  # the first went into the stuck put
        assert any("slow0123" in r.getMessage() and "stream frames dropped" in r.getMessage() for r in caplog.records)
        server = Server.__new__(Server)  # only its statistics: the link's figures and the sessions'
        server.link = type("L", (), {"period_statistics": lambda self: {"cycles": 1}})()
        server.sessions, server._dropped_before, server.statistics = {1: slow, 2: fast}, 0, []
        assert server.period_statistics() == {"cycles": 1, "frames_dropped": slow.dropped}
        slow.close()
        release.set()
        wait_until(lambda: len([m for k, m in stalled_log if k == "frame"]) == 1 + FRAME_BACKLOG, 5,
                   what="the stalled client's kept frames")
        kept = [m["data"] for k, m in stalled_log if k == "frame"]
        assert kept == [0] + list(range(ticks - FRAME_BACKLOG, ticks))
    finally:
        release.set()
        slow.close()
        fast.close()


class Collecting:
    """A session that keeps the frames it is sent, and counts its flushes."""

    closed = False

    def __init__(self):
        self.frames: list[bytes] = []
        self.flushes = 0

    def send_frame(self, line: bytes) -> None:
        self.frames.append(line)

    def flush(self) -> None:
        self.flushes += 1


@pytest.mark.parametrize("n", [1, 7])
def test_a_topic_is_read_and_encoded_once_a_tick_whatever_the_number_of_subscribers(n, monkeypatch):
    """One read (produce) and one JSON encoding per tick for n subscribers of a topic; each gets
    the frame ``encode`` gives for its own subscription id, byte for byte, and one flush a tick
    for all the topics it subscribes.
    A slower subscriber shares the ticks: it gets every fourth at a quarter of the rate."""
    encodes = []
    real = streams.encode_body
    monkeypatch.setattr(streams, "encode_body", lambda d: encodes.append(d) or real(d))
    reads = itertools.count()
    stream = TopicStream("measured_js", "so101", lambda: {"stamp": float(next(reads)), "position": [0.5, -1.25]})
    sessions = [Collecting() for _ in range(n)]
    slow = Collecting()
    for i, s in enumerate(sessions):
        stream.add(s, 10 + i, 0.001, 0.0)
    stream.add(slow, 99, 0.004, 0.0)
    other = TopicStream("goal_js", "so101", lambda: {"stamp": 0.0})  # the first session's second topic
    other.add(sessions[0], 5, 0.001, 0.0)
    for k in range(20):
        assert tick_all([stream, other], k * 0.001) == pytest.approx((k + 1) * 0.001)  # the next tick
    assert len(encodes) == 40 and next(reads) == 20  # one read and one encoding per topic a tick
    assert [s.flushes for s in sessions] == [20] * n  # one flush a tick, for both topics
    assert len(sessions[0].frames) == 40
    sessions[0].frames = [f for f in sessions[0].frames if b'"goal_js"' not in f]
    for i, s in enumerate(sessions):
        assert s.frames == [encode({"topic": "measured_js", "ns": "so101", "sub": 10 + i,
                                    "data": {"stamp": float(k), "position": [0.5, -1.25]}}) for k in range(20)]
    assert [msgspec.json.decode(f)["data"]["stamp"] for f in slow.frames] == [0.0, 4.0, 8.0, 12.0, 16.0]


def test_the_publishing_thread_copies_the_state_without_the_statistics_rings():
    """SnapshotBuffer.read(upto=): the periodic topics' one read per tick copies the joint state
    and counters (a few hundred bytes), not the 16 KiB of lateness and compute rings."""
    snap = SnapshotBuffer(Layout(6, 2), create=True)
    try:
        snap.begin()
        snap.data[:] = np.arange(snap.data.size)
        snap.end()
        upto = snap.layout.slices["lateness"].start
        out = np.full_like(snap.data, -1.0)
        got, seq = snap.read(out, upto=upto)
        assert got is out and seq == 2
        assert np.array_equal(out[:upto], np.arange(upto)) and np.all(out[upto:] == -1.0)
        assert snap.layout.slices["cycles"].stop <= upto
    finally:
        snap.close(unlink=True)


def test_a_stream_forgets_the_subscribers_of_a_closed_session_and_ends_with_the_last():
    """A session that closed gets no frame and no read is made for it; once no subscriber is
    left the stream says so (the server forgets it and its task ends)."""
    ended = []
    reads = itertools.count()
    stream = TopicStream("measured_js", "so101", lambda: next(reads), ended.append)
    a, b = Collecting(), Collecting()
    stream.add(a, 1, 0.01, 0.0)
    stream.add(b, 2, 0.01, 0.0)
    tick_all([stream], 0.0)
    b.closed = True
    tick_all([stream], 0.01)
    assert len(a.frames) == 2 and len(b.frames) == 1 and ended == []
    a.closed = True
    assert tick_all([stream], 0.02) == float("inf")
    assert ended == [stream] and stream.subscribers == [] and next(reads) == 2


def test_ros_ticks_the_publishing_thread_missed_are_counted_and_said(monkeypatch, caplog):
    """The ROS topics' thread never bursts to catch up: when a tick's work takes 3.5 periods, the
    next publication goes out at once with the newest sample, the 2 ticks wholly missed are
    skipped, counted (period_statistics' ros_ticks_skipped) and said in the log, and the ticks
    after are on time again. A driven clock: nothing here waits."""
    from crtk_bridge.transport.ros import periodic

    class Clock:
        t = 0.0

        def perf_counter(self):
            return self.t

        def sleep(self, s):
            self.t += s

        def monotonic(self):
            return self.t

    clock = Clock()
    monkeypatch.setattr(periodic, "time", clock)
    p = periodic.PeriodicTopics.__new__(periodic.PeriodicTopics)
    p.period_s, p.robot, p._error_said, p.skipped, p._skip_said = 0.001, "so101", -1.0, 0, -1.0
    p._stop = threading.Event()
    calls = []

    def publish_once():
        calls.append(clock.t)
        if len(calls) == 2:
            clock.t += 0.0035  # this tick's work took 3.5 periods
        if len(calls) == 6:
            p._stop.set()
        return True

    p.publish_once = publish_once
    with caplog.at_level(logging.WARNING, logger="crtk_bridge.ros"):
        p._run()
    assert p.skipped == 2
    assert any("2 ticks skipped" in r.getMessage() for r in caplog.records)
    assert calls[2] == pytest.approx(0.0045)  # at once, not at a tick 0.002 or 0.003 replayed
    assert all(b - a == pytest.approx(0.001) for a, b in zip(calls[2:], calls[3:]))  # then on time again

"""The ROS 2 graph over Zenoh (transport/ros), seen from outside as a ROS 2 node would see it.

The subscriber and publishers here are written against rmw_zenoh's wire format with eclipse-zenoh
and rosbags' CDR alone (their own type store, not the project's): key expressions, liveliness
tokens, attachments, type hashes. One ``--sim`` daemon (SO-101) listening on a loopback endpoint
serves every test; sessions have multicast scouting off and explicit endpoints.
"""

from __future__ import annotations

import json
import struct
import threading
import time

import numpy as np
import pytest
import zenoh
import zenoh.ext as zext
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

from crtk_bridge.client.connection import Connection
from crtk_bridge.errors import CommandError
from tests.conftest import ROOT, DaemonProcess, free_port, wait_until

# The published RIHS01 hashes these tests hold the graph to:
# - std_msgs/msg/String: the topic key expression example of ros2/rmw_zenoh docs/design.md
#   (`0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74...`), also asserted by roslibrust's
#   ros2_hash_checks test;
# - sensor_msgs/msg/JointState: `ros2 topic info /joint_states --verbose` on a real ROS 2 Jazzy
#   system ("Topic type hash: RIHS01_a13ee3a3..." for joint_state_broadcaster's publisher), also
#   in cyclonedds-python's type-hash test.
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
JOINT_STATE_HASH = "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
JOINT_STATE_DDS = "sensor_msgs::msg::dds_::JointState_"
ARM = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]
NODE = "crtk_bridge_so101"

# the test's own type store: rosbags' Kilted types plus crtk_msgs from their .msg text
STORE = get_typestore(Stores.ROS2_KILTED)
STORE.register({
    **get_types_from_msg("std_msgs/Header header\nstring state\nbool is_homed\nbool is_busy\n",
                         "crtk_msgs/msg/OperatingState"),
    **get_types_from_msg("std_msgs/Header header\nstring string\n", "crtk_msgs/msg/StringStamped"),
})
Header = STORE.types["std_msgs/msg/Header"]
Time = STORE.types["builtin_interfaces/msg/Time"]
JointStateMsg = STORE.types["sensor_msgs/msg/JointState"]
StringStampedMsg = STORE.types["crtk_msgs/msg/StringStamped"]
StringMsg = STORE.types["std_msgs/msg/String"]


def zenoh_session(connect: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([connect]))
    conf.insert_json5("timestamping/enabled", "true")  # AdvancedSubscriber history needs it
    return zenoh.open(conf)


def key(topic: str, dds: str, h: str) -> str:
    return f"0/{topic}/{dds}/{h}"


def cdr_header() -> object:
    ns = time.time_ns()
    return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="")


def state_command(word: str) -> bytes:
    return bytes(STORE.serialize_cdr(StringStampedMsg(header=cdr_header(), string=word),
                                     "crtk_msgs/msg/StringStamped"))


def joint_state(position=(), velocity=(), name=()) -> bytes:
    msg = JointStateMsg(header=cdr_header(), name=list(name), position=np.array(position, dtype=np.float64),
                        velocity=np.array(velocity, dtype=np.float64), effort=np.array([], dtype=np.float64))
    return bytes(STORE.serialize_cdr(msg, "sensor_msgs/msg/JointState"))


class Topic:
    """Every sample of one key expression (wildcards allowed), decoded as ``ros_type``."""

    def __init__(self, session: zenoh.Session, key_expr: str, ros_type: str, advanced: bool = False):
        self.samples: list[tuple[str, object, bytes | None]] = []
        self.lock = threading.Lock()
        self.ros_type = ros_type
        if advanced:  # a TRANSIENT_LOCAL subscription as rmw_zenoh declares it: history from late publishers
            self.sub = zext.declare_advanced_subscriber(
                session, key_expr, self._on, history=zext.HistoryConfig(detect_late_publishers=True))
        else:
            self.sub = session.declare_subscriber(key_expr, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), self.ros_type)
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        with self.lock:
            self.samples.append((str(sample.key_expr), msg, att))

    def messages(self) -> list:
        with self.lock:
            return [m for _, m, _ in self.samples]

    def wait(self, predicate, timeout=10.0, what="a sample"):
        return wait_until(lambda: next((m for m in reversed(self.messages()) if predicate(m)), None),
                          timeout, what=what)

    def close(self) -> None:
        self.sub.undeclare()


@pytest.fixture(scope="module")
def ros_daemon(tmp_path_factory):
    port = free_port()
    d = tmp_path_factory.mktemp("zros")
    endpoint = f"tcp/127.0.0.1:{port}"
    daemon = DaemonProcess(["--profile", str(ROOT / "profiles/so101.yaml"), "--sim", "--no-realtime",
                            "--zenoh-listen", endpoint], d / "so101.sock", d / "daemon.log")
    daemon.endpoint = endpoint
    yield daemon
    daemon.stop()


@pytest.fixture(scope="module")
def ros(ros_daemon):
    """A plain Zenoh peer connected to the daemon's endpoint (a ROS 2 node's view of the graph)."""
    s = zenoh_session(ros_daemon.endpoint)
    yield s
    s.close()


@pytest.fixture(scope="module")
def errors(ros):
    t = Topic(ros, "0/so101/error/**", "crtk_msgs/msg/StringStamped")
    yield t
    t.close()


@pytest.fixture(scope="module")
def states(ros):
    t = Topic(ros, "0/so101/operating_state/**", "crtk_msgs/msg/OperatingState")
    yield t
    t.close()


def tokens(session: zenoh.Session) -> list[str]:
    return [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/**", timeout=3.0) if r.ok]


def test_type_hashes_of_the_store_equal_ros2s():
    from crtk_bridge.transport.ros.types import JOINT_STATE, STRING, type_hash

    assert type_hash(STRING) == STRING_HASH
    assert type_hash(JOINT_STATE) == JOINT_STATE_HASH


def test_measured_js_in_rmw_zenoh_format(ros_daemon, ros):
    """Key expression, CDR JointState, attachment layout and liveliness tokens, as a ROS 2 node
    on rmw_zenoh would need them."""
    topic = Topic(ros, "0/so101/measured_js/**", "sensor_msgs/msg/JointState")
    try:
        wait_until(lambda: len(topic.samples) >= 20, 10, what="20 measured_js samples over Zenoh")
        with topic.lock:
            samples = list(topic.samples)
    finally:
        topic.close()
    assert {k for k, _, _ in samples} == {key("so101/measured_js", JOINT_STATE_DDS, JOINT_STATE_HASH)}
    now_ns = time.time_ns()
    seqs, gids = [], set()
    for _, msg, att in samples:
        assert list(msg.name) == ARM and len(msg.position) == 5 and np.all(np.isfinite(msg.position))
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        assert abs(stamp - now_ns * 1e-9) < 30  # the bus read's wall-clock time
        assert att is not None and len(att) == 33
        seq, ts_ns, gid_len = struct.unpack_from("<qqB", att)
        assert gid_len == 16
        assert 0 < now_ns - ts_ns < 30e9  # source timestamp: ns since the epoch, just now
        seqs.append(seq)
        gids.add(att[17:])
    assert len(gids) == 1  # one publisher, one constant GID
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # consecutive, no gap on loopback
    assert seqs[0] >= 1

    live = tokens(ros)
    nodes = [t for t in live if t.endswith(f"/NN/%/%/{NODE}")]
    assert len(nodes) == 1, live
    _, domain, zid, nid, eid, kind = nodes[0].split("/")[:6]
    assert (domain, nid, eid, kind) == ("0", "0", "0", "NN")
    prefix = f"@ros2_lv/0/{zid}/0/"
    pub = [t for t in live if t.startswith(prefix) and "/MP/" in t and "/%so101%measured_js/" in t]
    assert len(pub) == 1
    assert pub[0].split("/", 5)[5] == (f"MP/%/%/{NODE}/%so101%measured_js/{JOINT_STATE_DDS}/"
                                       f"{JOINT_STATE_HASH}/::,10:,:,:,,")
    sub = [t for t in live if t.startswith(prefix) and "/MS/" in t and "/%so101%servo_jp/" in t]
    assert len(sub) == 1 and sub[0].endswith(f"/{JOINT_STATE_DDS}/{JOINT_STATE_HASH}/::,10:,:,:,,")
    desc = [t for t in live if "/%robot_description/" in t]
    assert len(desc) == 1 and desc[0].endswith(f"/std_msgs::msg::dds_::String_/{STRING_HASH}/:1:,1:,:,:,,")
    # one token per endpoint: entity ids are unique within the node
    assert len({t.split("/")[4] for t in live if t.startswith(prefix)}) == len([t for t in live if t.startswith(prefix)])


def test_period_statistics_count_what_the_transports_dropped(ros_daemon, ros):
    """With the ROS graph publishing, period_statistics carries the front's loss counters: the
    stream frames dropped for slow clients and the ROS topics' skipped ticks (numbers, never
    absent, so that a loss is never silent)."""
    topic = Topic(ros, "0/so101/measured_js/**", "sensor_msgs/msg/JointState")
    conn = Connection(str(ros_daemon.socket_path))
    try:
        wait_until(lambda: len(topic.samples) >= 5, 10, what="measured_js published")
        stats = conn.request("period_statistics")
    finally:
        conn.close()
        topic.close()
    assert isinstance(stats["frames_dropped"], int) and stats["frames_dropped"] >= 0
    assert isinstance(stats["ros_ticks_skipped"], int) and stats["ros_ticks_skipped"] >= 0


def test_joint_states_and_tf_come_from_the_same_snapshot_as_the_namespaces(ros):
    """/joint_states: every joint of the robot; /tf: the arm's base -> tip transform, equal to
    measured_cp (both from one sample)."""
    js = Topic(ros, "0/joint_states/**", "sensor_msgs/msg/JointState")
    tf = Topic(ros, "0/tf/**", "tf2_msgs/msg/TFMessage")
    cp = Topic(ros, "0/so101/measured_cp/**", "geometry_msgs/msg/PoseStamped")
    try:
        msg = js.wait(lambda m: True, what="/joint_states")
        assert list(msg.name) == ARM + ["gripper"] and len(msg.position) == 6
        pose = cp.wait(lambda m: m.header.stamp.sec > 0, what="a valid measured_cp")
        t = tf.wait(lambda m: any(x.header.stamp == pose.header.stamp for x in m.transforms),
                    what="/tf of the same sample as measured_cp")
        (x,) = [x for x in t.transforms if x.header.stamp == pose.header.stamp]
        assert (x.header.frame_id, x.child_frame_id) == ("base_link", "gripper_frame_link")
        assert pose.header.frame_id == "base_link"
        assert np.allclose([x.transform.translation.x, x.transform.translation.y, x.transform.translation.z],
                           [pose.pose.position.x, pose.pose.position.y, pose.pose.position.z])
    finally:
        for topic in (js, tf, cp):
            topic.close()


def test_late_joiner_gets_latched_operating_state_and_robot_description(ros_daemon):
    late = zenoh_session(ros_daemon.endpoint)  # joins after the daemon published both once
    try:
        state = Topic(late, "0/so101/operating_state/**", "crtk_msgs/msg/OperatingState", advanced=True)
        desc = Topic(late, "0/robot_description/**", "std_msgs/msg/String", advanced=True)
        msg = state.wait(lambda m: True, what="the latched operating_state")
        assert msg.state in ("DISABLED", "ENABLED", "PAUSED", "FAULT") and msg.header.frame_id == "so101"
        urdf = desc.wait(lambda m: True, what="the latched robot_description").data
        assert urdf == (ROOT / "profiles/urdf/so101.urdf").read_text()
    finally:
        late.close()


def test_commands_from_a_plain_zenoh_publisher_follow_the_control_rules(ros_daemon, ros, errors, states):
    js_key = key("so101/servo_jp", JOINT_STATE_DDS, JOINT_STATE_HASH)
    cmd_key = key("so101/state_command", "crtk_msgs::msg::dds_::StringStamped_", "*")
    setpoints = Topic(ros, "0/so101/setpoint_js/**", "sensor_msgs/msg/JointState")
    measured = Topic(ros, "0/so101/measured_js/**", "sensor_msgs/msg/JointState")
    socket_client = Connection(str(ros_daemon.socket_path))
    # the publishers' liveliness tokens, as a ROS node declares them (the graph holds control
    # only while a remote command publisher is live)
    publishers = [publisher_token(ros, "so101/servo_jp", JOINT_STATE_DDS, JOINT_STATE_HASH, 1),
                  publisher_token(ros, "so101/state_command", "crtk_msgs::msg::dds_::StringStamped_",
                                  _hash("crtk_msgs/msg/StringStamped"), 2)]
    try:
        from crtk_bridge.transport.ros.types import STRING_STAMPED, type_hash
        cmd_key = cmd_key.replace("*", type_hash(STRING_STAMPED))
        ros.put(cmd_key, state_command("enable"))
        states.wait(lambda m: m.state == "ENABLED", what="ENABLED after state_command enable over Zenoh")

        # the ROS graph holds control now: a socket session is read-only, except for stops
        reply = _request(socket_client, {"cmd": "servo_jp", "ns": "so101", "data": {"position": [0.0] * 5}})
        assert reply["error"]["code"] == "read_only" and "ROS 2 graph over Zenoh" in reply["error"]["message"]

        start = np.array(measured.wait(lambda m: True).position)
        target = start + np.array([0.05, -0.05, 0.05, 0.0, 0.0])
        ros.put(js_key, joint_state(target))
        setpoints.wait(lambda m: len(m.position) == 5 and np.allclose(m.position, target, atol=1e-6),
                       what="setpoint_js at the servo_jp target")
        measured.wait(lambda m: np.allclose(m.position, target, atol=0.02), what="the arm at the servo_jp target")

        # a stop from the socket is never refused; then the socket takes control, and ROS is refused
        assert _request(socket_client, {"cmd": "pause"})["ok"]
        states.wait(lambda m: m.state == "PAUSED", what="PAUSED from the socket's stop")
        ros.put(cmd_key, state_command("resume"))
        states.wait(lambda m: m.state == "ENABLED", what="ENABLED after resume over Zenoh")
    finally:
        for token in publishers:
            token.undeclare()
        setpoints.close()
        measured.close()
        socket_client.close()


def test_control_is_released_when_the_last_ros_commander_leaves(ros_daemon, ros, errors, states):
    """A ROS node's publisher token coming and going is its connect / disconnect. Zenoh sends
    declarations ahead of data, so a publisher's last samples may be handled after its token went:
    control is released then too; and a plain put (no token) leaves control free."""
    state_key = key("so101/state_command", "crtk_msgs::msg::dds_::StringStamped_", _hash("crtk_msgs/msg/StringStamped"))
    js_key = key("so101/servo_jp", JOINT_STATE_DDS, JOINT_STATE_HASH)
    move_key = key("so101/move_jp", JOINT_STATE_DDS, JOINT_STATE_HASH)
    setpoints = Topic(ros, "0/so101/setpoint_js/**", "sensor_msgs/msg/JointState")
    goals = Topic(ros, "0/so101/goal_js/**", "sensor_msgs/msg/JointState")
    measured = Topic(ros, "0/so101/measured_js/**", "sensor_msgs/msg/JointState")
    probe = Connection(str(ros_daemon.socket_path))
    try:
        def state() -> tuple[str, bool]:
            st = probe.request("operating_state", timeout=10.0)
            return st["state"], st["is_busy"]

        ros.put(state_key, state_command("disable"))
        wait_until(lambda: state() == ("DISABLED", False), 10, what="DISABLED")
        ros.put(state_key, state_command("enable"))
        wait_until(lambda: state() == ("ENABLED", False), 10, what="ENABLED")
        wait_until(lambda: _request(probe, {"cmd": "acquire"})["ok"], 5, what="control free after an enable with no token")
        assert _request(probe, {"cmd": "release"})["ok"]
        start = np.array(measured.wait(lambda m: True).position)
        # the token still there: the graph holds control until it goes
        token = publisher_token(ros, "so101/servo_jp", JOINT_STATE_DDS, JOINT_STATE_HASH, 10)
        ros.put(js_key, joint_state(start))
        setpoints.wait(lambda m: len(m.position) == 5 and np.allclose(m.position, start, atol=1e-6),
                       what="setpoint_js at the servo_jp target")
        assert _request(probe, {"cmd": "acquire"})["error"]["code"] == "read_only"
        token.undeclare()
        wait_until(lambda: _request(probe, {"cmd": "acquire"})["ok"], 5,
                   what="control released when the ROS publisher left")
        assert _request(probe, {"cmd": "release"})["ok"]
        # the token goes right after the sample: the sample is handled after the token went
        for i in range(1, 4):
            target = start + np.array([0.01 * i, 0.0, 0.0, 0.0, 0.0])
            token = publisher_token(ros, "so101/move_jp", JOINT_STATE_DDS, JOINT_STATE_HASH, 10 + i)
            ros.put(move_key, joint_state(target))
            token.undeclare()
            goals.wait(lambda m: len(m.position) == 5 and np.allclose(m.position, target, atol=1e-6),
                       what=f"goal_js at the move_jp target ({i})")
            wait_until(lambda: _request(probe, {"cmd": "acquire"})["ok"], 5,
                       what=f"control released when the ROS publisher left right after its sample ({i})")
            assert _request(probe, {"cmd": "release"})["ok"]
        assert _request(probe, {"cmd": "acquire"})["ok"]
        # the socket holds control now: a ROS motion command is refused on /so101/error, a stop is not
        n = len(errors.messages())
        ros.put(js_key, joint_state(start))
        wait_until(lambda: any("holds control" in m.string for m in errors.messages()[n:]), 5,
                   what="read_only refusal on /so101/error")
        ros.put(state_key, state_command("disable"))
        wait_until(lambda: state() == ("DISABLED", False), 10,
                   what="DISABLED from a ROS stop while the socket holds control")
        assert _request(probe, {"cmd": "release"})["ok"]
    finally:
        setpoints.close()
        goals.close()
        measured.close()
        probe.close()


def test_hostile_payloads_are_refused_without_harm(ros_daemon, ros, errors, states):
    cmd_key = key("so101/state_command", "crtk_msgs::msg::dds_::StringStamped_", _hash("crtk_msgs/msg/StringStamped"))
    js_key = key("so101/servo_jp", JOINT_STATE_DDS, JOINT_STATE_HASH)
    move_key = key("so101/move_jp", JOINT_STATE_DDS, JOINT_STATE_HASH)
    setpoints = Topic(ros, "0/so101/setpoint_js/**", "sensor_msgs/msg/JointState")
    try:
        n = len(states.messages())  # DISABLED now (the test before ends so): wait for a fresh ENABLED
        ros.put(cmd_key, state_command("enable"))
        wait_until(lambda: any(m.state == "ENABLED" for m in states.messages()[n:]), 10, what="ENABLED")
        # enabled, no motion command accepted yet: setpoint_js is invalid (stamp 0, empty)
        setpoints.wait(lambda m: m.header.stamp.sec == 0 and not len(m.position), what="no setpoint after enable")
        good = joint_state([0.0] * 5)
        cases = [
            (js_key, good[:23], "not a CDR sensor_msgs/msg/JointState"),  # truncated
            (key("so101/servo_jp", "std_msgs::msg::dds_::String_", STRING_HASH),
             bytes(STORE.serialize_cdr(StringMsg(data="go"), "std_msgs/msg/String")),
             "published as std_msgs::msg::dds_::String_"),  # wrong type
            (js_key, joint_state([0.0, float("nan"), 0.0, 0.0, 0.0]), "data.position: entry 1 is non-finite (nan)"),
            (js_key, joint_state([0.0] * 4), "Expected `array` of 5 numbers"),  # wrong length
            (js_key, joint_state([0.0] * 5, name=["a", "b", "c", "d", "e"]), "joint names"),
            (move_key, joint_state([3.0, 0.0, 0.0, 0.0, 0.0]), "joint 'shoulder_pan' is outside its limits"),
            (cmd_key, state_command("explode"), "unknown command 'explode'"),
            (cmd_key, b"\x00\x01\x00\x00\xff\xff\xff\x7f", "not a CDR crtk_msgs/msg/StringStamped"),
        ]
        for k, payload, expected in cases:
            n = len(errors.messages())
            ros.put(k, payload)
            wait_until(lambda: any(expected in m.string for m in errors.messages()[n:]), 10,
                       what=f"refusal {expected!r} on /so101/error (got {[m.string for m in errors.messages()[n:]]})")
        # nothing moved, nothing faulted, and the graph still serves commands
        assert states.messages()[-1].state == "ENABLED"
        assert all(m.state != "FAULT" for m in states.messages())
        n = len(setpoints.messages())
        wait_until(lambda: len(setpoints.messages()) > n, 5, what="a fresh setpoint_js")
        assert not len(setpoints.messages()[-1].position)  # no command was accepted
        n = len(states.messages())
        ros.put(cmd_key, state_command("disable"))
        wait_until(lambda: any(m.state == "DISABLED" for m in states.messages()[n:]), 10,
                   what="DISABLED after the hostile payloads")
    finally:
        setpoints.close()


def publisher_token(session: zenoh.Session, topic: str, dds: str, h: str, eid: int) -> zenoh.LivelinessToken:
    """The liveliness token rmw_zenoh declares for a publisher of ``topic`` (a ROS node's)."""
    return session.liveliness().declare_token(
        f"@ros2_lv/0/{session.info.zid()}/0/{eid}/MP/%/%/test_node/%{topic.replace('/', '%')}/{dds}/{h}/"
        "::,10:,:,:,,")


def _hash(ros_type: str) -> str:
    return STORE.hash_rihs01(ros_type)


def _request(conn: Connection, req: dict) -> dict:
    """One request on the socket (the project's client): ``{"ok": True}`` or ``{"ok": False,
    "error": {"code", "message"}}``."""
    try:
        conn.request(req["cmd"], req.get("ns"), req.get("data"), timeout=10.0)
        return {"ok": True}
    except CommandError as exc:
        return {"ok": False, "error": {"code": exc.code, "message": str(exc)}}

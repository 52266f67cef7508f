"""The ROS 2 message types of the graph, in ONE rosbags type store: CDR encoding and decoding and
RIHS01 type hashes (the ones rmw_zenoh puts in key expressions and liveliness tokens).

The store is ROS 2 Kilted's (std_msgs, sensor_msgs, geometry_msgs, tf2_msgs, builtin_interfaces)
plus crtk_msgs, registered from the message definitions of crtk_msgs 1.3.0
(docs/architecture.md, "Sources": CRTK). Recording (rosbag2 MCAP) is to reuse
:data:`TYPESTORE`, so a bag and the live graph carry the same types and hashes.

Costs (bench/bench_zenoh.py): a 6-joint JointState encodes in about 5 us.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

from ...errors import CrtkBridgeError

# crtk_msgs 1.3.0 (collaborative-robotics/crtk_msgs, msg/*.msg): only the fields count for the
# RIHS01 hash; the comments of the originals are left out.
CRTK_MSGS = {
    "crtk_msgs/msg/OperatingState": "std_msgs/Header header\nstring state\nbool is_homed\nbool is_busy\n",
    "crtk_msgs/msg/StringStamped": "std_msgs/Header header\nstring string\n",
}

JOINT_STATE = "sensor_msgs/msg/JointState"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
EMPTY = "std_msgs/msg/Empty"
OPERATING_STATE = "crtk_msgs/msg/OperatingState"
STRING_STAMPED = "crtk_msgs/msg/StringStamped"


def _typestore():
    store = get_typestore(Stores.ROS2_KILTED)
    types: dict = {}
    for name, text in CRTK_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


#: the one type store of the project (Zenoh graph now, recording later)
TYPESTORE = _typestore()
_T = TYPESTORE.types
Time = _T["builtin_interfaces/msg/Time"]
Header = _T["std_msgs/msg/Header"]
JointState = _T[JOINT_STATE]
Point = _T["geometry_msgs/msg/Point"]
Quaternion = _T["geometry_msgs/msg/Quaternion"]
Vector3 = _T["geometry_msgs/msg/Vector3"]
Pose = _T["geometry_msgs/msg/Pose"]
PoseStamped = _T[POSE_STAMPED]
Twist = _T["geometry_msgs/msg/Twist"]
TwistStamped = _T[TWIST_STAMPED]
Wrench = _T["geometry_msgs/msg/Wrench"]
WrenchStamped = _T[WRENCH_STAMPED]
Transform = _T["geometry_msgs/msg/Transform"]
TransformStamped = _T["geometry_msgs/msg/TransformStamped"]
TFMessage = _T[TF_MESSAGE]
String = _T[STRING]
OperatingState = _T[OPERATING_STATE]
StringStamped = _T[STRING_STAMPED]

_HASHES: dict[str, str] = {}
_EMPTY = np.empty(0, dtype=np.float64)


def type_hash(ros_type: str) -> str:
    """``RIHS01_<64 hex>`` of a type of the store (cached: hashing walks the nested types)."""
    h = _HASHES.get(ros_type)
    if h is None:
        h = _HASHES[ros_type] = TYPESTORE.hash_rihs01(ros_type)
    return h


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_`` (rmw_zenoh's
    type segment of key expressions and tokens)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def encode(msg: Any, ros_type: str) -> bytes:
    """CDR (little endian, with the 4-byte encapsulation header) of ``msg``."""
    return bytes(TYPESTORE.serialize_cdr(msg, ros_type))


class CdrTemplate:
    """One message's CDR whose numbers are rewritten in place, for the periodic topics: rosbags
    lays the message out once (strings, sequence lengths, alignment); each sample then only
    overwrites its float64 fields and header stamps, with no message object built and no
    serializer walked. The layout is fixed by what does not change between samples (frame ids,
    joint names, which vectors are present): the caller keeps one template per layout.

    ``build(floats, stamps)`` returns the message of ``n_floats`` float64 values and ``n_stamps``
    header stamps (protocol stamps, seconds), through the same builders as a one-off encoding. It
    is called once, with sentinels: values whose 8 bytes occur exactly once in the encoding,
    which locates each field. Usage: write
    ``template.floats[...]`` and :meth:`stamp`, then :meth:`render`."""

    _STAMP = np.dtype([("sec", "<i4"), ("nanosec", "<u4")])

    def __init__(self, ros_type: str, build: Callable[[np.ndarray, list[float]], Any], n_floats: int,
                 n_stamps: int = 1):
        for seed in range(8):  # a sentinel repeated elsewhere in the bytes is unlikely; retry if so
            rng = np.random.default_rng(seed)
            floats = rng.uniform(1e5, 2e5, n_floats)
            stamps = [float(s) for s in rng.uniform(1.5e9, 2e9, n_stamps)]  # protocol stamps (s)
            data = encode(build(floats.copy(), stamps), ros_type)
            patterns = [f.tobytes() for f in floats.astype("<f8")]
            patterns += [np.array((t.sec, t.nanosec), dtype=self._STAMP).tobytes() for t in map(stamp, stamps)]
            if all(data.count(pat) == 1 for pat in patterns):
                break
        else:
            raise CrtkBridgeError(f"cannot lay out a CDR template of {ros_type}")
        self._buf = bytearray(data)
        self._out = np.frombuffer(self._buf, dtype=np.uint8)
        where = np.array([data.index(pat) for pat in patterns], dtype=np.intp)
        self._index = (where[:, None] + np.arange(8)).ravel()  # byte positions, in source order
        self._src = np.zeros(8 * (n_floats + n_stamps), dtype=np.uint8)
        #: the message's float64 fields, in the order ``build`` placed them
        self.floats = self._src[:8 * n_floats].view("<f8")
        self._stamps = self._src[8 * n_floats:].view(self._STAMP)

    def stamp(self, i: int, seconds: float) -> None:
        """Header stamp ``i`` from a protocol stamp (seconds since the epoch; 0 stays 0 = invalid)."""
        ns = int(round(seconds * 1e9)) if seconds > 0 else 0
        self._stamps[i] = divmod(ns, 1_000_000_000)

    def render(self) -> bytes:
        """The CDR bytes of the fields as written now."""
        self._out[self._index] = self._src
        return bytes(self._buf)


def decode(data: bytes | memoryview, ros_type: str) -> Any:
    """A message from its CDR bytes. Raises whatever rosbags raises on bad data (SerdeError,
    IndexError, struct.error, UnicodeDecodeError...): the caller refuses the sample."""
    return TYPESTORE.deserialize_cdr(data, ros_type)


# ------------------------------------------------------------------ builders from protocol payloads
def stamp(seconds: float) -> Any:
    """builtin_interfaces/Time of a protocol stamp (seconds since the epoch; 0 stays 0 = invalid)."""
    ns = int(round(seconds * 1e9)) if seconds > 0 else 0
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def now() -> Any:
    ns = time.time_ns()
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def seconds(t: Any) -> float:
    return t.sec + t.nanosec * 1e-9


def _vec(values: Any) -> np.ndarray:
    return np.asarray(values, dtype=np.float64) if len(values) else _EMPTY


def joint_state(js: dict) -> Any:
    """sensor_msgs/JointState of a protocol JointState (link.joint_state)."""
    return JointState(header=Header(stamp=stamp(js["stamp"]), frame_id=js["frame_id"]), name=list(js["name"]),
                      position=_vec(js["position"]), velocity=_vec(js["velocity"]), effort=_vec(js["effort"]))


IDENTITY = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))


def pose_values(p: dict) -> tuple:
    """(position, orientation) of a protocol pose; the identity for an invalid one (empty vectors)."""
    return (p["position"], p["orientation"]) if len(p["position"]) else IDENTITY


def pose_stamped(p: dict) -> Any:
    """geometry_msgs/PoseStamped of a protocol pose (CartesianSpace.query); an invalid pose
    (stamp 0, empty vectors) is the identity with stamp 0."""
    pos, q = pose_values(p)
    return PoseStamped(header=Header(stamp=stamp(p["stamp"]), frame_id=p["frame_id"]),
                       pose=Pose(position=Point(x=pos[0], y=pos[1], z=pos[2]),
                                 orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))


def transform_stamped(p: dict) -> Any:
    """geometry_msgs/TransformStamped (for /tf) of a protocol pose: frame_id -> child_frame_id."""
    pos, q = pose_values(p)
    return TransformStamped(header=Header(stamp=stamp(p["stamp"]), frame_id=p["frame_id"]),
                            child_frame_id=p["child_frame_id"],
                            transform=Transform(translation=Vector3(x=pos[0], y=pos[1], z=pos[2]),
                                                rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))


def _v3(v: Any) -> Any:
    return Vector3(x=v[0], y=v[1], z=v[2]) if len(v) else Vector3(x=0.0, y=0.0, z=0.0)


def twist_stamped(t: dict) -> Any:
    return TwistStamped(header=Header(stamp=stamp(t["stamp"]), frame_id=t["frame_id"]),
                        twist=Twist(linear=_v3(t["linear"]), angular=_v3(t["angular"])))


def wrench_stamped(w: dict) -> Any:
    return WrenchStamped(header=Header(stamp=stamp(w["stamp"]), frame_id=w["frame_id"]),
                         wrench=Wrench(force=_v3(w["force"]), torque=_v3(w["torque"])))


def operating_state(st: dict, frame_id: str) -> Any:
    """crtk_msgs/OperatingState of the protocol's operating_state event data."""
    return OperatingState(header=Header(stamp=stamp(st.get("stamp", 0.0)), frame_id=frame_id),
                          state=str(st["state"]), is_homed=bool(st["is_homed"]), is_busy=bool(st["is_busy"]))


def string_stamped(text: str, frame_id: str, at: float | None = None) -> Any:
    return StringStamped(header=Header(stamp=stamp(at) if at else now(), frame_id=frame_id), string=text)

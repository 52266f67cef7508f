"""rmw_zenoh's wire format (Kilted; Jazzy >= 0.2.5), so ROS 2 nodes running
``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` see our node, publishers and subscriptions.

Facts from ros2/rmw_zenoh (docs/design.md, rmw_zenoh_cpp/src/detail/liveliness_utils.cpp,
attachment_helpers.cpp, rmw_publisher_data.cpp) (docs/architecture.md,
"Sources": ROS 2 over Zenoh):

* data key expression: ``<domain>/<topic without leading slash>/<dds type>/<RIHS01 hash>``;
* liveliness tokens (the ROS graph): node
  ``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>``, endpoint
  ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<MP|MS>/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>``,
  names mangled ``/`` -> ``%`` (an empty namespace or enclave is ``%``);
* QoS text ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:
  <liveliness>,<lease s>,<ns>`` with a field left empty where it equals rmw_zenoh's default
  (reliable, volatile, keep last 42, qos.cpp): ROS 2's default profile (keep last 10) is
  ``::,10:,:,:,,``, a latched one (transient local, depth 1) ``:1:,1:,:,:,,``;
* every sample carries an attachment: int64 LE sequence number (from 1), int64 LE source
  timestamp (ns since the epoch), u8 16, the publisher's 16-byte GID;
* publishers are ``zenoh.ext`` AdvancedPublishers with congestion control DROP (a slow
  subscriber loses samples, it never blocks us); TRANSIENT_LOCAL ones add a cache of ``depth``
  samples and publisher detection, so late joiners get the latched value.

The GID: rmw_zenoh hashes the entity's token with XXH3-128; ROS tools only compare GIDs for
equality, so ours is a BLAKE2b-128 of the same token (hashlib, no extra dependency): constant for
the endpoint's life and distinct per endpoint.
"""

from __future__ import annotations

import enum
import hashlib
import itertools
import struct
import time
from dataclasses import dataclass
from typing import Any, Callable

import zenoh
import zenoh.ext as zext

from ...errors import CrtkBridgeError
from .types import dds_type_name, type_hash

ADMIN_SPACE = "@ros2_lv"
ATTACHMENT = struct.Struct("<qqB16s")  # sequence number, source timestamp (ns), GID length, GID
GID_SIZE = 16


class Reliability(enum.IntEnum):  # rmw_qos_reliability_policy_e
    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(enum.IntEnum):  # rmw_qos_durability_policy_e
    TRANSIENT_LOCAL = 1
    VOLATILE = 2


KEEP_LAST = 1  # rmw_qos_history_policy_e; the only history used here
#: rmw_zenoh's defaults (rmw_zenoh_cpp/src/detail/qos.cpp, Jazzy and later): reliable, volatile,
#: keep last 42; a token leaves a field empty when it equals these
DEFAULT_DEPTH = 42


@dataclass(frozen=True)
class QoS:
    """An endpoint's QoS; the default is ROS 2's default profile (rmw_qos_profile_default)."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    depth: int = 10

    def text(self) -> str:
        """The QoS segment of an endpoint token (fields equal to rmw's defaults left empty)."""
        rel = "" if self.reliability == Reliability.RELIABLE else str(int(self.reliability))
        dur = "" if self.durability == Durability.VOLATILE else str(int(self.durability))
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        return f"{rel}:{dur}:,{depth}:,:,:,,"

    @property
    def latched(self) -> bool:
        return self.durability == Durability.TRANSIENT_LOCAL


DEFAULT_QOS = QoS()
#: ROS 1's "latch": the last value for every late joiner (operating_state, /robot_description)
LATCHED = QoS(durability=Durability.TRANSIENT_LOCAL, depth=1)


def mangle(name: str) -> str:
    """A ROS name as one key segment: ``/so101/measured_js`` -> ``%so101%measured_js``; ``/`` -> ``%``."""
    return name.replace("/", "%") if name else "%"


def topic_key(domain_id: int, topic: str, ros_type: str) -> str:
    """The data key expression of ``topic`` (a fully qualified name, ``/so101/measured_js``)."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash(ros_type)}"


def attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    return ATTACHMENT.pack(seq, stamp_ns, GID_SIZE, gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID). Raises ValueError on another layout."""
    if len(data) != ATTACHMENT.size:
        raise ValueError(f"attachment of {len(data)} bytes, expected {ATTACHMENT.size}")
    seq, ts, n, gid = ATTACHMENT.unpack(data)
    if n != GID_SIZE:
        raise ValueError(f"attachment GID length {n}, expected {GID_SIZE}")
    return seq, ts, gid


class Node:
    """One ROS 2 node on a Zenoh session: its liveliness token and the ids of its endpoints."""

    def __init__(self, session: zenoh.Session, domain_id: int, name: str, namespace: str = "/"):
        self.session = session
        self.domain_id = domain_id
        self.name = name
        self.namespace = namespace
        self.zid = str(session.info.zid())
        self.nid = 0
        self._eids = itertools.count(1)
        self.token_key = (f"{ADMIN_SPACE}/{domain_id}/{self.zid}/{self.nid}/{self.nid}/NN/%/"
                          f"{mangle(namespace.strip('/'))}/{name}")
        self._token = session.liveliness().declare_token(self.token_key)
        self.endpoints: list[Publisher | Subscription] = []

    def endpoint_token(self, kind: str, topic: str, ros_type: str, qos: QoS) -> tuple[int, str]:
        eid = next(self._eids)
        key = (f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.nid}/{eid}/{kind}/%/"
               f"{mangle(self.namespace.strip('/'))}/{self.name}/{mangle(topic)}/{dds_type_name(ros_type)}/"
               f"{type_hash(ros_type)}/{qos.text()}")
        return eid, key

    def publisher(self, topic: str, ros_type: str, qos: QoS = DEFAULT_QOS) -> Publisher:
        pub = Publisher(self, topic, ros_type, qos)
        self.endpoints.append(pub)
        return pub

    def subscription(self, topic: str, ros_type: str, callback: Callable[[zenoh.Sample], None],
                     qos: QoS = DEFAULT_QOS, any_type: bool = False) -> Subscription:
        sub = Subscription(self, topic, ros_type, callback, qos, any_type)
        self.endpoints.append(sub)
        return sub

    def close(self) -> None:
        """Undeclare every endpoint, then the node (tokens vanish from the ROS graph)."""
        for ep in reversed(self.endpoints):
            ep.close()
        self.endpoints.clear()
        _undeclare(self._token)


class Publisher:
    """A ROS 2 publisher: ``put`` never blocks (congestion control DROP)."""

    def __init__(self, node: Node, topic: str, ros_type: str, qos: QoS):
        self.topic = topic
        self.ros_type = ros_type
        self.qos = qos
        self.key = topic_key(node.domain_id, topic, ros_type)
        self.eid, self.token_key = node.endpoint_token("MP", topic, ros_type, qos)
        self.gid = hashlib.blake2b(self.token_key.encode(), digest_size=GID_SIZE).digest()
        self.seq = 0
        try:
            self._pub = zext.declare_advanced_publisher(
                node.session, self.key, congestion_control=zenoh.CongestionControl.DROP,
                cache=zext.CacheConfig(qos.depth) if qos.latched else None,
                publisher_detection=qos.latched or None)
        except zenoh.ZError as exc:  # e.g. a session opened without timestamping
            raise CrtkBridgeError(f"zenoh: cannot declare the ROS publisher {topic}: {exc}") from None
        self._token = node.session.liveliness().declare_token(self.token_key)
        # whether anyone subscribes (a plain publisher's matching status, kept by a listener):
        # a periodic topic nobody reads is then not even encoded
        self._watch = node.session.declare_publisher(self.key)
        self._matching = self._watch.declare_matching_listener(self._on_matching)
        # after the listener, so no change is missed; ``.matching``: the status object itself
        # is always true, which had every topic encoded at start-up with nobody subscribed
        self.wanted: bool = self._watch.matching_status.matching

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:  # a Zenoh thread
        self.wanted = status.matching

    def put(self, payload: bytes) -> None:
        self.seq += 1
        self._pub.put(payload, attachment=attachment(self.seq, time.time_ns(), self.gid))

    def close(self) -> None:
        _undeclare(self._matching)
        _undeclare(self._watch)
        _undeclare(self._token)
        _undeclare(self._pub)


class Subscription:
    """A ROS 2 subscription. ``callback(sample)`` runs on a Zenoh thread.

    ``any_type``: receive the topic whatever type a publisher declares (key
    ``<domain>/<topic>/*/*``), so that a publisher of the wrong type is told so instead of being
    silently unmatched; the callback checks :func:`type_mismatch`."""

    def __init__(self, node: Node, topic: str, ros_type: str, callback: Callable[[zenoh.Sample], None],
                 qos: QoS, any_type: bool):
        self.topic = topic
        self.ros_type = ros_type
        self.key = topic_key(node.domain_id, topic, ros_type)
        self.eid, self.token_key = node.endpoint_token("MS", topic, ros_type, qos)
        listen = f"{node.domain_id}/{topic.strip('/')}/*/*" if any_type else self.key
        self._sub = node.session.declare_subscriber(listen, callback)
        self._token = node.session.liveliness().declare_token(self.token_key)

    def close(self) -> None:
        _undeclare(self._token)
        _undeclare(self._sub)


def type_mismatch(key: str, ns: str, cmd: str, ros_type: str) -> str | None:
    """None when a sample's key (``<domain>/<ns>/<cmd>/<dds type>/<hash>``) carries ``ros_type``
    and its hash (or Humble's ``TypeHashNotSupported``), else the type and hash it declares."""
    _, _, tail = key.partition(f"{ns}/{cmd}/")
    dds_type, _, h = tail.partition("/")
    if dds_type == dds_type_name(ros_type) and h in (type_hash(ros_type), "TypeHashNotSupported"):
        return None
    return f"{dds_type} ({h})"


def _undeclare(entity: Any) -> None:
    try:
        entity.undeclare()
    except zenoh.ZError:
        pass  # the session is already closed: its entities went with it

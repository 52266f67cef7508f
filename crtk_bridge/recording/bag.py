"""One rosbag2 MCAP bag (rosbags' writer), with the topics and types of the ROS 2 graph.

Written by ONE thread (a recording's writer thread, or the black box's): it turns the control
loop's per-cycle samples (core/samples.py rows) and the daemon's events into CDR with the graph's
type store and encoders (transport/ros/types.py, periodic.Encoders) and hands them to rosbags.
Topics (docs/recording.md): per namespace ``measured_js``, ``setpoint_js``, ``goal_js``, where it
has kinematics ``measured_cp``, ``setpoint_cp`` (and the robot's ``/tf``), ``operating_state``
(latched), ``error`` / ``warning`` / ``status``; robot-wide ``/<robot>/commands`` (every command
received: what, from which session) and a latched ``/robot_description``.

Loss bound: rosbags closes a chunk only when it holds 1 MiB; :meth:`BagWriter.flush` closes the
pending chunk and flushes the file, so a killed daemon loses only what came after the last flush.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

from ..core.samples import MARKER, STAMP, STATE
from ..transport.ros import types as T
from ..transport.ros.periodic import Encoders

JOINT_TOPICS = ("measured_js", "setpoint_js", "goal_js")
CARTESIAN_TOPICS = ("measured_cp", "setpoint_cp")
EVENT_TOPICS = ("error", "warning", "status")

_INFINITE = QosTime(sec=2147483647, nsec=4294967295)


def _qos(durability: QosDurability, depth: int) -> Qos:
    return Qos(history=QosHistory.KEEP_LAST, depth=depth, reliability=QosReliability.RELIABLE,
               durability=durability, deadline=_INFINITE, lifespan=_INFINITE,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=_INFINITE,
               avoid_ros_namespace_conventions=False)


#: the graph's QoS (transport/ros/graph.py): latched topics are TRANSIENT_LOCAL depth 1
LATCHED = _qos(QosDurability.TRANSIENT_LOCAL, 1)
VOLATILE = _qos(QosDurability.VOLATILE, 10)
EVENTS = _qos(QosDurability.VOLATILE, 100)


def bag_path(path: str) -> tuple[Path, Path]:
    """(bag directory, its .mcap file) for ``path`` as given: ``run1.mcap`` or ``run1`` ->
    ``run1/`` holding ``run1/run1.mcap`` (and ``metadata.yaml`` once closed)."""
    p = Path(os.path.abspath(os.path.expanduser(path)))
    if p.suffix == ".mcap":
        p = p.with_suffix("")
    return p, p / f"{p.name}.mcap"


def urdf_text(profile: Any) -> str | None:
    """The URDF of the first namespace with kinematics (the graph's /robot_description), or None."""
    for ns in profile.namespaces:
        if ns.kinematics is not None:
            try:
                return Path(ns.kinematics.urdf).read_text()
            except OSError:
                return None
    return None


class BagWriter:
    """A bag being written. ``link`` reads the rows (server/link.py's views, same layout as the
    snapshot); ``spaces``: namespace -> CartesianSpace of this writer's own (pinocchio data is
    per thread). Every method raises OSError / rosbags' WriterError on a write failure."""

    def __init__(self, path: str, link: Any, robot: str, namespaces: Iterable[str], spaces: dict,
                 custom: dict[str, str] | None = None):
        self.dir, self.file = bag_path(path)
        self.link = link
        self.robot = robot
        self.namespaces = list(namespaces)
        self.spaces = {ns: cs for ns, cs in spaces.items() if ns in self.namespaces}
        self.enc = Encoders()
        self._open_storage(custom)
        self.messages = 0
        self.samples = 0
        self.first_cycle = -1
        self.last_cycle = -1
        self.last_stamp_ns = 0
        self._conns: dict[tuple[str, str], Any] = {}
        add = self._add
        for ns in self.namespaces:
            for topic in JOINT_TOPICS:
                add(ns, topic, T.JOINT_STATE, VOLATILE)
            if ns in self.spaces:
                for topic in CARTESIAN_TOPICS:
                    add(ns, topic, T.POSE_STAMPED, VOLATILE)
            add(ns, "operating_state", T.OPERATING_STATE, LATCHED)
            for topic in EVENT_TOPICS:
                add(ns, topic, T.STRING_STAMPED, EVENTS)
        add(robot, "commands", T.STRING_STAMPED, EVENTS)
        if self.spaces:
            self._conns[("", "tf")] = self._connect("/tf", T.TF_MESSAGE, EVENTS)
        self._conns[("", "robot_description")] = self._connect("/robot_description", T.STRING, LATCHED)
        self._js = [(ns, topic, self._conns[(ns, topic)]) for ns in self.namespaces for topic in JOINT_TOPICS]
        self._cart = [(ns, cs, [(t, self._conns[(ns, t)]) for t in CARTESIAN_TOPICS]) for ns, cs in self.spaces.items()]
        self._tf = self._conns.get(("", "tf"))

    def _add(self, ns: str, topic: str, ros_type: str, qos: Qos) -> None:
        self._conns[(ns, topic)] = self._connect(f"/{ns}/{topic}", ros_type, qos)

    # the storage: rosbags' rosbag2 MCAP writer (recording/live.py's LiveWriter: Foxglove channels)
    def _open_storage(self, custom: dict[str, str] | None) -> None:
        self.writer = Writer(self.dir, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        for k, v in (custom or {}).items():
            self.writer.set_custom_data(k, v)
        self.writer.open()

    def _connect(self, topic: str, ros_type: str, qos: Qos) -> Any:
        return self.writer.add_connection(topic, ros_type, typestore=T.TYPESTORE, offered_qos_profiles=[qos])

    def _write(self, conn: Any, t_ns: int, data: bytes) -> None:
        self.writer.write(conn, t_ns, data)
        self.messages += 1

    # ---------------------------------------------------------------- content
    def robot_description(self, urdf: str, t_ns: int) -> None:
        self._write(self._conns[("", "robot_description")], t_ns, T.encode(T.String(data=urdf), T.STRING))

    def rows(self, rows: np.ndarray) -> None:
        """Every cycle's sample (core/samples.py slot rows): one message per topic per cycle,
        logged at the cycle's stamp."""
        link, enc = self.link, self.enc
        for row in rows:
            t_ns = int(row[STAMP] * 1e9)
            buf = row[STATE:]
            for ns, topic, conn in self._js:
                self._write(conn, t_ns, enc.joint_state(link.joint_state(topic, ns, buf)))
            poses = []
            for ns, cs, topics in self._cart:
                st = link.ns_arrays(ns, buf)
                for topic, conn in topics:
                    d = cs.query(topic, st, "spatial")
                    if topic == "measured_cp":
                        poses.append(d)
                    self._write(conn, t_ns, enc.cartesian(T.POSE_STAMPED, d))
            if self._tf is not None and poses:
                self._write(self._tf, t_ns, enc.tf(poses))
            cycle = int(row[MARKER])
            if self.first_cycle < 0:
                self.first_cycle = cycle
            self.last_cycle = cycle
            self.last_stamp_ns = t_ns
            self.samples += 1

    def event(self, msg: dict, t_ns: int) -> None:
        """An operating_state / error / warning / status event of the daemon (as sessions get it):
        on its namespace's topic, robot-wide ones on every recorded namespace's (as the graph)."""
        ev = msg.get("event")
        d = msg.get("data") or {}
        if ev == "operating_state":
            for ns in self.namespaces:
                self._write(self._conns[(ns, "operating_state")], t_ns,
                            T.encode(T.operating_state(d, ns), T.OPERATING_STATE))
        elif ev in EVENT_TOPICS:
            ns = d.get("ns")
            text = str(d.get("message", ""))
            at = d.get("stamp") or t_ns * 1e-9
            for target in ([ns] if ns in self.namespaces else self.namespaces):
                self._write(self._conns[(target, ev)], t_ns,
                            T.encode(T.string_stamped(text, target, at), T.STRING_STAMPED))

    def command(self, entry: dict, t_ns: int) -> None:
        """A command received: ``entry`` = {session, cmd, ns, data} as JSON on ``/<robot>/commands``."""
        text = json.dumps(entry, separators=(",", ":"), default=str)
        self._write(self._conns[(self.robot, "commands")], t_ns,
                    T.encode(T.string_stamped(text, entry.get("ns") or self.robot, t_ns * 1e-9), T.STRING_STAMPED))

    # ---------------------------------------------------------------- durability
    def flush(self) -> None:
        """Close rosbags' pending chunk (it closes one only at 1 MiB) and flush the file to the
        OS: what was written so far survives a killed daemon."""
        storage = self.writer.storage
        if storage is not None and storage.chunk.bio.tell():
            storage.close_chunk()
        if storage is not None:
            storage.bio.flush()

    def close(self, custom: dict[str, str] | None = None) -> int:
        """Write the summary and metadata.yaml; returns the file's size in bytes."""
        for k, v in (custom or {}).items():
            self.writer.set_custom_data(k, v)
        self.writer.close()
        return self.file.stat().st_size

    def abort(self) -> None:
        try:
            self.writer.abort()
        except Exception:
            pass

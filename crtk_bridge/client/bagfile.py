"""Reading a recording back (``crtk-ctl replay`` and ``crtk-ctl plot``; docs/recording.md).

A bag written by the daemon (recording/bag.py: a rosbag2 MCAP folder or its ``.mcap`` file) is
read with rosbags' reader and decoded with the ROS graph's type store (transport/ros/types.py,
crtk_msgs included). What the tools need, as numpy arrays on the recording's clock (the log time
of each message: the cycle's stamp, seconds since the epoch): per namespace the joint states
(``measured_js``, ``setpoint_js``, ``goal_js``), the operating-state changes and the events.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crtk_bridge.errors import CrtkBridgeError

JOINT_TOPICS = ("measured_js", "setpoint_js", "goal_js")
EVENT_TOPICS = ("error", "warning", "status")


class BagError(CrtkBridgeError):
    """A recording cannot be read or does not hold what was asked (one line, naming the file)."""


@dataclass
class JointSeries:
    """One JointState topic: ``t`` (s, the recording's clock) and per field an array of shape
    (samples, joints), NaN where a sample left the field empty (no setpoint yet, no effort...)."""

    names: list[str]
    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray

    def has(self, what: str) -> bool:
        values = getattr(self, what)
        return values.size > 0 and bool(np.isfinite(values).any())


@dataclass
class Recording:
    """What ``crtk-ctl replay`` / ``plot`` read of a bag."""

    path: Path
    robot: str | None
    custom: dict
    namespaces: list[str]
    joints: dict[tuple[str, str], JointSeries] = field(default_factory=dict)
    #: per namespace: (t, state, is_homed, is_busy) on every operating_state message
    states: dict[str, list[tuple[float, str, bool, bool]]] = field(default_factory=dict)
    #: (t, kind, namespace, text) of every error / warning / status event
    events: list[tuple[float, str, str, str]] = field(default_factory=list)
    start: float = 0.0
    end: float = 0.0

    def series(self, ns: str, topic: str) -> JointSeries:
        s = self.joints.get((ns, topic))
        if s is None:
            raise BagError(f"{self.path}: no /{ns}/{topic} in this recording (namespaces recorded: "
                           f"{', '.join(self.namespaces) or 'none'})")
        return s


def _bag_path(path: str | Path) -> Path:
    p = Path(path).expanduser()
    if p.is_dir() or p.suffix == ".mcap" and p.exists():
        return p
    if p.suffix == ".mcap" and (p.with_suffix("") / p.name).exists():  # run1.mcap -> run1/run1.mcap
        return p.with_suffix("") / p.name
    raise BagError(f"{p}: no such recording (a rosbag2 bag folder or its .mcap file)")


def _custom_data(where: Path) -> dict:
    """The bag's custom_data (robot, daemon version, rate...) from its metadata.yaml, if any."""
    import yaml

    folder = where if where.is_dir() else where.parent
    try:
        doc = yaml.safe_load((folder / "metadata.yaml").read_text())
        return dict(doc["rosbag2_bagfile_information"].get("custom_data") or {})
    except (OSError, KeyError, TypeError, AttributeError, yaml.YAMLError):
        return {}


def _rows(msgs: list, attr: str, width: int) -> np.ndarray:
    out = np.full((len(msgs), width), np.nan)
    for i, m in enumerate(msgs):
        v = getattr(m, attr)
        if len(v) == width:
            out[i] = v
    return out


def read(path: str | Path, namespaces: list[str] | None = None, topics=JOINT_TOPICS) -> Recording:
    """Read the bag at ``path``: the joint ``topics`` of ``namespaces`` (default: every namespace
    recorded), the operating states and events. Raises :class:`BagError` naming the file."""
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError

    from crtk_bridge.transport.ros.types import TYPESTORE

    where = _bag_path(path)
    try:
        reader = Reader(where)
        reader.open()
    except (ReaderError, OSError) as exc:
        raise BagError(f"{where}: not a readable rosbag2 bag ({exc}); a bag must be closed (a killed daemon's "
                       "last file: docs/recording.md, Losses)") from None
    try:
        custom = _custom_data(where)
        conns = {c.topic: c for c in reader.connections}
        if "robot" not in custom:  # no metadata.yaml (a killed daemon's bag): /<robot>/commands names it
            robots = [t[1:-len("/commands")] for t in conns if t.endswith("/commands") and t.count("/") == 2]
            if len(robots) == 1:
                custom["robot"] = robots[0]
        recorded = sorted({t[1:].rsplit("/", 1)[0] for t in conns if t.endswith("/measured_js")})
        wanted = recorded if not namespaces else list(namespaces)
        missing = [ns for ns in wanted if ns not in recorded]
        if missing:
            raise BagError(f"{where}: namespace {missing[0]} is not in this recording (recorded: "
                           f"{', '.join(recorded) or 'none'})")
        rec = Recording(where, custom.get("robot"), custom, wanted)
        want = {}
        for ns in wanted:
            for topic in topics:
                if f"/{ns}/{topic}" in conns:
                    want[f"/{ns}/{topic}"] = ("js", ns, topic)
            want[f"/{ns}/operating_state"] = ("state", ns, None)
            for kind in EVENT_TOPICS:
                want[f"/{ns}/{kind}"] = ("event", ns, kind)
        chosen = [conns[t] for t in want if t in conns]
        got: dict[str, list] = {t: [] for t in want}
        stamps: dict[str, list] = {t: [] for t in want}
        for conn, t_ns, data in reader.messages(connections=chosen):
            got[conn.topic].append(TYPESTORE.deserialize_cdr(data, conn.msgtype))
            stamps[conn.topic].append(t_ns * 1e-9)
        seen_events = set()
        for topic, (kind, ns, sub) in want.items():
            msgs, t = got[topic], np.asarray(stamps[topic])
            if kind == "js" and msgs:
                names = next((list(m.name) for m in msgs if len(m.name)), [])
                n = len(names)
                rec.joints[(ns, sub)] = JointSeries(names, t, _rows(msgs, "position", n), _rows(msgs, "velocity", n),
                                                    _rows(msgs, "effort", n))
            elif kind == "state":
                rec.states[ns] = [(float(ti), str(m.state), bool(m.is_homed), bool(m.is_busy))
                                  for ti, m in zip(t, msgs)]
            elif kind == "event":
                for ti, m in zip(t, msgs):
                    key = (round(float(ti), 6), sub, m.string)  # a robot-wide event is on every namespace
                    if key not in seen_events:
                        seen_events.add(key)
                        rec.events.append((float(ti), sub, ns, str(m.string)))
        rec.events.sort()
        rec.start = reader.start_time * 1e-9
        rec.end = reader.end_time * 1e-9
        return rec
    finally:
        reader.close()

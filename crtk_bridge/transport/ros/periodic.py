"""The ROS graph's periodic topics, published from their own thread (front process).

Every tick (the loop rate, or ``transport.zenoh.publish_rate_hz``) the thread reads the control
loop's snapshot once, skips the tick when the loop has published no new cycle since the last one,
and puts one sample of each topic somebody subscribes to: ``measured_js`` / ``setpoint_js`` /
``goal_js`` per namespace, the cartesian ones where a namespace has kinematics, ``/joint_states``
and ``/tf``. Each message is encoded once per tick, whatever the number of subscribers (Zenoh fans
the one put out), by rewriting the numbers of a CDR template (types.CdrTemplate): no message
object and no serializer walk per sample. The tick's puts go out together once every message is
encoded: a put that finds Zenoh's sender idle wakes it (measured here: ~19 us a put when puts are
spread over the tick, ~5 us in a burst, and a third less CPU for the process at 12 topics).

Why a thread: the event loop serves the socket and Zenoh clients, and a 1 kHz timer on it costs a
wake-up per tick and rounds its sleeps to the selector's millisecond. The snapshot in shared
memory is the latest-value slot: a tick that comes late reads the newest sample and the ticks it
missed are skipped, never queued; they are counted (``skipped``, period_statistics'
``ros_ticks_skipped``) and said in the log at most once a second. Only this thread touches these publishers (the event-driven
topics stay on the event loop), and it computes cartesian topics with its own kinematics
(pinocchio data is not thread-safe).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable

import numpy as np

from ...server.cartesian import CartesianSpace
from ...server.link import ControlLink
from . import types as T
from .rmw import Publisher

log = logging.getLogger("crtk_bridge.ros")

JOINT_TOPICS = ("measured_js", "setpoint_js", "goal_js")
#: periodic cartesian topics: ROS type, and the number of float64 fields
CARTESIAN_TOPICS = {
    "measured_cp": (T.POSE_STAMPED, 7), "setpoint_cp": (T.POSE_STAMPED, 7),
    "measured_cv": (T.TWIST_STAMPED, 6), "measured_cf": (T.WRENCH_STAMPED, 6),
}
_BUILDERS: dict[str, Callable[[dict], Any]] = {
    T.POSE_STAMPED: T.pose_stamped, T.TWIST_STAMPED: T.twist_stamped, T.WRENCH_STAMPED: T.wrench_stamped}
_SIX = {T.TWIST_STAMPED: ("linear", "angular"), T.WRENCH_STAMPED: ("force", "torque")}
ZERO3 = (0.0, 0.0, 0.0)


class Encoders:
    """CDR of the periodic messages, one template per layout (types.CdrTemplate), made on first use."""

    def __init__(self) -> None:
        self._templates: dict[tuple, T.CdrTemplate] = {}

    def _template(self, key: tuple, ros_type: str, build: Callable, n_floats: int, n_stamps: int = 1) -> T.CdrTemplate:
        t = self._templates.get(key)
        if t is None:
            t = self._templates[key] = T.CdrTemplate(ros_type, build, n_floats, n_stamps)
        return t

    def joint_state(self, js: dict) -> bytes:
        """sensor_msgs/JointState of a protocol JointState (as T.joint_state, then encoded)."""
        p, v, f = js["position"], js["velocity"], js["effort"]
        a, b = len(p), len(p) + len(v)
        frame, names = js["frame_id"], js["name"]

        def build(x: np.ndarray, stamps: list) -> Any:
            return T.joint_state({"stamp": stamps[0], "frame_id": frame, "name": names,
                                  "position": x[:a], "velocity": x[a:b], "effort": x[b:]})

        t = self._template((T.JOINT_STATE, frame, tuple(names), a, b, b + len(f)), T.JOINT_STATE, build,
                           b + len(f))
        t.floats[:a] = p
        t.floats[a:b] = v
        t.floats[b:] = f
        t.stamp(0, js["stamp"])
        return t.render()

    def cartesian(self, ros_type: str, d: dict) -> bytes:
        """PoseStamped, TwistStamped or WrenchStamped of a protocol payload (CartesianSpace.query)."""
        frame = d["frame_id"]
        if ros_type == T.POSE_STAMPED:
            def build(x: np.ndarray, stamps: list) -> Any:
                return T.pose_stamped({"stamp": stamps[0], "frame_id": frame, "position": x[:3],
                                       "orientation": x[3:]})
            t = self._template((ros_type, frame), ros_type, build, 7)
            pos, q = T.pose_values(d)
            t.floats[:3] = pos
            t.floats[3:] = q
        else:
            a, b = _SIX[ros_type]

            def build(x: np.ndarray, stamps: list) -> Any:
                return _BUILDERS[ros_type]({"stamp": stamps[0], "frame_id": frame, a: x[:3], b: x[3:]})
            t = self._template((ros_type, frame), ros_type, build, 6)
            t.floats[:3] = d[a] if len(d[a]) else ZERO3
            t.floats[3:] = d[b] if len(d[b]) else ZERO3
        t.stamp(0, d["stamp"])
        return t.render()

    def tf(self, poses: list[dict]) -> bytes:
        """tf2_msgs/TFMessage of protocol poses (each frame_id -> child_frame_id)."""
        frames = tuple((p["frame_id"], p["child_frame_id"]) for p in poses)

        def build(x: np.ndarray, stamps: list) -> Any:
            return T.TFMessage(transforms=[
                T.transform_stamped({"stamp": stamps[i], "frame_id": fr, "child_frame_id": child,
                                     "position": x[7 * i:7 * i + 3], "orientation": x[7 * i + 3:7 * i + 7]})
                for i, (fr, child) in enumerate(frames)])
        t = self._template((T.TF_MESSAGE, frames), T.TF_MESSAGE, build, 7 * len(poses), len(poses))
        for i, p in enumerate(poses):
            pos, q = T.pose_values(p)
            t.floats[7 * i:7 * i + 3] = pos
            t.floats[7 * i + 3:7 * i + 7] = q
            t.stamp(i, p["stamp"])
        return t.render()


class PeriodicTopics:
    """The publishing thread. ``pubs``: the graph's publishers by (namespace or "", topic);
    ``spaces``: a CartesianSpace per kinematic namespace, owned by this thread."""

    def __init__(self, link: ControlLink, namespaces: list[str], pubs: dict[tuple[str, str], Publisher],
                 spaces: dict[str, CartesianSpace], rate_hz: float, robot: str):
        self.link = link
        self.namespaces = namespaces
        self.pubs = pubs
        self.spaces = spaces
        self.period_s = 1.0 / rate_hz
        self.robot = robot
        self.encoders = Encoders()
        self._buf = np.zeros_like(link.snap.data)  # this thread's copy of the snapshot
        slices = link.snap.layout.slices
        self._cycles = slices["cycles"].start
        self._state_size = slices["lateness"].start  # the state and counters, not the statistics rings
        self._last_cycle = -1.0
        self._periodic = [p for (ns, topic), p in pubs.items()
                          if topic in JOINT_TOPICS or topic in CARTESIAN_TOPICS or topic in ("joint_states", "tf")]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"ros topics {robot}", daemon=True)
        self._error_said = -1.0
        self.published = 0  # ticks that put samples (for tests and the bench)
        self.skipped = 0  # ticks missed because the thread was late (their samples never published)
        self._skip_said = -1.0

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        """Stop the thread (returns within one tick)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)

    def _run(self) -> None:
        period = self.period_s
        clock = time.perf_counter
        next_t = clock()
        while not self._stop.is_set():
            try:
                self.publish_once()
            except Exception:  # a bug here must not end the publications silently, nor flood the log
                now = time.monotonic()
                if now - self._error_said >= 1.0:
                    self._error_said = now
                    log.exception("%s: publishing the ROS topics failed", self.robot)
            next_t += period
            delay = next_t - clock()
            if delay > 0:
                time.sleep(delay)
            else:  # behind: skip the missed ticks, never burst; counted, never silent
                missed = int(-delay / period)
                if missed:
                    self._missed(missed)
                next_t = clock()

    def _missed(self, n: int) -> None:
        self.skipped += n
        now = time.monotonic()
        if now - self._skip_said >= 1.0:
            self._skip_said = now
            log.warning("%s: the ROS topics' thread fell behind: %d ticks skipped so far (their samples were "
                        "not published; period_statistics' ros_ticks_skipped counts them)", self.robot, self.skipped)

    def publish_once(self) -> bool:
        """One sample of every periodic topic somebody subscribes to, from one snapshot read.
        False when nobody subscribes or the loop published no new cycle since the last tick."""
        if not any(p.wanted for p in self._periodic):
            return False
        buf, _ = self.link.snap.read(self._buf, upto=self._state_size)
        if buf[self._cycles] == self._last_cycle:
            return False
        self._last_cycle = buf[self._cycles]
        link, pubs, enc = self.link, self.pubs, self.encoders
        out: list[tuple[Publisher, bytes]] = []  # put together at the end: one wake-up of Zenoh's sender
        joint_states = pubs[("", "joint_states")].wanted
        tf = ("", "tf") in pubs and pubs[("", "tf")].wanted
        all_js = []
        transforms = []
        for ns in self.namespaces:
            for topic in JOINT_TOPICS:
                pub = pubs[(ns, topic)]
                if pub.wanted or (joint_states and topic == "measured_js"):
                    js = link.joint_state(topic, ns, buf)
                    if topic == "measured_js":
                        all_js.append(js)
                    if pub.wanted:
                        out.append((pub, enc.joint_state(js)))
            cs = self.spaces.get(ns)
            if cs is None:
                continue
            wanted = [t for t in CARTESIAN_TOPICS if (ns, t) in pubs and pubs[(ns, t)].wanted]
            if not wanted and not tf:
                continue
            st = link.ns_arrays(ns, buf)
            measured_cp = None
            for topic in wanted:
                d = cs.query(topic, st, "spatial")
                if topic == "measured_cp":
                    measured_cp = d
                out.append((pubs[(ns, topic)], enc.cartesian(CARTESIAN_TOPICS[topic][0], d)))
            if tf:  # the same pose as measured_cp's, computed once
                transforms.append(measured_cp or cs.query("measured_cp", st, "spatial"))
        if joint_states:
            out.append((pubs[("", "joint_states")], enc.joint_state(joint_states_of(all_js))))
        if transforms:
            out.append((pubs[("", "tf")], enc.tf(transforms)))
        for pub, payload in out:
            pub.put(payload)
        self.published += 1
        return True


def joint_states_of(all_js: list[dict]) -> dict:
    """/joint_states: every namespace's measured_js in one JointState (a vector only when every
    namespace has it)."""
    js = {"stamp": all_js[0]["stamp"], "frame_id": "", "name": [n for j in all_js for n in j["name"]]}
    for f in ("position", "velocity", "effort"):
        js[f] = [v for j in all_js for v in j[f]] if all(len(j[f]) for j in all_js) else []
    return js

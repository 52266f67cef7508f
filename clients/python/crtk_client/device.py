"""CRTK devices over a :class:`~crtk_client.connection.Connection`, with the names and
return conventions of crtk_python_client 1.4 (``measured_js() -> (p, v, e, ts)``, ``enable(t) ->
bool``, ``move_jp(goal) -> handle``; ``handle.wait() -> bool``).

Differences from crtk_python_client, on purpose (reference/crtk-anchors.md section 4):

- a refused command raises :class:`~crtk_client.errors.CommandError` with the daemon's code and
  message instead of being dropped silently; so ``MoveHandle.wait()`` can never hang on a rejected
  move (the move raised already);
- move completion uses the daemon's ``busy_seq`` counter, not clocks: a wait can neither return
  on a stale idle state nor depend on clock skew;
- queries are answered by the daemon on request (one round trip), so they are never stale;
  ``ts == 0.0`` still means the data is invalid (CRTK 4.1.2.3) and the caller must check it;
- ``pause()``, ``resume()``, ``is_paused()`` and ``is_fault()`` exist (CRTK 3.4).

Units are SI: rad, rad/s, N·m, s; stamps in seconds since the Unix epoch.

numpy is imported by the functions that return or take arrays, not by this module: ``crtk-ctl
state`` and ``enable`` need none, and importing numpy alone costs more than their round trip
(bench/bench_cli.py; tests/test_cli_imports.py).
"""

from __future__ import annotations

import math
import numbers
import os
import queue
import threading
import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from crtk_client.connection import (
    PROTOCOL_VERSION, Connection, DaemonConnectionError, Event, encode_vector)
from crtk_client.pacing import Pacing
from crtk_client.paths import (
    SYSTEM_SOCKET_DIR, default_socket_dir, default_socket_path, find_sockets)
from crtk_client import vocabulary
from crtk_client.errors import CommandError, CrtkBridgeError

#: Topics and queries that are robot-wide (sent without ``ns``).
ROBOT_TOPICS = frozenset(vocabulary.ROBOT_TOPICS)
#: Per-namespace joint-state topics and queries.
JS_TOPICS = vocabulary.JOINT_TOPICS
STATES = tuple(vocabulary.OperatingState)


#: Cartesian pose queries (answered as 4x4 matrices, or position + quaternion with ``*_pq``).
CP_TOPICS = tuple(t for t in vocabulary.CartesianTopic if t.endswith("_cp"))
#: Cartesian twist queries (6-vectors ``[linear; angular]``), in the spatial or body frame.
CV_TOPICS = tuple(t for t in vocabulary.CartesianTopic if t.endswith("_cv"))
#: Cartesian wrench queries (6-vectors ``[force; torque]``), in the spatial or body frame.
CF_TOPICS = tuple(t for t in vocabulary.CartesianTopic if t.endswith("_cf"))
CARTESIAN_TOPICS = CP_TOPICS + CV_TOPICS + CF_TOPICS
#: Reference frames of twists and wrenches (docs/cartesian.md): ``spatial`` = the base frame's
#: axes (namespace ``<ns>``), ``body`` = the tip frame's axes (namespace ``<ns>/body``).
FRAMES = ("spatial", "body")

#: stream commands :meth:`Device.stream` sends, by payload: a joint vector, a pose, a relative
#: pose, a twist or wrench
JOINT_STREAM_COMMANDS = ("servo_jp", "servo_jr", "servo_jv", "servo_jf",
                         "interpolate_jp", "interpolate_jr", "interpolate_jv", "interpolate_jf")
POSE_STREAM_COMMANDS = ("servo_cp", "interpolate_cp")
DELTA_STREAM_COMMANDS = ("servo_cr", "interpolate_cr")
SIX_STREAM_COMMANDS = ("servo_cv", "interpolate_cv", "servo_cf", "interpolate_cf")
#: stream commands without an end (velocity, effort): a stream of them ends with ``hold``
ENDLESS_COMMANDS = ("servo_jv", "servo_jf", "interpolate_jv", "interpolate_jf",
                    "servo_cv", "interpolate_cv", "servo_cf", "interpolate_cf")
#: relative stream commands: a stream of them moves by the offset given, in total
RELATIVE_COMMANDS = ("servo_jr", "interpolate_jr", "servo_cr", "interpolate_cr")


def joint_state(data: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A wire JointState as ``(position, velocity, effort, ts)``: float64 arrays (empty when the
    robot does not provide that vector) and the stamp in s (``0.0``: invalid data)."""
    import numpy as np
    return (np.asarray(data.get("position") or (), dtype=float),
            np.asarray(data.get("velocity") or (), dtype=float),
            np.asarray(data.get("effort") or (), dtype=float),
            float(data.get("stamp") or 0.0))


# -- cartesian helpers: crtk_bridge/vectors.py, the one implementation the daemon uses too (numpy
# only: the client does not need pinocchio); loaded on first use, so that a plain command needs
# no numpy

def matrix_from_quaternion(quaternion) -> np.ndarray:
    """3x3 rotation matrix of a quaternion ``[x, y, z, w]`` (ROS order), normalised first.
    Raises ``ValueError`` on a zero or non-finite quaternion."""
    from crtk_client import vectors
    return vectors.matrix_from_quaternion(quaternion)


def quaternion_from_matrix(rotation) -> np.ndarray:
    """Unit quaternion ``[x, y, z, w]`` (``w >= 0``) of a 3x3 rotation matrix (or the rotation
    block of a 4x4 pose)."""
    from crtk_client import vectors
    return vectors.quaternion_from_matrix(rotation)


def pose_matrix(position, quaternion) -> np.ndarray:
    """The 4x4 homogeneous matrix of ``position`` [x, y, z] (m) and ``quaternion`` [x, y, z, w]."""
    from crtk_client import vectors
    return vectors.pose_matrix(position, quaternion)


def pose_pq(matrix) -> tuple[np.ndarray, np.ndarray]:
    """``(position [3] in m, quaternion [4] x, y, z, w with w >= 0)`` of a 4x4 homogeneous matrix."""
    from crtk_client import vectors
    return vectors.pose_pq(matrix)


def pose_from_wire(data: dict) -> tuple[np.ndarray, float]:
    """A wire pose (``{"stamp", "position", "orientation", ...}``) as ``(4x4 matrix, ts)``; the
    matrix is all NaN when the pose is invalid (``ts == 0``, empty vectors)."""
    import numpy as np
    p, q, ts = pq_from_wire(data)
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        return np.full((4, 4), np.nan), ts
    return pose_matrix(p, q), ts


def pq_from_wire(data: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """A wire pose as ``(position [3], quaternion [4] xyzw, ts)``; NaN vectors when invalid."""
    import numpy as np
    p = np.asarray(data.get("position") or (), dtype=float)
    q = np.asarray(data.get("orientation") or (), dtype=float)
    if p.shape != (3,) or q.shape != (4,):
        p, q = np.full(3, np.nan), np.full(4, np.nan)
    return p, q, float(data.get("stamp") or 0.0)


def six_from_wire(data: dict, a: str, b: str) -> tuple[np.ndarray, float]:
    """A wire twist (``a, b = "linear", "angular"``) or wrench (``"force", "torque"``) as
    ``(vector [6], ts)``; NaN when invalid."""
    import numpy as np
    v = np.asarray(list(data.get(a) or ()) + list(data.get(b) or ()), dtype=float)
    if v.shape != (6,):
        v = np.full(6, np.nan)
    return v, float(data.get("stamp") or 0.0)


def encode_pose(pose, what: str = "pose") -> dict:
    """A pose as the wire's ``{"position": [3], "orientation": [4]}``.

    ``pose`` is a 4x4 homogeneous matrix (numpy array or nested lists; the rotation block must be
    a rotation within 1e-3), a ``(position[3], quaternion[4] xyzw)`` pair, or a dict with
    ``position`` and ``orientation``. The quaternion is normalised (its norm must lie in
    (0.5, 1.5), as the daemon requires). Raises :class:`CommandError` ``bad_request`` before
    anything is sent (:func:`crtk_bridge.vectors.any_pose`).
    """
    from crtk_client import vectors
    p, q = vectors.any_pose(pose, what)
    return {"position": p.tolist(), "orientation": q.tolist()}


def pose_share(delta: dict, before: float, reached: float) -> dict:
    """The part of a relative pose ``delta`` (wire form, as :func:`encode_pose` returns) between
    the fractions ``before`` and ``reached`` of it: that part of the translation, and of the
    rotation's angle about the same axis, so the parts of ``0 .. 1`` in a row make ``delta``."""
    import numpy as np
    dp = np.asarray(delta["position"], float)
    dq = np.asarray(delta["orientation"], float)
    dq = dq / np.linalg.norm(dq)
    if dq[3] < 0:
        dq = -dq
    s = float(np.linalg.norm(dq[:3]))
    angle = 2.0 * math.atan2(s, float(dq[3]))
    axis = dq[:3] / s if s > 0 else np.zeros(3)
    part = angle * reached - angle * before
    return {"position": (dp * reached - dp * before).tolist(),
            "orientation": [*(axis * math.sin(part / 2)).tolist(), math.cos(part / 2)]}


@dataclass(frozen=True)
class StreamReport:
    """What :meth:`Device.stream` did: ``samples`` of ``cmd`` sent at up to ``rate_hz`` (after the
    cap at the loop rate) over ``elapsed_s`` on the wall clock; ``held``: it ended with ``hold``
    (not counted in ``samples``)."""

    cmd: str
    samples: int
    rate_hz: float
    elapsed_s: float
    held: bool


def encode_six(values, a: str, b: str, what: str) -> dict:
    """A 6-vector as ``{a: values[:3], b: values[3:]}`` (twist: linear, angular; wrench: force,
    torque). Raises :class:`CommandError` ``bad_request`` unless 6 finite numbers."""
    v = encode_vector(values, what)
    if len(v) != 6:
        raise CommandError("bad_request", f"{what}: needs 6 numbers [{a} x y z, {b} x y z], got {len(v)}")
    return {a: v[:3], b: v[3:]}


class MoveHandle:
    """The handle of an accepted ``move_*`` (or ``home``), numbered ``busy_seq`` by the daemon."""

    def __init__(self, connection: Connection, busy_seq: int, cmd: str = "move"):
        self._conn = connection
        self.busy_seq = busy_seq
        self.cmd = cmd

    def __repr__(self) -> str:
        return f"MoveHandle({self.cmd}, busy_seq={self.busy_seq}, busy={self.is_busy()})"

    def is_busy(self) -> bool:
        """True until an operating_state with ``busy_seq >= self.busy_seq`` and ``is_busy``
        false has arrived, i.e. while this motion runs. Does not block."""
        return self._conn.idle_seq < self.busy_seq

    def wait(self, is_busy: bool = False, timeout: float = 30.0) -> bool:
        """Block up to ``timeout`` s. With ``is_busy=False`` (default): until the motion has
        ended (an operating_state with ``busy_seq >= self.busy_seq`` and ``is_busy`` false; a
        motion that ended on a FAULT counts as ended, check ``is_fault()``). With ``is_busy=True``:
        until it has started (immediate, the busy edge precedes the move's reply).

        Returns False on timeout. Raises :class:`DaemonConnectionError` if the daemon goes away.
        """
        n = self.busy_seq
        if is_busy:
            return self._conn.wait_for(lambda c: c.max_busy_seq >= n, timeout)
        return self._conn.wait_for(lambda c: c.idle_seq >= n, timeout)


class Subscription:
    """A stream of frames of one topic (``subscribe``), at up to ``rate_hz``.

    Without a callback, frames (the wire ``data`` dicts: a JointState for ``*_js``) are queued,
    at most ``maxsize``; when the queue is full the oldest frame is dropped (a slow reader loses
    frames, as on the daemon side). Read them with :meth:`get` or by iterating. With a callback,
    ``callback(data)`` runs on the connection's reader thread: keep it short, and do not call
    request methods from it (that raises ``RuntimeError``).

    Iteration ends when :meth:`close` is called; it raises :class:`DaemonConnectionError` when
    the daemon goes away. A context manager.
    """

    _CLOSED = object()

    def __init__(self, connection: Connection, topic: str, rate_hz: float, ns: str | None,
                 callback: Callable[[dict], None] | None = None, maxsize: int = 1000):
        self._conn = connection
        self.topic = topic
        self.ns = ns
        self.rate_hz = rate_hz
        self.dropped = 0
        self._callback = callback
        self._queue: queue.Queue = queue.Queue(maxsize=maxsize)
        self._error: BaseException | None = None
        self._closed = False
        self.sub = connection._open_stream(topic, rate_hz, ns, self._sink)

    def __repr__(self) -> str:
        return f"Subscription({self.topic!r}, ns={self.ns!r}, sub={self.sub}, rate_hz={self.rate_hz})"

    def _put(self, item) -> None:
        while True:
            try:
                self._queue.put_nowait(item)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def _sink(self, data: dict | None, error: BaseException | None) -> None:
        if error is not None:
            self._error = error
            self._put(self._CLOSED)
        elif self._callback is not None:
            self._callback(data)
        else:
            self._put(data)

    def get(self, timeout: float | None = None) -> dict:
        """The next frame; blocks up to ``timeout`` s (``None``: forever). Raises
        ``TimeoutError`` when none comes, ``EOFError`` after :meth:`close`, and
        :class:`DaemonConnectionError` when the daemon went away."""
        if self._closed and self._queue.empty():
            raise EOFError(f"subscription to {self.topic} closed")
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError(f"no {self.topic} frame within {timeout:g} s") from None
        if item is self._CLOSED:
            self._put(self._CLOSED)  # keep later get() calls failing the same way
            if self._error is not None:
                raise DaemonConnectionError(str(self._error)) from self._error
            raise EOFError(f"subscription to {self.topic} closed")
        return item

    def __iter__(self) -> Iterator[dict]:
        while True:
            try:
                yield self.get()
            except EOFError:
                return

    def close(self) -> None:
        """Unsubscribe (best effort) and end iteration. Idempotent; does not raise."""
        if self._closed:
            return
        self._closed = True
        self._conn._close_stream(self.sub)
        self._put(self._CLOSED)

    def __enter__(self) -> "Subscription":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Device:
    """One CRTK namespace of a robot (``so101``, ``so101/gripper``); get it from
    :meth:`Robot.device`. Child namespaces are attributes: ``arm.gripper`` is ``so101/gripper``.

    All namespaces of a robot share one operating state. Every method that talks to the daemon
    blocks for one round trip (bounded by the connection timeout, then ``TimeoutError``), raises
    :class:`CommandError` when the daemon refuses and :class:`DaemonConnectionError` when it is
    gone. Motion and state commands take control of the robot if nobody holds it (else
    ``read_only``).
    """

    def __init__(self, robot: "Robot", name: str, info: dict):
        self._robot = robot
        self._conn = robot.connection
        self.name = name
        self.info = info
        self.joint_names: list[str] = list(info.get("joints") or [])
        #: per joint, "rad" (revolute: rad, rad/s, N*m) or "m" (prismatic: m, m/s, N); "rad" from
        #: a daemon older than the ``units`` field of ``list``
        self.joint_units: list[str] = list(info.get("units") or ["rad"] * len(self.joint_names))

    def __repr__(self) -> str:
        return f"Device({self.name!r}, joints={self.joint_names})"

    def __getattr__(self, attr: str) -> "Device":
        if attr.startswith("_"):
            raise AttributeError(attr)
        child = f"{self.name}/{attr}"
        if child in self._robot.namespaces:
            return self._robot.device(child)
        raise AttributeError(
            f"{type(self).__name__} {self.name!r} has no attribute or child namespace {attr!r}")

    def _req(self, cmd: str, data: Any = None, ns: bool = True, timeout: float | None = None):
        return self._conn.request(cmd, self.name if ns else None, data, timeout)

    def list(self) -> dict:
        """This namespace's entry of ``list``: ``{"name", "joints", "commands", "queries",
        "topics"}`` (asked afresh)."""
        for entry in self._conn.request("list").get("namespaces", []):
            if entry.get("name") == self.name:
                return entry
        raise CommandError("unknown_namespace", f"{self.name}: no longer listed by the daemon")

    # -- operating state (CRTK section 3) ----------------------------------------------------

    def _state(self) -> dict:
        st = self._conn.operating_state
        if st is None:  # the daemon pushes one on connect; ask if it has not arrived yet
            st = self._conn.request("operating_state")
            self._conn._set_operating_state(st, from_reply=True)
        return st

    def operating_state(self) -> str:
        """The robot's state: ``"DISABLED"``, ``"ENABLED"``, ``"PAUSED"`` or ``"FAULT"``.
        From the latest pushed operating_state event (the daemon pushes every change): no round
        trip once the first event has arrived."""
        return str(self._state()["state"])

    def operating_state_full(self) -> dict:
        """The latest OperatingState: ``{"state", "is_homed", "is_busy", "busy_seq", "stamp"}``."""
        return dict(self._state())

    def is_enabled(self) -> bool:
        return self.operating_state() == "ENABLED"

    def is_disabled(self) -> bool:
        return self.operating_state() == "DISABLED"

    def is_paused(self) -> bool:
        return self.operating_state() == "PAUSED"

    def is_fault(self) -> bool:
        return self.operating_state() == "FAULT"

    def is_homed(self) -> bool:
        return bool(self._state().get("is_homed"))

    def is_busy(self) -> bool:
        """True while a ``move_*`` or ``home`` runs (servo commands keep it false)."""
        return bool(self._state().get("is_busy"))

    def state_command(self, command: str) -> str:
        """Send a state command (``enable``, ``disable``, ``pause``, ``resume``, ``home``,
        ``unhome``) without waiting; return the state the daemon reports after it. Raises
        :class:`CommandError` (``invalid_state`` per the CRTK transition table, ``read_only``)."""
        reply = self._send_state_command(command)[0]
        return str(reply.get("state")) if isinstance(reply, dict) else self.operating_state()

    def _send_state_command(self, command: str) -> tuple[Any, int, int]:
        """Send; return (reply, state events seen before the reply, busy_seq known before)."""
        conn = self._conn
        seq_before = conn.max_busy_seq
        mark = [0]

        def on_reply(data):  # reader thread, in wire order
            mark[0] = conn.state_events
            if isinstance(data, dict) and "state" in data:
                conn._set_operating_state(data, from_reply=True)

        reply = conn._request(command, self.name, None, None, on_reply)
        return reply, mark[0], seq_before

    def _transition(self, command: str, target: str, timeout: float) -> bool:
        _, mark, _ = self._send_state_command(command)
        result = [False]

        def done(c: Connection) -> bool:
            st = c.operating_state or {}
            if st.get("state") == target:
                result[0] = True
                return True
            # a FAULT pushed after the reply: the transition failed, do not wait out the timeout
            return c.state_events > mark and st.get("state") == "FAULT"

        self._conn.wait_for(done, max(0.0, timeout))
        return result[0]

    def enable(self, timeout: float = 5.0) -> bool:
        """Power the robot (DISABLED or FAULT -> ENABLED) and wait up to ``timeout`` s for
        ENABLED. Returns True if reached, False on timeout or on a FAULT meanwhile. Raises
        :class:`CommandError` when refused (``invalid_state`` from PAUSED: use :meth:`resume`)."""
        return self._transition("enable", "ENABLED", timeout)

    def disable(self, timeout: float = 5.0) -> bool:
        """Cut motor power (-> DISABLED, legal in every state); wait up to ``timeout`` s.
        Returns True if DISABLED was reached."""
        return self._transition("disable", "DISABLED", timeout)

    def pause(self, timeout: float = 5.0) -> bool:
        """ENABLED -> PAUSED (motion stops, power stays on); wait up to ``timeout`` s. Returns
        True if PAUSED was reached. Raises :class:`CommandError` ``invalid_state`` from DISABLED
        or FAULT."""
        return self._transition("pause", "PAUSED", timeout)

    def resume(self, timeout: float = 5.0) -> bool:
        """PAUSED -> ENABLED; wait up to ``timeout`` s. Returns True if ENABLED was reached.
        Raises :class:`CommandError` ``invalid_state`` unless PAUSED."""
        return self._transition("resume", "ENABLED", timeout)

    def home(self, timeout: float = 30.0) -> bool:
        """Move every joint to its profile home position (legal only in ENABLED) and wait up to
        ``timeout`` s until ``is_homed`` and not ``is_busy`` for *this* home (by ``busy_seq``, so
        a stale idle state cannot end the wait). Returns True when homed; False on timeout or if
        the homing ended without ``is_homed`` in FAULT/DISABLED. Raises :class:`CommandError`."""
        reply, _, seq_before = self._send_state_command("home")
        n = seq_before + 1
        if isinstance(reply, dict) and isinstance(reply.get("busy_seq"), int):
            n = max(n, reply["busy_seq"])
        result = [False]

        def done(c: Connection) -> bool:
            st = c.operating_state or {}
            if c.idle_seq < n:
                return False
            if st.get("is_homed") and not st.get("is_busy"):
                result[0] = True
                return True
            return st.get("state") in ("FAULT", "DISABLED")

        self._conn.wait_for(done, max(0.0, timeout))
        return result[0]

    def unhome(self, timeout: float = 5.0) -> bool:
        """Clear ``is_homed`` (legal in every state); wait up to ``timeout`` s for it. Returns
        True once not homed. Motion other than ``home`` is then refused with ``not_homed``."""
        self._send_state_command("unhome")
        return self._conn.wait_for(
            lambda c: not (c.operating_state or {}).get("is_homed", False), max(0.0, timeout))

    # -- queries (CRTK 4.2); each is one round trip -----------------------------------------

    def _js(self, level: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        return joint_state(self._req(level))

    def measured_js(self):
        """``(position [rad], velocity [rad/s], effort [N·m], ts [s])`` measured now; numpy
        float64 arrays in :attr:`joint_names` order, empty when not provided; ``ts == 0.0``:
        invalid data."""
        return self._js("measured_js")

    def measured_jp(self):
        """``(position [rad], ts)``; see :meth:`measured_js`."""
        p, _, _, ts = self._js("measured_js")
        return p, ts

    def measured_jv(self):
        """``(velocity [rad/s], ts)``; see :meth:`measured_js`."""
        _, v, _, ts = self._js("measured_js")
        return v, ts

    def measured_jf(self):
        """``(effort [N·m], ts)``; see :meth:`measured_js`."""
        _, _, f, ts = self._js("measured_js")
        return f, ts

    def setpoint_js(self):
        """``(position, velocity, effort, ts)`` of the servo setpoint; only the vectors of the
        active command level are filled (CRTK 4.2.5: servo_jp: position; servo_jv: velocity,
        plus the integrated position on position-only hardware; interpolate_jp and move_jp:
        position and velocity; servo_jf: effort). ``ts == 0`` when disabled or freed."""
        return self._js("setpoint_js")

    def setpoint_jp(self):
        p, _, _, ts = self._js("setpoint_js")
        return p, ts

    def setpoint_jv(self):
        _, v, _, ts = self._js("setpoint_js")
        return v, ts

    def setpoint_jf(self):
        _, _, f, ts = self._js("setpoint_js")
        return f, ts

    def goal_js(self):
        """``(position, velocity, effort, ts)`` of the goal of the running or last
        ``interpolate_*`` / ``move_*`` command (position for jp/jr, velocity for jv, effort for
        jf); ``ts == 0`` when there is none (after a servo command, or while disabled)."""
        return self._js("goal_js")

    def goal_jp(self):
        p, _, _, ts = self._js("goal_js")
        return p, ts

    def goal_jv(self):
        _, v, _, ts = self._js("goal_js")
        return v, ts

    def goal_jf(self):
        _, _, f, ts = self._js("goal_js")
        return f, ts

    # -- motion (CRTK 4.3) -------------------------------------------------------------------

    def _vec(self, values, what: str) -> list[float]:
        return encode_vector(values, f"{self.name}: {what}")

    def supports(self, cmd: str) -> bool:
        """True if ``cmd`` is in this namespace's ``commands`` or ``queries`` of ``list`` (as of
        connecting). A daemon that lists neither is assumed to support everything."""
        lists = [x for x in (self.info.get("commands"), self.info.get("queries")) if x is not None]
        return not lists or any(cmd in x for x in lists)

    def _check_supported(self, cmd: str) -> None:
        if not self.supports(cmd):
            have = ", ".join(c for c in self.info.get("commands") or () if c.split("_")[0]
                             in ("servo", "interpolate", "move", "hold", "free")) or "none"
            raise CommandError("unsupported",
                               f"{self.name}: {cmd} is not supported by this namespace "
                               f"(motion commands it lists: {have})")

    def _motion(self, cmd: str, field: str | None = None, values=None) -> Any:
        """Send one motion command after checking it is listed; ``field`` names the payload
        vector (``position`` / ``velocity`` / ``effort``)."""
        self._check_supported(cmd)
        data = None if field is None else {field: self._vec(values, f"{cmd} {field}")}
        return self._req(cmd, data)

    def servo_jp(self, setpoint_p, setpoint_v=None) -> None:
        """Set the position setpoint (rad), optionally with a velocity feed-forward (rad/s), one
        entry per joint. Preemptive; send continuously at about the loop rate. Blocks for the
        reply; raises :class:`CommandError` (``step_too_large``, ``out_of_limits``,
        ``invalid_state``, ``bad_request``...)."""
        self._check_supported("servo_jp")
        data = {"position": self._vec(setpoint_p, "servo_jp position")}
        if setpoint_v is not None and len(setpoint_v) > 0:
            data["velocity"] = self._vec(setpoint_v, "servo_jp velocity")
        self._req("servo_jp", data)

    def servo_jr(self, setpoint_p) -> None:
        """Move the position setpoint by ``setpoint_p`` (rad), relative to the current setpoint.
        Blocks for the reply; raises :class:`CommandError` like :meth:`servo_jp`."""
        self._motion("servo_jr", "position", setpoint_p)

    def servo_jv(self, setpoint_v) -> None:
        """Set the joint velocity setpoint (rad/s, one per joint; clipped to the velocity
        limits). Preemptive; on position-only hardware the daemon integrates it into the
        position setpoint. Send continuously: a stream silent for the profile's
        ``safety.servo_timeout_s`` holds. Raises :class:`CommandError`."""
        self._motion("servo_jv", "velocity", setpoint_v)

    def servo_jf(self, setpoint_f) -> None:
        """Set the joint effort setpoint (N·m, one per joint). Needs effort control: raises
        :class:`CommandError` ``unsupported`` (without sending) when the namespace does not
        list ``servo_jf``."""
        self._motion("servo_jf", "effort", setpoint_f)

    def interpolate_jp(self, goal_p) -> None:
        """Set the joint position goal (rad) of an interpolated stream, sent at a rate below the
        loop rate (e.g. 20-50 Hz): the daemon moves the setpoint linearly to each goal over one
        estimated command period (the latency this adds), never faster than the joint's
        velocity limit. Preemptive. Raises :class:`CommandError` (``step_too_large`` for a goal
        farther than ``safety.servo_step_max`` from the previous goal)."""
        self._motion("interpolate_jp", "position", goal_p)

    def interpolate_jr(self, goal_r) -> None:
        """Like :meth:`interpolate_jp` with a goal relative (rad) to the running interpolation
        goal, or to the setpoint when none runs."""
        self._motion("interpolate_jr", "position", goal_r)

    def interpolate_jv(self, goal_v) -> None:
        """Set the joint velocity goal (rad/s); the setpoint velocity ramps to it at the
        acceleration limits. Raises :class:`CommandError`."""
        self._motion("interpolate_jv", "velocity", goal_v)

    def interpolate_jf(self, goal_f) -> None:
        """Set the joint effort goal (N·m), reached by a linear ramp over one command period.
        Needs effort control (else ``unsupported``)."""
        self._motion("interpolate_jf", "effort", goal_f)

    def hold(self) -> None:
        """Stop and hold: a running move decelerates to rest, a stream holds its last position
        setpoint (nothing commanded yet: the measured position). Raises :class:`CommandError`."""
        self._motion("hold")

    def free(self) -> None:
        """Switch torque off on this namespace's joints while the robot stays ENABLED (the arm
        can be moved by hand; setpoint_js becomes invalid). The next motion command torques them
        back on from where they are, without a jump. Needs ``free`` in the namespace's
        commands (else ``unsupported``)."""
        self._motion("free")

    def _move(self, cmd: str, goal) -> MoveHandle:
        self._check_supported(cmd)
        return self._start_move(cmd, {"position": self._vec(goal, f"{cmd} position")})

    def _start_move(self, cmd: str, data: dict) -> MoveHandle:
        seq_before = self._conn.max_busy_seq
        reply = self._req(cmd, data)
        n = seq_before + 1
        if isinstance(reply, dict) and isinstance(reply.get("busy_seq"), int):
            n = max(n, reply["busy_seq"])
        return MoveHandle(self._conn, n, cmd)

    def move_jp(self, goal) -> MoveHandle:
        """Move to the joint goal (rad, one per joint) along a jerk-limited trajectory, ending at
        rest. Returns once the daemon accepted it, with a :class:`MoveHandle` to wait on. Raises
        :class:`CommandError` when refused (``invalid_state``, ``not_homed``, ``out_of_limits``,
        ``bad_request``, ``read_only``), so there is never a handle to wait on in vain."""
        return self._move("move_jp", goal)

    def move_jr(self, goal) -> MoveHandle:
        """Like :meth:`move_jp` with a goal relative (rad) to the running move's goal, or to the
        setpoint when no move runs."""
        return self._move("move_jr", goal)

    # -- timed streams -----------------------------------------------------------------------

    def stream(self, cmd: str, values, duration: float, rate_hz: float = 50.0,
               frame: str = "spatial") -> StreamReport:
        """Send the stream command ``cmd`` (``servo_jp``/``jr``/``jv``/``jf``, ``interpolate_j*``,
        ``servo_cp``/``cr``/``cv``/``cf``, ``interpolate_c*``) with ``values`` (its payload, as
        the method of that name takes it; ``frame`` for twists and wrenches) at ``rate_hz`` for
        ``duration`` s, and return a :class:`StreamReport`.

        The stream ends at ``duration`` on the wall clock whatever the rate: samples are paced
        on the clock (first at once, last at ``duration``), and one whose reply comes late is
        followed by the newest one due, those missed are skipped (client/pacing.py). A rate
        above the daemon's loop rate is capped to it (a ``RuntimeWarning`` says so). A relative
        command (``_jr``, ``_cr``) moves by ``values`` in total, split over the samples sent. A
        command without an end (velocity, effort) ends with ``hold`` at ``duration``, so it
        stops then, not at the servo timeout. When the stream is cut short (a refused sample,
        ``KeyboardInterrupt``), ``hold`` is sent (best effort) before the exception goes on, unless
        the daemon refused the first sample (nothing of the stream runs).
        Raises :class:`CommandError` (``bad_request`` for a bad duration, rate or payload,
        before anything is sent)."""
        import numpy as np
        if cmd not in JOINT_STREAM_COMMANDS + POSE_STREAM_COMMANDS + DELTA_STREAM_COMMANDS + SIX_STREAM_COMMANDS:
            raise CommandError("bad_request", f"{self.name}: {cmd!r} is not a stream command (servo_*, "
                               "interpolate_*)")
        for what, value in (("duration", duration), ("rate_hz", rate_hz)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                    math.isfinite(value) and value > 0):
                raise CommandError("bad_request", f"{self.name}: {cmd} stream: {what} must be a finite "
                                   f"number > 0, got {value!r}")
        self._check_supported(cmd)
        loop = self._robot.loop_rate_hz
        if loop is not None and rate_hz > loop:
            warnings.warn(f"{self.name}: {cmd} stream at {rate_hz:g} Hz is above {self._robot.name}'s loop "
                          f"rate: sending at {loop:g} Hz", RuntimeWarning, stacklevel=2)
            rate_hz = loop
        if not math.isfinite(duration * rate_hz):
            raise CommandError("bad_request", f"{self.name}: {cmd} stream: {duration:g} s at {rate_hz:g} Hz is "
                               "more samples than can be counted: give a shorter duration")
        relative = cmd in RELATIVE_COMMANDS
        method = getattr(self, cmd)
        if cmd in JOINT_STREAM_COMMANDS:
            vec = np.asarray(self._vec(values, f"{cmd} stream"), dtype=float)

            def send(tick):
                method((vec * tick.reached - vec * tick.before).tolist() if relative else vec.tolist())
        elif cmd in SIX_STREAM_COMMANDS:
            a, b = ("linear", "angular") if cmd.endswith("_cv") else ("force", "torque")
            encode_six(values, a, b, f"{self._frame_ns(frame)}: {cmd}")  # refused before sending

            def send(tick):
                method(values, frame=frame)
        else:
            pose = encode_pose(values, f"{self.name}: {cmd}")

            def send(tick):
                method(pose_share(pose, tick.before, tick.reached) if relative else pose)
        endless = cmd in ENDLESS_COMMANDS
        pacing = Pacing(duration, rate_hz)
        held, samples = False, 0
        t0 = time.monotonic()
        try:
            for tick in pacing:
                if tick.final and endless:
                    self.hold()  # the end of a velocity or effort stream is a stop
                    held = True
                else:
                    send(tick)
                    samples += 1
        except BaseException as exc:
            # a first sample refused started nothing: a hold would stop another session's motion
            if not held and not (samples == 0 and isinstance(exc, CommandError)):
                try:
                    self.hold()
                except Exception:  # noqa: BLE001 - the first error is the one to report
                    pass
            raise
        return StreamReport(cmd, samples, float(rate_hz), time.monotonic() - t0, held)

    # -- cartesian space (docs/cartesian.md) -------------------------------------------------
    #
    # Poses are the tip frame in the base frame (``list`` -> ``cartesian``: ``base_frame``,
    # ``tip_frame``). crtk_python_client returns a PyKDL Frame; without PyKDL, the numpy
    # equivalent is a 4x4 homogeneous matrix (rotation block + translation in m), and the ``*_pq``
    # variants give ``(position [3] m, quaternion [4] x, y, z, w with w >= 0, ts)``. Twists are
    # ``[vx, vy, vz, wx, wy, wz]`` (m/s, rad/s), wrenches ``[fx, fy, fz, tx, ty, tz]`` (N, N·m),
    # of the tip frame's origin, in the ``spatial`` frame (base frame's axes, the default) or the
    # ``body`` frame (tip frame's axes; sent to the namespace ``<ns>/body``). Queries always
    # return arrays of their natural shape; ``ts == 0.0`` marks invalid data, and the arrays are
    # then NaN (never a silent identity). Each call is one round trip; a query or command this
    # namespace does not list raises :class:`CommandError` ``unsupported`` without sending.

    def _frame_ns(self, frame: str) -> str:
        if frame == "spatial":
            return self.name
        if frame == "body":
            return f"{self.name}/body"
        raise CommandError("bad_request", f"{self.name}: frame must be one of {', '.join(FRAMES)}, "
                           f"got {frame!r}")

    def _check_query(self, query: str) -> None:
        if not self.supports(query):
            have = ", ".join(q for q in self.info.get("queries") or () if q.endswith(
                ("_cp", "_cv", "_cf", "kinematics"))) or "none"
            raise CommandError("unsupported", f"{self.name}: {query} is not supported by this "
                               f"namespace (cartesian queries it lists: {have})")

    def _cartesian_query(self, query: str, frame: str = "spatial") -> dict:
        """The wire reply of a cartesian query (``measured_cp``, ``measured_cv``...), checked to
        be listed; ``frame`` picks ``<ns>`` or ``<ns>/body`` (twist and wrench queries only)."""
        self._check_query(query)
        ns = self._frame_ns(frame) if query in CV_TOPICS + CF_TOPICS else self.name
        return self._conn.request(query, ns)

    def _pose_query(self, query: str) -> tuple[np.ndarray, float]:
        return pose_from_wire(self._cartesian_query(query))

    def _pq_query(self, query: str) -> tuple[np.ndarray, np.ndarray, float]:
        return pq_from_wire(self._cartesian_query(query))

    def measured_cp(self) -> tuple[np.ndarray, float]:
        """``(pose, ts)``: the measured pose of the tip frame in the base frame (FK of the
        measured joints), a 4x4 homogeneous numpy matrix (translation in m); ``ts`` is the stamp of
        the joint sample it comes from. All NaN with ``ts == 0.0`` when invalid."""
        return self._pose_query("measured_cp")

    def measured_cp_pq(self) -> tuple[np.ndarray, np.ndarray, float]:
        """``(position [3] m, quaternion [4] x, y, z, w, ts)``: :meth:`measured_cp` as the
        daemon sends it (quaternion with ``w >= 0``)."""
        return self._pq_query("measured_cp")

    def setpoint_cp(self) -> tuple[np.ndarray, float]:
        """``(pose 4x4, ts)`` of the position setpoint (FK of ``setpoint_js``). Valid only while
        the active command is position based (servo/interpolate/move ``_jp``/``_cp``, relative
        commands, hold, integrated velocity commands); NaN with ``ts == 0.0`` otherwise."""
        return self._pose_query("setpoint_cp")

    def setpoint_cp_pq(self) -> tuple[np.ndarray, np.ndarray, float]:
        """:meth:`setpoint_cp` as ``(position [3], quaternion [4] xyzw, ts)``."""
        return self._pq_query("setpoint_cp")

    def goal_cp(self) -> tuple[np.ndarray, float]:
        """``(pose 4x4, ts)`` of the running or last interpolate / move goal; NaN with
        ``ts == 0.0`` when there is none."""
        return self._pose_query("goal_cp")

    def goal_cp_pq(self) -> tuple[np.ndarray, np.ndarray, float]:
        """:meth:`goal_cp` as ``(position [3], quaternion [4] xyzw, ts)``."""
        return self._pq_query("goal_cp")

    def measured_cv(self, frame: str = "spatial") -> tuple[np.ndarray, float]:
        """``(twist [6], ts)``: ``[vx, vy, vz]`` (m/s) and ``[wx, wy, wz]`` (rad/s) of the tip,
        in ``frame`` (``"spatial"``: base axes; ``"body"``: tip axes), from the measured joint
        velocities. NaN with ``ts == 0.0`` when invalid (the backend measures no velocity)."""
        return six_from_wire(self._cartesian_query("measured_cv", frame), "linear", "angular")

    def setpoint_cv(self, frame: str = "spatial") -> tuple[np.ndarray, float]:
        """``(twist [6], ts)`` of the setpoint (J × ``setpoint_js`` velocity), in ``frame``;
        valid when the setpoint has both position and velocity."""
        return six_from_wire(self._cartesian_query("setpoint_cv", frame), "linear", "angular")

    def goal_cv(self, frame: str = "spatial") -> tuple[np.ndarray, float]:
        """``(twist [6], ts)`` of the velocity goal of an ``interpolate_*v``, in ``frame``."""
        return six_from_wire(self._cartesian_query("goal_cv", frame), "linear", "angular")

    def measured_cf(self, frame: str = "spatial") -> tuple[np.ndarray, float]:
        """``(wrench [6], ts)``: ``[fx, fy, fz]`` (N) and ``[tx, ty, tz]`` (N·m) the tool exerts,
        in ``frame``, estimated from the measured joint efforts (gravity not compensated). Needs
        a backend that measures effort (else ``unsupported``)."""
        return six_from_wire(self._cartesian_query("measured_cf", frame), "force", "torque")

    def setpoint_cf(self, frame: str = "spatial") -> tuple[np.ndarray, float]:
        """``(wrench [6], ts)`` of the effort setpoint, in ``frame``. Needs effort control."""
        return six_from_wire(self._cartesian_query("setpoint_cf", frame), "force", "torque")

    def _cartesian_command(self, cmd: str, data: dict, ns: str | None = None) -> Any:
        return self._conn.request(cmd, ns or self.name, data)

    def _pose_command(self, cmd: str, pose) -> Any:
        self._check_supported(cmd)
        return self._cartesian_command(cmd, encode_pose(pose, f"{self.name}: {cmd}"))

    def servo_cp(self, pose) -> None:
        """Set the cartesian position setpoint: ``pose`` is the tip frame in the base frame, a
        4x4 homogeneous matrix (m) or a ``(position [3] m, quaternion [4] xyzw)`` pair. The
        daemon solves IK (seeded with the current setpoint) and sends ``servo_jp``; send
        continuously at about the loop rate. Blocks for the reply; raises
        :class:`CommandError` (``ik_failed`` for an unreachable pose, ``step_too_large``,
        ``invalid_state``, ``bad_request``...)."""
        self._pose_command("servo_cp", pose)

    def servo_cr(self, delta) -> None:
        """Move the setpoint by ``delta`` (4x4 or (position, quaternion)), in the base frame: the
        translation is added to the position, the rotation pre-multiplies the orientation
        (``R_new = R_delta · R``). Quick successive calls accumulate. Raises
        :class:`CommandError` like :meth:`servo_cp`."""
        self._pose_command("servo_cr", delta)

    def interpolate_cp(self, pose) -> None:
        """Set the cartesian goal of an interpolated stream (20-50 Hz), solved by IK into
        ``interpolate_jp``. Raises :class:`CommandError` like :meth:`servo_cp`."""
        self._pose_command("interpolate_cp", pose)

    def interpolate_cr(self, delta) -> None:
        """Like :meth:`interpolate_cp`, relative (base frame, as :meth:`servo_cr`) to the last
        interpolate goal, else to the setpoint."""
        self._pose_command("interpolate_cr", delta)

    def move_cp(self, pose) -> MoveHandle:
        """Move to ``pose`` (4x4 or (position, quaternion); the tip frame in the base frame): the
        daemon solves IK and runs a jerk-limited joint trajectory (the tip's path is not a
        straight line). Returns once accepted, with a :class:`MoveHandle` to wait on. Raises
        :class:`CommandError` when refused (``ik_failed`` for an unreachable pose, naming the
        residual; ``invalid_state``, ``not_homed``, ``out_of_limits``...), so there is never a
        handle to wait on in vain."""
        self._check_supported("move_cp")
        return self._start_move("move_cp", encode_pose(pose, f"{self.name}: move_cp"))

    def move_cr(self, delta) -> MoveHandle:
        """Like :meth:`move_cp` with a goal relative (base frame, as :meth:`servo_cr`) to the
        running move's goal, else to the setpoint."""
        self._check_supported("move_cr")
        return self._start_move("move_cr", encode_pose(delta, f"{self.name}: move_cr"))

    def _six_command(self, cmd: str, values, frame: str, a: str, b: str) -> None:
        self._check_supported(cmd)
        ns = self._frame_ns(frame)
        self._cartesian_command(cmd, encode_six(values, a, b, f"{ns}: {cmd}"), ns)

    def servo_cv(self, twist, frame: str = "spatial") -> None:
        """Set the cartesian velocity setpoint ``twist`` = ``[vx, vy, vz, wx, wy, wz]`` (m/s,
        rad/s) of the tip, in ``frame`` (``"spatial"``: base axes; ``"body"``: tip axes, sent to
        ``<ns>/body``). Becomes ``servo_jv`` of the damped least-squares J⁺·twist (a 5-joint arm
        cannot follow every twist exactly). Send continuously: a silent stream holds after the
        servo timeout. Raises :class:`CommandError`."""
        self._six_command("servo_cv", twist, frame, "linear", "angular")

    def interpolate_cv(self, twist, frame: str = "spatial") -> None:
        """Set the cartesian velocity goal (``interpolate_jv`` of J⁺·twist), in ``frame``."""
        self._six_command("interpolate_cv", twist, frame, "linear", "angular")

    def servo_cf(self, wrench, frame: str = "spatial") -> None:
        """Set the wrench setpoint ``[fx, fy, fz, tx, ty, tz]`` (N, N·m) at the tip, in ``frame``
        (``servo_jf`` of Jᵀ·wrench). Needs effort control (else ``unsupported``, locally)."""
        self._six_command("servo_cf", wrench, frame, "force", "torque")

    def interpolate_cf(self, wrench, frame: str = "spatial") -> None:
        """Set the wrench goal (``interpolate_jf`` of Jᵀ·wrench), in ``frame``. Needs effort
        control."""
        self._six_command("interpolate_cf", wrench, frame, "force", "torque")

    def forward_kinematics(self, jp) -> np.ndarray:
        """The pose (4x4 homogeneous matrix, m) of the tip frame in the base frame for joint
        positions ``jp`` (rad, one per joint). Pure computation: valid in every state. Raises
        :class:`CommandError` (``bad_request`` for a wrong length, ``unsupported`` without
        kinematics). Unlike crtk_python_client there is no ``extra=``: errors raise."""
        self._check_query("forward_kinematics")
        data = self._cartesian_command("forward_kinematics", {"jp": self._vec(jp, "forward_kinematics jp")})
        return pose_from_wire(data)[0]

    def inverse_kinematics(self, pose, jp_seed=None) -> tuple[np.ndarray, bool, str]:
        """Solve IK for ``pose`` (4x4 or (position, quaternion); tip in base frame), starting
        from ``jp_seed`` (rad; default: the measured joints). Returns ``(jp, ok, message)``:
        ``ok`` False (with ``jp`` the best found and a message naming the residuals) when the
        pose is not reachable within the profile's IK tolerances; nothing raises for that. The
        argument order differs from crtk_python_client's ``inverse_kinematics(jp, cp)``: the
        seed is optional here. Raises :class:`CommandError` for a malformed request."""
        import numpy as np
        self._check_query("inverse_kinematics")
        data = encode_pose(pose, f"{self.name}: inverse_kinematics")
        if jp_seed is not None:
            data["jp"] = self._vec(jp_seed, "inverse_kinematics seed")
        reply = self._cartesian_command("inverse_kinematics", data)
        return (np.asarray(reply.get("jp") or (), dtype=float), bool(reply.get("result")),
                str(reply.get("message") or ""))

    # -- events --------------------------------------------------------------------------------

    def wait_for_event(self, code: str | None = None, timeout: float = 5.0,
                       kind: str | None = None, since: int | None = None) -> Event | None:
        """Wait up to ``timeout`` s for a status/warning/error event about this namespace (or the
        whole robot) with ``code`` (any if None) and ``kind``; return it, or None on timeout.
        Only events arriving after the call count, unless ``since`` (an
        :attr:`Connection.event_count` taken earlier) says from where to look."""
        return self._robot.wait_for_event(code, timeout, kind=kind, since=since, ns=self.name)

    # -- streams -------------------------------------------------------------------------------

    def subscribe(self, topic: str, rate_hz: float,
                  callback: Callable[[dict], None] | None = None,
                  maxsize: int = 1000, frame: str = "spatial") -> Subscription:
        """Stream ``topic`` (``measured_js``, ``setpoint_js``, ``goal_js``, ``operating_state``,
        ``period_statistics``, and the cartesian queries the namespace lists: ``measured_cp``,
        ``measured_cv``...) at up to ``rate_hz`` (capped at the loop rate). ``frame``
        (``"spatial"`` / ``"body"``) applies to twist and wrench topics. Returns a
        :class:`Subscription`; frames are the wire ``data`` dicts (``joint_state(frame)``,
        ``pose_from_wire(frame)`` turn them into arrays). Raises :class:`CommandError` for an
        unknown topic."""
        if topic in CARTESIAN_TOPICS:
            self._check_query(topic)
            ns = self._frame_ns(frame) if topic in CV_TOPICS + CF_TOPICS else self.name
            return Subscription(self._conn, topic, rate_hz, ns, callback, maxsize)
        ns = None if topic in ROBOT_TOPICS else self.name
        return Subscription(self._conn, topic, rate_hz, ns, callback, maxsize)


class Robot:
    """A connected robot: its ``list`` info and one :class:`Device` per namespace.

    ``robot.device("so101")`` or ``robot["so101"]``; ``robot.device()`` is the default device
    (the first namespace), and attributes not found on the robot are looked up on it, so
    ``robot.measured_js()`` works. A context manager; :meth:`close` closes the connection.
    """

    def __init__(self, connection: Connection, info: dict):
        self.connection = connection
        self.info = info
        self.name: str = str(info.get("robot", ""))
        self.protocol_version = info.get("protocol_version")
        self.daemon_version = info.get("daemon_version")
        self._ns_info = {e["name"]: e for e in info.get("namespaces", [])}
        self.namespaces: list[str] = list(self._ns_info)
        self._devices: dict[str, Device] = {}
        self._lock = threading.Lock()

    def __repr__(self) -> str:
        return f"Robot({self.name!r}, namespaces={self.namespaces}, socket={self.connection.path!r})"

    def device(self, name: str | None = None) -> Device:
        """The :class:`Device` of namespace ``name`` (default: the first). Raises ``KeyError``
        listing the namespaces when there is no such namespace."""
        if name is None:
            if not self.namespaces:
                raise KeyError(f"robot {self.name!r} lists no namespace")
            name = self.namespaces[0]
        with self._lock:
            dev = self._devices.get(name)
            if dev is None:
                if name not in self._ns_info:
                    base, _, frame = name.rpartition("/")
                    hint = ""
                    if frame in FRAMES and base in self._ns_info:
                        hint = (f"; {frame} is a frame of {base}'s twists and wrenches: use {base} with "
                                f"frame={frame!r} (docs/cartesian.md)")
                    raise KeyError(f"robot {self.name!r} has no namespace {name!r} "
                                   f"(namespaces: {', '.join(self.namespaces)}){hint}")
                dev = self._devices[name] = Device(self, name, self._ns_info[name])
            return dev

    def __getitem__(self, name: str) -> Device:
        return self.device(name)

    @property
    def loop_rate_hz(self) -> float | None:
        """The daemon's control loop rate (Hz) from ``list``, or None when it does not say."""
        rate = self.info.get("rate_hz")
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not (
                math.isfinite(rate) and rate > 0):
            return None
        return float(rate)

    def __getattr__(self, attr: str):
        if attr.startswith("_"):
            raise AttributeError(attr)
        if attr in self._ns_info:
            return self.device(attr)
        if not self.namespaces:
            raise AttributeError(f"Robot {self.name!r} has no attribute {attr!r} (and no namespace)")
        return getattr(self.device(), attr)

    def list(self) -> dict:
        """The daemon's ``list`` reply, asked afresh."""
        return self.connection.request("list")

    def period_statistics(self) -> dict:
        """The control loop's timing: ``rate_hz``, ``period_s``, lateness and compute
        percentiles (s), ``overruns``, ``cycles``."""
        return self.connection.request("period_statistics")

    def calibrate(self, action: str, timeout: float | None = None, **data: Any) -> Any:
        """``calibrate`` (docs/calibration.md, docs/protocol.md): ``begin`` a sweep by hand from
        the middle pose, ``status`` (``{"seen": {joint: [lowest, highest, now]}}``, rad from the
        middle pose), ``end`` (``grippers=[...]``: ``{"calibration": {joint: keys}}``),
        ``cancel``; the robot must be DISABLED. ``import`` (``format="lerobot"``, ``file={...}``,
        ``grippers=[...]``) converts another tool's calibration file, in any state. Returns the
        reply's data; takes control. Raises :class:`CommandError` (``invalid_state`` when not
        DISABLED, naming the state)."""
        return self.connection.request("calibrate", None, {"action": action, **data}, timeout=timeout)

    def record(self, path: str, duration_s: float | None = None, namespaces: list[str] | None = None) -> dict:
        """Start recording every control cycle into the rosbag2 MCAP bag ``path`` (``run1.mcap``
        or ``run1`` -> ``run1/run1.mcap``), written by the daemon on its machine (a relative path
        is made absolute here). Returns ``{"recording", "path", "bag"}`` once the file is open;
        the recording runs until :meth:`record_stop`, its ``duration_s``, or this connection's
        end (docs/recording.md). Takes no control."""
        data: dict[str, Any] = {"path": os.path.abspath(os.path.expanduser(path))}
        if duration_s is not None:
            data["duration_s"] = duration_s
        if namespaces:
            data["namespaces"] = list(namespaces)
        return self.connection.request("record", None, data)

    def record_stop(self, recording: int | None = None, wait: bool = False, timeout: float | None = None) -> dict:
        """Stop a recording (default: this connection's latest) and return its result once the bag
        is closed: ``path``, ``samples``, ``first_cycle``, ``last_cycle``, ``lost``, ``bytes``...
        ``wait=True``: a recording with a duration runs to its end first."""
        data: dict[str, Any] = {"wait": wait}
        if recording is not None:
            data["recording"] = recording
        return self.connection.request("record_stop", None, data, timeout=timeout)

    def blackbox(self, path: str, timeout: float | None = None) -> dict:
        """Write the black box (the last ``recording.blackbox_s`` seconds of every cycle) to the
        bag ``path`` now; returns ``{"path", "samples", "seconds", ...}``."""
        return self.connection.request("blackbox", None, {"path": os.path.abspath(os.path.expanduser(path))},
                                       timeout=timeout)

    def acquire(self) -> None:
        """Take control explicitly; raises :class:`CommandError` ``read_only`` if another
        session holds it."""
        self.connection.request("acquire")

    def release(self) -> None:
        """Give control up (disconnecting does too)."""
        self.connection.request("release")

    @property
    def events(self):
        """The last status/warning/error events (a deque of :class:`Event`)."""
        return self.connection.events

    def wait_for_event(self, code: str | None = None, timeout: float = 5.0, *,
                       kind: str | None = None, since: int | None = None,
                       ns: str | None = None) -> Event | None:
        """Wait up to ``timeout`` s for a status/warning/error event with ``code`` (any if None),
        of ``kind`` (``"error"``, ``"warning"``, ``"status"``; any if None) and, if ``ns`` is
        given, about that namespace or the whole robot. Returns the first match, or None on
        timeout. Only events arriving after the call count, unless ``since`` (a value of
        :attr:`Connection.event_count` taken earlier, e.g. before sending a command) says from
        where to look. Raises :class:`DaemonConnectionError` if the daemon goes away."""
        conn = self.connection
        start = conn.event_count if since is None else since
        found: list[Event] = []

        def match(c: Connection) -> bool:
            for e in c.events_since(start):
                if _event_matches(e, kind, code, ns, self.name):
                    found.append(e)
                    return True
            return False

        conn.wait_for(match, max(0.0, timeout))
        return found[0] if found else None

    def close(self) -> None:
        self.connection.close()

    def __enter__(self) -> "Robot":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _event_matches(ev: Event, kind: str | None, code: str | None, ns: str | None, robot: str) -> bool:
    if kind is not None and ev.kind != kind:
        return False
    if code is not None and ev.data.get("code") != code:
        return False
    if ns is not None and ev.data.get("ns") not in (ns, robot, None):
        return False
    return True


def _check_timeout(timeout: Any) -> float:
    """``timeout`` of :func:`connect` / :func:`list_robots`: a finite number of seconds > 0, else
    CrtkBridgeError naming it (a negative one hung a Zenoh connect for ever; inf and NaN escaped
    as OverflowError / ValueError from deep inside)."""
    if isinstance(timeout, bool) or not isinstance(timeout, numbers.Real) or not (
            math.isfinite(timeout) and timeout > 0):
        raise CrtkBridgeError(f"crtk-bridge client: timeout: must be a finite number of seconds > 0, "
                              f"got {timeout!r}")
    return float(timeout)


def list_robots(zenoh_connect: str | list[str] | None = None, timeout: float = 5.0,
                zenoh_config: str | None = None, zenoh_lease_ms: int | None = None) -> list[str]:
    """The robots a client can reach, sorted: those with a socket in the default directory (see
    :func:`~crtk_client.paths.find_sockets`), or with ``zenoh_connect``, those whose
    daemons serve on the Zenoh network there (raises :class:`DaemonConnectionError` when the
    endpoint does not answer; ``zenoh_config`` and ``zenoh_lease_ms`` as for :func:`connect`)."""
    timeout = _check_timeout(timeout)
    if zenoh_connect:
        from crtk_client.zenoh_link import list_robots as on_zenoh

        return on_zenoh(zenoh_connect, timeout, zenoh_config, zenoh_lease_ms)
    return sorted(os.path.basename(p)[:-len(".sock")] for p in find_sockets())


def resolve_socket(socket: str | None = None, robot: str | None = None) -> str:
    """The socket path to use: ``socket`` if given, else the default path of ``robot`` (or its
    path under the systemd unit when only that exists), else the
    only ``*.sock`` in the default directory (see :func:`~crtk_client.paths.find_sockets`).
    Raises :class:`DaemonConnectionError` when none or several are found (listing them)."""
    if socket:
        return str(socket)
    if robot:
        path = default_socket_path(robot)
        system = os.path.join(SYSTEM_SOCKET_DIR, f"{robot}.sock")
        if not os.path.exists(path) and os.path.exists(system):
            return system  # the daemon runs under the systemd unit
        return path
    found = find_sockets()
    if len(found) == 1:
        return found[0]
    if not found:
        raise DaemonConnectionError(
            f"crtk-bridge daemon not running: no *.sock in {default_socket_dir()} "
            "(start crtk-bridge, or give --socket PATH / --robot NAME)")
    raise DaemonConnectionError(
        "several crtk-bridge sockets, choose one with --socket or --robot: " + ", ".join(found))


def connect(socket: str | None = None, robot: str | None = None,
            timeout: float = 5.0, zenoh_connect: str | list[str] | None = None,
            zenoh_config: str | None = None, zenoh_lease_ms: int | None = None) -> Robot:
    """Connect to a crtk-bridge daemon and return its :class:`Robot`.

    ``socket``: a socket path; else ``robot``: a robot name, at its default path; else the only
    socket in the default directory. ``zenoh_connect``: instead of a socket, the Zenoh router or
    peer to join (an endpoint such as ``tcp/127.0.0.1:7447``, or several); ``robot`` chooses the
    daemon there (default: the only one); ``zenoh_config``: a Zenoh configuration file (JSON5) for
    what the endpoint needs, e.g. TLS certificates; ``zenoh_lease_ms``: this client's Zenoh link
    lease (default 2000 ms: the daemon notices a frozen client within it; docs/zenoh.md, "Lease").
    ``timeout`` (s): default reply timeout. Blocks for one ``list`` round trip. Raises
    :class:`DaemonConnectionError` (a ``ConnectionError`` naming the path or endpoint) if no daemon answers there,
    :class:`CrtkBridgeError` on a protocol version mismatch or a ``timeout`` that is not a finite
    number > 0.
    """
    timeout = _check_timeout(timeout)
    if zenoh_connect:
        if socket:
            raise CrtkBridgeError("give a socket path or a Zenoh endpoint (zenoh_connect), not both")
        from crtk_client.zenoh_link import open_stream

        stream = open_stream(zenoh_connect, robot, timeout, zenoh_config, zenoh_lease_ms)
        conn = Connection(stream.name, timeout=timeout, stream=stream)
    else:
        conn = Connection(resolve_socket(socket, robot), timeout=timeout)
    try:
        info = conn.request("list")
        version = info.get("protocol_version")
        if version is not None and version != PROTOCOL_VERSION:
            raise CrtkBridgeError(
                f"crtk-bridge at {conn.path} speaks protocol version {version}, this client "
                f"speaks {PROTOCOL_VERSION}: upgrade the older side")
        return Robot(conn, info)
    except BaseException:
        conn.close()
        raise

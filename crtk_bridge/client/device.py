"""CRTK devices over a :class:`~crtk_bridge.client.connection.Connection`, with the names and
return conventions of crtk_python_client 1.4 (``measured_js() -> (p, v, e, ts)``, ``enable(t) ->
bool``, ``move_jp(goal) -> handle``; ``handle.wait() -> bool``).

Differences from crtk_python_client, on purpose (reference/crtk-anchors.md section 4):

- a refused command raises :class:`~crtk_bridge.errors.CommandError` with the daemon's code and
  message instead of being dropped silently; so ``MoveHandle.wait()`` can never hang on a rejected
  move (the move raised already);
- move completion uses the daemon's ``busy_seq`` counter, not clocks: a wait can neither return
  on a stale idle state nor depend on clock skew;
- queries are answered by the daemon on request (one round trip), so they are never stale;
  ``ts == 0.0`` still means the data is invalid (CRTK 4.1.2.3) and the caller must check it;
- ``pause()``, ``resume()``, ``is_paused()`` and ``is_fault()`` exist (CRTK 3.4).

Units are SI: rad, rad/s, N·m, s; stamps in seconds since the Unix epoch.
"""

from __future__ import annotations

import os
import queue
import threading
from typing import Any, Callable, Iterator

import numpy as np

from crtk_bridge.client.connection import (
    PROTOCOL_VERSION, Connection, DaemonConnectionError, Event, encode_vector)
from crtk_bridge.client.paths import (
    SYSTEM_SOCKET_DIR, default_socket_dir, default_socket_path, find_sockets)
from crtk_bridge.errors import CommandError, CrtkBridgeError

#: Topics and queries that are robot-wide (sent without ``ns``).
ROBOT_TOPICS = frozenset({"operating_state", "period_statistics"})
#: Per-namespace joint-state topics and queries.
JS_TOPICS = ("measured_js", "setpoint_js", "goal_js")
STATES = ("DISABLED", "ENABLED", "PAUSED", "FAULT")


def joint_state(data: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A wire JointState as ``(position, velocity, effort, ts)``: float64 arrays (empty when the
    robot does not provide that vector) and the stamp in s (``0.0``: invalid data)."""
    return (np.asarray(data.get("position") or (), dtype=float),
            np.asarray(data.get("velocity") or (), dtype=float),
            np.asarray(data.get("effort") or (), dtype=float),
            float(data.get("stamp") or 0.0))


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
        """True if ``cmd`` is in this namespace's ``commands`` of ``list`` (as of connecting).
        A daemon that lists no commands is assumed to support everything."""
        commands = self.info.get("commands")
        return commands is None or cmd in commands

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
        seq_before = self._conn.max_busy_seq
        reply = self._req(cmd, {"position": self._vec(goal, f"{cmd} position")})
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
                  maxsize: int = 1000) -> Subscription:
        """Stream ``topic`` (``measured_js``, ``setpoint_js``, ``goal_js``, ``operating_state``,
        ``period_statistics``) at up to ``rate_hz`` (capped at the loop rate). Returns a
        :class:`Subscription`; frames are the wire ``data`` dicts (``joint_state(frame)`` turns a
        JointState into arrays). Raises :class:`CommandError` for an unknown topic."""
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
                    raise KeyError(f"robot {self.name!r} has no namespace {name!r} "
                                   f"(namespaces: {', '.join(self.namespaces)})")
                dev = self._devices[name] = Device(self, name, self._ns_info[name])
            return dev

    def __getitem__(self, name: str) -> Device:
        return self.device(name)

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


def resolve_socket(socket: str | None = None, robot: str | None = None) -> str:
    """The socket path to use: ``socket`` if given, else the default path of ``robot`` (or its
    path under the systemd unit when only that exists), else the
    only ``*.sock`` in the default directory (see :func:`~crtk_bridge.client.paths.find_sockets`).
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
            timeout: float = 5.0) -> Robot:
    """Connect to a crtk-bridge daemon and return its :class:`Robot`.

    ``socket``: a socket path; else ``robot``: a robot name, at its default path; else the only
    socket in the default directory. ``timeout`` (s): default reply timeout. Blocks for one
    ``list`` round trip. Raises :class:`DaemonConnectionError` (a ``ConnectionError`` naming the
    path) if no daemon answers there, :class:`CrtkBridgeError` on a protocol version mismatch.
    """
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

"""The socket server: sessions, control ownership, queries, subscriptions, event fan-out.

Runs in the front process (asyncio). See docs/protocol.md for the wire protocol.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import os
import socket
import struct
import time
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import CrtkBridgeError
from ..profile import joint_bus_id
from .cartesian import FRAMED, CartesianSpace
from .link import ControlLink, ControlLost
from .protocol import (
    JOINT_QUERIES, JOINT_VECTORS, MAX_LINE, PAYLOADS, PROTOCOL_VERSION, RECORDING_COMMANDS, ROBOT_QUERIES,
    SESSION_COMMANDS,
    STATE_COMMANDS, STOP_COMMANDS, TOPICS, MaintenanceCommand, ProtocolError, decode_payload, decode_request, encode,
    error, ok,
)
from .streams import Subscriber, TopicStream, tick_all

log = logging.getLogger("crtk_bridge.server")

#: a session's unsent bytes above which stream frames are dropped (replies and events never are)
SEND_BUFFER_LIMIT = 256 * 1024
#: connections waiting to be accepted; beyond it a client's non-blocking connect fails (EAGAIN)
BACKLOG = 1024


class Session:
    """One client session: a socket connection, or a remote client over Zenoh (transport/tunnel.py
    subclasses it; the server's control rules, streams and client-loss handling are the same)."""

    def __init__(self, sid: int, writer: asyncio.StreamWriter | None, peer: str | None = None):
        self.id = sid
        self.writer = writer
        self.subs: dict[int, Subscriber] = {}
        self.dropped = 0  # stream frames dropped (period_statistics' frames_dropped adds them up)
        self._drop_said = -1.0
        self.closed = False
        self.peer = _peer(writer) if peer is None else peer

    def describe(self) -> str:
        """Who this session is, for refusals: ``session 3 (pid 1234 python3, uid 1000)``."""
        return f"session {self.id} ({self.peer})" if self.peer else f"session {self.id}"

    def send(self, msg: Any) -> None:
        if not self.closed:
            self.writer.write(encode(msg))

    def send_frame(self, line: bytes) -> None:
        """A stream frame (a JSON line, encoded once for every subscriber of its topic:
        server/streams.py): dropped, and counted, while the client is not reading fast enough."""
        if self.closed:
            return
        if self.writer.transport.get_write_buffer_size() > SEND_BUFFER_LIMIT:
            self.count_dropped()
            return
        self.writer.write(line)

    def flush(self) -> None:
        """The stream frames of a tick are all sent (a socket writes each at once)."""

    def count_dropped(self, n: int = 1) -> None:
        """``n`` stream frames were dropped: counted, and said in the log at most once a second."""
        self.dropped += n
        now = time.monotonic()
        if now - self._drop_said >= 1.0:
            self._drop_said = now
            log.warning("%s: %d stream frames dropped so far: it reads slower than its subscriptions send "
                        "(period_statistics' frames_dropped counts every session's)", self.describe(), self.dropped)

    def close(self) -> None:
        self.closed = True
        self.writer.close()


class Server:
    def __init__(self, link: ControlLink, commands: list[str], socket_path: str):
        self.link = link
        self.profile = link.profile
        self.robot = self.profile.name
        self.commands = commands  # motion and state commands the control process supports
        self.cartesian: dict[str, CartesianSpace] = {
            ns.name: self.cartesian_space(ns.name) for ns in self.profile.namespaces if ns.kinematics is not None
        }
        self.socket_path = socket_path
        self.sessions: dict[int, Session] = {}
        self._streams: dict[tuple[str, str | None], TopicStream] = {}  # (topic, ns) -> its subscribers
        self._streams_task: asyncio.Task | None = None  # ticks every stream (_run_streams)
        self._streams_wake: asyncio.Future | None = None  # _run_streams' sleep; a new subscriber ends it
        self._dropped_before = 0  # stream frames dropped by sessions that ended
        #: callables adding figures to period_statistics (the ROS graph's skipped ticks)
        self.statistics: list = []
        self.controller: Session | None = None
        self.state: dict = {"state": "DISABLED", "is_homed": False, "is_busy": False, "busy_seq": 0, "stamp": 0.0}
        self.last_error: dict | None = None  # the latest error event: the reason of a FAULT
        self._sids = itertools.count(1)
        self._subids = itertools.count(1)
        self._server: asyncio.base_events.Server | None = None
        self.control_lost = asyncio.Event()
        self.shutting_down = False  # set before the control process is asked to stop
        #: callables given every event the sessions get (operating_state, error, warning, status),
        #: on the event loop: other transports (the ROS 2 graph) follow the robot through them
        self.listeners: list = []
        #: callables given every valid request (session, cmd, ns, data) before it is handled, and
        #: every session that ends: the recorder (recording/recorder.py) logs the commands
        self.command_listeners: list = []
        self.detach_listeners: list = []
        #: serves record / record_stop / blackbox (recording/recorder.py); None: not offered
        self.recorder = None
        #: every command and query this daemon knows (data typed by protocol.PAYLOADS, else none)
        self._known = set(self.commands) | set(TOPICS) | set(SESSION_COMMANDS) | set(MaintenanceCommand) | {
            c for cs in self.cartesian.values() for c in cs.commands + cs.queries} | set(RECORDING_COMMANDS)

    def cartesian_space(self, ns: str) -> CartesianSpace:
        """A new CartesianSpace of kinematic namespace ``ns``, with its own pinocchio data (a
        thread other than the event loop's computing cartesian data needs its own)."""
        link = self.link
        return CartesianSpace(self.profile, ns, self.profile.namespace(ns).kinematics, link.ns_commands[ns],
                              link.ns_measures_effort[ns], native=ns in link.native_cartesian,
                              measures_wrench=link.ns_measures_wrench[ns])

    # ---------------------------------------------------------------- events from the loop
    def on_event(self, msg: dict) -> None:
        ev = msg.get("event")
        if ev == "operating_state":
            self.state = msg["data"]
        elif ev in ("error", "warning", "status"):
            d = msg["data"]
            if ev == "error":
                self.last_error = msg  # told again to a session that joins while in FAULT (attach)
            level = {"error": logging.ERROR, "warning": logging.WARNING}.get(ev, logging.INFO)
            log.log(level, "%s [%s] %s", ev, d.get("code"), d.get("message"))
        for s in list(self.sessions.values()):
            s.send(msg)
        for listener in self.listeners:
            try:
                listener(msg)
            except Exception:
                log.exception("%s: an event listener failed", self.robot)

    def on_control_lost(self) -> None:
        """The control process died: every client learns FAULT; the daemon exits non-zero."""
        if self.shutting_down:
            return
        now = time.time()  # the control process, whose clock stamps events, is gone
        self.state = dict(self.state, state="FAULT", is_busy=False, stamp=now)
        msg = {"event": "error", "data": {"stamp": now, "ns": self.robot, "code": "control_process_died",
                                          "message": f"{self.robot}: the control process stopped; daemon exiting"}}
        self.on_event({"event": "operating_state", "data": self.state})
        self.on_event(msg)
        self.control_lost.set()

    # ---------------------------------------------------------------- serving
    async def start(self) -> None:
        path = Path(self.socket_path)
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o750)
        if path.exists() or path.is_symlink():
            # a stale socket from a crashed daemon, unless one still answers there
            try:
                r, w = await asyncio.open_unix_connection(str(path))
                w.close()
                raise CrtkBridgeError(f"{self.robot}: another daemon is already serving {path}")
            except (ConnectionRefusedError, FileNotFoundError):
                path.unlink()
        # bind under a temporary name and rename: the socket file appears only once it listens,
        # so a client that sees the file never gets "connection refused"
        tmp = path.with_name(f".{path.name}.{os.getpid()}")
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        old = os.umask(0o117)  # socket file mode 0660
        try:
            self._server = await asyncio.start_unix_server(self._session, path=str(tmp), limit=MAX_LINE,
                                                           backlog=BACKLOG)
        finally:
            os.umask(old)
        os.chmod(tmp, 0o660)
        os.rename(tmp, path)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            for s in list(self.sessions.values()):
                s.close()
            try:
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
            except (asyncio.TimeoutError, Exception):
                pass
        for cs in self.cartesian.values():
            cs.close()
        try:
            os.unlink(self.socket_path)
        except FileNotFoundError:
            pass

    def new_session_id(self) -> int:
        return next(self._sids)

    def attach(self, s: Session) -> None:
        """Serve a new session: it gets the current operating_state at once, and in FAULT the error
        event that caused it (docs/protocol.md)."""
        self.sessions[s.id] = s
        s.send({"event": "operating_state", "data": self.state})
        if self.state.get("state") == "FAULT" and self.last_error is not None:
            s.send(self.last_error)

    def detach(self, s: Session, client_lost: bool = True) -> None:
        """A session ended (its socket closed, a remote client's liveliness token went away): its
        streams stop and, if it held control, the control process hears of the client loss (the
        robot stops safely: docs/protocol.md, Client loss). ``client_lost=False`` while the
        daemon shuts down (the control process is stopping the robot already)."""
        s.closed = True
        for t in s.subs.values():
            t.cancel()
        if self.sessions.pop(s.id, None) is not None:
            self._dropped_before += s.dropped
        for listener in self.detach_listeners:
            try:
                listener(s)
            except Exception:
                log.exception("%s: a session listener failed", self.robot)
        if self.controller is s:
            self.controller = None
            if client_lost:
                self.link.send_nowait("_client_lost")

    async def _session(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        s = Session(self.new_session_id(), writer)
        self.attach(s)
        try:
            while True:
                try:
                    line = await reader.readuntil(b"\n")
                except asyncio.LimitOverrunError:
                    s.send(error(None, "bad_request", f"request line longer than {MAX_LINE} bytes; discarded"))
                    await _discard_line(reader)
                    continue
                except (asyncio.IncompleteReadError, ConnectionError):
                    break  # closed; a last line without its newline is not a request
                if line.strip():  # blank lines are ignored (no reply)
                    await self.handle_line(s, line)
                if writer.transport.get_write_buffer_size() > 4 * SEND_BUFFER_LIMIT:
                    await writer.drain()  # replies pile up: the client is not reading
        finally:
            self.detach(s)
            writer.close()

    async def handle_line(self, s: Session, line: bytes) -> None:
        """One request line of session ``s``; its reply (and any error) goes to ``s``. A session's
        lines are handled one at a time, in order."""
        rid = None  # the reply's id: null until the envelope (id, cmd, ns) is valid
        try:
            req = decode_request(line)
            rid = req.id
            data = self._payload(req)
            for listener in self.command_listeners:
                try:
                    listener(s, req.cmd, req.ns, data)
                except Exception:
                    log.exception("%s: a command listener failed", self.robot)
            result = await self._dispatch(s, rid, req.cmd, req.ns, data)
            if result is not _SENT:
                s.send(ok(rid, result))
        except ProtocolError as exc:
            s.send(error(exc.rid if exc.rid is not None else rid, exc.code, str(exc)))
        except ControlLost:
            s.send(error(rid, "internal", f"{self.robot}: the control process is not running"))
        except asyncio.TimeoutError:
            s.send(error(rid, "internal", f"{self.robot}: the control process did not answer"))

    def _payload(self, req: Any) -> dict:
        """The typed payload of a request (docs/protocol.md, Payloads); joint vectors have one
        entry per joint of the namespace. Nothing ill-typed goes further."""
        if req.cmd not in PAYLOADS and req.cmd not in self._known:
            return {}  # unknown command: refused by _dispatch, its data never looked at
        who = req.ns or self.robot
        data = decode_payload(req, who)
        joints = self.link.ns_names.get(req.ns) if req.cmd in JOINT_VECTORS else None
        if joints is not None:
            for field, values in data.items():
                if len(values) != len(joints):
                    raise ProtocolError("bad_request", f"{who}: {req.cmd} refused: Expected `array` of {len(joints)} "
                                        f"numbers ({', '.join(joints)}), got {len(values)} - at `data.{field}`",
                                        req.id)
        return data

    def _check_ns(self, cmd: str, ns: str | None, required: bool) -> str | None:
        if ns is None:
            if required:
                raise ProtocolError("bad_request", f"{self.robot}: {cmd} needs a namespace 'ns' "
                                    f"(one of: {', '.join(self.link.ns_index)})")
            return None
        if ns not in self.link.ns_index:
            raise ProtocolError("unknown_namespace",
                                f"{self.robot}: unknown namespace {ns!r} (have: {', '.join(self.link.ns_index)})")
        return ns

    def _frame(self, cmd: str, ns: str | None) -> tuple[str | None, str]:
        """``so101/body`` -> (``so101``, "body") for commands and queries whose frame differs."""
        if ns:
            base, _, last = ns.rpartition("/")
            if last in ("body", "spatial") and base in self.cartesian:
                if cmd not in FRAMED:
                    raise ProtocolError("unsupported", f"{ns}: {cmd} is not available in the {last}/ namespace "
                                        f"(only {', '.join(FRAMED)})")
                return base, last
        return ns, "spatial"

    async def _dispatch(self, s: Session, rid: int, cmd: str, ns: str | None, data: Any) -> Any:
        # a subscription's frame is its topic's (_subscribe: ``so101/body`` for measured_cv), not the command's
        ns, frame = (ns, "spatial") if cmd == "subscribe" else self._frame(cmd, ns)
        cs = self.cartesian.get(ns) if ns else None
        if cs is not None and (cmd in cs.queries or cmd in cs.commands):
            if cmd == "forward_kinematics":
                return cs.forward_kinematics(data)
            if cmd == "inverse_kinematics":
                return await cs.inverse_kinematics(data, self.link.ns_arrays(ns))  # IK off the loop
            if cmd in cs.queries:
                return cs.query(cmd, self.link.ns_arrays(ns), frame)
            self._take_control(s, cmd)
            cmd, data = await cs.translate(cmd, data, self.link.ns_arrays(ns), frame, self.state.get("is_busy", False))
            return await self._forward(s, rid, cmd, ns, data)
        if cmd in JOINT_QUERIES:
            return self.link.joint_state(cmd, self._check_ns(cmd, ns, True))
        if cmd == "operating_state":
            return self.state
        if cmd == "period_statistics":
            return self.period_statistics()
        if cmd == "list":
            return self.describe()
        if cmd == "subscribe":
            return self._subscribe(s, ns, data)
        if cmd == "unsubscribe":
            sub = data["sub"]
            task = s.subs.pop(sub, None)
            if task is None:
                raise ProtocolError("bad_request", f"no subscription {sub!r} in this session")
            task.cancel()
            return None
        if cmd == "acquire":
            self._take_control(s, cmd)
            return None
        if cmd == "release":
            if self.controller is s:
                self.controller = None
            return None
        if cmd in RECORDING_COMMANDS:  # served by the front process; takes nobody's control
            if self.recorder is None:
                raise ProtocolError("unsupported", f"{self.robot}: {cmd}: recording is not available in this daemon")
            return await self.recorder.request(s, cmd, data)
        if cmd == MaintenanceCommand.CALIBRATE:  # robot-wide; the control process checks the state
            self._take_control(s, cmd)
            return await self._forward(s, rid, cmd, None, data)
        if cmd not in self.commands:
            if _is_crtk_command(cmd) and cmd not in self._known:
                raise ProtocolError("unsupported", f"{ns or self.robot}: {cmd} is not supported by this robot")
            raise ProtocolError("unknown_command", f"{self.robot}: unknown command {cmd!r}")
        self._check_ns(cmd, ns, cmd not in STATE_COMMANDS)
        if cmd not in STOP_COMMANDS:  # a stop is never refused, and takes nobody's control
            self._take_control(s, cmd)
        return await self._forward(s, rid, cmd, ns, data)

    async def _forward(self, s: Session, rid: int, cmd: str, ns: str | None, data: Any) -> Any:
        """Send a command to the control process; its reply goes to ``s`` in order with events."""
        delivered = []

        def deliver(reply: dict) -> None:
            delivered.append(True)
            s.send(dict(reply, id=rid))

        try:
            # a state command may run a lifecycle transition: the loop replies by its time limit
            timeout = max(10.0, self.link.transition_timeout_s) if cmd in STATE_COMMANDS else 10.0
            await self.link.request(cmd, ns, data, timeout_s=timeout, deliver=deliver)
        except asyncio.TimeoutError:
            if not delivered:  # the reply and the timeout can land in the same loop pass
                raise
        return _SENT

    def _take_control(self, s: Session, cmd: str) -> None:
        if self.controller is None or self.controller.closed:
            self.controller = s
        elif self.controller is not s:
            raise ProtocolError("read_only", f"{self.robot}: {cmd} refused: {self.controller.describe()} holds "
                                f"control (it must release or disconnect; {', '.join(STOP_COMMANDS)} are "
                                "accepted from any session)")

    def _subscribe(self, s: Session, ns: str | None, data: dict) -> dict:
        topic = data["topic"]  # typed by protocol.Subscribe: a str, and rate_hz a number > 0
        base, _ = self._frame(topic, ns)
        cs = self.cartesian.get(base) if base else None
        cart_topics = [q for q in cs.queries if q.startswith(("measured_", "setpoint_", "goal_"))] if cs else []
        if topic not in TOPICS and topic not in cart_topics:
            raise ProtocolError("bad_request", f"unknown topic {topic!r} for {ns or self.robot} "
                                f"(topics: {', '.join(list(TOPICS) + cart_topics)})")
        self._check_ns("subscribe", base, topic in JOINT_QUERIES or topic in cart_topics)
        rate = min(data["rate_hz"], 1.0 / self.link.period_s)
        sub = next(self._subids)
        loop = asyncio.get_running_loop()
        stream = self._streams.get((topic, ns))
        if stream is None:
            stream = self._streams[(topic, ns)] = TopicStream(topic, ns, self._producer(topic, ns), self._stream_ended)
        s.subs[sub] = stream.add(s, sub, 1.0 / rate, loop.time())
        if self._streams_task is None or self._streams_task.done():
            self._streams_task = loop.create_task(self._run_streams())
        elif self._streams_wake is not None and not self._streams_wake.done():
            self._streams_wake.set_result(None)  # its first frame now, not at the next tick
        return {"sub": sub, "rate_hz": rate}

    def _producer(self, topic: str, ns: str | None):
        """The data of ``topic`` on ``ns`` now (a stream's one read a tick)."""
        base, frame = self._frame(topic, ns)
        cs = self.cartesian.get(base) if base else None
        if topic in JOINT_QUERIES:
            return lambda: self.link.joint_state(topic, ns)
        if topic == "operating_state":  # robot-wide, with or without a (cartesian) ns
            return lambda: self.state
        if topic == "period_statistics":
            return self.period_statistics
        return lambda: cs.query(topic, self.link.ns_arrays(base), frame)

    async def _run_streams(self) -> None:
        """Tick every stream when its next subscriber is due, until no stream is left."""
        loop = asyncio.get_running_loop()
        while self._streams:
            due = tick_all(list(self._streams.values()), loop.time())
            if not self._streams:
                break  # the last subscriber's session ended
            delay = due - loop.time()
            if delay <= 0:
                await asyncio.sleep(0)  # behind: let the rest of the loop run, never hold it
                continue
            wake = self._streams_wake = loop.create_future()
            timer = loop.call_later(delay, _wake, wake)
            try:
                await wake
            finally:
                timer.cancel()
                self._streams_wake = None

    def _stream_ended(self, stream: TopicStream) -> None:
        if self._streams.get((stream.topic, stream.ns)) is stream:
            del self._streams[(stream.topic, stream.ns)]

    def period_statistics(self) -> dict:
        """The control loop's statistics, and ``frames_dropped``: the stream frames the front dropped
        for every session since it started (a client reading slower than it subscribed); with the
        ROS graph, ``ros_ticks_skipped``."""
        stats = self.link.period_statistics()
        stats["frames_dropped"] = self._dropped_before + sum(s.dropped for s in self.sessions.values())
        for more in self.statistics:
            stats.update(more())
        return stats

    def describe(self) -> dict:
        namespaces = []
        for ns in self.profile.namespaces:
            cs = self.cartesian.get(ns.name)
            cart_q = cs.queries if cs else []
            entry = {
                "name": ns.name,
                "joints": list(ns.joints),
                # each joint's id on its bus (servo id, drive node id; null: none), so that a tool
                # can tell the daemon's robot from another profile's (crtk-ctl calibrate --profile)
                "ids": [joint_bus_id(self.profile.joints[self.profile.joint_index(j)]) for j in ns.joints],
                "commands": list(STATE_COMMANDS) + self.link.ns_commands[ns.name] + (cs.commands if cs else []),
                "queries": list(JOINT_QUERIES + ROBOT_QUERIES) + cart_q,
                "topics": list(TOPICS) + [q for q in cart_q if not q.endswith("kinematics")],
                # per joint: "rad" (revolute: rad, rad/s, N*m) or "m" (prismatic: m, m/s, N)
                "units": [self.profile.joints[i].unit for i in self.link.ns_joints[ns.name]],
                # per joint: the profile's [position_min, position_max] (rad or m): where the
                # loop clips servo / interpolate positions (a client can say what it really sent)
                "position_limits": [[self.profile.joints[i].limits.position_min, self.profile.joints[i].limits.position_max]
                                    for i in self.link.ns_joints[ns.name]],
                # per joint: {mode: [scale, bias]}, LeRobot's number = scale * value + bias; null: none
                "lerobot": [self.link.lerobot_maps[i] for i in self.link.ns_joints[ns.name]],
            }
            if cs:
                entry["cartesian"] = {"base_frame": cs.cfg.base_frame, "tip_frame": cs.cfg.tip_frame,
                                      "frames": ["spatial", "body"]}
            if self.profile.backends is not None:  # several buses: the one this namespace lives on
                entry["bus"] = self.profile.namespace_bus(ns)
            namespaces.append(entry)
        return {"robot": self.robot, "protocol_version": PROTOCOL_VERSION, "daemon_version": __version__,
                "backend": self.profile.backend_type, "rate_hz": 1.0 / self.link.period_s,
                "servo_step_max": self.profile.safety.servo_step_max, "namespaces": namespaces}


def _wake(fut: asyncio.Future) -> None:
    if not fut.done():
        fut.set_result(None)


_SENT = object()  # the reply was already delivered, in order with the loop's events
_CRTK_PREFIXES = ("servo_", "interpolate_", "move_", "measured_", "setpoint_", "goal_")


def _is_crtk_command(cmd: str) -> bool:
    return cmd.startswith(_CRTK_PREFIXES) or cmd in ("hold", "free")


async def _discard_line(reader: asyncio.StreamReader) -> None:
    """Drop the rest of an over-long line, up to and including its newline (or until EOF)."""
    while True:
        try:
            await reader.readuntil(b"\n")
            return
        except asyncio.LimitOverrunError as exc:
            await reader.readexactly(exc.consumed)
        except (asyncio.IncompleteReadError, ConnectionError):
            return


def _peer(writer: asyncio.StreamWriter) -> str:
    """``pid 1234 python3, uid 1000`` of the process at the other end (SO_PEERCRED), or ""."""
    sock = writer.get_extra_info("socket")
    try:
        pid, uid, _ = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i")))
    except (AttributeError, OSError):
        return ""
    try:
        with open(f"/proc/{pid}/comm") as f:
            name = " " + f.read().strip()
    except OSError:
        name = ""
    return f"pid {pid}{name}, uid {uid}"

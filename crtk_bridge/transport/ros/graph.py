"""The robot as a ROS 2 graph over Zenoh (rmw_zenoh's format), in the front process.

One ROS node, ``crtk_bridge_<robot>``, per daemon. Per CRTK namespace (names and types as the
dVRK uses them, docs/architecture.md, "Sources": CRTK):

* published at the loop rate (or ``transport.zenoh.publish_rate_hz``): ``measured_js``,
  ``setpoint_js``, ``goal_js`` (sensor_msgs/JointState); where the namespace has kinematics
  ``measured_cp``, ``setpoint_cp`` (geometry_msgs/PoseStamped), ``measured_cv``
  (TwistStamped) and, where efforts are measured, ``measured_cf`` (WrenchStamped);
* ``operating_state`` (crtk_msgs/OperatingState), latched, published on every change;
* ``error`` / ``warning`` / ``status`` (crtk_msgs/StringStamped): the daemon's events, and every
  refusal of a command received here;
* subscribed: ``state_command`` (crtk_msgs/StringStamped) and the motion commands the namespace
  supports (``servo_jp`` ... JointState; ``servo_cp`` ... PoseStamped; ``servo_cv`` TwistStamped;
  ``servo_cf`` WrenchStamped; ``hold`` / ``free`` std_msgs/Empty);

and robot-wide ``/joint_states`` (every joint's measured state), ``/tf`` (each kinematic
namespace's base -> tip transform, from ``measured_cp``, as the dVRK broadcasts it) and a latched
``/robot_description`` (the URDF).

Commands take the socket's path: the ROS graph is ONE session of the server (:class:`RosSession`):
each sample becomes a protocol request, typed and bounded by the same code (``Server._handle``),
under the same control rules: the ROS session takes control like any session and is refused
(``read_only``) while another holds it; ``disable``, ``pause`` and ``hold`` are accepted whoever
holds control. It gives control up when the last ROS publisher of a command topic leaves the
graph (its liveliness token goes), as a socket session does when it disconnects, and holds it only
while such a publisher is live: Zenoh sends declarations ahead of data, so a publisher's last
samples may arrive after its token went (and a plain Zenoh put has no token at all); a command
handled while no remote command publisher is known is followed by a liveliness query of the graph,
and control is released when it finds none. A refusal is
published on the namespace's ``error`` topic. ``state_command`` is subscribed VOLATILE on
purpose: crtk_python_client latches it, and a daemon (re)starting must never replay an old
``enable`` (the robot never enables itself).

Nothing here blocks the event loop: the periodic topics are published from their own thread
(periodic.py: one snapshot read and one CDR encoding per message per tick, stale ticks skipped,
never queued), a Zenoh put never waits (congestion control DROP), samples arrive on Zenoh's
threads and are handed to the loop with ``call_soon_threadsafe``, and IK for pose commands runs
on the server's worker as for the socket.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from pathlib import Path
from typing import Any, Callable

import msgspec
import numpy as np
import zenoh

from ... import vectors
from ...errors import CrtkBridgeError
from ...server.protocol import STATE_COMMANDS, STOP_COMMANDS
from ...server.server import Server, Session
from . import types as T
from .periodic import CARTESIAN_TOPICS, JOINT_TOPICS, PeriodicTopics
from .rmw import LATCHED, Node, Publisher, QoS, Subscription, mangle, type_mismatch

log = logging.getLogger("crtk_bridge.ros")

#: CRTK command -> (ROS type, the JointState vector it reads or the cartesian payload kind)
JOINT_COMMANDS = {
    "servo_jp": "position", "servo_jr": "position", "move_jp": "position", "move_jr": "position",
    "interpolate_jp": "position", "interpolate_jr": "position",
    "servo_jv": "velocity", "interpolate_jv": "velocity",
    "servo_jf": "effort", "interpolate_jf": "effort",
}
POSE_COMMANDS = ("servo_cp", "interpolate_cp", "move_cp", "servo_cr", "interpolate_cr", "move_cr")
TWIST_COMMANDS = ("servo_cv", "interpolate_cv")
WRENCH_COMMANDS = ("servo_cf", "interpolate_cf")
EMPTY_COMMANDS = ("hold", "free")
#: motion commands in flight per topic beyond which new samples are dropped (a flood never grows
#: the loop's queue without bound; stops and state commands are never dropped)
MAX_IN_FLIGHT = 32


def command_type(cmd: str) -> str:
    if cmd in JOINT_COMMANDS:
        return T.JOINT_STATE
    if cmd in POSE_COMMANDS:
        return T.POSE_STAMPED
    if cmd in TWIST_COMMANDS:
        return T.TWIST_STAMPED
    if cmd in WRENCH_COMMANDS:
        return T.WRENCH_STAMPED
    return T.EMPTY


class Refused(CrtkBridgeError):
    """A sample refused before it reaches the server (undecodable, wrong type, non-finite)."""


class RosSession(Session):
    """The ROS graph as one session of the server: replies and events come back through
    :meth:`send`, and are published (events on their topics, refusals on ``error``)."""

    def __init__(self, sid: int, on_message: Callable[[dict], None], describe: str):
        super().__init__(sid, None, peer=describe)
        self._on_message = on_message

    def send(self, msg: Any) -> None:
        if self.closed:
            return
        try:
            self._on_message(msg)
        except Exception:  # never break the server's fan-out to the other sessions
            log.exception("ROS graph: publishing %s failed", msg.get("event", "a reply"))

    def send_frame(self, line: bytes) -> None:  # the ROS session never subscribes to socket streams
        pass

    def close(self) -> None:
        self.closed = True


class RosGraph:
    def __init__(self, session: zenoh.Session, server: Server, *, domain_id: int = 0,
                 rate_hz: float | None = None, endpoint: str = ""):
        self.zenoh = session
        self.server = server
        self.link = server.link
        self.domain_id = domain_id
        loop_rate = 1.0 / self.link.period_s
        self.rate_hz = min(rate_hz, loop_rate) if rate_hz else loop_rate
        self.namespaces = [ns.name for ns in server.profile.namespaces]
        self.node: Node | None = None
        self.session: RosSession | None = None
        self.periodic: PeriodicTopics | None = None  # the thread publishing the periodic topics
        self._loop: asyncio.AbstractEventLoop | None = None
        self._pubs: dict[tuple[str, str], Publisher] = {}  # (ns or "", topic) -> publisher
        self._subs: list[Subscription] = []
        self._rids = iter(range(1, 1 << 62))
        self._pending: dict[int, tuple[str, str]] = {}  # request id -> (ns, cmd)
        self._in_flight: dict[tuple[str, str], int] = {}
        self._dropped = 0  # motion samples dropped by the MAX_IN_FLIGHT bound
        self._drop_said = -1.0
        self._command_topics: set[str] = set()  # mangled names of our command topics
        self._remote_commanders: set[str] = set()  # liveliness tokens of remote command publishers
        self._liveliness = None
        self._checking = False  # a liveliness query for remote command publishers is under way
        self._endpoint = endpoint

    # ---------------------------------------------------------------- life cycle
    async def start(self) -> None:
        """Declare the node, its endpoints and the server session; start publishing.
        Raises CrtkBridgeError when the Zenoh session cannot declare them."""
        self._loop = asyncio.get_running_loop()
        server = self.server
        robot = server.robot
        self.node = Node(self.zenoh, self.domain_id, "crtk_bridge_" + re.sub(r"\W", "_", robot))
        try:
            self._declare()
        except BaseException:
            self.node.close()
            raise
        where = f"ROS 2 graph over Zenoh, domain {self.domain_id}" + (f", {self._endpoint}" if self._endpoint else "")
        self.session = RosSession(server.new_session_id(), self._on_message, where)
        server.attach(self.session)  # publishes the current operating_state (latched)
        urdf = self._urdf()
        if urdf is not None:
            self._pubs[("", "robot_description")].put(T.encode(T.String(data=urdf), T.STRING))
        self._liveliness = self.zenoh.liveliness().declare_subscriber(
            f"@ros2_lv/{self.domain_id}/**", self._on_token, history=True)
        spaces = {ns: server.cartesian_space(ns) for ns in server.cartesian}  # the thread's own
        self.periodic = PeriodicTopics(self.link, self.namespaces, self._pubs, spaces, self.rate_hz, robot)
        self.periodic.start()
        server.statistics.append(self._statistics)

    def _statistics(self) -> dict:
        return {"ros_ticks_skipped": self.periodic.skipped if self.periodic is not None else 0}

    def _declare(self) -> None:
        node = self.node
        server = self.server
        for ns in self.namespaces:
            base = f"/{ns}/"
            topics = [(t, T.JOINT_STATE) for t in JOINT_TOPICS]
            cs = server.cartesian.get(ns)
            if cs is not None:
                topics += [(t, typ) for t, (typ, _) in CARTESIAN_TOPICS.items() if t in cs.queries]
            for topic, typ in topics:
                self._pubs[(ns, topic)] = node.publisher(base + topic, typ)
            self._pubs[(ns, "operating_state")] = node.publisher(base + "operating_state", T.OPERATING_STATE,
                                                                 LATCHED)
            for topic in ("error", "warning", "status"):
                self._pubs[(ns, topic)] = node.publisher(base + topic, T.STRING_STAMPED, QoS(depth=100))
            commands = [c for c in server.link.ns_commands[ns] if c in JOINT_COMMANDS or c in EMPTY_COMMANDS]
            if cs is not None:
                commands += [c for c in cs.commands if c not in JOINT_COMMANDS]
            for cmd in ["state_command"] + commands:
                typ = T.STRING_STAMPED if cmd == "state_command" else command_type(cmd)
                self._command_topics.add(mangle(base + cmd))
                self._subs.append(node.subscription(base + cmd, typ, self._receiver(ns, cmd, typ), any_type=True))
        self._pubs[("", "joint_states")] = node.publisher("/joint_states", T.JOINT_STATE)
        if server.cartesian:
            self._pubs[("", "tf")] = node.publisher("/tf", T.TF_MESSAGE, QoS(depth=100))
        self._pubs[("", "robot_description")] = node.publisher("/robot_description", T.STRING, LATCHED)

    def _urdf(self) -> str | None:
        """The URDF of the first namespace with kinematics (the robot's model), or None."""
        for ns in self.server.profile.namespaces:
            if ns.kinematics is not None:
                try:
                    return Path(ns.kinematics.urdf).read_text()
                except OSError as exc:
                    log.warning("%s: /robot_description not published: %s", self.server.robot, exc)
                    return None
        return None

    async def close(self) -> None:
        """Stop publishing, leave the graph; control held by the ROS session is released."""
        if self.periodic is not None:
            await self._loop.run_in_executor(None, self.periodic.close)  # within one tick
            for cs in self.periodic.spaces.values():
                cs.close()
        if self._liveliness is not None:
            try:
                self._liveliness.undeclare()
            except zenoh.ZError:
                pass
        if self.session is not None:
            # while the daemon stops, the control process is stopping the robot already
            self.server.detach(self.session, client_lost=not self.server.shutting_down)
        if self.node is not None:
            self.node.close()

    def _release(self) -> None:
        """Give control up as a socket session does when it disconnects."""
        if self.server.controller is self.session:
            self.server.controller = None
            self.server.link.send_nowait("_client_lost")

    # ---------------------------------------------------------------- event-driven publications
    def _publish_state(self, state: dict) -> None:
        for ns in self.namespaces:
            self._pubs[(ns, "operating_state")].put(T.encode(T.operating_state(state, ns), T.OPERATING_STATE))

    def _publish_text(self, kind: str, ns: str | None, text: str, at: float | None = None) -> None:
        """An ``error`` / ``warning`` / ``status`` line on ``ns``'s topic; robot-wide (``ns``
        not a namespace) on every namespace's."""
        targets = [ns] if ns in self.namespaces else self.namespaces
        for target in targets:
            self._pubs[(target, kind)].put(T.encode(T.string_stamped(text, target, at), T.STRING_STAMPED))

    def _on_message(self, msg: dict) -> None:
        """What the server sends the ROS session: events, and replies to its requests."""
        ev = msg.get("event")
        if ev == "operating_state":
            self._publish_state(msg["data"])
        elif ev in ("error", "warning", "status"):
            d = msg["data"]
            self._publish_text(ev, d.get("ns"), str(d.get("message", "")), d.get("stamp"))
        elif "ok" in msg:
            ns, cmd = self._pending.pop(msg.get("id"), (None, None))
            if not msg["ok"]:
                self._publish_text("error", ns, msg["error"]["message"])

    # ---------------------------------------------------------------- commands
    def _receiver(self, ns: str, cmd: str, ros_type: str) -> Callable[[zenoh.Sample], None]:
        def received(sample: zenoh.Sample) -> None:
            """Zenoh thread: hand the sample to the event loop (nothing else happens here)."""
            try:
                self._loop.call_soon_threadsafe(self._command, ns, cmd, ros_type, str(sample.key_expr),
                                                sample.payload.to_bytes())
            except RuntimeError:
                pass  # the loop is closed: the daemon is stopping
        return received

    def _command(self, ns: str, cmd: str, ros_type: str, key: str, payload: bytes) -> None:
        if self.session is None or self.session.closed:
            return
        stop = cmd in STOP_COMMANDS or cmd == "state_command"
        slot = (ns, cmd)
        if not stop and self._in_flight.get(slot, 0) >= MAX_IN_FLIGHT:
            self._dropped += 1
            now = time.monotonic()
            if now - self._drop_said >= 1.0:  # at most one warning a second
                self._drop_said = now
                self._publish_text("warning", ns, f"{ns}: {cmd} samples dropped ({self._dropped} so far): they "
                                   f"arrive faster than the robot takes them ({MAX_IN_FLIGHT} waiting)")
            return
        try:
            wrong = type_mismatch(key, ns, cmd, ros_type)
            if wrong is not None:
                raise Refused(f"{ns}: {cmd} refused: published as {wrong}; {cmd} takes {ros_type} "
                              f"({T.type_hash(ros_type)})")
            request_cmd, data = self._request(ns, cmd, ros_type, payload)
        except Refused as exc:
            self._publish_text("error", ns, str(exc))
            return
        rid = next(self._rids)
        self._pending[rid] = (ns, request_cmd)
        line = msgspec.json.encode({"id": rid, "cmd": request_cmd, "ns": ns, "data": data})
        self._in_flight[slot] = self._in_flight.get(slot, 0) + 1
        task = self._loop.create_task(self.server.handle_line(self.session, line))
        task.add_done_callback(lambda _t, slot=slot: self._done(slot))

    def _done(self, slot: tuple[str, str]) -> None:
        self._in_flight[slot] -= 1
        self._check_commanders()

    def _request(self, ns: str, cmd: str, ros_type: str, payload: bytes) -> tuple[str, dict | None]:
        """The protocol request (cmd, data) of a sample. Raises Refused."""
        try:
            msg = T.decode(payload, ros_type)
        except Exception as exc:  # rosbags raises several kinds on bad bytes
            raise Refused(f"{ns}: {cmd} refused: not a CDR {ros_type}: {exc}") from None
        if cmd == "state_command":
            word = msg.string
            if word not in STATE_COMMANDS:
                raise Refused(f"{ns}: state_command refused: unknown command {word!r} "
                              f"(one of: {', '.join(STATE_COMMANDS)})")
            return word, None
        if cmd in JOINT_COMMANDS:
            return cmd, self._joint_payload(ns, cmd, msg)
        if cmd in POSE_COMMANDS:
            p, q = msg.pose.position, msg.pose.orientation
            return cmd, _finite(ns, cmd, {"position": [p.x, p.y, p.z], "orientation": [q.x, q.y, q.z, q.w]})
        if cmd in TWIST_COMMANDS:
            v, w = msg.twist.linear, msg.twist.angular
            return cmd, _finite(ns, cmd, {"linear": [v.x, v.y, v.z], "angular": [w.x, w.y, w.z]})
        if cmd in WRENCH_COMMANDS:
            f, t = msg.wrench.force, msg.wrench.torque
            return cmd, _finite(ns, cmd, {"force": [f.x, f.y, f.z], "torque": [t.x, t.y, t.z]})
        return cmd, None  # hold, free

    def _joint_payload(self, ns: str, cmd: str, msg: Any) -> dict:
        """The JointState vector the command reads (``servo_jp`` also its velocity feed-forward),
        reordered by ``name`` when the names are given (in any order); lengths are checked by
        the server as for the socket."""
        field = JOINT_COMMANDS[cmd]
        joints = self.link.ns_names[ns]
        order = None
        if len(msg.name):
            names = list(msg.name)
            if sorted(names) != sorted(joints):
                raise Refused(f"{ns}: {cmd} refused: joint names {names} are not the namespace's "
                              f"({', '.join(joints)})")
            order = [names.index(j) for j in joints]
        data = {}
        fields = [field, "velocity"] if cmd == "servo_jp" else [field]
        for f in fields:
            values = np.asarray(getattr(msg, f), dtype=np.float64)
            if f != field and not len(values):
                continue  # no feed-forward
            if not len(values):
                raise Refused(f"{ns}: {cmd} refused: JointState.{f} is empty ({cmd} reads {f})")
            if order is not None:
                if len(values) != len(order):
                    raise Refused(f"{ns}: {cmd} refused: JointState.{f} has {len(values)} values for "
                                  f"{len(order)} names")
                values = values[order]
            data[f] = values.tolist()
        return _finite(ns, cmd, data)

    # ---------------------------------------------------------------- the graph's commanders
    def _on_token(self, sample: zenoh.Sample) -> None:
        """Zenoh thread: a liveliness token came or went."""
        key = str(sample.key_expr)
        if not self._is_commander(key):
            return
        gone = sample.kind == zenoh.SampleKind.DELETE
        try:
            self._loop.call_soon_threadsafe(self._commander, key, gone)
        except RuntimeError:
            pass

    def _is_commander(self, key: str) -> bool:
        """Whether a liveliness token is a remote publisher of one of our command topics."""
        parts = key.split("/")
        return (len(parts) >= 13 and parts[5] == "MP" and parts[2] != self.node.zid
                and parts[9] in self._command_topics)

    def _check_commanders(self) -> None:
        """After a command: holding control with no remote command publisher known (its token
        went before its last sample arrived, or it never had one), ask the graph; release when
        none is live. A token arriving meanwhile keeps control (its going releases it)."""
        if self._remote_commanders or self._checking or self.session is None or self.session.closed \
                or self.server.controller is not self.session:
            return
        self._checking = True
        self._loop.create_task(self._recheck())

    async def _recheck(self) -> None:
        try:
            live = await self._loop.run_in_executor(None, self._live_commanders)
        finally:
            self._checking = False
        if not live and not self._remote_commanders:
            self._release()

    def _live_commanders(self) -> bool:
        """Worker thread: whether the graph holds a remote command publisher's token now."""
        try:
            replies = self.zenoh.liveliness().get(f"@ros2_lv/{self.domain_id}/**", timeout=1.0)
            return any(r.ok is not None and self._is_commander(str(r.ok.key_expr)) for r in replies)
        except zenoh.ZError:  # the session is closing: the daemon stops, control goes with it
            return True

    def _commander(self, key: str, gone: bool) -> None:
        if not gone:
            self._remote_commanders.add(key)
            return
        self._remote_commanders.discard(key)
        if not self._remote_commanders:
            self._release()


def _finite(ns: str, cmd: str, data: dict) -> dict:
    """``data`` when every vector in it is finite (crtk_bridge/vectors.py, the reader the socket's
    clients and core use); else Refused naming the field and entry (JSON cannot carry NaN, CDR can)."""
    for f, values in data.items():
        try:
            vectors.floats(values, f"{ns}: {cmd} refused: data.{f}")
        except vectors.InvalidVector as exc:
            raise Refused(exc.message) from None
    return data


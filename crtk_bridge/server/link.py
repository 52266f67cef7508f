"""The front process's side of the control process: the command pair and the snapshot.

Requests go to the control process over the SOCK_SEQPACKET pair (msgpack); each gets exactly one
reply, matched by an internal id. Events (operating_state, warnings, ...) come back on the same
pair, in order with the replies they precede. Joint state is read from the shared-memory snapshot
without a round trip through the loop.
"""

from __future__ import annotations

import asyncio
import itertools
import socket
from collections import deque
from typing import Any, Callable

import msgspec
import numpy as np

from ..core.actuator import FRAME_BODY
from ..core.snapshot import RING, SnapshotBuffer
from ..errors import CrtkBridgeError
from ..profile import Profile

_encode = msgspec.msgpack.Encoder().encode
_decode = msgspec.msgpack.Decoder().decode


class ControlLost(CrtkBridgeError):
    """The control process is gone."""


class ControlLink:
    def __init__(self, profile: Profile, chan: socket.socket, snapshot: SnapshotBuffer,
                 on_event: Callable[[dict], None]):
        self.profile = profile
        self.chan = chan
        self.snap = snapshot
        self.on_event = on_event
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future] = {}
        self._outq: deque[bytes] = deque()  # messages waiting for room on the pair, in order
        # the messages sent on the pair, counted twice each in shared memory, before the send (odd:
        # a send under way) and after it (even): the loop skips its receive (a system call) in a
        # cycle where the count did not move since the pair was emptied (core/loop.py)
        self._posted = snapshot.posted
        self._posted[0] = 0
        self.lost = False
        self._buf = np.empty_like(snapshot.data)
        self._slices = snapshot.layout.slices
        self._state_size = self._slices["lateness"].start  # the state and counters, not the rings
        self.ns_index = {ns.name: k for k, ns in enumerate(profile.namespaces)}
        self.ns_joints = {ns.name: np.array([profile.joint_index(j) for j in ns.joints]) for ns in profile.namespaces}
        self.ns_names = {ns.name: list(ns.joints) for ns in profile.namespaces}
        self.measures_velocity = True
        self.measures_effort = False
        #: the loop's ONE effective period (s) and a state command's longest run, from ``_ready``
        self.period_s = 1.0 / profile.loop.rate_hz
        self.transition_timeout_s = 10.0
        #: per namespace (from the control process's _ready): what its joints measure, its motion commands
        self.ns_measures_velocity = {ns: True for ns in self.ns_index}
        self.ns_measures_effort = {ns: False for ns in self.ns_index}
        self.ns_measures_wrench = {ns: False for ns in self.ns_index}  # native cartesian: the tip wrench
        self.ns_commands: dict[str, list[str]] = {ns: [] for ns in self.ns_index}
        #: per joint (robot order, from _ready): LeRobot's numbers as affine maps of its SI value, or None
        self.lerobot_maps: list[dict | None] = [None] * len(profile.joints)
        #: namespaces whose backend does cartesian control and measures the tip pose itself
        self.native_cartesian: set[str] = set()

    # ---------------------------------------------------------------- start-up
    def wait_ready(self, timeout_s: float) -> dict:
        """Block until the control process says it is ready. Raises RuntimeError with its reason."""
        self.chan.settimeout(timeout_s)
        try:
            while True:
                data = self.chan.recv(1 << 16)
                if not data:
                    raise RuntimeError("the control process exited during start-up")
                msg = _decode(data)
                ev = msg.get("event")
                if ev == "_ready":
                    caps = msg["data"]["capabilities"]
                    self.measures_velocity = caps["measures_velocity"]
                    self.measures_effort = caps["measures_effort"]
                    self.period_s = float(msg["data"].get("period_s", self.period_s))
                    self.transition_timeout_s = float(msg["data"].get("transition_timeout_s",
                                                                      self.transition_timeout_s))
                    for ns, c in msg["data"]["namespace_capabilities"].items():
                        self.ns_measures_velocity[ns] = c["measures_velocity"]
                        self.ns_measures_effort[ns] = c["measures_effort"]
                        self.ns_measures_wrench[ns] = bool(c.get("measures_wrench", False))
                    self.ns_commands.update(msg["data"]["namespace_commands"])
                    self.native_cartesian = set(msg["data"].get("native_cartesian", ()))
                    self.lerobot_maps = list(msg["data"].get("lerobot_maps") or self.lerobot_maps)
                    return msg["data"]
                if ev == "_startup_failed":
                    raise RuntimeError(msg["data"]["message"])
                self.on_event(msg)  # e.g. the realtime warning, the first operating_state
        except socket.timeout:
            raise RuntimeError(f"the control process did not start within {timeout_s} s") from None
        finally:
            self.chan.settimeout(None)

    def attach(self, loop: asyncio.AbstractEventLoop, on_lost: Callable[[], None]) -> None:
        self.chan.setblocking(False)
        self._on_lost = on_lost
        loop.add_reader(self.chan.fileno(), self._readable)

    def _readable(self) -> None:
        while True:
            try:
                data = self.chan.recv(1 << 16)
            except BlockingIOError:
                return
            except OSError:
                data = b""
            if not data:
                self._lose()
                return
            msg = _decode(data)
            rid = msg.get("id")
            if "ok" in msg and rid is None:
                continue  # the reply to a notice we sent without an id (_client_lost): nobody asked
            if rid is not None and "ok" in msg:
                entry = self._pending.pop(rid, None)
                if entry is not None:
                    fut, deliver = entry
                    if deliver is not None:
                        # deliver now, before any event that follows it on the pair: a client
                        # must see the reply before the events the command caused later
                        deliver(msg)
                    if not fut.done():
                        fut.set_result(msg)
            else:
                self.on_event(msg)

    def _lose(self) -> None:
        if self.lost:
            return
        self.lost = True
        self._outq.clear()
        try:
            asyncio.get_running_loop().remove_reader(self.chan.fileno())
            asyncio.get_running_loop().remove_writer(self.chan.fileno())
        except (RuntimeError, ValueError):
            pass
        for fut, _ in self._pending.values():
            if not fut.done():
                fut.set_exception(ControlLost("control process is gone"))
        self._pending.clear()
        self._on_lost()

    # ---------------------------------------------------------------- requests
    async def request(self, cmd: str, ns: str | None, data: Any, timeout_s: float = 10.0,
                      deliver: Callable[[dict], None] | None = None) -> dict:
        """Send one request to the control loop; returns its reply message.

        ``deliver``, if given, is called with the reply as soon as it is read, in order with the
        events around it (the awaiting coroutine may resume only after later events were fanned out).
        """
        if self.lost:
            raise ControlLost("control process is gone")
        rid = next(self._ids)
        payload = _encode({"id": rid, "cmd": cmd, "ns": ns, "data": data})  # may raise: nothing pending yet
        fut = asyncio.get_running_loop().create_future()
        self._pending[rid] = (fut, deliver)
        try:
            self._post(payload)
        except ControlLost:
            self._pending.pop(rid, None)
            raise
        try:
            return await asyncio.wait_for(fut, timeout_s)
        finally:
            self._pending.pop(rid, None)

    def send_nowait(self, cmd: str) -> None:
        if not self.lost:
            try:
                self._post(_encode({"id": None, "cmd": cmd}))
            except ControlLost:
                pass

    def _post(self, data: bytes) -> None:
        """Send ``data`` to the control process now or, when the pair is full (the loop is
        behind), as soon as it has room, in order: a request or notice is never failed or dropped
        for want of room (a stop refused as 'not running'; a lost ``_shutdown`` meant no park and
        no torque off). Raises ControlLost when the pair is gone."""
        if not self._outq:
            try:
                self._send(data)
                return
            except BlockingIOError:
                pass
            except OSError as exc:
                raise ControlLost(str(exc)) from exc
        self._outq.append(data)
        if len(self._outq) == 1:
            asyncio.get_running_loop().add_writer(self.chan.fileno(), self._writable)

    def _send(self, data: bytes) -> None:
        """One message on the pair, counted for the loop: odd while the send is under way (the
        loop then receives in every cycle until the count is even again), even once it is done."""
        posted = self._posted
        posted[0] += 1
        try:
            self.chan.send(data)
        finally:
            posted[0] += 1

    def _writable(self) -> None:
        while self._outq:
            try:
                self._send(self._outq[0])
            except BlockingIOError:
                return
            except OSError:  # the pair is gone: _readable sees the EOF and says so
                self._outq.clear()
                break
            self._outq.popleft()
        asyncio.get_running_loop().remove_writer(self.chan.fileno())

    # ---------------------------------------------------------------- snapshot views
    def read(self, statistics: bool = False) -> np.ndarray:
        """A consistent copy of the snapshot: its state and counters (the joint state, what a
        stream tick or a query needs), or with ``statistics`` the whole block, its lateness and
        compute rings too (16 KiB: eight times the state of a 6-joint arm, copied in every tick
        of every stream before)."""
        buf, _ = self.snap.read(self._buf, upto=None if statistics else self._state_size)
        return buf

    def cycles(self) -> int:
        return int(self.snap.data[self._slices["cycles"]][0])

    def joint_state(self, topic: str, ns: str, buf: np.ndarray | None = None) -> dict:
        """measured_js / setpoint_js / goal_js of one namespace as a JointState payload, from
        ``buf`` (a snapshot copy the caller read) or a fresh read."""
        buf = self.read() if buf is None else buf
        s = self._slices
        idx = self.ns_joints[ns]
        k = self.ns_index[ns]
        names = self.ns_names[ns]
        if topic == "measured_js":
            return {
                "stamp": float(buf[s["measured_stamp"]][0]), "frame_id": ns, "name": names,
                "position": buf[s["measured_p"]][idx].tolist(),
                "velocity": buf[s["measured_v"]][idx].tolist() if self.ns_measures_velocity[ns] else [],
                "effort": buf[s["measured_f"]][idx].tolist() if self.ns_measures_effort[ns] else [],
            }
        if topic == "setpoint_js":
            has_p, has_v, has_f = (bool(buf[s[f]][k]) for f in ("ns_has_p", "ns_has_v", "ns_has_f"))
            return {
                "stamp": float(buf[s["ns_setpoint_stamp"]][k]), "frame_id": ns, "name": names,
                "position": buf[s["setpoint_p"]][idx].tolist() if has_p else [],
                "velocity": buf[s["setpoint_v"]][idx].tolist() if has_v else [],
                "effort": buf[s["setpoint_f"]][idx].tolist() if has_f else [],
            }
        # goal_js: the goal of the running or last interpolate / move command
        has_p, has_v, has_f = (bool(buf[s[f]][k]) for f in ("ns_goal_has_p", "ns_goal_has_v", "ns_goal_has_f"))
        return {
            "stamp": float(buf[s["ns_goal_stamp"]][k]), "frame_id": ns, "name": names,
            "position": buf[s["goal_p"]][idx].tolist() if has_p else [],
            "velocity": buf[s["goal_v"]][idx].tolist() if has_v else [],
            "effort": buf[s["goal_f"]][idx].tolist() if has_f else [],
        }

    def ns_arrays(self, ns: str, buf: np.ndarray | None = None) -> dict:
        """One consistent snapshot of a namespace's joint state as numpy arrays and flags (from
        ``buf``, a snapshot copy the caller read, or a fresh read)."""
        buf = self.read() if buf is None else buf
        s = self._slices
        idx = self.ns_joints[ns]
        k = self.ns_index[ns]
        return {
            "measured_stamp": float(buf[s["measured_stamp"]][0]),
            "measured_p": buf[s["measured_p"]][idx], "measured_v": buf[s["measured_v"]][idx],
            "measured_f": buf[s["measured_f"]][idx],
            "measures_velocity": self.ns_measures_velocity[ns], "measures_effort": self.ns_measures_effort[ns],
            "setpoint_stamp": float(buf[s["ns_setpoint_stamp"]][k]),
            "setpoint_p": buf[s["setpoint_p"]][idx], "setpoint_v": buf[s["setpoint_v"]][idx],
            "setpoint_f": buf[s["setpoint_f"]][idx],
            "setpoint_has_p": bool(buf[s["ns_has_p"]][k]), "setpoint_has_v": bool(buf[s["ns_has_v"]][k]),
            "setpoint_has_f": bool(buf[s["ns_has_f"]][k]),
            "goal_stamp": float(buf[s["ns_goal_stamp"]][k]),
            "goal_p": buf[s["goal_p"]][idx], "goal_v": buf[s["goal_v"]][idx], "goal_f": buf[s["goal_f"]][idx],
            "goal_has_p": bool(buf[s["ns_goal_has_p"]][k]), "goal_has_v": bool(buf[s["ns_goal_has_v"]][k]),
            "goal_has_f": bool(buf[s["ns_goal_has_f"]][k]),
            # the tip pose a native cartesian backend measures itself (stamp 0 for the others)
            "native_stamp": float(buf[s["ns_cart_stamp"]][k]),
            "native_p": buf[s["ns_cart_p"]][3 * k:3 * k + 3].copy(),
            "native_q": buf[s["ns_cart_q"]][4 * k:4 * k + 4].copy(),
            "native_f": buf[s["ns_cart_f"]][6 * k:6 * k + 6].copy(),
            # what it was commanded (core/native_cartesian.py; stamp 0: nothing)
            "native_sp_stamp": float(buf[s["ns_cart_sp_stamp"]][k]),
            "native_sp_p": buf[s["ns_cart_sp_p"]][3 * k:3 * k + 3].copy(),
            "native_sp_q": buf[s["ns_cart_sp_q"]][4 * k:4 * k + 4].copy(),
            "native_tw_stamp": float(buf[s["ns_cart_tw_stamp"]][k]),
            "native_tw": buf[s["ns_cart_tw"]][6 * k:6 * k + 6].copy(),
            "native_tw_body": int(buf[s["ns_cart_tw_frame"]][k]) == FRAME_BODY,
            "native_goal_stamp": float(buf[s["ns_cart_goal_stamp"]][k]),
            "native_goal_p": buf[s["ns_cart_goal_p"]][3 * k:3 * k + 3].copy(),
            "native_goal_q": buf[s["ns_cart_goal_q"]][4 * k:4 * k + 4].copy(),
        }

    def period_statistics(self) -> dict:
        buf = self.read(statistics=True)
        s = self._slices
        cycles = int(buf[s["cycles"]][0])
        n = min(cycles, RING)
        late = buf[s["lateness"]][:RING]
        comp = buf[s["compute"]][:RING]
        if n < RING:  # ring slots 1..n hold samples
            late, comp = late[1 : n + 1], comp[1 : n + 1]
        stats = {"rate_hz": 1.0 / self.period_s, "period_s": self.period_s,
                 "cycles": cycles, "overruns": int(buf[s["overruns"]][0]), "samples": int(n)}
        if n:
            p = np.percentile(late, [50, 99])
            c = np.percentile(comp, [50, 99])
            stats.update(lateness_p50_s=float(p[0]), lateness_p99_s=float(p[1]), lateness_max_s=float(late.max()),
                         compute_p50_s=float(c[0]), compute_p99_s=float(c[1]))
        return stats

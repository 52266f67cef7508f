"""Recordings and the black box, in the front process (docs/recording.md, docs/architecture.md).

Threads, none of them the event loop's and none in the control process:

* the **drain** thread wakes every ``DRAIN_PERIOD_S`` and takes every cycle's sample the control
  loop pushed into the shared ring since (core/samples.py). Samples the loop overwrote before
  they were read are counted and said (a ``samples_lost`` warning, at most one a second), and
  counted in each running recording's ``lost``. It appends the samples to the black box (the
  last ``recording.blackbox_s`` seconds of cycles, in memory) and offers them to each recording's
  bounded queue; a recording whose writer is so far behind that its queue is full counts the
  batch as lost rather than wait.
* one **writer** thread per recording, and one for a black box dump: CDR encoding (the ROS
  graph's type store and encoders) and rosbags' MCAP writing (recording/bag.py). A writer
  flushes its file every ``FLUSH_PERIOD_S``, which bounds what a killed daemon loses. A write
  error (disk full...) ends that recording with a ``recording_failed`` warning; the robot and
  the other recordings go on.

The event loop only queues: events and commands (``Server.listeners``, ``command_listeners``)
are put on the recordings' queues and the black box's event list; requests (``record``,
``record_stop``, ``blackbox``) await futures the threads complete.
"""

from __future__ import annotations

import asyncio
import logging
import os
import queue
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from .. import __version__
from ..core.samples import MARKER, STAMP, SampleReader, SampleRing
from ..errors import CrtkBridgeError
from ..server.protocol import ProtocolError
from .bag import BagWriter, bag_path, urdf_text

log = logging.getLogger("crtk_bridge.recording")

DRAIN_PERIOD_S = 0.02
FLUSH_PERIOD_S = 0.5  # a killed daemon loses at most this much of a recording, plus the queue
QUEUE_BATCHES = 250  # a recording's queue: drain batches (~DRAIN_PERIOD_S of cycles each), events
WARN_EVERY_S = 1.0
#: requests that are not recorded as commands: queries, subscriptions, these commands themselves
RECORDING_COMMANDS = ("record", "record_stop", "blackbox")
NOT_COMMANDS = frozenset(("measured_js", "setpoint_js", "goal_js", "operating_state", "period_statistics", "list",
                          "subscribe", "unsubscribe", "forward_kinematics", "inverse_kinematics", "measured_cp",
                          "setpoint_cp", "goal_cp", "measured_cv", "setpoint_cv", "goal_cv", "measured_cf",
                          "setpoint_cf") + RECORDING_COMMANDS)


def default_blackbox_dir() -> str:
    """``$STATE_DIRECTORY/blackbox`` under the systemd unit (StateDirectory=crtk-bridge), else
    ``$XDG_STATE_HOME/crtk-bridge/blackbox`` (``~/.local/state/...``)."""
    unit = os.environ.get("STATE_DIRECTORY")
    if unit:
        return os.path.join(unit.split(":")[0], "blackbox")
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return os.path.join(state, "crtk-bridge", "blackbox")


def _event_ns(msg: dict) -> int:
    stamp = (msg.get("data") or {}).get("stamp") or 0.0
    return int(stamp * 1e9) if stamp > 0 else time.time_ns()


class BlackBox:
    """The last ``capacity`` cycles' samples (ring rows) and the events of the same window.
    Rows are appended by the drain thread only; events by the event loop (under a lock)."""

    def __init__(self, capacity: int, width: int, window_s: float):
        self.rows = np.zeros((capacity, width))
        self.capacity = capacity
        self.window_ns = int(window_s * 1e9)
        self.count = 0  # rows held
        self.pos = 0  # next row to write
        self.events: deque[tuple[int, str, Any]] = deque()
        self.lock = threading.Lock()

    def append(self, rows: np.ndarray) -> None:
        n = len(rows)
        if n >= self.capacity:
            rows = rows[-self.capacity:]
            n = self.capacity
        end = self.pos + n
        if end <= self.capacity:
            self.rows[self.pos:end] = rows
        else:
            k = self.capacity - self.pos
            self.rows[self.pos:] = rows[:k]
            self.rows[:n - k] = rows[k:]
        self.pos = end % self.capacity
        self.count = min(self.capacity, self.count + n)

    def add(self, t_ns: int, kind: str, item: Any) -> None:
        with self.lock:
            self.events.append((t_ns, kind, item))
            limit = t_ns - self.window_ns
            while self.events and self.events[0][0] < limit:
                self.events.popleft()

    def snapshot(self) -> tuple[np.ndarray, list]:
        """The rows in cycle order (a copy) and the events since the oldest row."""
        if self.count < self.capacity:
            rows = self.rows[:self.count].copy()
        else:
            rows = np.concatenate([self.rows[self.pos:], self.rows[:self.pos]])
        first = int(rows[0, STAMP] * 1e9) if len(rows) else 0
        with self.lock:
            events = [e for e in self.events if e[0] >= first]
        return rows, events


class Recording:
    """One recording: its bag, its writer thread and the bounded queue feeding it."""

    def __init__(self, rid: int, recorder: "Recorder", path: str, session: Any, duration_s: float | None,
                 namespaces: list[str], rotate_s: float | None = None):
        """``rotate_s``: ``path`` is a folder; a new bag ``<robot>-<UTC time>`` in it every
        ``rotate_s`` seconds of cycles (the start-up recording)."""
        self.id = rid
        self.rotate_s = rotate_s
        self.segments: list[dict] = []  # the bags closed so far (rotation)
        self.recorder = recorder
        self.path = path
        self.session = session
        self.duration_s = duration_s
        self.namespaces = namespaces
        self.queue: queue.Queue = queue.Queue(maxsize=QUEUE_BATCHES)
        self.lost = 0  # cycles lost: overwritten in the ring, or dropped because the queue was full
        self.opened: asyncio.Future = recorder.loop.create_future()
        self.finished: asyncio.Future = recorder.loop.create_future()
        self.stopping = False
        self.bag: BagWriter | None = None
        self.max_write_s = 0.0  # the longest single batch write (the bench's "largest write stall")
        self._thread = threading.Thread(target=self._run, name=f"recording {rid}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def offer(self, item: tuple) -> None:
        """From the drain thread or the event loop: never blocks."""
        try:
            self.queue.put_nowait(item)
        except queue.Full:
            if item[0] == "rows":
                self.lost += len(item[1])

    def stop(self) -> None:
        if not self.stopping:
            self.stopping = True
            try:
                self.queue.put_nowait(("stop",))
            except queue.Full:  # the writer is behind: it sees `stopping` after this batch
                pass

    def _done(self, fut: asyncio.Future, value: Any) -> None:
        def set_it() -> None:
            if not fut.done():
                fut.set_result(value)
        try:
            self.recorder.loop.call_soon_threadsafe(set_it)
        except RuntimeError:
            pass  # the loop is closed: the daemon is stopping

    # ---------------------------------------------------------------- writer thread
    def _open(self, t0: int) -> BagWriter:
        """A new bag (the next segment, with rotation), its description and the current state first."""
        rec = self.recorder
        path = self.path
        if self.rotate_s is not None:
            os.makedirs(self.path, exist_ok=True)
            when = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(t0 * 1e-9))
            path = os.path.join(self.path, f"{rec.robot}-{when}-{t0 % 10**9:09d}")
        bag = BagWriter(path, rec.link, rec.robot, self.namespaces, self._spaces, rec.custom_data())
        if rec.urdf is not None:
            bag.robot_description(rec.urdf, t0)
        bag.event({"event": "operating_state", "data": rec.server.state}, t0)
        return bag

    def _run(self) -> None:
        rec = self.recorder
        spaces = self._spaces = {}
        try:
            spaces.update({ns: rec.server.cartesian_space(ns) for ns in self.namespaces if ns in rec.server.cartesian})
            self.bag = self._open(time.time_ns())
        except Exception as exc:
            for cs in spaces.values():
                cs.close()
            self._done(self.opened, f"{rec.robot}: record {self.path}: {_why(exc)}")
            self._done(self.finished, None)
            rec.forget(self)
            return
        self._done(self.opened, None)
        error = None
        try:
            self._write_until_stopped()
            size = self.bag.close(self._stats_custom())
        except Exception as exc:
            error = f"{rec.robot}: recording {self.bag.file} stopped: {_why(exc)}; the robot goes on"
            self.bag.abort()
            size = _size(self.bag.file)
        finally:
            for cs in spaces.values():
                cs.close()
            rec.forget(self)
        result = self.result(size)
        if error is not None:
            result["error"] = error
            rec.say("warning", "recording_failed", error, path=str(self.bag.file))
        self._done(self.finished, result)

    def _write_until_stopped(self) -> None:
        last_flush = time.monotonic()
        end_ns = None
        while True:
            try:
                item = self.queue.get(timeout=FLUSH_PERIOD_S / 2)
            except queue.Empty:
                item = None
            if item is not None:
                kind = item[0]
                if kind == "stop":
                    return
                t = time.perf_counter()
                if kind == "rows":
                    rows = item[1]
                    if self.rotate_s is not None and len(rows):
                        self._rotating(rows)
                    elif self.duration_s is not None and len(rows):
                        if end_ns is None:
                            end_ns = int(rows[0, STAMP] * 1e9) + int(self.duration_s * 1e9)
                        keep = (rows[:, STAMP] * 1e9).astype(np.int64) < end_ns
                        self.bag.rows(rows[keep])
                        if not keep.all():
                            return  # its duration is over
                    else:
                        self.bag.rows(rows)
                elif kind == "event":
                    self.bag.event(item[2], item[1])
                elif kind == "command":
                    self.bag.command(item[2], item[1])
                self.max_write_s = max(self.max_write_s, time.perf_counter() - t)
            if self.stopping and self.queue.empty():
                return
            now = time.monotonic()
            if now - last_flush >= FLUSH_PERIOD_S:
                t = time.perf_counter()
                self.bag.flush()
                self.max_write_s = max(self.max_write_s, time.perf_counter() - t)
                last_flush = now

    def _rotating(self, rows: np.ndarray) -> None:
        """Write ``rows``, closing the bag and opening the next one where a segment's
        ``rotate_s`` seconds of cycles end."""
        while len(rows):
            bag = self.bag
            if bag.samples == 0:
                self._segment_end = int(rows[0, STAMP] * 1e9) + int(self.rotate_s * 1e9)
            keep = (rows[:, STAMP] * 1e9).astype(np.int64) < self._segment_end
            n = int(np.count_nonzero(keep))  # a prefix: the stamps increase
            bag.rows(rows[:n])
            rows = rows[n:]
            if len(rows):
                size = bag.close(self._stats_custom())
                self.segments.append(self.result(size))
                self.bag = self._open(int(rows[0, STAMP] * 1e9))

    def _stats_custom(self) -> dict[str, str]:
        b = self.bag
        return {"first_cycle": str(b.first_cycle), "last_cycle": str(b.last_cycle), "samples": str(b.samples),
                "lost": str(self.lost)}

    def result(self, size: int) -> dict:
        b = self.bag
        out = {"recording": self.id, "path": str(b.file), "bag": str(b.dir), "samples": b.samples,
               "first_cycle": b.first_cycle, "last_cycle": b.last_cycle, "lost": self.lost,
               "messages": b.messages, "bytes": size, "max_write_s": self.max_write_s}
        if self.rotate_s is not None:
            out["segments"] = len(self.segments) + 1
        return out


class Recorder:
    """The front's recording service: started by the daemon after the server, closed before it."""

    def __init__(self, server: Any, ring: SampleRing, source: str | None = None, record_dir: str | None = None,
                 live: Any = None):
        """``live``: where the Foxglove live view listens (recording/exposure.py's Listen), or None."""
        self.server = server
        self.link = server.link
        self.profile = server.profile
        self.robot = server.robot
        self.ring = ring
        self.reader = SampleReader(ring)
        rc = self.profile.recording
        rate = 1.0 / self.link.period_s
        self.blackbox_s = rc.blackbox_s
        self.blackbox = BlackBox(max(1, int(round(rc.blackbox_s * rate))), ring.width, rc.blackbox_s) \
            if rc.blackbox_s > 0 else None
        where = rc.blackbox_dir or default_blackbox_dir()
        if source and not os.path.isabs(os.path.expanduser(where)):
            where = os.path.join(os.path.dirname(os.path.abspath(source)), where)
        self.blackbox_dir = os.path.expanduser(where)
        #: the start-up recording's folder (``--record`` or recording.dir), rotated every rotate_s
        where = record_dir or rc.dir
        if where and source and not record_dir and not os.path.isabs(os.path.expanduser(where)):
            where = os.path.join(os.path.dirname(os.path.abspath(source)), where)
        self.record_dir = os.path.abspath(os.path.expanduser(where)) if where else None
        self.rotate_s = rc.rotate_s
        self.urdf = urdf_text(self.profile)
        self.loop: asyncio.AbstractEventLoop | None = None
        self.recordings: dict[int, Recording] = {}
        self._finished: dict[int, Recording] = {}  # the last recordings that ended, by id
        self._active: tuple[Recording, ...] = ()  # what the drain thread offers samples to
        self._ids = iter(range(1, 1 << 62))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._drain_loop, name=f"recording drain {self.robot}", daemon=True)
        #: black boxes to write, in order: (path, once drained beyond this cycle, the request's future)
        self._dumps: deque[tuple[str, int, asyncio.Future | None]] = deque()
        self._dumping: threading.Thread | None = None
        self._lost_said = 0.0
        self._lost_unsaid = 0
        self._state = str(server.state.get("state"))
        self.lost = 0  # cycles overwritten in the ring before the drain read them
        self.live_listen = live
        self.live = None  # the Foxglove live view (recording/live.py), fed as the recordings are

    def custom_data(self) -> dict[str, str]:
        # prismatic_joints: the joints in m, m/s, N (profile ``unit: m``), so that a plot labels them
        return {"robot": self.robot, "daemon_version": __version__, "rate_hz": f"{1.0 / self.link.period_s:g}",
                "backend": self.profile.backend_type,
                "prismatic_joints": ",".join(j.name for j in self.profile.joints if j.unit == "m")}

    # ---------------------------------------------------------------- life cycle (event loop)
    def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.server.listeners.append(self.on_event)
        self.server.command_listeners.append(self.on_command)
        self.server.detach_listeners.append(self.on_detach)
        if self.live_listen is not None:
            from .live import LiveView  # foxglove-sdk: loaded only when asked

            live = LiveView(self, self.live_listen)
            live.start()
            self.live = live
        self._thread.start()

    async def start_recording(self) -> None:
        """The start-up recording (``--record DIR`` / recording.dir), if asked: every namespace,
        a new bag every ``recording.rotate_s``, until the daemon stops. Raises CrtkBridgeError
        naming the folder when it cannot start (start-up ends, the robot DISABLED)."""
        if self.record_dir is None:
            return
        r = Recording(next(self._ids), self, self.record_dir, None, None, list(self.link.ns_index),
                      rotate_s=self.rotate_s)
        self.recordings[r.id] = r
        r.start()
        problem = await r.opened
        if problem is not None:
            self.recordings.pop(r.id, None)
            raise CrtkBridgeError(f"{problem} (--record or profile recording.dir)")
        self._active = self._active + (r,)
        print(f"crtk-bridge: recording every cycle into {self.record_dir} (a new bag every "
              f"{self.rotate_s:g} s; docs/recording.md)", flush=True)

    async def close(self) -> None:
        """Stop every recording (their bags closed, holding the loop's last cycles) and the drain thread."""
        await self.loop.run_in_executor(None, self._wait_drained, 2.0)
        for r in list(self.recordings.values()):
            r.stop()
        for r in list(self.recordings.values()):
            try:
                await asyncio.wait_for(asyncio.shield(r.finished), 10.0)
            except asyncio.TimeoutError:
                log.error("%s: recording %s did not close in 10 s", self.robot, r.path)
        self._stop.set()
        if self._thread.ident is not None:  # started (a start-up that failed early may not have)
            await self.loop.run_in_executor(None, self._thread.join, 5.0)
        if self.live is not None:
            await self.loop.run_in_executor(None, self.live.close)
        if self._dumping is not None:
            await self.loop.run_in_executor(None, self._dumping.join, 30.0)

    def _wait_drained(self, timeout_s: float) -> None:
        """Until the drain thread took every cycle the (stopped) loop pushed."""
        deadline = time.monotonic() + timeout_s
        while self.reader.next <= self.ring.head() and self._thread.is_alive() and time.monotonic() < deadline:
            time.sleep(DRAIN_PERIOD_S / 2)

    def forget(self, r: Recording) -> None:
        """Any thread: ``r`` takes no more samples."""
        def drop() -> None:
            self.recordings.pop(r.id, None)
            self._active = tuple(x for x in self._active if x is not r)
            self._finished[r.id] = r  # record_stop still answers with its result
            while len(self._finished) > 32:
                self._finished.pop(next(iter(self._finished)))
        self._call(drop)

    def _call(self, fn, *args) -> None:
        try:
            self.loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:
            pass

    def say(self, kind: str, code: str, message: str, **extra: Any) -> None:
        """Any thread: an event to every session (and the log), as the control loop's are."""
        msg = {"event": kind, "data": {"stamp": time.time(), "ns": self.robot, "code": code, "message": message,
                                       **extra}}
        self._call(self.server.on_event, msg)

    # ---------------------------------------------------------------- listeners (event loop)
    def on_event(self, msg: dict) -> None:
        ev = msg.get("event")
        if ev not in ("operating_state", "error", "warning", "status"):
            return
        t_ns = _event_ns(msg)
        if self.blackbox is not None:
            self.blackbox.add(t_ns, "event", msg)
        for r in self._active:
            r.offer(("event", t_ns, msg))
        if self.live is not None:
            self.live.offer(("event", t_ns, msg))
        if ev == "operating_state":
            state = str(msg["data"].get("state"))
            if state == "FAULT" and self._state != "FAULT" and self.blackbox is not None:
                stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
                path = os.path.join(self.blackbox_dir, f"{self.robot}-fault-{stamp}-{int(time.time_ns() % 10**9):09d}")
                self._dumps.append((path, self.ring.head(), None))
            self._state = state

    def on_command(self, session: Any, cmd: str, ns: str | None, data: Any) -> None:
        if cmd in NOT_COMMANDS:
            return
        t_ns = time.time_ns()
        entry = {"session": session.describe(), "cmd": cmd, "ns": ns, "data": data}
        if self.blackbox is not None:
            self.blackbox.add(t_ns, "command", entry)
        for r in self._active:
            r.offer(("command", t_ns, entry))
        if self.live is not None:
            self.live.offer(("command", t_ns, entry))

    def on_detach(self, session: Any) -> None:
        """A session ended: the recordings it started stop (as its streams do)."""
        for r in list(self.recordings.values()):
            if r.session is session:
                r.stop()

    # ---------------------------------------------------------------- requests (event loop)
    async def request(self, session: Any, cmd: str, data: dict) -> Any:
        if cmd == "record":
            return await self.record(session, data["path"], data.get("duration_s"), data.get("namespaces"))
        if cmd == "record_stop":
            return await self.record_stop(session, data.get("recording"), data.get("wait", False))
        return await self.write_blackbox(data["path"])

    async def record(self, session: Any, path: str, duration_s: float | None, namespaces: list[str] | None) -> dict:
        known = list(self.link.ns_index)
        if namespaces:
            unknown = [ns for ns in namespaces if ns not in known]
            if unknown:
                raise ProtocolError("unknown_namespace", f"{self.robot}: record refused: unknown namespace "
                                    f"{unknown[0]!r} (have: {', '.join(known)})")
        bag, _ = bag_path(path)
        if bag.exists():
            raise ProtocolError("bad_request", f"{self.robot}: record refused: {bag} exists already; give another path")
        for r in self.recordings.values():
            if r.bag is not None and r.bag.dir == bag or bag_path(r.path)[0] == bag:
                raise ProtocolError("bad_request", f"{self.robot}: record refused: {bag} is being recorded already")
        r = Recording(next(self._ids), self, path, session, duration_s, list(namespaces or known))
        self.recordings[r.id] = r
        r.start()
        problem = await r.opened
        if problem is not None:
            self.recordings.pop(r.id, None)
            raise ProtocolError("bad_request", problem)
        self._active = self._active + (r,)
        return {"recording": r.id, "path": str(r.bag.file), "bag": str(r.bag.dir)}

    async def record_stop(self, session: Any, rid: int | None, wait: bool) -> dict:
        if rid is None:
            mine = [r for r in self.recordings.values() if r.session is session]
            if not mine:
                raise ProtocolError("bad_request", f"{self.robot}: record_stop: this session records nothing")
            r = mine[-1]
        else:
            r = self.recordings.get(rid) or self._finished.get(rid)
            if r is None:
                raise ProtocolError("bad_request", f"{self.robot}: record_stop: no recording {rid}")
        if not (wait and r.duration_s is not None):
            r.stop()
        return await asyncio.shield(r.finished)

    async def write_blackbox(self, path: str) -> dict:
        if self.blackbox is None:
            raise ProtocolError("unsupported", f"{self.robot}: blackbox: no black box (profile recording.blackbox_s is 0)")
        bag, _ = bag_path(path)
        if bag.exists():
            raise ProtocolError("bad_request", f"{self.robot}: blackbox refused: {bag} exists already; give another path")
        if any(bag_path(d[0])[0] == bag for d in self._dumps):
            raise ProtocolError("bad_request", f"{self.robot}: blackbox refused: {bag} is being written already")
        fut = self.loop.create_future()
        self._dumps.append((path, self.ring.head(), fut))
        result = await fut
        if "error" in result:
            raise ProtocolError("internal", result["error"])
        return result

    # ---------------------------------------------------------------- drain thread
    def _drain_loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._drain_once()
            except Exception:  # a bug must not end the black box silently
                log.exception("%s: draining the sample ring failed", self.robot)
            self._stop.wait(DRAIN_PERIOD_S)
        try:
            self._drain_once()  # the last cycles for the recordings closing
        except Exception:
            pass

    def _drain_once(self) -> None:
        rows, lost = self.reader.drain()
        if lost:
            self.lost += lost
            for r in self._active:
                r.lost += lost
            self._lost_unsaid += lost
        if self._lost_unsaid and time.monotonic() - self._lost_said >= WARN_EVERY_S:
            self._lost_said = time.monotonic()
            self.say("warning", "samples_lost", f"{self.robot}: {self._lost_unsaid} cycles' samples were overwritten "
                     f"in the ring before the front read them ({self.lost} since start); the front process is "
                     "starved of CPU", value=self._lost_unsaid)
            self._lost_unsaid = 0
        if len(rows):
            if self.blackbox is not None:
                self.blackbox.append(rows)
            for r in self._active:
                if not r.stopping:
                    r.offer(("rows", rows))
            if self.live is not None:
                self.live.offer(("rows", rows))
        dump = self._dumps[0] if self._dumps else None
        if dump is not None and self.reader.next > dump[1] and (self._dumping is None or not self._dumping.is_alive()):
            self._dumps.popleft()
            snap = self.blackbox.snapshot()
            self._dumping = threading.Thread(target=self._write_dump, args=(dump[0], snap, dump[2]),
                                             name=f"black box {self.robot}", daemon=True)
            self._dumping.start()

    def _write_dump(self, path: str, snap: tuple[np.ndarray, list], fut: asyncio.Future | None) -> None:
        rows, events = snap
        spaces = {}
        bag = None
        result: dict = {}
        try:
            if fut is None:
                os.makedirs(self.blackbox_dir, exist_ok=True)
            spaces = {ns: self.server.cartesian_space(ns) for ns in self.server.cartesian}
            bag = BagWriter(path, self.link, self.robot, list(self.link.ns_index), spaces, self.custom_data())
            t0 = int(rows[0, STAMP] * 1e9) if len(rows) else time.time_ns()
            if self.urdf is not None:
                bag.robot_description(self.urdf, t0)
            bag.rows(rows)
            for t_ns, kind, item in events:
                if kind == "event":
                    bag.event(item, t_ns)
                else:
                    bag.command(item, t_ns)
            first, last = (int(rows[0, MARKER]), int(rows[-1, MARKER])) if len(rows) else (-1, -1)
            size = bag.close({"first_cycle": str(first), "last_cycle": str(last), "samples": str(len(rows)),
                              "window_s": f"{self.blackbox_s:g}"})
            span = (rows[-1, STAMP] - rows[0, STAMP]) if len(rows) else 0.0
            result = {"path": str(bag.file), "bag": str(bag.dir), "samples": len(rows), "first_cycle": first,
                      "last_cycle": last, "seconds": float(span), "bytes": size}
            if fut is None:
                self.say("status", "blackbox_written", f"{self.robot}: black box of the {span:.1f} s before the "
                         f"fault written to {bag.file}", path=str(bag.file))
        except Exception as exc:
            if bag is not None:
                bag.abort()
            result = {"error": f"{self.robot}: black box {bag_path(path)[1]} not written: {_why(exc)}"}
            if fut is None:
                self.say("warning", "blackbox_failed", result["error"], path=str(bag_path(path)[1]))
        finally:
            for cs in spaces.values():
                cs.close()
        if fut is not None:
            self._call(lambda: fut.done() or fut.set_result(result))


def _why(exc: Exception) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}" + (f" ({exc.filename})" if exc.filename else "")
    return str(exc) or exc.__class__.__name__


def _size(path: Any) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0

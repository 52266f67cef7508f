"""The live view in Foxglove (``crtk-bridge --foxglove-listen HOST:PORT``; docs/recording.md).

foxglove-sdk's WebSocket server (protocol ``foxglove.sdk.v1`` / ws-protocol), in the front process
only, started after the control process is forked. It carries the ROS 2 graph's topics, types and
CDR bytes (the recording's: recording/bag.py's encoders, ``ros2msg`` schemas from the graph's type
store), so Foxglove decodes them as it does a bag or a ROS 2 connection, plus ``/robot_description``
(the URDF) for its 3D panel. Read-only: no client publishing, services or parameters are offered.

Fed by the recorder's drain of the control loop's sample ring (recording/recorder.py), never by
the control process, and written by one thread of its own off the event loop: the drain offers
batches to a bounded queue (a full queue drops the batch, counted; the robot and the recordings
never wait for a viewer). Joint and pose topics go out at most ``RATE_HZ`` samples a second (a
viewer's refresh; a recording holds every cycle), and only while a client is subscribed.
Latched topics (``/robot_description``, ``operating_state``) are sent again to each new subscriber.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any

import numpy as np

from ..core.samples import STAMP, STATE
from ..errors import CrtkBridgeError
from ..transport.ros import types as T
from .bag import BagWriter
from .exposure import Listen

log = logging.getLogger("crtk_bridge.recording.live")

RATE_HZ = 100.0
QUEUE_ITEMS = 500  # drain batches (~20 ms of cycles each) and events: ~10 s


class LiveWriter(BagWriter):
    """A BagWriter whose storage is a set of Foxglove channels of ``context``: same topics,
    same CDR, no file."""

    def __init__(self, context: Any, link: Any, robot: str, namespaces: list[str], spaces: dict):
        self._context = context
        super().__init__("live", link, robot, namespaces, spaces)
        self.channels = dict(self._conns)
        # /tf: the graph's base -> tip, plus base -> every URDF link at the measured positions (what
        # robot_state_publisher adds on a ROS system), so that Foxglove's 3D panel poses the arm
        self._links_tf, self._tf = self._tf, None

    def _open_storage(self, custom: dict[str, str] | None) -> None:
        self.writer = None

    def _connect(self, topic: str, ros_type: str, qos: Any) -> Any:
        import foxglove

        msgdef = T.TYPESTORE.generate_msgdef(ros_type, ros_version=2)[0]
        return foxglove.Channel(topic, schema=foxglove.Schema(name=ros_type, encoding="ros2msg",
                                                              data=msgdef.encode()),
                                message_encoding="cdr", context=self._context)

    def _write(self, conn: Any, t_ns: int, data: bytes) -> None:
        conn.log(bytes(data), log_time=t_ns)
        self.messages += 1

    def rows(self, rows: np.ndarray) -> None:
        super().rows(rows)
        if self._links_tf is None:
            return
        link = self.link
        for row in rows:
            buf = row[STATE:]
            poses = []
            for ns, cs, _ in self._cart:
                st = link.ns_arrays(ns, buf)
                tip = cs.query("measured_cp", st, "spatial")
                poses.append(tip)
                kin = getattr(cs, "kin", None)
                if kin is None or not st["measured_stamp"] > 0:
                    continue
                for name, p, q in kin.link_poses(st["measured_p"]):
                    if name != tip["child_frame_id"]:
                        poses.append({"stamp": tip["stamp"], "frame_id": tip["frame_id"], "child_frame_id": name,
                                      "position": p, "orientation": q})
            if poses:
                self._write(self._links_tf, int(row[STAMP] * 1e9), self.enc.tf(poses))

    def watched(self) -> bool:
        """Whether a client is subscribed to any periodic topic."""
        return any(conn.has_sinks() for _, _, conn in self._js) or \
            (self._links_tf is not None and self._links_tf.has_sinks()) \
            or any(conn.has_sinks() for _, _, topics in self._cart for _, conn in topics)


class LiveView:
    """The server, its channels and its thread. ``start`` on the event loop (raises
    CrtkBridgeError naming --foxglove-listen when the server cannot start); ``offer`` from the
    drain thread or the event loop; ``close`` at shutdown."""

    def __init__(self, recorder: Any, listen: Listen):
        self.recorder = recorder
        self.listen = listen
        self.queue: queue.Queue = queue.Queue(maxsize=QUEUE_ITEMS)
        self.dropped = 0
        self.server = None
        self.writer: LiveWriter | None = None
        self.port = listen.port
        self._spaces: dict = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"foxglove {recorder.robot}", daemon=True)
        self._last_ns = 0

    def start(self) -> None:
        import foxglove
        from foxglove.websocket import ServerListener

        rec = self.recorder
        ctx = foxglove.Context()
        self._spaces = {ns: rec.server.cartesian_space(ns) for ns in rec.server.cartesian}
        self.writer = LiveWriter(ctx, rec.link, rec.robot, list(rec.link.ns_index), self._spaces)
        latched = {conn.id(): name for (ns, name), conn in self.writer.channels.items()
                   if name in ("robot_description", "operating_state")}
        view = self

        class Listener(ServerListener):
            def on_subscribe(self, client, channel) -> None:  # an SDK thread
                if channel.id in latched:
                    view.offer(("latched", latched[channel.id]))

        kwargs = {}
        if self.listen.tls_cert:
            try:
                with open(self.listen.tls_cert, "rb") as c, open(self.listen.tls_key, "rb") as k:
                    kwargs.update(tls_cert=c.read(), tls_key=k.read())
            except OSError as exc:
                raise CrtkBridgeError(f"{rec.robot}: --foxglove-listen: cannot read {exc.filename}: {exc.strerror} "
                                      "(transport.zenoh.tls)") from None
        try:
            self.server = foxglove.start_server(name=f"crtk-bridge {rec.robot}", host=self.listen.host,
                                                port=self.listen.port, context=ctx, capabilities=[],
                                                server_listener=Listener(), **kwargs)
        except Exception as exc:  # the SDK raises its own error types (address in use...)
            raise CrtkBridgeError(f"{rec.robot}: --foxglove-listen {self.listen.host}:{self.listen.port}: "
                                  f"the Foxglove server did not start: {exc}") from None
        self.port = self.server.port
        self._thread.start()

    @property
    def url(self) -> str:
        return self.listen._replace(port=self.port).url

    def offer(self, item: tuple) -> None:
        try:
            self.queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def close(self) -> None:
        self._stop.set()
        self.offer(("stop",))
        if self._thread.is_alive():
            self._thread.join(5.0)
        if self.server is not None:
            self.server.stop()
        for cs in self._spaces.values():
            cs.close()

    # ---------------------------------------------------------------- its thread
    def _run(self) -> None:
        rec, w = self.recorder, self.writer
        if rec.urdf is not None:
            w.robot_description(rec.urdf, time.time_ns())
        while not self._stop.is_set():
            item = self.queue.get()
            try:
                kind = item[0]
                if kind == "stop":
                    return
                if kind == "rows":
                    if w.watched():
                        w.rows(self._decimated(item[1]))
                elif kind == "event":
                    w.event(item[2], item[1])
                elif kind == "command":
                    w.command(item[2], item[1])
                elif kind == "latched":
                    if item[1] == "robot_description" and rec.urdf is not None:
                        w.robot_description(rec.urdf, time.time_ns())
                    elif item[1] == "operating_state":
                        w.event({"event": "operating_state", "data": dict(rec.server.state)}, time.time_ns())
            except Exception:  # a viewer's problem must not end the live view silently
                log.exception("%s: Foxglove live view", rec.robot)

    def _decimated(self, rows: np.ndarray) -> np.ndarray:
        """The rows at least 1/RATE_HZ apart (on the loop's clock) since the last one sent."""
        step = int(1e9 / RATE_HZ)
        keep = []
        last = self._last_ns
        for i, t in enumerate((rows[:, STAMP] * 1e9).astype(np.int64)):
            if t - last >= step:
                keep.append(i)
                last = int(t)
        self._last_ns = last
        return rows[keep]

"""The client's Zenoh transport (docs/zenoh.md, "Remote clients"): the socket protocol carried
over Zenoh, so that :class:`~crtk_client.connection.Connection` (and with it ``Robot``,
``Device``, ``crtk-ctl``) works unchanged on the arm's PC or across the lab.

:class:`ZenohStream` offers the few socket methods ``Connection`` uses (``sendall``, ``recv``,
``shutdown``, ``close``). Opening one declares the client's liveliness token, which opens a
session in the daemon (transport/tunnel.py); the daemon greets it with the operating state, and
the stream is open once that greeting arrived. Closing the stream (or losing the process or the
link) removes the token: the daemon handles it as a socket closing (client loss). The daemon's
token going away ends the stream as a socket's EOF would.

The session is a Zenoh client (it talks only to the router or peer it connects to), with
multicast scouting off.
"""

from __future__ import annotations

import queue
import socket
import threading
import time
import uuid
from typing import Any, Iterable

from crtk_client.connection import DaemonConnectionError
from crtk_client.errors import CrtkBridgeError
from crtk_client import tunnel_keys as keys
from crtk_client.zenoh_lease import ZENOH_LEASE_MS_DEFAULT, zenoh_lease_problem
from crtk_client.zenoh_session import SessionConfig, ZenohConnectError, open_session

#: who the one-line errors name, and the option that sets the endpoint
WHO = "crtk-bridge client"
HINT = "--zenoh-connect"
#: how long a client waits for the robot it asked for to show up on the network before saying so
DISCOVERY_S = 1.0


def _endpoints(zenoh_connect: str | Iterable[str]) -> list[str]:
    return [zenoh_connect] if isinstance(zenoh_connect, str) else list(zenoh_connect)


def open_client_session(zenoh_connect: str | Iterable[str], timeout: float, zenoh_config: str | None = None,
                        lease_ms: int | None = None) -> Any:
    """A Zenoh client session connected to ``zenoh_connect`` (an endpoint or several). Blocks up
    to ``timeout`` s. ``zenoh_config``: a Zenoh configuration file (JSON5) for what the endpoint
    needs beyond it, e.g. ``transport/link/tls/root_ca_certificate`` for a ``tls/`` router; the
    mode, endpoints, multicast scouting (off) and lease are set over it. ``lease_ms``: the link
    lease this client announces (default ZENOH_LEASE_MS_DEFAULT): the daemon, or the router
    between, drops this client after that much silence, which is how a frozen client's control
    is released. Raises DaemonConnectionError in one line naming the endpoint and what to do
    when it does not answer, CrtkBridgeError naming ``--zenoh-lease-ms`` on a lease out of range."""
    lease_ms = ZENOH_LEASE_MS_DEFAULT if lease_ms is None else lease_ms
    problem = zenoh_lease_problem(lease_ms)
    if problem:
        raise CrtkBridgeError(f"{WHO}: --zenoh-lease-ms (zenoh_lease_ms): {problem}")
    config = SessionConfig(mode="client", connect=_endpoints(zenoh_connect), listen=[], connect_timeout_s=timeout,
                         lease_ms=lease_ms)
    try:
        return open_session(config, WHO, hint=HINT, base=zenoh_config)
    except ZenohConnectError as exc:
        raise DaemonConnectionError(str(exc)) from None


def robots_on(session: Any, timeout: float) -> list[str]:
    """The robots whose daemons serve on this Zenoh network (their liveliness tokens), sorted."""
    replies = session.liveliness().get(keys.ALL_DAEMONS, timeout=timeout)
    return sorted({keys.robot_of(str(r.ok.key_expr)) for r in replies if r.ok is not None})


def list_robots(zenoh_connect: str | Iterable[str], timeout: float = 5.0, zenoh_config: str | None = None,
                lease_ms: int | None = None) -> list[str]:
    """The robots served on the Zenoh network at ``zenoh_connect``, sorted. Blocks for one
    liveliness query. Raises DaemonConnectionError when the endpoint does not answer."""
    session = open_client_session(zenoh_connect, timeout, zenoh_config, lease_ms)
    try:
        return robots_on(session, timeout)
    finally:
        session.close()


def where(zenoh_connect: str | Iterable[str], robot: str) -> str:
    """How messages name a robot reached over Zenoh: ``so101 over Zenoh (tcp/127.0.0.1:7447)``."""
    return f"{robot} over Zenoh ({', '.join(_endpoints(zenoh_connect))})"


class ZenohStream:
    """A byte stream to the daemon of ``robot``, opened on ``session``. Blocks until the daemon
    greeted this client (at most ``timeout`` s); raises DaemonConnectionError when it does not.
    ``owns_session``: close the Zenoh session with the stream."""

    def __init__(self, session: Any, robot: str, timeout: float, owns_session: bool = True, name: str = ""):
        import zenoh

        self.robot = robot
        self.cid = uuid.uuid4().hex
        self.name = name or robot
        self._session = session
        self._owns = owns_session
        self._chunks: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self._first: list[bytes] = []
        self._closed = threading.Event()
        self._entities: list[Any] = []
        live = session.liveliness()
        # callbacks run on Zenoh's own threads (indirect=False): a Python thread per subscriber
        # (the default) would keep a script that forgot close() from exiting
        on_reply = zenoh.handlers.Callback(self._on_reply, indirect=False)
        on_daemon = zenoh.handlers.Callback(self._on_daemon, indirect=False)
        try:
            # the reply subscriber first: it must exist before the daemon, seeing the token, greets
            self._entities.append(session.declare_subscriber(keys.replies(robot, self.cid), on_reply))
            # history: the token already declared is then known to this session, so losing the
            # link (the daemon frozen, killed, unplugged: no undeclaration ever sent) delivers its
            # DELETE; without it only an explicit undeclaration would, and requests would hang
            self._entities.append(live.declare_subscriber(keys.daemon_token(robot), on_daemon, history=True))
            self._pub = session.declare_publisher(keys.requests(robot, self.cid),
                                                  congestion_control=zenoh.CongestionControl.BLOCK,
                                                  reliability=zenoh.Reliability.RELIABLE)
            self._entities.append(self._pub)
            self._entities.append(live.declare_token(keys.client_token(robot, self.cid)))
            try:
                greeting = self._chunks.get(timeout=timeout)
            except queue.Empty:
                greeting = b""
            if not greeting:
                raise DaemonConnectionError(f"crtk-bridge daemon of {self.name} did not answer within {timeout:g} s")
            self._first.append(greeting)
        except BaseException:
            self.close()
            raise

    # -- Zenoh threads -----------------------------------------------------------------------
    def _on_reply(self, sample: Any) -> None:
        self._chunks.put(sample.payload.to_bytes())

    def _on_daemon(self, sample: Any) -> None:
        if str(sample.kind).endswith("DELETE"):
            self._chunks.put(b"")  # the daemon went away: end of stream

    # -- what Connection uses ----------------------------------------------------------------
    def sendall(self, data: bytes) -> None:
        if self._closed.is_set():
            raise OSError("the Zenoh stream is closed")
        try:
            self._pub.put(data)
        except Exception as exc:
            raise OSError(str(exc)) from exc

    def recv(self, size: int) -> bytes:
        """The next message the daemon sent (one or more whole lines); b"" at the end."""
        if self._first:
            return self._first.pop()
        chunk = self._chunks.get()
        if not chunk:
            self._chunks.put(b"")  # every later recv sees the end too
        return chunk

    def shutdown(self, how: int = socket.SHUT_RDWR) -> None:
        self._chunks.put(b"")

    def close(self) -> None:
        """Leave: the token goes first, so the daemon ends this client's session at once."""
        if self._closed.is_set():
            return
        self._closed.set()
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except Exception:
                pass
        self._entities = []
        self._chunks.put(b"")
        if self._owns:
            try:
                self._session.close()
            except Exception:
                pass


def open_stream(zenoh_connect: str | Iterable[str], robot: str | None, timeout: float,
                zenoh_config: str | None = None, lease_ms: int | None = None) -> ZenohStream:
    """Join the Zenoh network at ``zenoh_connect`` and open a stream to the daemon of ``robot``
    (default: the only robot there). Raises DaemonConnectionError in one line: the endpoint does
    not answer (start a router, check the address), no daemon there, or several and none chosen.
    ``zenoh_config``, ``lease_ms``: see :func:`open_client_session`."""
    session = open_client_session(zenoh_connect, timeout, zenoh_config, lease_ms)
    try:
        found = robots_on(session, timeout)
        # discovery is eventually consistent: a session just opened may not see every token yet
        settle = time.monotonic() + min(timeout, DISCOVERY_S)
        while (robot not in found if robot else not found) and time.monotonic() < settle:
            time.sleep(0.05)
            found = robots_on(session, timeout)
        at = ", ".join(_endpoints(zenoh_connect))
        if robot is None:
            if len(found) != 1:
                raise DaemonConnectionError(
                    f"no crtk-bridge daemon on the Zenoh network at {at} (start one with --zenoh-connect {at})"
                    if not found else
                    f"several robots on the Zenoh network at {at}, choose one with --robot: {', '.join(found)}")
            robot = found[0]
        elif robot not in found:
            raise DaemonConnectionError(
                f"no crtk-bridge daemon for robot {robot!r} on the Zenoh network at {at} "
                f"(robots there: {', '.join(found) or 'none'})")
    except BaseException:
        session.close()
        raise
    return ZenohStream(session, robot, timeout, owns_session=True, name=where(zenoh_connect, robot))

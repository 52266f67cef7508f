"""Opening a Zenoh session (docs/zenoh.md): the configuration keys every crtk-bridge session sets
(multicast scouting off, exactly the configured endpoints, start-up failing rather than retrying
forever, the link lease), and the one-line errors when a router does not answer or a port is
taken. Shared by the client (:mod:`crtk_client.zenoh_link`) and the daemon's front process
(``crtk_bridge.transport.zenoh_session``, which adds the profile's section and the exposure rule).

Imports ``zenoh`` lazily: importing this module costs nothing without the ``zenoh`` extra.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any, Iterable

import msgspec

from .errors import CrtkBridgeError
from .zenoh_lease import ZENOH_KEEP_ALIVE_PER_LEASE, ZENOH_LEASE_MS_DEFAULT

if TYPE_CHECKING:
    import zenoh


class SessionConfig(msgspec.Struct, kw_only=True):
    """What :func:`session_config` reads of a session's configuration: the daemon passes its
    profile's ``transport.zenoh`` section (the same fields), a client builds this one."""

    mode: str = "client"  # "peer" or "client"
    connect: list[str] = []
    listen: list[str] = []
    connect_timeout_s: float = 5.0
    lease_ms: int = ZENOH_LEASE_MS_DEFAULT
    tls: Any = None  # an object whose struct fields are transport/link/tls keys
    access_control: Any = None


#: endpoint protocols whose links are encrypted and authenticated by transport/link/tls
SECURE_PROTOCOLS = ("tls", "quic")
#: endpoint protocols that never leave this machine
LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe")


class ZenohConfigError(CrtkBridgeError):
    """The Zenoh transport's configuration is unsafe or invalid (names the profile key)."""


class ZenohConnectError(CrtkBridgeError, ConnectionError):
    """The Zenoh session could not open: a router or peer unreachable, a listen refused."""


def endpoint_host(endpoint: str) -> tuple[str, str]:
    """``tcp/127.0.0.1:7447?x=y`` -> (``tcp``, ``127.0.0.1``); ``tcp/[::1]:7447`` -> (``tcp``, ``::1``).
    The host is empty for a protocol without one (a Unix socket path). Raises ZenohConfigError when
    the endpoint has no ``protocol/`` prefix."""
    proto, sep, rest = endpoint.partition("/")
    if not sep or not proto or not rest:
        raise ZenohConfigError(f"{endpoint!r} is not a Zenoh endpoint (protocol/address, e.g. tcp/127.0.0.1:7447)")
    if proto in LOCAL_PROTOCOLS:
        return proto, ""
    address = rest.split("?", 1)[0].split("#", 1)[0]
    if address.startswith("["):
        return proto, address[1:].partition("]")[0]
    return proto, address.rsplit(":", 1)[0]


#: the longest a Zenoh session handshake may take (ms) on a link that opened: a few round trips,
#: well under a second on a LAN or over TLS across the internet
HANDSHAKE_MS_MAX = 2000


def handshake_ms(connect_timeout_s: float) -> int:
    """Zenoh's ``transport/unicast/open_timeout`` for a session whose start-up waits
    ``connect_timeout_s`` for each endpoint: that, at most HANDSHAKE_MS_MAX, at least 100 ms."""
    return max(100, int(min(HANDSHAKE_MS_MAX, connect_timeout_s * 1000)))


def session_config(config: Any, extra: dict[str, Any] | None = None,
                   base: str | None = None) -> "zenoh.Config":
    """The ``zenoh.Config`` of ``config``: multicast scouting off, exactly the configured endpoints,
    start-up failing (instead of retrying forever) when a connect endpoint does not answer within
    ``connect_timeout_s`` or a listen endpoint cannot be bound, the link lease ``lease_ms`` with a
    keep-alive every lease/4 (a peer expires this session after the lease IT was announced, and
    this session expires each peer after the peer's own: docs/zenoh.md, "Lease"). ``extra``: more
    Zenoh keys (path -> JSON value), e.g. ``{"timestamping/enabled": True}``. ``base``: a Zenoh configuration file
    (JSON5, Zenoh's own format: TLS, user-password authentication...) the keys above are set over."""
    import zenoh

    keys: dict[str, Any] = {
        "mode": config.mode,
        "scouting/multicast/enabled": False,
        "connect/endpoints": list(config.connect),
        "listen/endpoints": list(config.listen) if config.mode == "peer" else [],
        "connect/timeout_ms": int(config.connect_timeout_s * 1000),
        "connect/exit_on_failure": True,
        "listen/exit_on_failure": True,
        # announced to every peer at link open (OpenSyn/OpenAck): the peer drops this session after
        # that much silence; keep-alives go out on an idle link every lease/keep_alive
        "transport/link/tx/lease": config.lease_ms,
        "transport/link/tx/keep_alive": ZENOH_KEEP_ALIVE_PER_LEASE,
        # how long opening a link's session (Zenoh's handshake) may take: a client that lost its
        # daemon retries its endpoint, and a frozen daemon's kernel still accepts the TCP
        # connection, so the handshake hangs; closing the session waits for it (Zenoh's 10 s
        # default). A handshake is a few round trips: bounded by the start-up timeout and
        # HANDSHAKE_MS_MAX, closing a client whose daemon froze takes at most that
        "transport/unicast/open_timeout": handshake_ms(config.connect_timeout_s),
        # HLC timestamps on samples, as rmw_zenoh's default session has them: zenoh.ext's
        # AdvancedPublishers (the ROS graph's, transport/ros) need them for their sequencing
        "timestamping/enabled": True,
    }
    if config.tls is not None:
        for name in config.tls.__struct_fields__:
            value = getattr(config.tls, name)
            if value is not None:
                keys[f"transport/link/tls/{name}"] = value
    if config.access_control is not None:
        keys["access_control"] = config.access_control
    keys.update(extra or {})
    try:
        conf = zenoh.Config.from_file(base) if base else zenoh.Config()
    except (zenoh.ZError, OSError, ValueError) as exc:
        raise ZenohConfigError(f"cannot use the Zenoh configuration file {base}: {_first_line(exc)}") from None
    for path, value in keys.items():
        try:
            conf.insert_json5(path, json.dumps(value))
        except zenoh.ZError as exc:
            raise ZenohConfigError(f"Zenoh configuration key {path} = {json.dumps(value)} refused: "
                                   f"{_first_line(exc)}") from None
    return conf


#: /proc/net tables of this process's sockets, by the kind of endpoint they carry, and the state
#: of a listening socket in each (include/net/tcp_states.h: TCP_LISTEN 0x0A; an unconnected UDP
#: socket is TCP_CLOSE 0x07)
_PROC_NET = {"tcp": (("tcp", "tcp6"), "0A"), "udp": (("udp", "udp6"), "07")}
#: the socket kind of each endpoint protocol that binds a port
_PORT_KIND = {"tcp": "tcp", "tls": "tcp", "ws": "tcp", "udp": "udp", "quic": "udp"}


def _proc_address(hex_address: str) -> tuple[str, int]:
    """A /proc/net address ``0100007F:1F90`` -> (``127.0.0.1``, 8080); IPv6 too."""
    import socket

    addr, port = hex_address.split(":")
    raw = bytes.fromhex(addr)
    raw = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))  # host order per 32-bit word
    family = socket.AF_INET if len(raw) == 4 else socket.AF_INET6
    return socket.inet_ntop(family, raw), int(port, 16)


def listening_ports() -> set[tuple[str, str, int]]:
    """The ports this process listens on now: (kind "tcp" / "udp", host, port). Linux (/proc);
    empty elsewhere."""
    import os

    try:
        inodes = set()
        for fd in os.listdir("/proc/self/fd"):
            try:
                link = os.readlink(f"/proc/self/fd/{fd}")
            except OSError:
                continue
            if link.startswith("socket:["):
                inodes.add(link[8:-1])
        found = set()
        for kind, (tables, state) in _PROC_NET.items():
            for table in tables:
                try:
                    with open(f"/proc/self/net/{table}") as f:
                        next(f)
                        for line in f:
                            cols = line.split()
                            if cols[3] == state and cols[9] in inodes:
                                found.add((kind, *_proc_address(cols[1])))
                except OSError:
                    continue
        return found
    except OSError:
        return set()


def bound_listen(listen: Iterable[str], new: set[tuple[str, str, int]]) -> list[str]:
    """``listen`` with each endpoint on port 0 given the port its listener was bound on (one of
    ``new``, the ports that appeared when the session opened, by kind and host); an endpoint
    whose port cannot be found is kept as it is."""
    out = []
    left = sorted(new)
    for endpoint in listen:
        proto, host = endpoint_host(endpoint)
        base, _, query = endpoint.partition("?")
        kind = _PORT_KIND.get(proto)
        if kind is None or not base.endswith(":0"):
            out.append(endpoint)
            continue
        match = next((p for p in left if p[0] == kind and p[1] == host), None) or \
            next((p for p in left if p[0] == kind and p[1] in ("0.0.0.0", "::")), None)
        if match is None:
            out.append(endpoint)
            continue
        left.remove(match)
        out.append(f"{base[:-1]}{match[2]}" + (f"?{query}" if query else ""))
    return out


def open_session(config: Any, robot: str, extra: dict[str, Any] | None = None,
                 hint: str = "--zenoh-connect / transport.zenoh.connect", base: str | None = None,
                 bound: list[str] | None = None) -> "zenoh.Session":
    """Open the Zenoh session ``config`` describes. Blocks until every connect endpoint answered
    (at most ``connect_timeout_s``). ``robot`` prefixes errors (a robot name, or the client);
    ``hint`` names where the connect endpoints were set; ``base``: see :func:`session_config`.
    ``bound``: filled with the listen endpoints as bound, a port 0 replaced by the one the system
    gave (what to tell a peer). Raises ZenohConnectError in one line naming the endpoint and what
    to do (start a router, check the address, free the port), ZenohConfigError on a configuration
    Zenoh refuses."""
    import zenoh

    conf = session_config(config, extra, base)
    before = listening_ports() if bound is not None else set()
    try:
        session = zenoh.open(conf)
        if bound is not None:
            bound[:] = bound_listen(config.listen if config.mode == "peer" else [], listening_ports() - before)
        return session
    except zenoh.ZError as exc:
        text = _first_line(exc)
        if "connect" in text.lower() and config.connect:
            endpoints = ", ".join(config.connect)
            port = config.connect[0].rsplit(":", 1)[-1]
            tls = any(endpoint_host(e)[0] in SECURE_PROTOCOLS for e in config.connect)
            raise ZenohConnectError(
                f"{robot}: cannot reach the Zenoh router or peer at {endpoints} within "
                f"{config.connect_timeout_s:g} s: start a router there (e.g. `zenohd -l tcp/127.0.0.1:{port}`) "
                f"or check the address ({hint})"
                + ("; a tls/ endpoint also needs the CA that signed its certificate "
                   "(transport/link/tls/root_ca_certificate)" if tls else "")) from None
        if config.listen and ("listen" in text.lower() or "bind" in text.lower() or "address" in text.lower()):
            raise ZenohConnectError(
                f"{robot}: cannot listen on {', '.join(config.listen)} ({text}): is the port in use? "
                f"(--zenoh-listen / transport.zenoh.listen)") from None
        raise ZenohConnectError(f"{robot}: cannot open the Zenoh session: {text}") from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text.split(" at /", 1)[0].rstrip(". ")  # drop the Rust source location

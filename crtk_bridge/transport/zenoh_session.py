"""The Zenoh session: its configuration, the exposure rule, and opening it (docs/zenoh.md).

Used by the daemon's front process (never the control process: a Zenoh session does not survive
fork, so it is opened after the control process exists) and by the Python client. The defaults
are safe: multicast scouting off, listening on loopback only. An endpoint beyond this PC (a
listen on 0.0.0.0 or a LAN address, a connect to another machine's router) is refused unless it
is a TLS endpoint, certificates are configured and Zenoh's access control is enabled: anyone who
can publish on the robot's keys can move it.

    config = zenoh_config(profile, connect=["tcp/127.0.0.1:7447"])   # None: the transport is off
    check_exposure(config, "so101")                                  # before anything starts
    session = open_session(config, "so101")                          # blocks up to connect_timeout_s

Imports ``zenoh`` lazily, so that the daemon without the transport never loads it.
"""

from __future__ import annotations

import ipaddress
import json
from typing import TYPE_CHECKING, Any, Iterable

import msgspec

from ..errors import CrtkBridgeError
from ..profile import ZENOH_KEEP_ALIVE_PER_LEASE, Profile, ZenohTransport

if TYPE_CHECKING:
    import zenoh

#: The transport's configuration: the profile's ``transport.zenoh`` section with the command
#: line's endpoints and domain id applied (profile.py holds the struct, so profiles validate it).
ZenohConfig = ZenohTransport

#: endpoint protocols whose links are encrypted and authenticated by transport/link/tls
SECURE_PROTOCOLS = ("tls", "quic")
#: endpoint protocols that never leave this machine
LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe")


class ZenohConfigError(CrtkBridgeError):
    """The Zenoh transport's configuration is unsafe or invalid (names the profile key)."""


class ZenohConnectError(CrtkBridgeError, ConnectionError):
    """The Zenoh session could not open: a router or peer unreachable, a listen refused."""


def zenoh_config(profile: Profile, connect: Iterable[str] | None = None, listen: Iterable[str] | None = None,
                 ros_domain_id: int | None = None) -> ZenohConfig | None:
    """The transport's configuration: the profile's ``transport.zenoh`` section with the command
    line's endpoints (``--zenoh-connect`` / ``--zenoh-listen``, each replacing the profile's list
    when given) and ``--ros-domain-id``. ``None`` when the transport is off (no section and no
    endpoint on the command line). Pure."""
    connect = list(connect or ())
    listen = list(listen or ())
    base = profile.transport.zenoh
    if base is None:
        if not connect and not listen:
            return None
        # --zenoh-connect alone still listens on loopback: Zenoh peers joined to one router (ROS 2
        # nodes with rmw_zenoh) reach each other directly, through the locators it gossips
        base = ZenohConfig()
    changes: dict[str, Any] = {}
    if connect:
        changes["connect"] = connect
    if listen:
        changes["listen"] = listen
    if ros_domain_id is not None:
        changes["ros_domain_id"] = ros_domain_id
    return msgspec.structs.replace(base, **changes)


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


def is_loopback(endpoint: str) -> bool:
    """True when ``endpoint`` cannot reach beyond this machine: a Unix socket, ``localhost``, or a
    loopback address (127.0.0.0/8, ::1). ``0.0.0.0`` and ``[::]`` (every interface) are not."""
    proto, host = endpoint_host(endpoint)
    if proto in LOCAL_PROTOCOLS:
        return True
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: it may resolve anywhere


def check_exposure(config: ZenohConfig, robot: str) -> None:
    """Refuse, in one line naming the key, an endpoint beyond this PC unless it is a TLS endpoint
    (``tls/`` or ``quic/``), ``transport.zenoh.tls`` has the certificates it needs, and
    ``transport.zenoh.access_control`` is enabled. Loopback endpoints are always accepted. Pure;
    raises ZenohConfigError."""
    for key, flag in (("listen", "--zenoh-listen"), ("connect", "--zenoh-connect")):
        for endpoint in getattr(config, key):
            try:
                local = is_loopback(endpoint)
            except ZenohConfigError as exc:
                raise ZenohConfigError(f"{robot}: transport.zenoh.{key} ({flag}): {exc}") from None
            if local:
                continue
            where = f"{robot}: transport.zenoh.{key} ({flag}) {endpoint} reaches beyond this PC"
            hint = "see docs/zenoh.md, 'Across machines'"
            proto, _ = endpoint_host(endpoint)
            if proto not in SECURE_PROTOCOLS:
                raise ZenohConfigError(f"{where}: only a tls/ endpoint may (with transport.zenoh.tls and "
                                       f"transport.zenoh.access_control); use loopback, or {hint}")
            tls = config.tls
            needed = (("listen_certificate", "listen_private_key") if key == "listen"
                      else ("root_ca_certificate",))
            for name in needed:
                if tls is None or not getattr(tls, name):
                    raise ZenohConfigError(f"{where}: set transport.zenoh.tls.{name} ({hint})")
            acl = config.access_control
            if not acl or acl.get("enabled") is not True:
                raise ZenohConfigError(f"{where}: set transport.zenoh.access_control (enabled: true, with "
                                       f"rules naming who may publish on this robot's keys; {hint})")


def session_config(config: ZenohConfig, extra: dict[str, Any] | None = None,
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


def open_session(config: ZenohConfig, robot: str, extra: dict[str, Any] | None = None,
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

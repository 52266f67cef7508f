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

Imports ``zenoh`` lazily, so that the daemon without the transport never loads it. Opening a
session (its keys, its one-line errors) is the client library's :mod:`crtk_client.zenoh_session`,
shared with remote clients; this module adds the profile's section and the exposure rule.
"""

from __future__ import annotations

import ipaddress
from typing import Any, Iterable

import msgspec
# one implementation of opening a session, the client's (re-exported: the daemon's modules use them here)
from crtk_client.zenoh_session import (  # noqa: F401
    LOCAL_PROTOCOLS, SECURE_PROTOCOLS, ZenohConfigError, ZenohConnectError, bound_listen, endpoint_host,
    listening_ports, open_session, session_config)

from ..profile import Profile, ZenohTransport

#: The transport's configuration: the profile's ``transport.zenoh`` section with the command
#: line's endpoints and domain id applied (profile.py holds the struct, so profiles validate it).
ZenohConfig = ZenohTransport


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

"""Where the Foxglove live view may listen (``crtk-bridge --foxglove-listen HOST:PORT``;
docs/recording.md, Live view). Pure, light (no foxglove, no rosbags): checked before anything
starts, before the control process is forked.

The rule is the Zenoh transport's (transport/zenoh_session.py, ``check_exposure``): loopback is
always accepted; an address beyond this PC only with TLS (the WebSocket served as ``wss://`` with
``transport.zenoh.tls.listen_certificate`` / ``listen_private_key``) and with
``transport.zenoh.access_control`` enabled: the operator's explicit opt-in to exposing the robot.
The live view is read-only either way (no client publishing, no services, no parameters).
"""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Any, NamedTuple

from ..errors import CrtkBridgeError


class ListenError(CrtkBridgeError):
    """--foxglove-listen is malformed or not allowed (one line, naming the option and the fix)."""


class Listen(NamedTuple):
    host: str
    port: int
    tls_cert: str | None  # PEM files: wss:// when set
    tls_key: str | None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{'wss' if self.tls_cert else 'ws'}://{host}:{self.port}"


def parse(text: str, robot: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8765`` for IPv6; port 0: any free one) -> (host, port)."""
    where = f"{robot}: --foxglove-listen {text}"
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise ListenError(f"{where}: give HOST:PORT, e.g. 127.0.0.1:8765")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    try:
        number = int(port)
    except ValueError:
        raise ListenError(f"{where}: the port {port!r} is not a number (0-65535)") from None
    if not 0 <= number <= 65535:
        raise ListenError(f"{where}: the port {number} is not in 0-65535")
    return host, number


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name may resolve anywhere; 0.0.0.0 / :: are every interface


def check(text: str, profile: Any, source: str | None = None) -> Listen:
    """The Listen of ``--foxglove-listen text`` for ``profile``, or :class:`ListenError` naming
    the profile key to set (see the module)."""
    robot = profile.name
    host, port = parse(text, robot)
    if is_loopback(host):
        return Listen(host, port, None, None)
    where = f"{robot}: --foxglove-listen {text} reaches beyond this PC"
    hint = "use 127.0.0.1, or see docs/recording.md, 'Live view in Foxglove'"
    zenoh = profile.transport.zenoh
    tls = zenoh.tls if zenoh is not None else None
    paths = []
    for name in ("listen_certificate", "listen_private_key"):
        value = getattr(tls, name, None) if tls is not None else None
        if not value:
            raise ListenError(f"{where}: only with TLS: set transport.zenoh.tls.{name} (the WebSocket's "
                              f"certificate, as for Zenoh) and transport.zenoh.access_control; {hint}")
        p = Path(value).expanduser()
        if not p.is_absolute() and source:
            p = Path(source).resolve().parent / p
        paths.append(str(p))
    acl = zenoh.access_control if zenoh is not None else None
    if not acl or acl.get("enabled") is not True:
        raise ListenError(f"{where}: set transport.zenoh.access_control (enabled: true): exposing the robot "
                          f"beyond this PC is opted into there, as for Zenoh; {hint}")
    return Listen(host, port, paths[0], paths[1])

"""Where a robot's socket lives (docs/protocol.md, "Default path").

Standard library only, and imported by the daemon as well as the client, so that both sides agree
on the path: ``from crtk_client.paths import default_socket_path``. Importing this module
does not import the rest of the client (``crtk_bridge.client`` loads its names lazily).
"""

from __future__ import annotations

import os

#: Socket directory under the systemd unit (``RuntimeDirectory=crtk-bridge``).
SYSTEM_SOCKET_DIR = "/run/crtk-bridge"


def default_socket_dir() -> str:
    """The directory holding every robot's socket for this user.

    ``$XDG_RUNTIME_DIR/crtk-bridge`` when ``XDG_RUNTIME_DIR`` is set, else ``/tmp/crtk-bridge-<uid>``.
    Pure: does not create the directory.
    """
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime:
        return os.path.join(runtime, "crtk-bridge")
    return f"/tmp/crtk-bridge-{os.getuid()}"


def default_socket_path(robot: str) -> str:
    """The default socket path of robot ``robot`` (the profile's robot name), e.g. ``so101``.

    ``$XDG_RUNTIME_DIR/crtk-bridge/<robot>.sock`` if ``XDG_RUNTIME_DIR`` is set, else
    ``/tmp/crtk-bridge-<uid>/<robot>.sock``. Pure: touches no file.
    """
    if not robot or "/" in robot or robot in (".", ".."):
        raise ValueError(f"invalid robot name for a socket path: {robot!r}")
    return os.path.join(default_socket_dir(), f"{robot}.sock")


def find_sockets() -> list[str]:
    """The ``*.sock`` files of the default directory, sorted; if it has none, those of
    :data:`SYSTEM_SOCKET_DIR` (the systemd unit's). An empty list when no daemon has a socket."""
    for d in (default_socket_dir(), SYSTEM_SOCKET_DIR):
        try:
            names = sorted(n for n in os.listdir(d) if n.endswith(".sock"))
        except OSError:
            continue
        if names:
            return [os.path.join(d, n) for n in names]
    return []

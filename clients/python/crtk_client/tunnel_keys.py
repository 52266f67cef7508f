"""The key expressions of the socket protocol carried over Zenoh (docs/zenoh.md, "Key layout").

Shared by the daemon's side (transport/tunnel.py) and the client's (client/zenoh_link.py); standard
library only. Every key starts with ``crtk_bridge/``, so none collides with rmw_zenoh's
(``<domain id>/...`` data keys, ``@ros2_lv/...`` liveliness tokens).

    crtk_bridge/<robot>/daemon            liveliness token: the daemon of <robot> serves here
    crtk_bridge/<robot>/client/<cid>      liveliness token: a client session is open
    crtk_bridge/<robot>/in/<cid>          client -> daemon: request lines (docs/protocol.md)
    crtk_bridge/<robot>/out/<cid>         daemon -> client: replies, events and stream frames
"""

from __future__ import annotations

PREFIX = "crtk_bridge"
#: every daemon's liveliness token (``crtk_bridge/*/daemon``): how a client lists the robots
ALL_DAEMONS = f"{PREFIX}/*/daemon"


def daemon_token(robot: str) -> str:
    return f"{PREFIX}/{robot}/daemon"


def client_token(robot: str, cid: str) -> str:
    return f"{PREFIX}/{robot}/client/{cid}"


def requests(robot: str, cid: str) -> str:
    return f"{PREFIX}/{robot}/in/{cid}"


def replies(robot: str, cid: str) -> str:
    return f"{PREFIX}/{robot}/out/{cid}"


def robot_of(daemon_key: str) -> str:
    """``crtk_bridge/so101/daemon`` -> ``so101``."""
    return daemon_key.split("/")[1]


def last(key: str) -> str:
    """The last chunk of a key: a client id in ``.../client/<cid>`` or ``.../in/<cid>``."""
    return key.rsplit("/", 1)[-1]

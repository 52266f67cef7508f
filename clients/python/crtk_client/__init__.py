"""Python client of the crtk-bridge daemon (docs/protocol.md, version 1): the ``crtk-client``
distribution (clients/python), which needs numpy and msgspec only (``crtk-client[zenoh]`` adds
the Zenoh transport). It installs alone on a PC that only talks to a daemon, beside LeRobot or
any tool pinning other servo SDKs; crtk-bridge installs it too, and ``crtk_bridge.client`` is the
same library under its historical name.

    from crtk_client import connect
    robot = connect(robot="so101")          # or connect(socket="/run/crtk-bridge/so101.sock")
    # across the lab: connect(robot="so101", zenoh_connect="tcp/127.0.0.1:7447") (docs/zenoh.md)
    arm = robot.device("so101")             # arm.gripper is the "so101/gripper" namespace
    if arm.enable(5.0):
        p, ts = arm.measured_jp()
        arm.move_jp(p + 0.1).wait()

Names are loaded lazily (PEP 562), so ``crtk_client.paths`` imports only the standard library:
the daemon uses it for the default socket path.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

#: name -> the module of this package that defines it
EXPORTS = {
    "default_socket_path": "paths",
    "default_socket_dir": "paths",
    "find_sockets": "paths",
    "Connection": "connection",
    "DaemonConnectionError": "connection",
    "Event": "connection",
    "PROTOCOL_VERSION": "connection",
    "connect": "device",
    "list_robots": "device",
    "resolve_socket": "device",
    "Robot": "device",
    "Device": "device",
    "MoveHandle": "device",
    "Subscription": "device",
    "joint_state": "device",
    "pose_matrix": "device",
    "pose_pq": "device",
    "matrix_from_quaternion": "device",
    "quaternion_from_matrix": "device",
    "CommandError": "errors",
    "CrtkBridgeError": "errors",
}

__all__ = sorted(EXPORTS)


def lazy_exports(namespace: dict):
    """``(__getattr__, __dir__)`` for a package that re-exports EXPORTS lazily (PEP 562): this
    one, and ``crtk_bridge.client`` under the historical name. A name is imported from its
    crtk_client module on first use and kept in ``namespace`` (the package's globals())."""
    package = namespace["__name__"]

    def __getattr__(name: str):
        if name not in EXPORTS:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{__name__}.{EXPORTS[name]}"), name)
        namespace[name] = value
        return value

    def __dir__():
        return __all__

    return __getattr__, __dir__


__getattr__, __dir__ = lazy_exports(globals())

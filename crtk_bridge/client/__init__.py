"""Python client of the crtk-bridge daemon (docs/protocol.md, version 1).

    from crtk_bridge.client import connect
    robot = connect(robot="so101")          # or connect(socket="/run/crtk-bridge/so101.sock")
    # across the lab: connect(robot="so101", zenoh_connect="tcp/127.0.0.1:7447") (docs/zenoh.md)
    arm = robot.device("so101")             # arm.gripper is the "so101/gripper" namespace
    if arm.enable(5.0):
        p, ts = arm.measured_jp()
        arm.move_jp(p + 0.1).wait()
        T, ts = arm.measured_cp()           # 4x4 numpy pose of the tip in the base frame (m)
        T[2, 3] += 0.02                     # 2 cm up
        arm.move_cp(T).wait()               # or arm.move_cp((position, quaternion_xyzw))

Names and return conventions follow crtk_python_client 1.4. The library is the ``crtk-client``
distribution (clients/python, import package :mod:`crtk_client`), which installs alone beside
LeRobot; this package is the same library under its historical name (``crtk_bridge.client.device``
IS ``crtk_client.device``) plus crtk-bridge's own tools (``crtk-ctl``, calibrate, teleop, replay,
plot). Names are loaded lazily (PEP 562).
"""

from __future__ import annotations

from crtk_client import EXPORTS as _EXPORTS
from crtk_client import lazy_exports as _lazy_exports

__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = _lazy_exports(globals())

"""Robotiq 2F-85 / 2F-140 adaptive grippers over Modbus RTU (``tables.py``: the register map from
Robotiq's instruction manual; ``backend.py``: the backend; ``crtk_bridge/sim/robotiq.py``: its
simulator). docs/architecture.md, "Adding a backend"."""

"""Wire-level simulated devices: product code, not test code (docs/architecture.md, "Simulators are product").

Each simulator answers the vendor SDK's real packets on a real OS channel (a pseudo-terminal for
serial buses, TCP on loopback for a UR controller), so ``--sim`` and the tests run the same backend code path as hardware.

- :mod:`crtk_bridge.sim.pty`      raw pseudo-terminal pair with an optional stable symlink
- :mod:`crtk_bridge.sim.bus`      what both servo-bus simulators share (:class:`BusSimulator`)
- :mod:`crtk_bridge.sim.feetech`  Feetech STS3215 servo bus (:class:`FeetechSimulator`)
- :mod:`crtk_bridge.sim.dynamixel` Dynamixel X-series Protocol 2.0 bus (:class:`DynamixelSimulator`)
- :mod:`crtk_bridge.sim.ur`       Universal Robots controller on a 127.x address (:class:`URSimulator`,
  a subprocess; ``ur_wire`` RTDE codec, ``ur_robot`` arm and modes, ``ur_script`` rtde_control)
- :mod:`crtk_bridge.sim.canopen402` CiA 402 drives on a CAN bus (:class:`CanopenSimulator`)
- :mod:`crtk_bridge.sim.control`  JSON-lines control socket to inspect and change a running sim
- :mod:`crtk_bridge.sim.cli`      ``crtk-sim`` console script

This layer imports nothing of ``crtk_bridge.core``; only profiles, errors and vendor tables (data).
"""

from __future__ import annotations

from ..errors import CrtkBridgeError


class SimulatorError(CrtkBridgeError):
    """A simulator could not start or was asked something impossible (message names path/id)."""


def simulator_class(device: str) -> type:
    """The simulator class of ``crtk-sim`` device ``device``, from the one registry of backends
    and their simulators (:mod:`crtk_bridge.registry`). Raises SimulatorError naming the valid
    devices (or what to install)."""
    from .. import registry

    try:
        return registry.simulator_class(device)
    except CrtkBridgeError as exc:
        raise SimulatorError(str(exc)) from exc


def __getattr__(name: str):
    # Lazy re-export: importing the package must stay cheap and free of import cycles.
    if name == "FeetechSimulator":
        from .feetech import FeetechSimulator

        return FeetechSimulator
    if name == "DynamixelSimulator":
        from .dynamixel import DynamixelSimulator

        return DynamixelSimulator
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["SimulatorError", "FeetechSimulator", "DynamixelSimulator", "simulator_class"]

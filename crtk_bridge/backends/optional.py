"""Optional capabilities of a backend, beyond the seam every backend implements (core/actuator.py).

As python-can's optional bus features, each is declared in one way and probed in one way: a
backend that has one inherits its abstract base class here and implements its methods; the entry
layer asks :func:`require`, which returns the backend typed as that capability or raises one line
naming the robot, the profile section, the backend and the registered backends that have it. No
``hasattr`` probing: a backend that offers a method of the same name by accident has no capability.

- :class:`BusScanner`: find the devices on the bus and compare them with the profile
  (``crtk-bridge check --scan``).
- :class:`DeviceSetup`: give each joint's device its bus id and the profile's baud rate, one at a
  time (``crtk-bridge setup-servos``).

The serial servo backends (backends/serial_servo.py) have both; CANopen and UR neither.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any, TypeVar

from ..errors import CrtkBridgeError


class BusScanner(abc.ABC):
    """The backend can scan its bus (``crtk-bridge check --scan``; called on a backend that is not
    open: the scan opens the port for itself and writes nothing)."""

    #: what the capability lets a command do (in :func:`require`'s message)
    ability = "scan its bus (crtk-bridge check --scan)"

    @property
    @abc.abstractmethod
    def port_name(self) -> str:
        """The port scanned, as resolved once scanned (before: as the profile gives it)."""

    @abc.abstractmethod
    def scan_plan(self, all_bauds: bool) -> tuple[int | None, str]:
        """(the rate scanned at, or None; what the scan covers, for the line printed before it,
        e.g. ``"at 1000000 baud (then every other rate), ids 0-253"``)."""

    @abc.abstractmethod
    def scan(self, all_bauds: bool = False) -> Any:
        """Find the devices on the bus (``all_bauds``: also at the other rates they support).
        Blocks (seconds). Raises CrtkBridgeError when the bus does not open."""

    @abc.abstractmethod
    def scan_report(self, scan: Any, hint: str = "") -> tuple[list[str], list[str], dict]:
        """(one line per finding; the mismatches with the profile, one line each; the findings as
        data: ``check --json``'s bus keys, docs/check.md, ``servos_answered`` included) of
        :meth:`scan`'s result. ``hint``: the command that fixes a device found at another rate."""


class DeviceSetup(abc.ABC):
    """The backend can give each joint's device its id and the profile's baud rate, one device
    connected at a time (``crtk-bridge setup-servos``; writes the devices' EEPROM)."""

    ability = "set up its devices' ids and baud rate (crtk-bridge setup-servos)"

    @abc.abstractmethod
    def setup_devices(self, joints: list[int], emit: Callable[[dict], None],
                      ask: Callable[[str], str] | None, timeout_s: float) -> int:
        """Set up the devices of ``joints`` (indices, in that order), reporting each step to
        ``emit`` (docs: setup-servos --json); ``ask`` prompts the user (None: wait up to
        ``timeout_s`` per device instead). Returns setup-servos' exit status."""


C = TypeVar("C", BusScanner, DeviceSetup)


def require(backend: object, capability: type[C], *, robot: str, where: str, backend_type: str) -> C:
    """``backend`` as ``capability``, or CrtkBridgeError naming the robot, the profile section
    ``where`` (``backend`` / ``backends.<bus>``), the backend and the backends that have it."""
    if isinstance(backend, capability):
        return backend
    able = ", ".join(_backends_with(capability)) or "none"
    raise CrtkBridgeError(f"{robot}: {where}: backend {backend_type!r} ({type(backend).__name__}) cannot "
                          f"{capability.ability}; backends that can: {able}")


def _backends_with(capability: type) -> list[str]:
    """The registered backends whose class has ``capability`` (imports them: the error path only)."""
    from ..registry import backend_class, names

    out = []
    for name in names():
        try:
            if issubclass(backend_class(name), capability):
                out.append(name)
        except CrtkBridgeError:
            continue
    return out

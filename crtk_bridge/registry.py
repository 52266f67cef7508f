"""The one registry of backends: a backend name (a profile's ``backend.type``) -> its
:class:`Registration`, which names the backend class AND its wire-level simulator, both imported
only when chosen (docs/architecture.md, "Adding a backend").

The shipped backends are in :data:`BUILTIN`. Another distribution adds one through the
``crtk_bridge.backends`` entry-point group (as python-can's ``can.interface``), naming a
:class:`Registration` in a module that imports nothing heavy::

    # pyproject.toml of the other distribution
    [project.entry-points."crtk_bridge.backends"]
    robotiq = "robotiq_crtk.registration:BACKEND"

    # robotiq_crtk/registration.py
    from crtk_bridge.registry import Registration
    BACKEND = Registration("robotiq_crtk.backend:RobotiqBackend",
                           simulator="robotiq_crtk.sim:RobotiqSimulator")

The daemon's profile check, ``crtk-bridge check``, ``--sim`` and ``crtk-sim`` all resolve names
here, so such a backend is found everywhere a shipped one is. A built-in name wins over an entry
point of the same name. A missing vendor SDK breaks only its own backend, with what to pip install;
an unknown name lists the valid ones.

A leaf module: it imports only the standard library and :mod:`crtk_bridge.errors` (the entry layer
and the simulators use it; neither core nor the backends are imported until a name is chosen).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from importlib import metadata

from .errors import BackendUnavailableError, ProfileError

#: the entry-point group another distribution registers its backends in
GROUP = "crtk_bridge.backends"


@dataclass(frozen=True)
class Registration:
    """One backend: where its class and its simulator live, imported only when chosen."""

    #: ``"module:Class"`` of the :class:`~crtk_bridge.core.actuator.Actuator` subclass
    backend: str
    #: ``"module:Class"`` of its wire-level simulator (``crtk-sim``, ``--sim``, the conformance
    #: suite), or None: the backend has none (``--sim`` refuses it, naming it)
    simulator: str | None = None
    #: its ``crtk-sim`` device name; None: the backend's name
    device: str | None = None
    #: what to ``pip install`` when an import fails; None: ``crtk-bridge[<name>]`` for a shipped
    #: backend (pyproject's extras), the registering distribution's name for an entry point's
    install: str | None = None


#: the shipped backends (the same lazy import as an entry point's)
BUILTIN: dict[str, Registration] = {
    "feetech": Registration("crtk_bridge.backends.feetech.backend:FeetechBackend",
                            simulator="crtk_bridge.sim.feetech:FeetechSimulator"),
    "dynamixel": Registration("crtk_bridge.backends.dynamixel.backend:DynamixelBackend",
                              simulator="crtk_bridge.sim.dynamixel:DynamixelSimulator"),
    "canopen402": Registration("crtk_bridge.backends.canopen402.backend:Canopen402Backend",
                               simulator="crtk_bridge.sim.canopen402:CanopenSimulator", device="canopen"),
    "ur": Registration("crtk_bridge.backends.ur.backend:UrBackend", simulator="crtk_bridge.sim.ur:URSimulator"),
    "robotiq": Registration("crtk_bridge.backends.robotiq.backend:RobotiqBackend", simulator="crtk_bridge.sim.robotiq:RobotiqSimulator"),
}


def _entry_points() -> dict[str, metadata.EntryPoint]:
    """The ``crtk_bridge.backends`` entry points not shadowed by a built-in name (not loaded)."""
    return {ep.name: ep for ep in metadata.entry_points(group=GROUP) if ep.name not in BUILTIN}


def names() -> list[str]:
    """Every registered backend name, sorted (nothing is imported)."""
    return sorted({*BUILTIN, *_entry_points()})


def registration(name: str, source: str = "<profile>") -> Registration:
    """The registration of backend ``name``, with ``install`` filled in. Loads its entry point
    (only that one) if it is not built in. Raises ProfileError naming the valid backends."""
    reg = BUILTIN.get(name)
    if reg is not None:
        return reg if reg.install else _replace(reg, install=f"crtk-bridge[{name}]")
    ep = _entry_points().get(name)
    if ep is None:
        raise ProfileError(f"{source}: backend.type: unknown backend {name!r}; valid backends: {', '.join(names())}")
    dist = getattr(ep, "dist", None)
    origin = f"entry point {name!r} of {dist.name if dist else 'an installed distribution'} ({ep.value})"
    try:
        reg = ep.load()
    except ImportError as exc:
        raise BackendUnavailableError(f"backend {name!r}: {origin} does not import: {exc}") from exc
    if not isinstance(reg, Registration):
        raise ProfileError(f"{source}: backend {name!r}: {origin} is a {type(reg).__name__}, not a "
                           f"crtk_bridge.registry.Registration")
    return reg if reg.install else _replace(reg, install=dist.name if dist else name)


def _replace(reg: Registration, **changes) -> Registration:
    from dataclasses import replace

    return replace(reg, **changes)


def _import(name: str, what: str, target: str, install: str | None) -> type:
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise BackendUnavailableError(
            f"{what} {name!r} needs a package that is not installed ({exc.name}): pip install '{install}'"
        ) from exc
    try:
        return getattr(module, attr)
    except AttributeError:
        raise BackendUnavailableError(f"{what} {name!r}: {module_name} has no {attr!r} (registered as {target})") from None


def backend_class(name: str, source: str = "<profile>") -> type:
    """The Actuator subclass registered as ``name``, imported now. Raises ProfileError for an
    unknown name, BackendUnavailableError when its SDK is missing (naming what to install)."""
    reg = registration(name, source)
    return _import(name, "backend", reg.backend, reg.install)


def simulator_device(name: str, source: str = "<profile>") -> str:
    """The ``crtk-sim`` device that simulates backend ``name``. Raises ProfileError for an unknown
    backend, BackendUnavailableError naming it when it has no simulator."""
    reg = registration(name, source)
    if reg.simulator is None:
        raise BackendUnavailableError(f"{source}: backend {name!r} has no simulator (its registration names none)")
    return reg.device or name


def devices() -> dict[str, str]:
    """``crtk-sim`` device name -> backend name, for every registered backend with a simulator.
    Loads the entry points (their registration modules only)."""
    out = {}
    for name in names():
        try:
            reg = registration(name)
        except (ProfileError, BackendUnavailableError):
            continue  # a broken plug-in must not hide the others; naming it says why
        if reg.simulator is not None:
            out.setdefault(reg.device or name, name)
    return out


def simulator_class(device: str) -> type:
    """The simulator class of ``crtk-sim`` device ``device`` (imported now). Raises ProfileError
    naming the valid devices, BackendUnavailableError when its SDK is missing."""
    known = devices()
    name = known.get(device)
    if name is None:
        raise ProfileError(f"no simulator {device!r}; valid: {', '.join(known)}")
    reg = registration(name)
    return _import(device, "simulator", reg.simulator, reg.install)


def backend_simulator(name: str, source: str = "<profile>") -> type:
    """The simulator class of backend ``name`` (imported now). Raises as :func:`simulator_device`."""
    return simulator_class(simulator_device(name, source))

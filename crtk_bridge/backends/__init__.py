"""Backend registry: backend name -> (module, class), imported only when chosen.

As in python-can's interface table, a missing vendor SDK breaks only its own backend (with the pip
extra to install), and an unknown name lists the valid ones.
"""

from __future__ import annotations

import importlib

from ..errors import BackendUnavailableError, ProfileError

BACKENDS: dict[str, tuple[str, str]] = {
    "feetech": ("crtk_bridge.backends.feetech.backend", "FeetechBackend"),
    "dynamixel": ("crtk_bridge.backends.dynamixel.backend", "DynamixelBackend"),
    "canopen402": ("crtk_bridge.backends.canopen402.backend", "Canopen402Backend"),
    "ur": ("crtk_bridge.backends.ur.backend", "UrBackend"),
}


def backend_class(name: str, source: str = "<profile>") -> type:
    """Return the Actuator subclass registered as ``name``. Imports it lazily.

    Raises ProfileError for an unknown name, BackendUnavailableError when its SDK is missing.
    """
    try:
        module_name, class_name = BACKENDS[name]
    except KeyError:
        raise ProfileError(
            f"{source}: backend.type: unknown backend {name!r}; valid backends: {', '.join(sorted(BACKENDS))}"
        ) from None
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise BackendUnavailableError(
            f"backend {name!r} needs a package that is not installed ({exc.name}): "
            f"pip install 'crtk-bridge[{name}]'"
        ) from exc
    return getattr(module, class_name)


def create_backend(profile, *, source: str = "<profile>"):
    """Construct (not open) the backend a profile names. Validates its ``backend`` section.

    A profile with several buses (``backends``) gets one backend per bus behind a
    :class:`~.composite.CompositeActuator`."""
    if profile.backends is not None:
        from .composite import create_composite

        return create_composite(profile, lambda bus, src: create_backend(bus, source=src), source)
    return backend_class(profile.backend_type, source)(profile, source=source)

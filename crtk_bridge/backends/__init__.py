"""Backends: one folder per vendor, found by name through the one registry
(:mod:`crtk_bridge.registry`: the shipped table and the ``crtk_bridge.backends`` entry points),
imported only when chosen.

As in python-can's interface table, a missing vendor SDK breaks only its own backend (with what to
pip install), and an unknown name lists the valid ones.
"""

from __future__ import annotations

from ..registry import BUILTIN as BACKENDS  # noqa: F401  (the shipped backends, by name)
from ..registry import backend_class


def create_backend(profile, *, source: str = "<profile>"):
    """Construct (not open) the backend a profile names. Validates its ``backend`` section.

    A profile with several buses (``backends``) gets one backend per bus behind a
    :class:`~.composite.CompositeActuator`."""
    if profile.backends is not None:
        from .composite import create_composite

        return create_composite(profile, lambda bus, src: create_backend(bus, source=src), source)
    return backend_class(profile.backend_type, source)(profile, source=source)


__all__ = ["BACKENDS", "backend_class", "create_backend"]

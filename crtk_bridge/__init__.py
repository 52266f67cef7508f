"""crtk-bridge: the CRTK robot API served on real hardware.

Layers (imports point downward only, see DESIGN.md): entry (cli, daemon) -> server / client ->
core -> core.actuator <- backends; sim stands apart. ``profile`` and ``errors`` are plain data
and exceptions that every layer may import.
"""

__version__ = "0.1.0"

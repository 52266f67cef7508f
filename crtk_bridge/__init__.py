"""crtk-bridge: the CRTK robot API served on real hardware.

Layers and which may import which: docs/architecture.md, "Layers" and "Dependencies" (a test
checks the code against that table). In short: entry (cli, daemon) -> server / transport /
recording -> core -> core.actuator (the seam) <- backends; the simulators share only the vendors'
tables with the backends; the client needs neither core nor the server. ``profile``, ``errors``
and the leaf modules (``vocabulary``, ``registry``...) are data and helpers every layer may import.
"""

__version__ = "0.1.0"

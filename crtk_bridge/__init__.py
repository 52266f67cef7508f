"""crtk-bridge: the CRTK robot API served on real hardware.

Layers and which may import which: docs/architecture.md, "Layers" and "Dependencies" (a test
checks the code against that table). In short: entry (cli, daemon) -> server / transport /
recording -> core -> core.actuator (the seam) <- backends; the simulators share only the vendors'
tables with the backends; the client needs neither core nor the server. ``profile``, ``errors``
and the leaf modules (``vocabulary``, ``registry``...) are data and helpers every layer may import.
The client library and the leaves it needs (``errors``, ``vocabulary``, ``vectors``) are the
``crtk_client`` package (clients/python), which crtk-bridge installs with itself.
"""

__version__ = "0.1.0"


def _client_of_a_stale_checkout() -> None:
    """An editable install made before ``crtk_client`` existed maps ``crtk_bridge`` only: find the
    package in this checkout's clients/python (an installed crtk-bridge always has it)."""
    import importlib.util
    import sys
    from pathlib import Path

    if importlib.util.find_spec("crtk_client") is None:
        src = Path(__file__).resolve().parent.parent / "clients" / "python"
        if (src / "crtk_client" / "__init__.py").is_file():
            sys.path.append(str(src))


_client_of_a_stale_checkout()

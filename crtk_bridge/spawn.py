"""Start a module of THIS crtk_bridge in a child Python process (the simulators of ``--sim``, the
UR backend's worker), whatever the current folder.

``python -m crtk_bridge.x`` puts the current folder first on ``sys.path``: started from a clone of
the repository (or any folder holding a ``crtk_bridge`` directory) the child would run that
folder's code, not the installed package the parent runs, and the two may differ. So the child
runs without the current folder on its path (``-P``, Python 3.11+; a ``-c`` bootstrap that drops
it on 3.10) and with the folder this package was imported from first on ``PYTHONPATH``: the same
code as the parent, installed or from a source tree.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

#: the ``sys.path`` entry this crtk_bridge was imported from (site-packages, or a source tree)
PACKAGE_ROOT = str(Path(__file__).resolve().parents[1])

# Python 3.10 has no -P: drop the current folder ('' with -c), then run the module as -m would
_BOOTSTRAP = ("import runpy, sys; sys.path[:1] == [''] and sys.path.pop(0); sys.argv = sys.argv[1:]; "
              "runpy.run_module(sys.argv[0], run_name='__main__', alter_sys=True)")


def module_argv(module: str, *args: str, safe_path: bool | None = None) -> list[str]:
    """The argv running ``python -m module args...`` from this package (see the module docstring).
    ``safe_path``: use ``-P`` (default: when this Python has it)."""
    if safe_path is None:
        safe_path = sys.version_info >= (3, 11)
    if safe_path:
        return [sys.executable, "-P", "-m", module, *args]
    return [sys.executable, "-c", _BOOTSTRAP, module, *args]


def module_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default: this process's environment) with :data:`PACKAGE_ROOT` first on PYTHONPATH."""
    env = dict(os.environ if env is None else env)
    rest = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p and p != PACKAGE_ROOT]
    env["PYTHONPATH"] = os.pathsep.join([PACKAGE_ROOT, *rest])
    return env

"""The real LeRobot in a venv of its own, for the LeRobot tests and ``bench/bench_lerobot.py``.

LeRobot cannot share the project's venv: it pins ``dynamixel-sdk<3.9`` (crtk-bridge needs 4.x)
and a torch of several GB. :func:`ensure_venv` builds a venv from ``requirements.txt`` (every
package pinned, installed with ``--no-deps``: see the file's header) once per requirements hash,
under ``build/lerobot/`` (or ``$CRTK_LEROBOT_CACHE``), and reuses it while it is complete (a
marker file written last). Builders in several processes wait for one another on a file lock,
which a builder's children hold too. The LeRobot tests start the build in the background as
soon as their session is collected (conftest.py).

The plugin and the light client are never installed into that venv: :func:`install_plugin`
installs them (non-editable, ``--no-deps``) into a folder of their own, which the LeRobot
commands see through ``PYTHONPATH`` (:func:`lerobot_env`). LeRobot's plugin discovery reads the
distributions on ``sys.path``, so that folder's ``lerobot_robot_crtk`` is found as an installed
one would be, and the cached venv stays what its requirements say, shared by every checkout.

``python -m tests.lerobot.venv`` builds it and prints its path.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
REQUIREMENTS = HERE / "requirements.txt"
#: the distributions :func:`install_plugin` installs, from this checkout
PLUGIN_SOURCES = (ROOT / "clients" / "python", ROOT / "lerobot_robot_crtk")
#: what must import in a finished venv (lerobot 0.4.4's SO-101 classes and the scripts the tests run)
PROBE = ("import torch, torchvision, msgspec, scservo_sdk; "
         "from lerobot.robots.so_follower import SO101Follower; "
         "from lerobot.teleoperators.so_leader import SO101Leader; "
         "from lerobot.datasets.lerobot_dataset import LeRobotDataset; "
         "import lerobot.scripts.lerobot_record, lerobot.scripts.lerobot_replay, "
         "lerobot.scripts.lerobot_teleoperate")
MARKER = ".crtk-complete"
BUILD_TIMEOUT_S = 1800


class LeRobotVenvError(RuntimeError):
    """The LeRobot venv or the plugin could not be installed (the message says what failed)."""


def cache_root() -> Path:
    return Path(os.environ.get("CRTK_LEROBOT_CACHE") or ROOT / "build" / "lerobot")


def venv_key() -> str:
    h = hashlib.sha256(REQUIREMENTS.read_bytes())
    h.update(f"{sys.version_info[0]}.{sys.version_info[1]} {platform.machine()}".encode())
    return h.hexdigest()[:12]


def venv_path() -> Path:
    return cache_root() / f"venv-{venv_key()}"


def python(venv: Path) -> Path:
    return venv / "bin" / "python"


def _run(cmd: list, what: str, timeout: float = BUILD_TIMEOUT_S, **kw) -> str:
    try:
        out = subprocess.run([str(c) for c in cmd], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             text=True, timeout=timeout, **kw)
    except subprocess.TimeoutExpired as exc:
        raise LeRobotVenvError(f"{what}: timed out after {timeout:.0f} s") from exc
    if out.returncode != 0:
        tail = "\n".join(out.stdout.strip().splitlines()[-15:])
        raise LeRobotVenvError(f"{what} failed (exit {out.returncode}):\n{tail}")
    return out.stdout


def _size_mb(path: Path) -> float:
    total = 0
    for dirpath, _dirs, files in os.walk(path):
        for f in files:
            try:
                total += os.lstat(os.path.join(dirpath, f)).st_size
            except OSError:
                pass
    return total / 1e6


def ensure_venv(log=lambda msg: print(msg, file=sys.stderr, flush=True)) -> Path:
    """The LeRobot venv for this requirements file, built now if no complete one exists.

    Raises :class:`LeRobotVenvError` naming the step that failed and pip's last lines."""
    venv = venv_path()
    if (venv / MARKER).exists():
        return venv
    venv.parent.mkdir(parents=True, exist_ok=True)
    with open(venv.parent / f"{venv.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another builder: wait for it, then reuse its venv
        if (venv / MARKER).exists():
            return venv
        if venv.exists():
            shutil.rmtree(venv)  # an interrupted build
        t0 = time.monotonic()
        log(f"building the LeRobot venv {venv} from {REQUIREMENTS.relative_to(ROOT)} (one-off, a few minutes)")
        # the builders hold the lock too: one this process leaves behind (killed mid-build) keeps
        # the next builder waiting instead of writing into the folder it removes
        held = {"pass_fds": (lock.fileno(),)}
        _run([sys.executable, "-m", "venv", venv], f"python -m venv {venv}", **held)
        _run([python(venv), "-m", "pip", "install", "--no-deps", "--no-input", "--disable-pip-version-check",
              "-r", REQUIREMENTS], f"pip install --no-deps -r {REQUIREMENTS} into {venv}", **held)
        _run([python(venv), "-c", PROBE], f"importing LeRobot in {venv}", timeout=300, cwd=venv, **held)
        took = time.monotonic() - t0
        size = _size_mb(venv)
        (venv / MARKER).write_text(f"built in {took:.0f} s, {size:.0f} MB\n")
        log(f"LeRobot venv ready: {venv} (built in {took:.0f} s, {size:.0f} MB)")
    return venv


def install_plugin(venv: Path, dest: Path, sources=PLUGIN_SOURCES) -> Path:
    """Install this checkout's light client and LeRobot plugin (non-editable, without
    dependencies: the venv holds them) into ``dest``, a folder for ``PYTHONPATH``."""
    missing = [str(s.relative_to(ROOT)) for s in sources if not (s / "pyproject.toml").exists()]
    if missing:
        raise LeRobotVenvError(f"no distribution at {', '.join(missing)} (pyproject.toml missing)")
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    with _scratch_copies(sources, dest.parent / f"{dest.name}-src") as copies:
        _run([python(venv), "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--no-input",
              "--disable-pip-version-check", "--target", dest, *copies],
             f"pip install --target {dest} {' '.join(str(s.relative_to(ROOT)) for s in sources)}",
             timeout=600)
    return dest


class _scratch_copies:
    """Copies of the source trees to build from: a build in place would leave ``build/`` and
    ``*.egg-info`` folders in the checkout."""

    def __init__(self, sources, where: Path):
        self.sources, self.where = sources, where

    def __enter__(self) -> list[Path]:
        shutil.rmtree(self.where, ignore_errors=True)
        out = []
        for s in self.sources:
            d = self.where / s.name
            shutil.copytree(s, d, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
            out.append(d)
        return out

    def __exit__(self, *exc) -> None:
        shutil.rmtree(self.where, ignore_errors=True)


def lerobot_env(plugin_dir: Path | None = None, **extra: str) -> dict:
    """The environment to run LeRobot's commands in: offline (no hub), the plugin folder first on
    ``PYTHONPATH``, LeRobot's calibration and dataset folders as given in ``extra``."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    env.update(HF_HUB_OFFLINE="1", HF_DATASETS_OFFLINE="1", WANDB_MODE="disabled",
               TOKENIZERS_PARALLELISM="false", PYTHONUNBUFFERED="1")
    if plugin_dir is not None:
        env["PYTHONPATH"] = str(plugin_dir)
    env.update(extra)
    return env


if __name__ == "__main__":
    print(ensure_venv())

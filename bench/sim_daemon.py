"""For the bench scripts: ``crtk-bridge --sim`` on the SO-101 profile at a chosen loop rate."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent


def start(rate_hz: float, tmp: Path, startup_s: float = 30.0, args: list[str] = (),
          tree: Path = ROOT) -> tuple[subprocess.Popen, Path]:
    """Write profiles/so101.yaml at ``rate_hz`` into ``tmp``, start the daemon on the simulator
    (with more command-line ``args``; ``tree``: the checkout to run, another one for a before /
    after in one run) and wait (up to ``startup_s``) for its socket. Returns
    (process, socket path); the caller stops it (SIGTERM). Raises RuntimeError if it does not start."""
    data = yaml.safe_load((tree / "profiles" / "so101.yaml").read_text())
    data["loop"]["rate_hz"] = rate_hz
    for ns in data["namespaces"]:
        if "kinematics" in ns:
            ns["kinematics"]["urdf"] = str(tree / "profiles" / "urdf" / "so101.urdf")
    prof = tmp / f"so101-{rate_hz:g}hz.yaml"
    prof.write_text(yaml.safe_dump(data))
    sock = tmp / "so101.sock"
    daemon = subprocess.Popen([sys.executable, "-m", "crtk_bridge.cli", "--profile", str(prof), "--sim",
                               "--socket", str(sock), "--log-level", "ERROR", *args], stdout=subprocess.DEVNULL, cwd=tree,
                              env=dict(os.environ, PYTHONPATH=str(tree)))
    deadline = time.monotonic() + startup_s
    while not sock.exists():
        if daemon.poll() is not None or time.monotonic() > deadline:
            daemon.kill()
            daemon.wait()
            raise RuntimeError("daemon did not start")
        time.sleep(0.05)
    return daemon, sock

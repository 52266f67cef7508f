"""`crtk-ctl` imports only what the command needs (issue 23, item 4): a plain command (state, get
measured_js, enable, disable) loads neither numpy, the profile model (msgspec structs, YAML) nor
the calibration writer (ruamel.yaml): importing those alone took longer than the command's round
trip. Which modules a command loads is behaviour, asserted here; its wall time is for
bench/bench_cli.py only.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from .conftest import only_on

#: modules a plain command must not load, and why each is heavy
HEAVY = ("numpy", "yaml", "ruamel.yaml", "crtk_bridge.profile", "crtk_bridge.profile_write",
         "crtk_bridge.client.calibrate", "zenoh")

#: runs crtk-ctl's main in a fresh interpreter, then prints its exit status and which HEAVY
#: modules it loaded, as one JSON line on stderr (stdout is the command's)
_PROBE = """
import json, sys
from crtk_bridge.client.cli import main
code = main(sys.argv[2:])
heavy = [m for m in json.loads(sys.argv[1]) if m in sys.modules]
print(json.dumps({"code": code, "heavy": heavy}), file=sys.stderr)
"""


def loaded(*args: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(HEAVY), *args],
                         capture_output=True, text=True, timeout=60)
    return json.loads(out.stderr.strip().splitlines()[-1])


def test_version_and_a_missing_daemon_load_nothing_heavy(tmp_path):
    assert loaded("--version") == {"code": 0, "heavy": []}
    assert loaded("--socket", str(tmp_path / "none.sock"), "state") == {"code": 2, "heavy": []}


@only_on("so101-feetech")
@pytest.mark.reuse_daemon
def test_plain_commands_load_nothing_heavy(sim_daemon):
    sock = str(sim_daemon.socket_path)
    for cmd in (["state"], ["get", "measured_js"], ["--json", "get", "measured_js"], ["enable"],
                ["get", "operating_state"], ["disable"]):
        assert loaded("--socket", sock, *cmd) == {"code": 0, "heavy": []}, cmd


@only_on("so101-feetech")
@pytest.mark.reuse_daemon
def test_the_library_still_returns_numpy_arrays(sim_daemon):
    """The client library imports numpy where it returns arrays: measured_js is still numpy."""
    import numpy as np

    from crtk_bridge.client import connect
    with connect(socket=str(sim_daemon.socket_path), timeout=5.0) as robot:
        p, v, e, ts = robot.device(robot.namespaces[0]).measured_js()
    assert isinstance(p, np.ndarray) and p.dtype == float and len(p) and ts > 0

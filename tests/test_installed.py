"""The package works outside its checkout (issue 18, items 7 and 8): installed non-editable
(``pip install .``) into a venv in a temporary folder, its commands run from folders outside the
clone. The shipped profiles and URDFs are package data; a profile's relative paths resolve beside
the profile file first and among the shipped profiles second; simulators and the UR worker run the
installed package's code even from a folder holding another ``crtk_bridge``."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from crtk_bridge import spawn
from crtk_bridge.profile import load_profile, resolve_profile_arg, shipped_profile_names, shipped_profiles_dir

from .conftest import ROOT, only_on, wait_until

SHIPPED = sorted(p.name for p in (ROOT / "profiles").glob("*.yaml"))
URDFS = sorted(p.name for p in (ROOT / "profiles" / "urdf").glob("*.urdf"))


def decoy_folder(parent: Path) -> Path:
    """A folder holding a ``crtk_bridge`` package that must never be imported (as a clone of an
    older version would be): ``python -m crtk_bridge...`` started there runs it and exits 3."""
    d = parent / "decoy"
    (d / "crtk_bridge").mkdir(parents=True)
    (d / "crtk_bridge" / "__init__.py").write_text(
        "import sys\nsys.stderr.write('decoy crtk_bridge imported from the current folder\\n')\nsys.exit(3)\n")
    return d


def site_packages(installed) -> Path:
    out = subprocess.run([str(installed.python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                         capture_output=True, text=True, check=True)
    return Path(out.stdout.strip())


def test_the_install_is_not_editable_and_holds_every_shipped_profile_and_urdf(installed):
    site = site_packages(installed)
    out = subprocess.run([str(installed.python), "-c", "import crtk_bridge; print(crtk_bridge.__file__)"],
                         cwd=installed.cwd("where"), env=installed.env(), capture_output=True, text=True, check=True)
    assert Path(out.stdout.strip()).parent == site / "crtk_bridge"  # the installed copy, not the clone
    assert not list(site.glob("__editable__*crtk*"))
    data = site / "crtk_bridge" / "profiles"
    assert sorted(p.name for p in data.glob("*.yaml")) == SHIPPED
    assert sorted(p.name for p in (data / "urdf").glob("*.urdf")) == URDFS
    assert "so101_leader.yaml" in SHIPPED and "koch_leader.yaml" in SHIPPED


def test_init_profile_then_check_as_readme_says_from_a_folder_outside_the_clone(installed):
    """README, First time with a real arm, steps 2 and 4 (without --scan, which needs the arm)."""
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert "`crtk-bridge init-profile so101 my_arm.yaml`" in readme
    assert "`crtk-bridge check --profile my_arm.yaml --scan`" in readme
    cwd = installed.cwd("first")
    made = installed.run(["crtk-bridge", "init-profile", "so101", "my_arm.yaml"], cwd)
    assert made.returncode == 0, made.stderr
    text = (cwd / "my_arm.yaml").read_text()
    assert "urdf: urdf/so101.urdf" in text and "backend:" in text  # the shipped text, comments and all
    checked = installed.run(["crtk-bridge", "check", "--profile", "my_arm.yaml"], cwd)
    assert checked.returncode == 0, checked.stderr
    assert "kinematics so101: base_link -> gripper_frame_link" in checked.stdout
    again = installed.run(["crtk-bridge", "init-profile", "so101", "my_arm.yaml"], cwd)
    assert again.returncode == 1 and "my_arm.yaml exists" in again.stderr and "--force" in again.stderr
    # steps 5 and 6 on the simulator: the daemon on that profile, and calibrate writing into it
    assert "`crtk-bridge --profile my_arm.yaml`" in readme and "`crtk-ctl calibrate --profile my_arm.yaml" in readme
    proc = installed.popen(["crtk-bridge", "--profile", "my_arm.yaml", "--sim", "--no-realtime"], cwd, cwd / "d.log")
    try:
        wait_until(lambda: (installed.runtime / "crtk-bridge" / "so101.sock").exists() or proc.poll() is not None,
                   60, what="the my_arm.yaml daemon's socket")
        assert proc.poll() is None, (cwd / "d.log").read_text()
        lerobot = {name: {"id": k + 1, "drive_mode": 0, "homing_offset": 0, "range_min": 1000, "range_max": 3000}
                   for k, name in enumerate(["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex",
                                             "wrist_roll", "gripper"])}
        (cwd / "arm.json").write_text(json.dumps(lerobot, indent=4))
        cal = installed.run(["crtk-ctl", "calibrate", "--profile", "my_arm.yaml", "--import", "arm.json"], cwd)
        assert cal.returncode == 0 and "Wrote" in cal.stdout, cal.stdout + cal.stderr
        assert "range: [1000, 3000]" in (cwd / "my_arm.yaml").read_text()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(20)


def test_a_copied_shipped_profile_keeps_its_urdf(installed):
    """``cp profiles/so101.yaml ~/my_arm.yaml`` (item 8): its relative URDF path resolves among the
    installed shipped profiles."""
    cwd = installed.cwd("copy")
    (cwd / "my_arm.yaml").write_text((ROOT / "profiles" / "so101.yaml").read_text())
    checked = installed.run(["crtk-bridge", "check", "--profile", "my_arm.yaml", "--json"], cwd)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert '"so101"' in checked.stdout


def test_crtk_sim_ur_runs_from_an_installed_package_outside_the_clone(installed, short_tmp):
    """``crtk-sim ur`` crashed: its arm model read ../profiles/urdf/ur5e.urdf beside the package."""
    cwd = installed.cwd("simur")
    assert installed.run(["crtk-bridge", "init-profile", "ur5e", "ur.yaml"], cwd).returncode == 0
    control = short_tmp / "ur.ctl"
    from crtk_bridge.sim.loopback import free_loopback_host
    from crtk_bridge.sim.ur import PORTS

    host = free_loopback_host(PORTS.values())
    proc = installed.popen(["crtk-sim", "ur", "--profile", "ur.yaml", "--host", host, "--control", str(control)],
                           cwd, short_tmp / "sim.log")
    try:
        wait_until(lambda: control.exists() or proc.poll() is not None, 30, what="crtk-sim ur control socket")
        assert proc.poll() is None, (short_tmp / "sim.log").read_text()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(15)


def test_sim_daemon_and_ur_worker_run_the_installed_code_from_a_folder_holding_another_crtk_bridge(installed):
    """``--sim`` started ``python -m crtk_bridge.sim.cli`` (and the UR backend its worker), which
    imports the CURRENT folder's crtk_bridge first: a clone's, whatever version it is. Here the
    folder's is a decoy that exits at import; README's command, as written from the clone's root."""
    cwd = decoy_folder(installed.cwd("decoy"))
    log = cwd.parent / "daemon.log"
    proc = installed.popen(["crtk-bridge", "--profile", "profiles/ur5e.yaml", "--sim", "--no-realtime"], cwd, log)
    try:
        sock = installed.runtime / "crtk-bridge" / "ur5e.sock"
        wait_until(lambda: sock.exists() or proc.poll() is not None, 60, what="the ur5e daemon's socket")
        assert proc.poll() is None, log.read_text()
        state = installed.run(["crtk-ctl", "--robot", "ur5e", "state"], cwd)
        assert state.returncode == 0 and "DISABLED" in state.stdout, state.stdout + state.stderr + log.read_text()
        assert "decoy" not in log.read_text()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(20)


@pytest.mark.parametrize("safe_path", [True, False], ids=["-P", "py310-bootstrap"])
def test_spawned_modules_ignore_the_current_folder(tmp_path, safe_path):
    """spawn.module_argv / module_env, both ways (-P on 3.11+, the -c bootstrap 3.10 uses)."""
    if safe_path and sys.version_info < (3, 11):
        pytest.skip("-P needs Python 3.11")
    cwd = decoy_folder(tmp_path)
    out = subprocess.run(spawn.module_argv("crtk_bridge.sim.cli", "--version", safe_path=safe_path), cwd=cwd,
                         env=spawn.module_env(), capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "decoy" not in out.stderr, out.stderr
    assert "crtk-sim" in out.stdout
    naive = subprocess.run([sys.executable, "-m", "crtk_bridge.sim.cli", "--version"], cwd=cwd,
                           capture_output=True, text=True, timeout=60)
    assert naive.returncode == 3  # the decoy is what a plain -m would have run


def test_shipped_profiles_resolve_by_name_and_as_readme_writes_them(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert set(shipped_profile_names()) >= {"so101", "koch", "ur5e", "so101_leader", "koch_leader"}
    assert resolve_profile_arg("so101") == shipped_profiles_dir() / "so101.yaml"
    assert resolve_profile_arg("profiles/koch.yaml") == shipped_profiles_dir() / "koch.yaml"
    assert resolve_profile_arg("mine/koch.yaml") == Path("mine/koch.yaml")  # only the README spelling
    (tmp_path / "so101").write_text("name: x\n")
    assert resolve_profile_arg("so101") == Path("so101")  # an existing file always wins


def test_a_profiles_urdf_resolves_beside_it_first_then_among_the_shipped_profiles(tmp_path):
    text = (ROOT / "profiles" / "so101.yaml").read_text()
    (tmp_path / "copy.yaml").write_text(text)
    shipped = load_profile(tmp_path / "copy.yaml").namespace("so101").kinematics.urdf
    assert Path(shipped) == (shipped_profiles_dir() / "urdf" / "so101.urdf").resolve()
    (tmp_path / "urdf").mkdir()
    (tmp_path / "urdf" / "so101.urdf").write_text((ROOT / "profiles" / "urdf" / "so101.urdf").read_text())
    own = load_profile(tmp_path / "copy.yaml").namespace("so101").kinematics.urdf
    assert Path(own) == (tmp_path / "urdf" / "so101.urdf").resolve()
    (tmp_path / "other.yaml").write_text(text.replace("urdf/so101.urdf", "urdf/mine.urdf"))
    with pytest.raises(Exception) as err:
        load_profile(tmp_path / "other.yaml")
    message = str(err.value)
    assert "kinematics.urdf: no file" in message and str(tmp_path / "urdf" / "mine.urdf") in message
    assert "shipped profiles" in message and "\n" not in message


def test_init_profile_refuses_an_unknown_name_listing_the_shipped_ones_and_overwrites_only_with_force(
        tmp_path, capsys):
    from crtk_bridge.cli import main as bridge_main

    with pytest.raises(SystemExit) as exit_:
        bridge_main(["init-profile", "so100", str(tmp_path / "a.yaml")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "no shipped profile 'so100'" in err and "so101_leader" in err and "koch_leader" in err
    assert not (tmp_path / "a.yaml").exists()
    (tmp_path / "a.yaml").write_text("mine\n")
    assert bridge_main(["init-profile", "koch_leader", str(tmp_path / "a.yaml")]) == 1
    assert (tmp_path / "a.yaml").read_text() == "mine\n"
    assert bridge_main(["init-profile", "koch_leader", str(tmp_path / "a.yaml"), "--force"]) == 0
    assert load_profile(tmp_path / "a.yaml").name == "koch_leader"
    assert bridge_main(["init-profile", "so101", str(tmp_path / "no" / "dir.yaml")]) == 1
    assert "cannot write" in capsys.readouterr().err


@pytest.mark.parametrize("name, key", [("so101", "backend.port (crtk-bridge find-port)"),
                                       ("koch_leader", "backend.port (crtk-bridge find-port)"),
                                       ("bimanual_so101", "backends.left.port and backends.right.port"),
                                       ("ur5e", "backend.host"),
                                       ("canopen_2axis", "backend.interface and backend.channel")])
def test_init_profile_names_the_key_to_set_for_the_profiles_backend(tmp_path, capsys, name, key):
    """``init-profile ur5e`` said "set backend.port (crtk-bridge find-port)": a UR has no port but
    a host, a CiA 402 bus an interface and channel, the bimanual profile one port per bus (found
    in review)."""
    from crtk_bridge.cli import main as bridge_main

    assert bridge_main(["init-profile", name, str(tmp_path / "mine.yaml")]) == 0
    out = capsys.readouterr().out
    assert f"set {key}, then" in out, out
    assert out.count("backend") == key.count("backend"), out


def test_the_bridge_install_carries_the_client_library_under_both_names(installed):
    """``pip install .`` installs ``crtk_client`` (clients/python) with crtk-bridge, and the old
    names (``crtk_bridge.client.device``, ``crtk_bridge.errors``) are the same modules."""
    site = site_packages(installed)
    probe = ("import crtk_client, crtk_client.device, crtk_bridge.client.device, crtk_bridge.errors, crtk_client.errors;"
             "print(crtk_client.__file__);"
             "print(crtk_bridge.client.device is crtk_client.device and crtk_bridge.errors is crtk_client.errors)")
    out = subprocess.run([str(installed.python), "-c", probe], cwd=installed.cwd("both"), env=installed.env(),
                         capture_output=True, text=True, check=True)
    where, same = out.stdout.split()
    assert Path(where).parent == site / "crtk_client" and same == "True"


#: the vendor SDKs and daemon-only libraries crtk-bridge needs and the client must never load
DAEMON_ONLY = ("scservo_sdk", "dynamixel_sdk", "canopen", "can", "rtde_control", "rtde_receive", "pinocchio",
               "ruckig", "yaml", "ruamel", "rosbags", "serial")

#: run by the client-only venv's python: list, state and measured_js from the daemon; then what
#: it could import: crtk_bridge (must fail) and which DAEMON_ONLY modules got loaded
_CLIENT_ONLY_PROBE = """
import importlib.util, json, sys
from crtk_client import connect
from crtk_client.errors import CommandError
with connect(socket=sys.argv[1], timeout=10.0) as robot:
    arm = robot.device(robot.namespaces[0])
    p, v, e, ts = arm.measured_js()
    state = robot.operating_state()
    try:
        arm.servo_jp(p)
        refused = None
    except CommandError as exc:
        refused = exc.code
print(json.dumps({"namespaces": robot.namespaces, "n": len(p), "type": type(p).__name__, "state": state,
                  "refused": refused, "bridge": importlib.util.find_spec("crtk_bridge") is not None,
                  "loaded": sorted(m for m in json.loads(sys.argv[2]) if m in sys.modules)}))
"""


@only_on("so101-feetech")
@pytest.mark.reuse_daemon
def test_the_client_distribution_alone_works_and_needs_only_numpy_and_msgspec(sim_daemon, tmp_path):
    """``pip install ./clients/python`` (non-editable) into a venv that sees numpy and msgspec
    only: its metadata requires those two (zenoh an extra), it talks to a daemon (list, state,
    measured_js as numpy, a refusal as CommandError), it cannot import crtk_bridge and loads no
    vendor SDK."""
    import importlib.metadata

    import msgspec
    import numpy

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    deps = tmp_path / "deps"  # numpy and msgspec of the test venv, nothing else of it
    deps.mkdir()
    for package in (numpy, msgspec):
        folder = Path(package.__file__).parent
        (deps / folder.name).symlink_to(folder)
        libs = folder.parent / f"{folder.name}.libs"  # a manylinux wheel's bundled libraries
        if libs.is_dir():
            (deps / libs.name).symlink_to(libs)
    (site / "_deps.pth").write_text(f"{deps}\n")
    src = tmp_path / "src"
    shutil.copytree(ROOT / "clients" / "python", src, ignore=shutil.ignore_patterns("build", "*.egg-info",
                                                                                   "__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q",
                    "--disable-pip-version-check", str(src)], check=True, timeout=600, capture_output=True)
    assert not list(site.glob("__editable__*"))
    meta = subprocess.run([str(python), "-c", "import importlib.metadata as m, json; "
                           "print(json.dumps(m.requires('crtk-client')))"], capture_output=True, text=True, check=True)
    requires = sorted(json.loads(meta.stdout))
    assert [r.split(";")[0].split(">")[0].split("<")[0].strip() for r in requires] == \
        ["eclipse-zenoh", "msgspec", "numpy"], requires
    assert "extra == \"zenoh\"" in next(r for r in requires if r.startswith("eclipse-zenoh")), requires
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    out = subprocess.run([str(python), "-P", "-c", _CLIENT_ONLY_PROBE, str(sim_daemon.socket_path),
                          json.dumps(DAEMON_ONLY)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["namespaces"] == ["so101", "so101/gripper"] and got["n"] == 5 and got["type"] == "ndarray"
    assert got["state"] == "DISABLED" and got["refused"] == "invalid_state"  # servo_jp while DISABLED
    assert got["bridge"] is False and got["loaded"] == []
    assert importlib.metadata.version("crtk-bridge")  # the test venv's own, untouched

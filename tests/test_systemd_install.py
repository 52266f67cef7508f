"""systemd/README.md followed verbatim gives a working service: the unit verifies with
systemd-analyze, it runs the virtual environment the README creates, and the README's own install
commands (run here under a temporary root) lay out a profile whose URDF resolves."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from crtk_bridge.cli import main as bridge_main
from crtk_bridge.core.kinematics_check import check_kinematics
from crtk_bridge.profile import load_profile

from .conftest import ROOT

README = (ROOT / "systemd" / "README.md").read_text()
UNIT = (ROOT / "systemd" / "crtk-bridge@.service").read_text()


def sh_blocks(text: str) -> list[list[str]]:
    """The README's ```sh blocks as lists of commands (comments dropped, continuations joined)."""
    blocks = []
    for body in re.findall(r"```sh\n(.*?)```", text, re.S):
        body = body.replace("\\\n", " ")
        blocks.append([line.split("  #")[0].strip() for line in body.splitlines() if line.strip()])
    return blocks


def commands(prefix: str) -> list[str]:
    """Every README command starting with ``prefix``: in sh blocks and in inline `code`."""
    found = [c for block in sh_blocks(README) for c in block if c.startswith(prefix)]
    found += [c for c in re.findall(r"`([^`\n]+)`", README) if c.startswith(prefix)]
    return list(dict.fromkeys(found))


def exec_start() -> list[str]:
    lines = [ln for ln in UNIT.splitlines() if ln.startswith("ExecStart=")]
    assert len(lines) == 1
    return shlex.split(lines[0].removeprefix("ExecStart="))


def test_unit_runs_the_venv_the_readme_installs():
    (venv_cmd,) = commands("python3 -m venv ")
    venv = venv_cmd.split()[-1]
    assert venv.startswith("/opt/")
    assert f"{venv}/bin/pip install ." in commands(f"{venv}/bin/pip ")
    assert "apt-get install -y python3-venv" in commands("apt-get ")  # Debian's venv is a package
    # never a system-wide pip: Debian 12 refuses it (PEP 668)
    assert not [c for block in sh_blocks(README) for c in block if re.match(r"(sudo )?pip3? ", c)]
    argv = exec_start()
    assert argv[0] == f"{venv}/bin/crtk-bridge"
    assert argv[1:] == ["--profile", "/etc/crtk-bridge/%i.yaml", "--socket", "/run/crtk-bridge/%i.sock"]


def _verify(unit_text: str, tmp: Path) -> subprocess.CompletedProcess:
    unit = tmp / "crtk-bridge@so101.service"
    unit.write_text(unit_text)
    return subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_unit_verifies_with_systemd_analyze(tmp_path):
    venv = exec_start()[0].removesuffix("/bin/crtk-bridge")
    # the venv as the README makes it, under a temporary root: an executable bin/crtk-bridge
    fake = tmp_path / venv.lstrip("/")
    (fake / "bin").mkdir(parents=True)
    (fake / "bin" / "crtk-bridge").write_text("#!/bin/sh\n")
    (fake / "bin" / "crtk-bridge").chmod(0o755)
    proc = _verify(UNIT.replace(venv, str(fake)), tmp_path)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    # and the verification has teeth: a unit whose binary is missing fails it, naming the path
    proc = _verify(UNIT.replace(venv, str(tmp_path / "nowhere")), tmp_path)
    assert proc.returncode != 0 and f"{tmp_path}/nowhere/bin/crtk-bridge" in proc.stderr


def test_readme_install_commands_give_a_profile_whose_urdf_resolves(tmp_path, capsys):
    root = tmp_path / "root"
    (root / "etc" / "systemd" / "system").mkdir(parents=True)  # present on every systemd host
    installs = [c for c in commands("install ") if "/etc/" in c]
    assert any("profiles/urdf/so101.urdf" in c for c in installs), installs
    for cmd in installs:
        # verbatim, from the top of the clone, with /etc/ moved under the temporary root
        subprocess.run(["bash", "-c", cmd.replace(" /etc/", f" {root}/etc/")], cwd=ROOT, check=True)
    assert (root / "etc" / "systemd" / "system" / "crtk-bridge@.service").read_text() == UNIT

    profile_arg = exec_start()[exec_start().index("--profile") + 1]
    for robot in ("so101", "koch"):
        path = root / profile_arg.replace("%i", robot).lstrip("/")
        profile = load_profile(path)  # the URDF path, relative to the profile, resolves
        assert bridge_main(["check", "--profile", str(path)]) == 0, capsys.readouterr().err
        if robot == "so101":
            urdf = Path(profile.namespace("so101").kinematics.urdf)
            assert urdf == root / "etc" / "crtk-bridge" / "urdf" / "so101.urdf" and urdf.is_file()
            assert check_kinematics(profile, str(path)) == ["so101: base_link -> gripper_frame_link"]

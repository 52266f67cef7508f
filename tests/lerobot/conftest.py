"""Fixtures of the LeRobot tests: the real LeRobot in a venv of its own (built once, see venv.py),
this checkout's plugin installed beside it, and a LeRobot robot driven line by line (driver.py)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

from . import venv as lrvenv

DRIVER = Path(__file__).resolve().parent / "driver.py"


def _in_ci() -> bool:
    return os.environ.get("CI", "").lower() not in ("", "0", "false", "no")


@pytest.fixture(scope="session")
def lerobot_venv() -> Path:
    """The LeRobot venv (tests/lerobot/requirements.txt), built on first use and reused while its
    requirements do not change. In CI (``CI`` set) a failed build fails the tests; elsewhere they
    are skipped saying why."""
    try:
        return lrvenv.ensure_venv()
    except (lrvenv.LeRobotVenvError, OSError) as exc:
        msg = f"the LeRobot venv could not be built ({lrvenv.venv_path()}): {exc}"
        if _in_ci():
            pytest.fail(msg, pytrace=False)
        pytest.skip(msg + " (CI is not set: skipped; in CI this fails)")


@pytest.fixture(scope="session")
def lerobot_plugin(lerobot_venv) -> Path:
    """This checkout's clients/python and lerobot_robot_crtk, installed non-editable into a folder
    of the session's, which LeRobot's commands see on PYTHONPATH (venv.lerobot_env)."""
    base = Path(tempfile.mkdtemp(prefix="crtk-lrplugin-"))
    try:
        try:
            dest = lrvenv.install_plugin(lerobot_venv, base / "site")
        except lrvenv.LeRobotVenvError as exc:
            pytest.fail(f"installing the LeRobot plugin failed: {exc}", pytrace=False)
        yield dest
    finally:
        shutil.rmtree(base, ignore_errors=True)


class LeRobotDriver:
    """A LeRobot robot in the LeRobot venv's python (driver.py), one request per call."""

    def __init__(self, venv: Path, log: Path, plugin_dir: Path | None = None, **env: str):
        self.log_path = log
        self._log = open(log, "wb")
        self.proc = subprocess.Popen([str(lrvenv.python(venv)), str(DRIVER)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=self._log, text=True,
                                     env=lrvenv.lerobot_env(plugin_dir, **env), cwd=log.parent)

    def request(self, op: str, **kw) -> dict:
        self.proc.stdin.write(json.dumps({"op": op, **kw}) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise AssertionError(f"LeRobot driver exited ({self.proc.poll()}) on {op}:\n{self.output()}")
        return json.loads(line)

    def __call__(self, op: str, **kw) -> dict:
        reply = self.request(op, **kw)
        assert reply["ok"], f"LeRobot {op}: {reply['error']}\n{self.output()[-3000:]}"
        return reply

    def output(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def close(self) -> int:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.close()
                self.proc.wait(30)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode


@pytest.fixture
def lerobot_driver(lerobot_venv, short_tmp):
    """Start :class:`LeRobotDriver` processes (``start(plugin_dir=None, **env)``); all closed at
    the end of the test."""
    started = []

    def start(plugin_dir: Path | None = None, **env: str) -> LeRobotDriver:
        d = LeRobotDriver(lerobot_venv, short_tmp / f"lerobot-{len(started)}.log", plugin_dir, **env)
        started.append(d)
        return d

    yield start
    for d in started:
        d.close()

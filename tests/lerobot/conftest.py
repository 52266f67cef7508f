"""Fixtures of the LeRobot tests: the real LeRobot in a venv of its own (built once, see venv.py),
this checkout's plugin installed beside it, and a LeRobot robot driven line by line (driver.py).

A build of that venv takes minutes of mostly one core, and most of the suite waits on sockets and
simulators: when a session selects LeRobot tests and no complete venv exists, the build starts in
the background as soon as collection ends (:class:`BackgroundBuild`, ``python -m
tests.lerobot.venv``, niced), and the LeRobot tests run last, waiting for it. Under
pytest-xdist (``-n 2``) the controller, which outlives every worker, starts and stops that build
(:func:`xdist_collected`, called from tests/conftest.py), and the workers' LeRobot tests wait for
it on venv.py's lock."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from . import venv as lrvenv

HERE = Path(__file__).resolve().parent
DRIVER = HERE / "driver.py"


def _in_ci() -> bool:
    return os.environ.get("CI", "").lower() not in ("", "0", "false", "no")


def _is_lerobot(item) -> bool:
    return HERE in Path(str(item.path)).resolve().parents


class BackgroundBuild:
    """``python -m tests.lerobot.venv`` in a process group of its own (so its pip goes with it),
    output to a log file. venv.ensure_venv's file lock and completion marker keep a concurrent
    build (another session, a bench) from using or removing a half-built venv."""

    def __init__(self):
        fd, name = tempfile.mkstemp(prefix="crtk-lerobot-venv-", suffix=".log")
        self.log = Path(name)
        with os.fdopen(fd, "wb") as f:
            self.proc = subprocess.Popen([sys.executable, "-m", "tests.lerobot.venv"], cwd=lrvenv.ROOT, stdout=f,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
                                         preexec_fn=lambda: os.nice(10))  # the tests' daemons come first
        self.started = time.monotonic()

    def wait(self, timeout: float) -> None:
        """Return once the build succeeded; raise :class:`venv.LeRobotVenvError` with its log's tail."""
        try:
            rc = self.proc.wait(max(0.0, timeout - (time.monotonic() - self.started)))
        except subprocess.TimeoutExpired:
            self.stop()
            raise lrvenv.LeRobotVenvError(f"the background build timed out after {timeout:.0f} s "
                                          f"(log {self.log}):\n{self.tail()}") from None
        if rc != 0:
            raise lrvenv.LeRobotVenvError(f"the background build failed (exit {rc}, log {self.log}):\n{self.tail()}")

    def tail(self, lines: int = 20) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"

    def stop(self) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
                self.proc.wait(30)
            except (OSError, subprocess.TimeoutExpired):
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()


_build: BackgroundBuild | None = None


def pytest_collection_modifyitems(config, items):
    # the LeRobot tests last (stable order otherwise): the venv builds meanwhile
    items[:] = [i for i in items if not _is_lerobot(i)] + [i for i in items if _is_lerobot(i)]


def _xdist_worker(config) -> bool:
    return hasattr(config, "workerinput")


def pytest_collection_finish(session):
    global _build
    if _build is not None or session.config.option.collectonly or _xdist_worker(session.config):
        return  # a worker of pytest-xdist: its controller builds (xdist_collected)
    if not any(_is_lerobot(i) and "lerobot_venv" in getattr(i, "fixturenames", ()) for i in session.items):
        return
    if (lrvenv.venv_path() / lrvenv.MARKER).exists():
        return
    _build = BackgroundBuild()
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_line(f"building the LeRobot venv {lrvenv.venv_path()} in the background (log {_build.log})")


def pytest_sessionfinish(session):
    stop_build()


def stop_build() -> None:
    if _build is not None:
        _build.stop()  # no LeRobot test ran (-x, an interrupt): a later build starts over


#: the fixtures that need the venv: a LeRobot test file naming one needs it built
_VENV_FIXTURES = re.compile(r"\blerobot_(venv|plugin|launcher|reader|driver)\b")


def xdist_collected(config, nodeids) -> None:
    """pytest-xdist's controller, once a worker has collected: a worker may finish its share (and
    its session) while another's LeRobot tests still wait for the venv, so the build is the
    controller's, started when a collected LeRobot test file asks for the venv (it collects
    nothing itself: the files tell), stopped at its session's end (:func:`stop_build`)."""
    global _build
    if _build is not None or config.option.collectonly or (lrvenv.venv_path() / lrvenv.MARKER).exists():
        return
    files = {lrvenv.ROOT / nodeid.split("::", 1)[0] for nodeid in nodeids}
    if not any(HERE in f.parents and f.is_file() and _VENV_FIXTURES.search(f.read_text()) for f in files):
        return
    _build = BackgroundBuild()
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_line(f"building the LeRobot venv {lrvenv.venv_path()} in the background (log {_build.log})")


@pytest.fixture(scope="session")
def lerobot_venv() -> Path:
    """The LeRobot venv (tests/lerobot/requirements.txt), built on first use (or in the background
    since collection ended) and reused while its requirements do not change. In CI (``CI`` set) a
    failed build fails the tests; elsewhere they are skipped saying why."""
    try:
        if _build is not None:
            _build.wait(lrvenv.BUILD_TIMEOUT_S + 60)
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


class LaunchedProcess:
    """A LeRobot command the :class:`Launcher` forked: what the tests use of a ``subprocess.Popen``."""

    def __init__(self, launcher: Launcher, pid: int, command: str):
        self.launcher, self.pid, self.args = launcher, pid, [command]
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self.launcher("poll", pid=self.pid)["returncode"]
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if deadline is not None and time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(self.args, timeout)
            time.sleep(0.05)
        return self.returncode

    def kill(self) -> None:
        if self.returncode is None:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


class Launcher:
    """launcher.py in the LeRobot venv: LeRobot's console scripts run as forks of one interpreter
    that imported LeRobot once (``run``), with this checkout's plugin on its path."""

    def __init__(self, venv: Path, plugin_dir: Path, base: Path):
        self.log_path = base / "launcher.log"
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen([str(lrvenv.python(venv)), str(HERE / "launcher.py")], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=self._log, text=True, cwd=base,
                                     env=lrvenv.lerobot_env(plugin_dir, HF_LEROBOT_HOME=str(base / "hf")))
        self._ready = False

    def _line(self, op: str) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            self._log.flush()
            raise AssertionError(f"the LeRobot launcher exited ({self.proc.poll()}) on {op}:\n"
                                 f"{self.log_path.read_text(errors='replace')[-3000:]}")
        return json.loads(line)

    def __call__(self, op: str, **kw) -> dict:
        if not self._ready:
            self._ready = self._line("start")["ready"]
        self.proc.stdin.write(json.dumps({"op": op, **kw}) + "\n")
        self.proc.stdin.flush()
        reply = self._line(op)
        assert reply["ok"], f"LeRobot launcher {op}: {reply['error']}"
        return reply

    def run(self, command: str, args: list[str], log: Path, cwd: Path, env: dict) -> LaunchedProcess:
        log.write_bytes(b"")  # there from the start, as a Popen's redirected output is
        pid = self("run", command=command, args=[str(a) for a in args], log=str(log), cwd=str(cwd), env=env)["pid"]
        return LaunchedProcess(self, pid, command)

    def close(self) -> None:
        try:
            self.proc.stdin.close()
            self.proc.wait(30)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        self._log.close()


@pytest.fixture(scope="session")
def lerobot_launcher(lerobot_venv, lerobot_plugin):
    """:class:`Launcher`: LeRobot's commands with LeRobot imported once for the session (a module
    fixture asks for it first, so its import overlaps the start of the simulators and daemons)."""
    base = Path(tempfile.mkdtemp(prefix="crtk-lrlaunch-"))
    launcher = Launcher(lerobot_venv, lerobot_plugin, base)
    try:
        yield launcher
    finally:
        launcher.close()
        shutil.rmtree(base, ignore_errors=True)


@pytest.fixture(scope="session")
def lerobot_reader(lerobot_venv):
    """A :class:`LeRobotDriver` the session's tests read their datasets with (rig.read_dataset):
    LeRobot imported once, early (a module fixture asks for it first, so the import overlaps the
    start of its simulators and daemons), not once per dataset."""
    base = Path(tempfile.mkdtemp(prefix="crtk-lrread-"))
    d = LeRobotDriver(lerobot_venv, base / "reader.log", HF_LEROBOT_HOME=str(base / "hf"))
    try:
        yield d
    finally:
        d.proc.kill()  # it only reads files: no teardown of its interpreter to wait for
        d.close()
        shutil.rmtree(base, ignore_errors=True)


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

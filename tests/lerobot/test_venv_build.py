"""The LeRobot venv's build (venv.py) and its background start (conftest.py): in CI a failed build
fails the LeRobot tests, never skips them; the LeRobot tests run after the rest of the session
(which the build overlaps); and a builder killed mid-build leaves the lock held while its
children still write into the venv folder, so the next builder cannot remove it under them.
Each runs in a process of its own against a cache of its own (never the session's)."""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

from ..conftest import ROOT, wait_until

UNITS = "tests/lerobot/test_lerobot_units.py"


def pytest_run(args: list[str], tmp: Path, **env: str) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if k not in ("CI", "CRTK_LEROBOT_CACHE", "PYTEST_ADDOPTS")}
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *args], cwd=ROOT,
                          env={**base, **env}, capture_output=True, text=True, timeout=120)


def test_a_failed_background_build_fails_the_lerobot_tests_in_ci_and_skips_them_elsewhere(short_tmp):
    not_a_dir = short_tmp / "cache"
    not_a_dir.write_text("a file where the cache folder should be: the build fails at once\n")
    ci = pytest_run([UNITS], short_tmp, CI="true", CRTK_LEROBOT_CACHE=str(not_a_dir))
    out = ci.stdout + ci.stderr
    assert ci.returncode != 0, out
    assert "the background build failed" in out and "crtk-lerobot-venv-" in out, out  # its log, named
    assert "1 error" in out and "skipped" not in out, out
    local = pytest_run([UNITS, "-rs"], short_tmp, CRTK_LEROBOT_CACHE=str(not_a_dir))
    out = local.stdout + local.stderr
    assert local.returncode == 0, out
    assert "1 skipped" in out and "the background build failed" in out and "in CI this fails" in out, out


def test_under_xdist_the_controller_starts_the_one_background_build(short_tmp):
    # the workers collect the same tests; a worker's session may end while another's LeRobot tests
    # still wait for the venv, so the controller (which outlives them) builds, once
    not_a_dir = short_tmp / "cache"
    not_a_dir.write_text("a file where the cache folder should be: the build fails at once\n")
    tmp = short_tmp / "tmp"  # where the builds' logs go (tempfile), apart from other sessions'
    tmp.mkdir()
    ci = pytest_run(["-n", "2", UNITS, "tests/test_vocabulary.py"], short_tmp, CI="true",
                    CRTK_LEROBOT_CACHE=str(not_a_dir), TMPDIR=str(tmp))
    out = ci.stdout + ci.stderr
    assert ci.returncode != 0 and "1 error" in out and "skipped" not in out, out  # CI: a failed build fails
    logs = sorted(tmp.glob("crtk-lerobot-venv-*.log"))
    assert len(logs) == 1 and out.count("in the background (log ") == 1 and str(logs[0]) in out, (logs, out)


def test_the_lerobot_tests_run_after_the_rest_of_the_session(short_tmp):
    out = pytest_run(["--collect-only", UNITS, "tests/test_vocabulary.py"], short_tmp).stdout
    files = [ln.split("::")[0] for ln in out.splitlines() if "::" in ln]
    assert files and files[-1] == UNITS and "tests/test_vocabulary.py" in files, out
    first = files.index(UNITS)
    assert all(f == UNITS for f in files[first:]), files


def test_a_killed_builder_leaves_the_lock_to_its_children_still_writing(short_tmp):
    # the builder's first step (python -m venv) replaced by a program that says it started, then sleeps
    started = short_tmp / "child.pid"
    fake = short_tmp / "fake-python"
    fake.write_text(f"#!/bin/sh\necho $$ > {started}\nexec sleep 60\n")
    fake.chmod(0o755)
    builder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import sys
        from tests.lerobot import venv
        sys.executable = {str(fake)!r}
        venv.ensure_venv()
        """)], cwd=ROOT, env={**os.environ, "CRTK_LEROBOT_CACHE": str(short_tmp / "cache")},
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    child = None
    try:
        wait_until(lambda: started.exists() and started.read_text().strip(), 30, what="the builder's child")
        child = int(started.read_text())
        builder.kill()  # the builder dies mid-build; its child goes on
        builder.wait(10)
        lock = next((short_tmp / "cache").glob("*.lock"))
        with open(lock, "w") as f:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                held = False
            except BlockingIOError:
                held = True
            assert held, "a builder's child still runs, but the lock is free: a second builder would remove its venv"
            os.kill(child, signal.SIGKILL)
            child = None
            wait_until(lambda: _try_lock(f), 10, what="the lock free once the child is gone")
    finally:
        if builder.poll() is None:
            builder.kill()
            builder.wait()
        if child is not None:
            os.kill(child, signal.SIGKILL)


def _try_lock(f) -> bool:
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    fcntl.flock(f, fcntl.LOCK_UN)
    return True

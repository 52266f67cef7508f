"""Shared fixtures: real daemon and simulator processes, waited on with deadlines."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SO101 = ROOT / "profiles" / "so101.yaml"
SO101_URDF = ROOT / "profiles" / "urdf" / "so101.urdf"


def so101_data() -> dict:
    """profiles/so101.yaml as data, with its URDF path made absolute so a copy can live anywhere."""
    import yaml

    data = yaml.safe_load(SO101.read_text())
    for ns in data["namespaces"]:
        if "kinematics" in ns:
            ns["kinematics"]["urdf"] = str(SO101_URDF)
    return data


def wait_until(predicate, timeout=10.0, interval=0.01, what="condition"):
    """Poll ``predicate`` until it is truthy; fail the test naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


@pytest.fixture
def short_tmp():
    """A short temp dir: Unix socket paths must stay under 108 bytes."""
    d = tempfile.mkdtemp(prefix="crtk-")
    yield Path(d)
    shutil.rmtree(d, ignore_errors=True)


class DaemonProcess:
    """``crtk-bridge`` as a real subprocess."""

    def __init__(self, args: list[str], socket_path: Path, log_path: Path):
        self.socket_path = socket_path
        self.log_path = log_path
        self._log = open(log_path, "wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "crtk_bridge.cli", *args, "--socket", str(socket_path)],
            stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=ROOT,
        )
        try:
            wait_until(lambda: socket_path.exists() or self.proc.poll() is not None, 30, what="daemon socket")
        except AssertionError:
            self.stop()
            raise
        if self.proc.poll() is not None:
            raise AssertionError(f"daemon exited with {self.proc.returncode}:\n{self.output()}")

    def output(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def sim_control_path(self) -> str:
        for line in self.output().splitlines():
            if "simulator control socket" in line:
                return line.rsplit(" ", 1)[-1].rstrip(")")
        raise AssertionError("daemon did not print its simulator control socket:\n" + self.output())

    def terminate(self, timeout=15.0) -> int:
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(timeout)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


@pytest.fixture
def sim_daemon(short_tmp):
    """``crtk-bridge --profile profiles/so101.yaml --sim`` on its own socket."""
    d = DaemonProcess(["--profile", str(SO101), "--sim"], short_tmp / "so101.sock", short_tmp / "daemon.log")
    yield d
    d.stop()


class RawSession:
    """A plain JSON-lines session on the socket (as any language would speak it), recording
    every pushed operating_state event in order."""

    def __init__(self, path: str):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(path)
        self.states: list[dict] = []
        self.events: list[dict] = []
        self.lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self):
        f = self.sock.makefile("rb")
        for line in f:
            msg = json.loads(line)
            with self.lock:
                if msg.get("event") == "operating_state":
                    self.states.append(msg["data"])
                elif "event" in msg:
                    self.events.append(msg)

    def busy_edges(self) -> list[bool]:
        """is_busy of each state event, with repeats of the same value collapsed."""
        with self.lock:
            out: list[bool] = []
            for s in self.states:
                if not out or out[-1] != s["is_busy"]:
                    out.append(s["is_busy"])
            return out

    def close(self):
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()

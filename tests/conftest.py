"""Shared fixtures: real daemon and simulator processes, waited on with deadlines."""

from __future__ import annotations

import json
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from crtk_bridge.profile import load_profile

ROOT = Path(__file__).resolve().parent.parent
SO101 = ROOT / "profiles" / "so101.yaml"
SO101_URDF = ROOT / "profiles" / "urdf" / "so101.urdf"
KOCH = ROOT / "profiles" / "koch.yaml"


def profile_data(path: Path) -> dict:
    """A profile as data, with its URDF paths made absolute so a copy can live anywhere."""
    import yaml

    data = yaml.safe_load(path.read_text())
    for ns in data["namespaces"]:
        if "kinematics" in ns:
            ns["kinematics"]["urdf"] = str((path.parent / ns["kinematics"]["urdf"]).resolve())
    return data


def so101_data() -> dict:
    """profiles/so101.yaml as data, with its URDF path made absolute so a copy can live anywhere."""
    return profile_data(SO101)


# Arm goals (rad, shoulder_pan .. wrist_roll) used by the end-to-end tests on every simulated
# robot; SimRobot checks each lies inside the robot's limits with a margin.
SAFE_GOALS = {
    "small": (0.1, 0.2, 0.3, 0.0, 0.0),
    "reach": (0.6, 0.3, -0.4, 0.2, 0.0),
    "far": (-0.6, 0.3, -0.4, 0.2, 0.0),
    "wide": (1.2, -1.0, 1.0, 0.5, 1.5),
}
GOAL_MARGIN = 0.1  # rad inside the position limits


@dataclass(frozen=True, eq=False)
class SimRobot:
    """One simulated robot the conformance tests run on: its profile, simulator and namespaces.

    ``backend`` is the profile's backend type, which is also the ``crtk-sim`` device name; tests
    key their per-backend differences on it. Servo ids are strings, as the simulators' dump keys.
    """

    id: str
    profile: Path
    backend: str
    arm: str
    gripper: str
    joint_names: tuple[str, ...]
    gripper_joint: str
    arm_ids: tuple[str, ...]
    gripper_id: str
    servo_id: dict  # joint name -> bus id (int)
    pos_min: np.ndarray
    pos_max: np.ndarray
    home: np.ndarray
    servo_timeout_s: float
    goals: dict  # name -> np.ndarray, see SAFE_GOALS

    @classmethod
    def load(cls, id: str, path: Path) -> SimRobot:
        p = load_profile(path)
        arm_ns, grip_ns = p.namespaces[0], p.namespaces[1]
        by_name = {j.name: j for j in p.joints}
        arm = [by_name[n] for n in arm_ns.joints]
        (grip,) = [by_name[n] for n in grip_ns.joints]
        lo = np.array([j.limits.position_min for j in arm])
        hi = np.array([j.limits.position_max for j in arm])
        goals = {k: np.array(v) for k, v in SAFE_GOALS.items()}
        for k, g in goals.items():
            assert len(g) == len(arm) and np.all(g >= lo + GOAL_MARGIN) and np.all(g <= hi - GOAL_MARGIN), \
                f"{path}: SAFE_GOALS[{k!r}] = {g} is not inside the limits of {arm_ns.name}"
        return cls(id=id, profile=path, backend=p.backend_type, arm=arm_ns.name, gripper=grip_ns.name,
                   joint_names=tuple(arm_ns.joints), gripper_joint=grip.name,
                   arm_ids=tuple(str(j.backend["id"]) for j in arm), gripper_id=str(grip.backend["id"]),
                   servo_id={j.name: j.backend["id"] for j in p.joints}, pos_min=lo, pos_max=hi,
                   home=np.array([j.home for j in arm]), servo_timeout_s=p.safety.servo_timeout_s,
                   goals=goals)

    @property
    def n(self) -> int:
        return len(self.joint_names)

    @property
    def servo_ids(self) -> tuple[str, ...]:
        return self.arm_ids + (self.gripper_id,)

    def data(self) -> dict:
        return profile_data(self.profile)

    def vec(self, **by_joint: float) -> np.ndarray:
        """An arm vector, zero except the named joints: ``robot.vec(elbow_flex=0.1)``."""
        out = np.zeros(self.n)
        for name, value in by_joint.items():
            out[self.joint_names.index(name)] = value
        return out


SIM_ROBOTS = {r.id: r for r in (SimRobot.load("so101-feetech", SO101), SimRobot.load("koch-dynamixel", KOCH))}


def only_on(*ids: str):
    """Restrict a test that uses ``sim_daemon`` / ``sim_robot`` to some simulated robots."""
    return pytest.mark.parametrize("sim_robot", [SIM_ROBOTS[i] for i in ids], ids=list(ids), indirect=True)


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

    def __init__(self, args: list[str], socket_path: Path, log_path: Path, robot: SimRobot | None = None):
        self.robot = robot
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

    def _disable_quietly(self) -> None:
        """Teardown: disable (torque off) first, so that SIGTERM does not park an arm a test left
        ENABLED (profiles with shutdown.action: park); tests of shutdown use :meth:`terminate`."""
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(3.0)
                s.connect(str(self.socket_path))
                s.sendall(b'{"id": 1, "cmd": "disable"}\n')
                f = s.makefile("rb")
                for line in f:
                    if json.loads(line).get("id") == 1:
                        break
        except (OSError, ValueError):
            pass  # the daemon is gone or busy: SIGTERM still stops it safely

    def stop(self) -> None:
        if self.proc.poll() is None:
            self._disable_quietly()
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


@pytest.fixture(params=list(SIM_ROBOTS.values()), ids=list(SIM_ROBOTS))
def sim_robot(request) -> SimRobot:
    """Each simulated robot in turn (one conformance suite over every backend with a simulator)."""
    return request.param


@pytest.fixture
def sim_daemon(short_tmp, sim_robot):
    """``crtk-bridge --profile <robot profile> --sim`` on its own socket; ``.robot`` is the SimRobot."""
    d = DaemonProcess(["--profile", str(sim_robot.profile), "--sim"], short_tmp / f"{sim_robot.id}.sock",
                      short_tmp / "daemon.log", robot=sim_robot)
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

"""Simulated arms as a LeRobot user has them, for the LeRobot tests and bench/bench_lerobot.py.

:class:`CalibratedArm`: ``crtk-sim feetech`` on its own (its pty and control socket), its servos
holding a LeRobot calibration as ``lerobot-calibrate`` leaves them (Homing_Offset,
Min/Max_Position_Limit in EEPROM), the calibration file where LeRobot looks for it, and, when
asked, the daemon on that pty with the calibration imported from the same file
(``crtk-ctl calibrate --import``'s conversion, docs/calibration.md). LeRobot's own classes and the
daemon then read the same ticks as the same numbers: :func:`lerobot_reading` is LeRobot's
documented conversion, independent of both.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
from pathlib import Path

import numpy as np
import yaml

from crtk_bridge.backends.calibration import from_lerobot
from crtk_bridge.sim.control import control_request

from ..conftest import ROOT, DaemonProcess, SimRobot, standalone_sim, wait_until

SO101 = ROOT / "profiles" / "so101.yaml"
SO101_LEADER = ROOT / "profiles" / "so101_leader.yaml"
UR5E = ROOT / "profiles" / "ur5e.yaml"
#: a LeRobot SO-101 calibration (so_follower/<id>.json, written by lerobot-calibrate): homing
#: offsets of both signs, ranges off the middle, the full-turn wrist_roll LeRobot records
CALIBRATION = {
    "shoulder_pan": {"id": 1, "drive_mode": 0, "homing_offset": -41, "range_min": 745, "range_max": 3310},
    "shoulder_lift": {"id": 2, "drive_mode": 0, "homing_offset": 133, "range_min": 840, "range_max": 3281},
    "elbow_flex": {"id": 3, "drive_mode": 0, "homing_offset": -652, "range_min": 881, "range_max": 3064},
    "wrist_flex": {"id": 4, "drive_mode": 0, "homing_offset": 377, "range_min": 866, "range_max": 3171},
    "wrist_roll": {"id": 5, "drive_mode": 0, "homing_offset": 15, "range_min": 0, "range_max": 4095},
    "gripper": {"id": 6, "drive_mode": 0, "homing_offset": -1480, "range_min": 2017, "range_max": 3441},
}
MOTORS = tuple(CALIBRATION)
ARM = MOTORS[:5]
KEYS = tuple(f"{m}.pos" for m in MOTORS)


def lerobot_reading(name: str, present: float, calibration=CALIBRATION) -> float:
    """LeRobot's number for a servo's Present_Position (motors_bus._normalize, SO arms since
    0.4.4): degrees about the middle of the range for the arm, 0..100 for the gripper (100..0
    with drive_mode 1)."""
    c = calibration[name]
    lo, hi = c["range_min"], c["range_max"]
    if name == "gripper":
        pct = (min(hi, max(lo, present)) - lo) / (hi - lo) * 100
        return 100 - pct if c["drive_mode"] else pct
    return (present - (lo + hi) / 2) * 360 / 4095


def one_tick(name: str, calibration=CALIBRATION) -> float:
    """One servo tick in LeRobot's units of that joint."""
    c = calibration[name]
    return 100 / (c["range_max"] - c["range_min"]) if name == "gripper" else 360 / 4095


def pose_at(fraction: float, calibration=CALIBRATION) -> dict[str, int]:
    """Every servo at ``fraction`` of its calibrated range (ticks)."""
    return {n: int(round(c["range_min"] + fraction * (c["range_max"] - c["range_min"]))) for n, c in calibration.items()}


class CalibratedArm:
    """One simulated SO-101 (follower or leader profile) with a LeRobot calibration; see the module."""

    def __init__(self, profile: Path, tmp: Path, name: str, calibration=CALIBRATION, pose: dict | None = None):
        self.tmp = tmp / name
        self.tmp.mkdir(parents=True)
        self.name = name
        self.calibration = calibration
        self.robot = SimRobot.load(name, profile)
        self._stack = contextlib.ExitStack()
        self.sim_profile, remote = self._stack.enter_context(standalone_sim(self.robot, self.tmp))
        self.sim = remote.path
        self.port = yaml.safe_load(self.sim_profile.read_text())["backend"]["port"]
        self.calibration_dir = self.tmp / "calibration"
        self.calibration_dir.mkdir()
        (self.calibration_dir / f"{name}.json").write_text(json.dumps(calibration, indent=4))
        for motor, c in calibration.items():  # what lerobot-calibrate leaves in the servos' EEPROM
            for register, key in (("Homing_Offset", "homing_offset"), ("Min_Position_Limit", "range_min"),
                                  ("Max_Position_Limit", "range_max")):
                self.write(motor, register, c[key])
        if pose is not None:
            self.place(pose)
        self.daemon: DaemonProcess | None = None

    # the simulator's registers
    def write(self, motor: str, register: str, value: int) -> None:
        reply = control_request(self.sim, {"cmd": "write", "id": self.calibration[motor]["id"], "register": register,
                                           "value": int(value)})
        assert reply["ok"], (self.name, motor, register, reply)

    def read(self, motor: str, register: str = "Present_Position") -> int:
        reply = control_request(self.sim, {"cmd": "read", "id": self.calibration[motor]["id"], "register": register})
        assert reply["ok"], (self.name, motor, register, reply)
        return reply["value"]

    def ticks(self, register: str = "Present_Position") -> dict[str, int]:
        return {m: self.read(m, register) for m in self.calibration}

    def reading(self, register: str = "Present_Position") -> dict[str, float]:
        """The registers in LeRobot's units, by LeRobot's key (``<motor>.pos``)."""
        return {f"{m}.pos": lerobot_reading(m, t, self.calibration) for m, t in self.ticks(register).items()}

    def place(self, pose: dict[str, int]) -> None:
        """Set every joint there at once (Present_Position written from outside the bus)."""
        for motor, ticks in pose.items():
            self.write(motor, "Present_Position", ticks)

    def hand(self, pose: dict[str, int], speed: float) -> None:
        """A hand turns the (torque-off) joints toward ``pose`` at ``speed`` ticks/s; returns at once."""
        for motor, ticks in pose.items():
            reply = control_request(self.sim, {"cmd": "hand", "id": self.calibration[motor]["id"],
                                               "position": int(ticks), "speed": float(speed)})
            assert reply["ok"], (self.name, motor, reply)

    def wait_at(self, pose: dict[str, int], timeout: float = 10.0, tol: int = 0) -> None:
        wait_until(lambda: all(abs(self.read(m) - t) <= tol for m, t in pose.items()), timeout,
                   what=f"{self.name} at {pose}")

    def fault(self, motor: str, kind: str = "silent") -> None:
        reply = control_request(self.sim, {"cmd": "fault", "id": self.calibration[motor]["id"], "kind": kind})
        assert reply["ok"], reply

    # the daemon on its pty
    def imported_profile(self) -> Path:
        """The simulator-wired profile with its calibration imported from the LeRobot file."""
        data = yaml.safe_load(self.sim_profile.read_text())
        names = [j["name"] for j in data["joints"]]
        keys = from_lerobot(data["name"], self.calibration, names, [j["id"] for j in data["joints"]],
                            [4096] * len(names), [j["calibration"].get("direction", 1) for j in data["joints"]],
                            ["gripper"], True)
        for j in data["joints"]:
            j["calibration"] = {k: v for k, v in keys[j["name"]].items()
                                if k in ("offset", "direction", "range", "homing_offset")}
        out = self.tmp / "imported.yaml"
        out.write_text(yaml.safe_dump(data))
        return out

    def start_daemon(self) -> DaemonProcess:
        self.socket = self.tmp / "d.sock"
        self.daemon = DaemonProcess(["--profile", str(self.imported_profile())], self.socket, self.tmp / "daemon.log")
        return self.daemon

    def close(self) -> None:
        try:
            if self.daemon is not None:
                self.daemon.stop()
        finally:
            self._stack.close()


class Sampler:
    """Reads a simulated arm's registers every ``period`` s in a thread (what the follower did,
    as the servos saw it), until :meth:`stop`: ``samples`` = [(monotonic t, {motor: ticks})]."""

    def __init__(self, arm: CalibratedArm, period: float = 0.02, register: str = "Present_Position"):
        import threading
        import time

        self.samples: list[tuple[float, dict[str, int]]] = []
        self._stop = threading.Event()

        def run():
            while not self._stop.is_set():
                try:
                    self.samples.append((time.monotonic(), arm.ticks(register)))
                except (AssertionError, OSError):
                    pass
                self._stop.wait(period)

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def stop(self) -> list[tuple[float, dict[str, int]]]:
        self._stop.set()
        self._thread.join(5)
        return self.samples


def run_lerobot(launcher, command: str, args: list[str], log: Path, cwd: Path | None = None, **env: str):
    """Start one of LeRobot's console scripts (stdout and stderr to ``log``): its entry point, in a
    fork of ``launcher`` (conftest.Launcher: the LeRobot venv's interpreter with LeRobot and the
    plugin's folder on its path, LeRobot imported once). Returns a Popen-like ``poll`` / ``wait`` /
    ``kill`` handle."""
    return launcher.run(command, args, log, cwd or log.parent, env)


def finish(proc: subprocess.Popen, log: Path, timeout: float = 300) -> int:
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise AssertionError(f"{proc.args[0]} still running after {timeout} s:\n{tail(log)}") from None


def tail(log: Path, lines: int = 40) -> str:
    try:
        return "\n".join(log.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def on_the_way(values: np.ndarray, start: np.ndarray, end: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """Per frame: every joint between ``start`` and ``end`` (within ``tol``)."""
    lo, hi = np.minimum(start, end) - tol, np.maximum(start, end) + tol
    return np.all((values >= lo) & (values <= hi), axis=1)


def polyline_distance(points: np.ndarray, path: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Each point's distance (in ticks: ``/ scale``) to the nearest segment of ``path``, joint-wise max."""
    p = points[:, None, :] / scale
    a, b = path[:-1][None] / scale, path[1:][None] / scale
    ab = b - a
    denom = np.maximum((ab * ab).sum(-1), 1e-12)
    t = np.clip(((p - a) * ab).sum(-1) / denom, 0, 1)
    nearest = a + t[..., None] * ab
    return np.abs(p - nearest).max(-1).min(-1)


def read_dataset(reader, root: Path, repo_id: str = "local/crtk_test") -> dict:
    """The dataset's frames as plain lists, read by LeRobot itself (LeRobotDataset, in ``reader``: a
    conftest.LeRobotDriver, LeRobot imported once for the session): {"features": {...},
    "robot_type", "fps", "episode_index": [...], "frame_index": [...], "action": [[...]],
    "observation.state": [[...]], "action_names": [...], "state_names": [...]}."""
    return reader("dataset", repo_id=repo_id, root=str(root))["dataset"]

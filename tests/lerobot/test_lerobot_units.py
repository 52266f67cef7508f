"""LeRobot's own SO101Follower and the daemon read the same simulated bus with the same LeRobot
calibration file: the daemon's joints agree with LeRobot's numbers within one tick, at 3 poses
per joint (issue 21, "Tests (CI)").

One simulator (``crtk-sim feetech``, its pty) serves both, one after the other: LeRobot 0.4.4
first, in its own venv (tests/lerobot/venv.py), which writes its calibration into the servos as
``lerobot-calibrate`` leaves them and reads ``get_observation()`` at each pose; then the daemon
on the same pty, its profile's calibration imported from the same file (docs/calibration.md).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from crtk_bridge.backends.calibration import from_lerobot
from crtk_bridge.client import connect
from crtk_bridge.sim.control import control_request

from ..conftest import SO101, DaemonProcess, SimRobot, standalone_sim, wait_until

TICK = 2 * math.pi / 4096
DEG_TICK = 360 / 4096
#: a LeRobot SO-101 follower calibration (so_follower/<id>.json, written by lerobot-calibrate):
#: homing offsets of both signs, ranges off the middle, the full-turn wrist_roll LeRobot records
CALIBRATION = {
    "shoulder_pan": {"id": 1, "drive_mode": 0, "homing_offset": -41, "range_min": 745, "range_max": 3310},
    "shoulder_lift": {"id": 2, "drive_mode": 0, "homing_offset": 133, "range_min": 840, "range_max": 3281},
    "elbow_flex": {"id": 3, "drive_mode": 0, "homing_offset": -652, "range_min": 881, "range_max": 3064},
    "wrist_flex": {"id": 4, "drive_mode": 0, "homing_offset": 377, "range_min": 866, "range_max": 3171},
    "wrist_roll": {"id": 5, "drive_mode": 0, "homing_offset": 15, "range_min": 0, "range_max": 4095},
    "gripper": {"id": 6, "drive_mode": 0, "homing_offset": -1480, "range_min": 2017, "range_max": 3441},
}
ARM = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
#: where in its range each joint is at the three poses (+ k ticks, so no pose sits on a round number)
FRACTIONS = (0.08, 0.5, 0.94)


def poses() -> list[dict[str, int]]:
    return [{n: int(c["range_min"] + f * (c["range_max"] - c["range_min"])) + k for n, c in CALIBRATION.items()}
            for k, f in enumerate(FRACTIONS)]


def lerobot_formula(name: str, present: int) -> float:
    """LeRobot's documented conversion (motors_bus._normalize): degrees about the range middle
    for the arm, 0..100 for the gripper."""
    c = CALIBRATION[name]
    lo, hi = c["range_min"], c["range_max"]
    if name == "gripper":
        return (min(hi, max(lo, present)) - lo) / (hi - lo) * 100
    return (present - (lo + hi) / 2) * 360 / 4095


def set_pose(sim: str, pose: dict[str, int]) -> None:
    for name, ticks in pose.items():
        reply = control_request(sim, {"cmd": "write", "id": CALIBRATION[name]["id"], "register": "Present_Position",
                                      "value": ticks})
        assert reply["ok"], reply
    for name, ticks in pose.items():
        assert control_request(sim, {"cmd": "read", "id": CALIBRATION[name]["id"],
                                     "register": "Present_Position"})["value"] == ticks


def daemon_profile(profile_path, out):
    """The simulator-wired profile with its calibration imported from CALIBRATION."""
    data = yaml.safe_load(profile_path.read_text())
    names = [j["name"] for j in data["joints"]]
    keys = from_lerobot(data["name"], CALIBRATION, names, [j["id"] for j in data["joints"]], [4096] * len(names),
                        [j["calibration"].get("direction", 1) for j in data["joints"]], ["gripper"], True)
    for j in data["joints"]:
        j["calibration"] = {k: v for k, v in keys[j["name"]].items() if k in ("offset", "direction", "range",
                                                                                 "homing_offset")}
    out.write_text(yaml.safe_dump(data))
    return out


def test_the_daemon_reads_what_lerobots_own_so101_follower_reads(short_tmp, lerobot_driver):
    robot = SimRobot.load("so101", SO101)
    cal_dir = short_tmp / "calibration"
    cal_dir.mkdir()
    (cal_dir / "lrtest.json").write_text(json.dumps(CALIBRATION, indent=4))
    with standalone_sim(robot, short_tmp) as (profile, remote):
        sim = remote.path
        port = yaml.safe_load(profile.read_text())["backend"]["port"]

        # 1. LeRobot directly on the simulator's pty
        lr = lerobot_driver()
        lr("connect", type="so101_follower", config={"port": port, "id": "lrtest", "calibration_dir": str(cal_dir)})
        lr("write_calibration")  # what lerobot-calibrate leaves in the servos' EEPROM
        lr("torque_off")
        direct = []
        for pose in poses():
            set_pose(sim, pose)
            obs = lr("obs")["obs"]
            assert set(obs) == {f"{n}.pos" for n in CALIBRATION}, obs
            for name, ticks in pose.items():  # LeRobot on the simulator = LeRobot's own arithmetic
                assert obs[f"{name}.pos"] == pytest.approx(lerobot_formula(name, ticks), abs=1e-6), (name, ticks, obs)
            direct.append(obs)
        lr("disconnect")
        assert lr.close() == 0, lr.output()
        for name, c in CALIBRATION.items():  # the servos keep LeRobot's calibration
            assert control_request(sim, {"cmd": "read", "id": c["id"], "register": "Homing_Offset"})["value"] \
                == c["homing_offset"]

        # 2. the daemon on the same pty, calibrated from the same file
        prof = daemon_profile(profile, short_tmp / "imported.yaml")
        daemon = DaemonProcess(["--profile", str(prof)], short_tmp / "d.sock", short_tmp / "d.log")
        try:
            client = connect(socket=str(daemon.socket_path))
            try:
                grip_scale = 100 / ((CALIBRATION["gripper"]["range_max"] - CALIBRATION["gripper"]["range_min"]) * TICK)
                for pose, obs in zip(poses(), direct):
                    set_pose(sim, pose)
                    want_arm = np.array([obs[f"{n}.pos"] for n in ARM])
                    want_grip = obs["gripper.pos"]

                    def read():
                        arm = np.degrees(client.device("so101").measured_jp()[0])
                        grip = client.device("so101/gripper").measured_jp()[0][0] * grip_scale
                        return arm, grip

                    def same():
                        arm, grip = read()
                        return np.all(np.abs(arm - want_arm) <= DEG_TICK) and abs(grip - want_grip) <= grip_scale * TICK

                    try:
                        wait_until(same, 5, what=f"the daemon reading LeRobot's {obs} at {pose}")
                    except AssertionError:
                        raise AssertionError(f"daemon {read()} vs LeRobot {obs} at {pose}") from None
            finally:
                client.close()
        finally:
            daemon.stop()


"""LeRobot's own SO101Follower, and the plugin through the daemon, read the same simulated bus with
the same LeRobot calibration file: the plugin reports LeRobot's numbers within one tick, at 3 poses
per joint (issue 21, "Tests (CI)"), and the daemon's own joints (radians) are LeRobot's degrees.

One simulator (``crtk-sim feetech``, its pty) serves both, one after the other: LeRobot 0.4.4
first, in its own venv (tests/lerobot/venv.py), which writes its calibration into the servos as
``lerobot-calibrate`` leaves them and reads ``get_observation()`` at each pose; then the daemon
on the same pty, its profile's calibration imported from the same file (docs/calibration.md),
read through the plugin (``--robot.type=crtk``, ``units=lerobot``) and through the client.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from crtk_bridge.client import connect

from ..conftest import wait_until
from .rig import ARM, CALIBRATION, SO101, CalibratedArm, lerobot_reading, one_tick

TICK = 2 * math.pi / 4096
DEG_TICK = 360 / 4096
#: where in its range each joint is at the three poses (+ k ticks, so no pose sits on a round number)
FRACTIONS = (0.08, 0.5, 0.94)


def poses() -> list[dict[str, int]]:
    return [{n: int(c["range_min"] + f * (c["range_max"] - c["range_min"])) + k for n, c in CALIBRATION.items()}
            for k, f in enumerate(FRACTIONS)]


@pytest.fixture
def arm(short_tmp):
    a = CalibratedArm(SO101, short_tmp, "follower")
    yield a
    a.close()


def test_the_plugin_reports_what_lerobots_own_so101_follower_reports(arm, lerobot_driver, lerobot_plugin):
    # 1. LeRobot directly on the simulator's pty (the plugin's driver, used in 2., imports LeRobot meanwhile)
    lr = lerobot_driver()
    plugin = lerobot_driver(lerobot_plugin)
    lr("connect", type="so101_follower", config={"port": arm.port, "id": arm.name,
                                                 "calibration_dir": str(arm.calibration_dir)})
    lr("torque_off")
    direct = []
    for pose in poses():
        arm.place(pose)
        obs = lr("obs")["obs"]
        assert set(obs) == {f"{n}.pos" for n in CALIBRATION}, obs
        for name, ticks in pose.items():  # LeRobot on the simulator = LeRobot's own arithmetic
            assert obs[f"{name}.pos"] == pytest.approx(lerobot_reading(name, ticks), abs=1e-6), (name, ticks, obs)
        direct.append(obs)
    lr("disconnect")
    assert lr.close() == 0, lr.output()
    for name, c in CALIBRATION.items():  # LeRobot found its calibration in the servos and left it there
        assert arm.read(name, "Homing_Offset") == c["homing_offset"]

    # 2. the daemon on the same pty, calibrated from the same file, read by the plugin (connect()
    # enables the arm; disabled again from another client, so a hand can set the poses)
    arm.start_daemon()
    client = connect(socket=str(arm.socket))
    try:
        plugin("connect", type="crtk", config={"socket": str(arm.socket), "units": "lerobot"})
        assert client.device("so101").disable()
        for pose, obs in zip(poses(), direct):
            arm.place(pose)

            def plugin_reads():
                return plugin("obs")["obs"]

            def same_as_lerobot():
                got = plugin_reads()
                return all(abs(got[k] - obs[k]) <= one_tick(k[:-4]) for k in obs)

            try:
                wait_until(same_as_lerobot, 5, what=f"the plugin reading LeRobot's {obs} at {pose}")
            except AssertionError:
                raise AssertionError(f"plugin {plugin_reads()} vs LeRobot {obs} at {pose}") from None
        plugin("disconnect")
        grip_scale = 100 / ((CALIBRATION["gripper"]["range_max"] - CALIBRATION["gripper"]["range_min"]) * TICK)
        for pose, obs in zip(poses(), direct):
            arm.place(pose)
            want_arm = np.array([obs[f"{n}.pos"] for n in ARM])
            want_grip = obs["gripper.pos"]

            def read():
                arm_deg = np.degrees(client.device("so101").measured_jp()[0])
                grip = client.device("so101/gripper").measured_jp()[0][0] * grip_scale
                return arm_deg, grip

            def same():
                arm_deg, grip = read()
                return np.all(np.abs(arm_deg - want_arm) <= DEG_TICK) and abs(grip - want_grip) <= grip_scale * TICK

            try:
                wait_until(same, 5, what=f"the daemon reading LeRobot's {obs} at {pose}")
            except AssertionError:
                raise AssertionError(f"daemon {read()} vs LeRobot {obs} at {pose}") from None
    finally:
        plugin.close()
        client.close()

"""``crtk-ctl calibrate --import`` of a LeRobot calibration file (issue 12), and the calibration
arithmetic (backends/calibration.py).

The fixture is the LeRobot tests' calibration (tests/lerobot/rig.py's CALIBRATION) in LeRobot's
format (docs/calibration.md): a JSON object, indent 4, one entry per motor name with ``id``,
``drive_mode``, ``homing_offset``, ``range_min``, ``range_max``. LeRobot's readings are computed
(rig.lerobot_reading) from its documented conversion (joints in degrees:
``(present - (range_min + range_max) / 2) * 360 / (resolution - 1)``; the gripper 0..100:
``(clamp(present) - range_min) / (range_max - range_min) * 100``), with the servos holding
LeRobot's homing offsets in EEPROM as ``lerobot-calibrate`` leaves them. The daemon, restarted on
the imported profile, must report the same angles within one tick."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from crtk_bridge.backends.calibration import RangeWatch, from_lerobot, lerobot_maps, sweep_calibration
from crtk_bridge.client import connect
from crtk_bridge.errors import BackendError
from crtk_bridge.profile import load_profile
from crtk_bridge.sim.control import control_request

from .conftest import KOCH, DaemonProcess, wait_until
# the LeRobot calibration file and LeRobot's documented reading of it, as the LeRobot tests use them
from .lerobot.rig import ARM, lerobot_reading
from .lerobot.rig import CALIBRATION as LEROBOT
from .test_calibrate import BOTH, COMMENT, SOURCE, Tool, arm_ns, daemon, hand_all, profile  # noqa: F401 (fixtures)

TICK = 2 * math.pi / 4096


@BOTH
def test_import_then_the_restarted_daemon_reads_as_lerobot_does(short_tmp, profile, daemon):
    fixture = short_tmp / "so101_follower.json"
    fixture.write_text(json.dumps(LEROBOT, indent=4))
    tool = Tool(str(daemon.socket_path), "--profile", str(profile), "--import", str(fixture))
    try:
        assert tool.finish() == 0, tool.output()
    finally:
        tool.kill()
    assert "Imported" in tool.output() and f"Wrote {profile}" in tool.output(), tool.output()
    assert COMMENT[SOURCE[profile]] in profile.read_text()  # comments kept
    cal = {j.name: j.backend["calibration"] for j in load_profile(profile).joints}
    assert cal["elbow_flex"] == {"offset": 1972, "direction": 1, "range": [881, 3064], "homing_offset": -652}
    daemon.stop()

    again = DaemonProcess(["--profile", str(profile), "--sim"], short_tmp / "b.sock", short_tmp / "b.log")
    try:
        sim = again.sim_control_path()
        for name, c in LEROBOT.items():  # the servos hold LeRobot's homing offsets, as it left them
            assert control_request(sim, {"cmd": "write", "id": c["id"], "register": "Homing_Offset",
                                         "value": c["homing_offset"]})["ok"]
        robot = connect(socket=str(again.socket_path))
        try:
            for k, frac in enumerate((0.1, 0.5, 0.93)):
                present = {n: int(c["range_min"] + frac * (c["range_max"] - c["range_min"])) + k
                           for n, c in LEROBOT.items()}
                hand_all(sim, present)
                want_arm = np.radians([lerobot_reading(n, present[n]) for n in ARM])
                c = LEROBOT["gripper"]
                want_grip = lerobot_reading("gripper", present["gripper"]) / 100 * (c["range_max"] - c["range_min"]) * TICK

                def same():
                    arm = robot.device(arm_ns(profile)[0]).measured_jp()[0]
                    grip = robot.device(arm_ns(profile)[1]).measured_jp()[0][0]
                    return np.all(np.abs(arm - want_arm) <= TICK) and abs(grip - want_grip) <= TICK

                wait_until(same, 3, what=f"LeRobot's readings at {present}")
                # list's LeRobot maps turn the readings into LeRobot's own numbers (docs/protocol.md)
                maps = {ns["name"]: ns["lerobot"] for ns in robot.list()["namespaces"]}
                arm_maps, grip_maps = maps[arm_ns(profile)[0]], maps[arm_ns(profile)[1]]
                arm = robot.device(arm_ns(profile)[0]).measured_jp()[0]
                grip = robot.device(arm_ns(profile)[1]).measured_jp()[0][0]
                for name, m, rad in zip(ARM, arm_maps, arm):
                    scale, bias = m["degrees"]
                    assert abs(scale * rad + bias - lerobot_reading(name, present[name])) <= 360 / 4095, name
                scale, bias = grip_maps[0]["range_0_100"]
                c = LEROBOT["gripper"]
                assert abs(scale * grip + bias - lerobot_reading("gripper", present["gripper"])) <= \
                    100 / (c["range_max"] - c["range_min"])
        finally:
            robot.close()
    finally:
        again.stop()


def test_a_profile_of_another_robot_is_refused_naming_the_difference_and_left_alone(short_tmp, profile, daemon):
    """Issue 18 item 10: against the so101 daemon, ``--profile koch_copy.yaml`` wrote into the Koch's
    profile and exited 0. Refused (exit 1, nothing written) when the robot name, the backend or a
    joint's bus id differs from the daemon's."""
    fixture = short_tmp / "so101_follower.json"
    fixture.write_text(json.dumps(LEROBOT, indent=4))
    so101 = profile.read_text()
    cases = {
        "koch_copy.yaml": (KOCH.read_text(), "is robot 'koch', the daemon serves 'so101'"),
        "dxl_so101.yaml": (KOCH.read_text().replace("name: koch\n", "name: so101\n"),
                           "has backend 'dynamixel', the daemon's robot 'feetech'"),
        "ids.yaml": (so101.replace("  - name: gripper\n    id: 6\n", "  - name: gripper\n    id: 7\n"),
                     "joint 'gripper' has id 7, on the daemon's robot id 6"),
        "joints.yaml": (so101.replace("wrist_roll", "wrist_twist"), "has no joint 'wrist_roll'"),
    }
    for name, (text, why) in cases.items():
        other = short_tmp / name
        other.write_text(text)
        tool = Tool(str(daemon.socket_path), "--profile", str(other), "--import", str(fixture))
        try:
            code = tool.finish()
        finally:
            tool.kill()
        assert code == 1 and why in tool.output() and f"--profile {other}" in tool.output(), (name, tool.output())
        assert len(tool.output().splitlines()) == 1, tool.output()
        assert other.read_text() == text, name  # left alone
    tool = Tool(str(daemon.socket_path), "--profile", str(profile), "--import", str(fixture))
    try:
        assert tool.finish() == 0, tool.output()  # the daemon's own profile (a copy) is accepted
    finally:
        tool.kill()


# ---------------------------------------------------------------- the arithmetic, directly

NAMES, RES, DIRS = list(LEROBOT), [4096] * 6, [1] * 6


def test_lerobot_conversion_maps_homing_range_and_gripper_ends():
    cal = from_lerobot("so101", LEROBOT, NAMES, [1, 2, 3, 4, 5, 6], RES, DIRS, ["gripper"], True)
    assert cal["elbow_flex"] == {"offset": 1972, "direction": 1, "range": [881, 3064], "homing_offset": -652}
    assert cal["gripper"] == {"offset": 2017, "direction": 1, "range": [2017, 3441], "homing_offset": -1480}
    flipped = {**LEROBOT, "gripper": {**LEROBOT["gripper"], "drive_mode": 1}}
    grip = from_lerobot("so101", flipped, NAMES, [1, 2, 3, 4, 5, 6], RES, DIRS, ["gripper"], True)["gripper"]
    assert grip["offset"] == 3441 and grip["direction"] == -1  # LeRobot's 0 end is range_max then
    # a Dynamixel applies drive_mode itself (its Drive_Mode register): nothing to flip in software
    grip = from_lerobot("koch", flipped, NAMES, [1, 2, 3, 4, 5, 6], RES, DIRS, ["gripper"], False)["gripper"]
    assert grip["offset"] == 2017 and grip["direction"] == 1


def test_lerobot_maps_give_lerobot_numbers_of_the_radians_by_hand():
    """Per joint, ``scale * rad + bias`` is LeRobot's number for the same ticks, computed here by
    hand from LeRobot's formulas (module docstring), in each norm mode, for an imported calibration
    (half-tick middles, a flipped gripper), a joint the profile flips, and past the range (degrees
    are not clamped; RANGE modes are, and the maps say which interval)."""
    def rad_of(t, cal):
        return cal["direction"] * (t - cal["offset"]) * 2 * math.pi / 4096

    flipped = {**LEROBOT, "gripper": {**LEROBOT["gripper"], "drive_mode": 1}}
    for data, dirs in ((LEROBOT, DIRS), (flipped, DIRS), (LEROBOT, [-1] * 6)):
        cal = from_lerobot("so101", data, NAMES, [1, 2, 3, 4, 5, 6], RES, dirs, ["gripper"], True)
        for name in NAMES:
            c, k = data[name], cal[name]
            lo, hi = c["range_min"], c["range_max"]
            maps = lerobot_maps(k["offset"], k["direction"], k["range"], 4096)
            for t in (lo, lo + 1, (lo + hi) // 2, hi - 7, hi):
                rad = rad_of(t, k)
                deg = (t - (lo + hi) / 2) * 360 / 4095
                m100 = (t - lo) / (hi - lo) * 200 - 100
                p100 = (t - lo) / (hi - lo) * 100
                if name == "gripper" and c["drive_mode"]:
                    p100 = 100 - p100  # LeRobot's Feetech bus applies drive_mode in software
                for mode, want in (("degrees", deg), ("range_m100_100", m100), ("range_0_100", p100)):
                    if mode == "range_0_100" and name != "gripper":
                        continue  # LeRobot reads only the gripper in 0..100
                    scale, bias = maps[mode]
                    assert scale * rad + bias == pytest.approx(want, abs=1e-9), (name, mode, t)
            scale, bias = maps["degrees"]  # past the range: degrees go on (LeRobot does not clamp them)
            assert scale * rad_of(hi + 50, k) + bias == pytest.approx((hi + 50 - (lo + hi) / 2) * 360 / 4095)
    assert lerobot_maps(2048, 1, None, 4096) is None  # no range: LeRobot has no number for it


def test_lerobot_file_of_another_arm_is_refused_naming_motor_and_field():
    bad = {**LEROBOT, "elbow_flex": {**LEROBOT["elbow_flex"], "id": 9}, "extra_motor": LEROBOT["gripper"]}
    del bad["wrist_roll"]
    with pytest.raises(BackendError) as err:
        from_lerobot("so101", bad, NAMES, [1, 2, 3, 4, 5, 6], RES, DIRS, ["gripper"], True, "arm.json")
    text = str(err.value)
    assert text.startswith("so101: arm.json: ")
    assert "elbow_flex.id: 9, but the profile's joint 'elbow_flex' is servo id 3" in text
    assert "wrist_roll: missing" in text and "motor extra_motor: no joint of that name" in text


def watch_over(ticks: list[list[int]]) -> RangeWatch:
    w = RangeWatch(np.array(ticks[0], dtype=float), np.array([4096.0] * len(ticks[0])))
    for t in ticks[1:]:
        w.track(np.array(t, dtype=float))
    return w


def test_sweep_unwraps_refuses_a_travel_across_the_encoder_wrap_and_a_joint_that_did_not_move():
    # joint 0 sweeps 2048 -> 100 -> 3900 -> 2048 in steps (fine); joint 1 crosses 4095 -> 0
    path0 = list(range(2048, 99, -50)) + list(range(100, 3901, 50)) + [2048]
    path1 = [(3900 + 50 * min(k, 8)) % 4096 for k in range(len(path0))]  # 3900 .. 4300 = 204
    still = [2000] * len(path0)
    w = watch_over([list(t) for t in zip(path0, path1, still)])
    with pytest.raises(BackendError) as err:
        sweep_calibration("arm", ["a", "b", "c"], w, [1, 1, 1], [], [0, 0, 0])
    text = str(err.value)
    assert "joint 'b' travels across its servo's encoder wrap point" in text
    assert "joint 'c' did not move" in text and "'a'" not in text
    w = watch_over([list(t) for t in zip(path0, path0, path0)])
    cal = sweep_calibration("arm", ["a", "b", "c"], w, [1, -1, 1], ["c"], [5, None, 0])
    assert cal["a"] == {"offset": 2000, "direction": 1, "range": [100, 3900], "homing_offset": 5}
    assert cal["b"] == {"offset": 2000, "direction": -1, "range": [100, 3900]}  # direction kept
    # a gripper left nearer its high end when it was closed: zero there, opening lowers the ticks
    closing = [[t] for t in [*range(2048, 99, -100), *range(100, 3901, 100), 3880]]
    assert sweep_calibration("arm", ["c"], watch_over(closing), [1], ["c"], [None]) == \
        {"c": {"offset": 3900, "direction": -1, "range": [100, 3900]}}


# ---------------------------------------------------------------- where the calibration is written

def test_calibration_file_is_written_and_included_and_the_profile_left_alone(short_tmp, profile):
    from crtk_bridge.errors import ProfileError
    from crtk_bridge.profile_write import write_calibration

    text = profile.read_text().replace("name: so101\n", "name: so101\ncalibration_file: arm.calibration.yaml\n", 1)
    profile.write_text(text)
    assert load_profile(profile).joints[0].backend["calibration"]["offset"] == 2048  # no file yet: the profile's
    written = write_calibration(profile, {"shoulder_pan": {"offset": 2001, "direction": -1, "range": [700, 3300]}})
    assert written == short_tmp / "arm.calibration.yaml" and profile.read_text() == text
    assert "crtk-ctl calibrate" in written.read_text()  # a header says what the file is
    joints = {j.name: j.backend["calibration"] for j in load_profile(profile).joints}
    assert joints["shoulder_pan"] == {"offset": 2001, "direction": -1, "range": [700, 3300]}
    assert joints["elbow_flex"]["offset"] == 2048  # not in the file: the profile's own
    write_calibration(profile, {"gripper": {"offset": 1900, "direction": 1, "range": [1900, 3300]}})
    joints = {j.name: j.backend["calibration"] for j in load_profile(profile).joints}
    assert joints["shoulder_pan"]["offset"] == 2001 and joints["gripper"]["offset"] == 1900  # both kept
    written.write_text(written.read_text() + "no_such_joint: {offset: 1}\n")
    with pytest.raises(ProfileError, match="arm.calibration.yaml: no_such_joint: no joint of that name"):
        load_profile(profile)
    with pytest.raises(ProfileError, match="no joint 'nope'"):
        write_calibration(profile, {"nope": {"offset": 1}})

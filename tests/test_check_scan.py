"""``crtk-bridge check --profile P --scan``: the real command, in its own process, against the
Feetech and Dynamixel bus simulators on a pty: every servo's model, firmware and torque state,
missing and extra ids, a servo of another model, exit status 1 on any mismatch."""

from __future__ import annotations

import json
import subprocess
import sys

import yaml

from crtk_bridge.sim.dynamixel import DynamixelSimulator
from crtk_bridge.sim.feetech import FeetechSimulator

from .conftest import KOCH, ROOT, profile_data, so101_data


def scan(tmp_path, data: dict) -> subprocess.CompletedProcess:
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    return subprocess.run([sys.executable, "-m", "crtk_bridge.cli", "check", "--profile", str(path), "--scan"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)


def servo_lines(out: str) -> dict[int, str]:
    lines = [line.strip() for line in out.splitlines() if line.startswith("  id ")]
    return {int(line.split()[1]): line for line in lines}


def test_feetech_bus_that_matches_passes_with_model_firmware_and_torque(tmp_path):
    with FeetechSimulator(servo_ids=range(1, 7)) as sim:
        sim.servo(2).write("Torque_Enable", 1)
        data = so101_data()
        data["backend"]["port"] = sim.port
        proc = scan(tmp_path, data)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert f"backend: {sim.port}: 6 servos answered" in proc.stdout
    lines = servo_lines(proc.stdout)
    assert sorted(lines) == [1, 2, 3, 4, 5, 6]
    assert lines[1] == "id   1  shoulder_pan     sts3215 (model number 777)  firmware 3.10  torque off"
    assert lines[2].endswith("torque on") and "shoulder_lift" in lines[2]


def test_feetech_silent_and_extra_ids_fail_naming_joint_and_id(tmp_path):
    with FeetechSimulator(servo_ids=[1, 2, 3, 4, 5, 6, 9]) as sim:
        sim.set_fault(3, "silent")
        data = so101_data()
        data["backend"]["port"] = sim.port
        proc = scan(tmp_path, data)
    assert proc.returncode == 1
    lines = servo_lines(proc.stdout)
    assert lines[3] == "id   3  elbow_flex       MISSING: no reply"
    assert lines[9].startswith("id   9  (no joint)       sts3215") and lines[9].endswith("EXTRA: not in the profile")
    assert proc.stderr.strip() == (
        f"crtk-bridge: so101: backend ({sim.port}) does not match the profile: joint 'elbow_flex' (id 3): "
        "no reply at 1000000 baud; id 9 (sts3215) answered but no joint has this id")


def koch_servos(data: dict) -> dict[int, str]:
    return {j["id"]: j["model"] for j in data["joints"]}


def test_dynamixel_bus_that_matches_passes(tmp_path):
    data = profile_data(KOCH)
    with DynamixelSimulator(koch_servos(data)) as sim:
        data["backend"]["port"] = sim.port
        proc = scan(tmp_path, data)
        rx = sim.rx_bytes
    assert proc.returncode == 0, proc.stderr
    lines = servo_lines(proc.stdout)
    assert sorted(lines) == sorted(koch_servos(data))
    first = data["joints"][0]
    assert lines[first["id"]].startswith(f"id   {first['id']}  {first['name']:<16} {first['model']} (model number ")
    assert "firmware 52  torque off" in lines[first["id"]]
    # one broadcast ping found them all (253 single pings alone would be 2530 bytes on the wire)
    assert rx < 500, rx


def test_dynamixel_wrong_model_missing_and_extra_ids_fail(tmp_path):
    data = profile_data(KOCH)
    servos = koch_servos(data)
    first, last = data["joints"][0], data["joints"][-1]
    assert first["model"] != "xm430-w350"
    servos[first["id"]] = "xm430-w350"
    servos[40] = "xl330-m288"
    with DynamixelSimulator(servos) as sim:
        sim.set_fault(last["id"], "silent")
        data["backend"]["port"] = sim.port
        proc = scan(tmp_path, data)
    assert proc.returncode == 1
    lines = servo_lines(proc.stdout)
    assert lines[first["id"]].endswith(f"WRONG MODEL: the profile says {first['model']}")
    assert lines[last["id"]].endswith("MISSING: no reply") and lines[40].endswith("EXTRA: not in the profile")
    err = proc.stderr
    assert f"joint {first['name']!r} (id {first['id']}): is model number 1020 (xm430-w350), the profile says " \
           f"{first['model']}" in err
    assert f"joint {last['name']!r} (id {last['id']}): no reply at 1000000 baud" in err
    assert "id 40 (xl330-m288) answered but no joint has this id" in err


def test_scan_of_every_bus_of_a_two_bus_profile(tmp_path):
    data = profile_data(ROOT / "profiles" / "bimanual_so101.yaml")
    with FeetechSimulator(servo_ids=range(1, 7)) as left, FeetechSimulator(servo_ids=range(1, 6)) as right:
        data["backends"]["left"]["port"] = left.port
        data["backends"]["right"]["port"] = right.port
        proc = scan(tmp_path, data)
    assert proc.returncode == 1
    assert f"backends.left: {left.port}: 6 servos answered" in proc.stdout
    assert f"backends.right: {right.port}: 5 servos answered" in proc.stdout
    assert "backends.left" not in proc.stderr and f"backends.right ({right.port}) does not match" in proc.stderr
    assert "(id 6): no reply" in proc.stderr


def test_scan_of_a_port_that_does_not_open_fails(tmp_path):
    data = so101_data()
    data["backend"]["port"] = str(tmp_path / "ttyACM9")
    proc = scan(tmp_path, data)
    assert proc.returncode == 1
    assert f"so101: cannot open port {tmp_path / 'ttyACM9'}: no such device" in proc.stderr
    assert "  id " not in proc.stdout


def scan_all(tmp_path, data: dict) -> subprocess.CompletedProcess:
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    return subprocess.run([sys.executable, "-m", "crtk_bridge.cli", "check", "--profile", str(path), "--scan",
                           "--all-bauds"], cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_all_bauds_finds_a_servo_at_another_rate_with_the_setup_hint(tmp_path):
    with FeetechSimulator(servo_ids=range(1, 7)) as sim:
        sim.servo(6).write("Baud_Rate", 4)  # 115200: deaf at the profile's 1 Mbps
        data = so101_data()
        data["backend"]["port"] = sim.port
        proc = scan_all(tmp_path, data)
    assert proc.returncode == 1
    assert "id   6  gripper          MISSING: no reply" in proc.stdout
    assert "id   6  at 115200 baud  sts3215  OTHER RATE: the profile's is 1000000" in proc.stdout
    assert (f"id 6 (sts3215) answers at 115200 baud, not the profile's 1000000: run crtk-bridge setup-servos "
            f"--profile {tmp_path / 'robot.yaml'} with only that servo connected") in proc.stderr
    assert proc.stdout.count("OTHER RATE") == 1  # the others are found at the profile's rate only


def test_eeprom_settings_that_differ_are_reported_per_joint_naming_the_register(tmp_path):
    with FeetechSimulator(servo_ids=range(1, 7)) as sim:
        sim.servo(2).write("Homing_Offset", -50)
        sim.servo(4).write("Return_Delay_Time", 250)
        sim.servo(5).write("Min_Position_Limit", 100)  # wrist_roll's range is the whole turn
        sim.servo(1).write("Operating_Mode", 1)
        data = so101_data()
        data["backend"]["port"] = sim.port
        proc = scan(tmp_path, data)
    assert proc.returncode == 1
    out, err = proc.stdout, proc.stderr
    assert "EEPROM Homing_Offset = -50, expected 0 (joints[1] (shoulder_lift).calibration.homing_offset)" \
           "  (enable refused)" in out
    assert "EEPROM Return_Delay_Time = 250, expected 0 (backend.return_delay)\n" in out
    assert "EEPROM Min_Position_Limit = 100, expected <= 0 (joints[4] (wrist_roll).calibration.range)" in out
    assert "EEPROM Operating_Mode = 1, expected 0 (position)" in out
    assert "joint 'shoulder_lift' (id 2): Homing_Offset is -50" in err
    assert "joint 'wrist_flex' (id 4): Return_Delay_Time is 250, expected 0 (backend.return_delay): each " \
           "reply waits 500 us" in err
    assert "elbow_flex" not in err and "gripper" not in err



def test_a_backend_that_cannot_scan_is_named_with_those_that_can(tmp_path):
    # scanning is an optional capability (backends/optional.py), not a method looked up by name
    for profile, type_, cls in (("canopen_2axis", "canopen402", "Canopen402Backend"), ("ur5e", "ur", "UrBackend")):
        proc = subprocess.run([sys.executable, "-m", "crtk_bridge.cli", "check", "--profile",
                               str(ROOT / "profiles" / f"{profile}.yaml"), "--scan", "--json"],
                              cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 1
        bus, = json.loads(proc.stdout)["scan"]["buses"]
        assert bus["vendor"] == type_ and not bus["ok"]
        assert bus["error"] == (f"{profile}: backend: backend {type_!r} ({cls}) cannot scan its bus "
                                "(crtk-bridge check --scan); backends that can: dynamixel, feetech")


def test_init_profile_names_where_each_bus_of_a_mixed_profile_is_found():
    from crtk_bridge.cli import _where_the_robot_is

    assert _where_the_robot_is("backend: {type: feetech}") == "backend.port (crtk-bridge find-port)"
    assert _where_the_robot_is("backend: {type: ur}") == "backend.host"
    assert _where_the_robot_is("backend: {type: canopen402}") == "backend.interface and backend.channel"
    # a UR arm with a servo gripper: the arm's host, the gripper bus's port (it said port for both)
    mixed = "backends: {arm: {type: ur}, gripper: {type: dynamixel}}"
    assert _where_the_robot_is(mixed) == "backends.arm.host and backends.gripper.port"
    assert _where_the_robot_is("backends: {left: {type: feetech}, right: {type: feetech}}") == \
        "backends.left.port and backends.right.port"

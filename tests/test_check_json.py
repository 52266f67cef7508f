"""``crtk-bridge check --json``: the check's findings as one JSON document on stdout (keys in
docs/check.md), the same exit status as the text report. The real command in its own process,
against the simulated SO-101 bus (Feetech simulator on a pty)."""

from __future__ import annotations

import json
import subprocess
import sys

import yaml

from crtk_bridge.sim.feetech import FeetechSimulator

from .conftest import ROOT, so101_data

JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
TOP_KEYS = {"check_format", "profile", "ok", "valid", "error", "robot", "backend", "joints", "namespaces",
            "kinematics", "scan", "problems"}
BUS_KEYS = {"bus", "where", "vendor", "port", "baudrate", "ok", "error", "servos_answered", "joints", "extra",
            "other_rates", "problems"}
JOINT_KEYS = {"joint", "id", "expected_model", "status", "model", "model_number", "firmware", "torque",
              "eeprom", "eeprom_error"}


def check(tmp_path, data: dict, *options: str) -> tuple[int, dict, str]:
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    proc = subprocess.run([sys.executable, "-m", "crtk_bridge.cli", "check", "--profile", str(path), *options,
                           "--json"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    return proc.returncode, json.loads(proc.stdout), proc.stderr  # stdout is the document alone


def test_json_of_a_matching_so101_bus(tmp_path):
    with FeetechSimulator(servo_ids=range(1, 7)) as sim:
        sim.servo(2).write("Torque_Enable", 1)
        data = so101_data()
        data["backend"]["port"] = sim.port
        status, doc, err = check(tmp_path, data, "--scan")
    assert status == 0 and err == ""
    assert set(doc) == TOP_KEYS and doc["check_format"] == 1
    assert doc["ok"] and doc["valid"] and doc["error"] is None and doc["problems"] == []
    assert (doc["robot"], doc["backend"], doc["joints"]) == ("so101", "feetech", JOINTS)
    assert doc["namespaces"] == ["so101", "so101/gripper"] and doc["kinematics"]
    assert doc["scan"]["all_bauds"] is False
    [bus] = doc["scan"]["buses"]
    assert set(bus) == BUS_KEYS
    assert (bus["bus"], bus["where"], bus["vendor"], bus["port"], bus["baudrate"]) == \
           (None, "backend", "feetech", sim.port, 1_000_000)
    assert bus["ok"] and bus["error"] is None and bus["servos_answered"] == 6
    assert bus["extra"] == [] and bus["other_rates"] == [] and bus["problems"] == []
    assert [j["joint"] for j in bus["joints"]] == JOINTS and [j["id"] for j in bus["joints"]] == [1, 2, 3, 4, 5, 6]
    pan = bus["joints"][0]
    assert set(pan) == JOINT_KEYS
    assert pan == {"joint": "shoulder_pan", "id": 1, "expected_model": "sts3215", "status": "ok", "model": "sts3215",
                   "model_number": 777, "firmware": "3.10", "torque": False, "eeprom": [], "eeprom_error": None}
    assert bus["joints"][1]["torque"] is True


def test_json_of_a_mismatch_exits_1_naming_joint_id_and_register(tmp_path):
    with FeetechSimulator(servo_ids=[1, 2, 3, 4, 5, 6, 9]) as sim:
        sim.set_fault(3, "silent")
        sim.servo(2).write("Homing_Offset", -50)
        data = so101_data()
        data["backend"]["port"] = sim.port
        status, doc, err = check(tmp_path, data, "--scan")
    assert status == 1 and err == ""  # everything is in the document
    assert doc["valid"] and not doc["ok"]
    [bus] = doc["scan"]["buses"]
    assert not bus["ok"] and bus["servos_answered"] == 6
    elbow, lift = bus["joints"][2], bus["joints"][1]
    assert (elbow["joint"], elbow["id"], elbow["status"], elbow["model"]) == ("elbow_flex", 3, "missing", None)
    assert lift["status"] == "ok" and lift["eeprom"] == [{
        "register": "Homing_Offset", "value": -50, "expected": "0",
        "key": "joints[1] (shoulder_lift).calibration.homing_offset", "enable_refused": True,
        "why": lift["eeprom"][0]["why"], "remedy": lift["eeprom"][0]["remedy"]}]
    assert [(x["id"], x["model"]) for x in bus["extra"]] == [(9, "sts3215")]
    assert doc["problems"] == bus["problems"] and len(bus["problems"]) == 3
    assert "joint 'elbow_flex' (id 3): no reply at 1000000 baud" in bus["problems"]
    assert "id 9 (sts3215) answered but no joint has this id" in bus["problems"]


def test_json_of_an_invalid_profile_and_of_a_check_without_scan(tmp_path):
    data = so101_data()
    data["backend"]["port"] = "/dev/null"
    status, doc, err = check(tmp_path, data)  # no --scan: the bus is not opened
    assert status == 0 and doc["ok"] and doc["valid"] and doc["scan"] is None
    data["backend"]["baudrate"] = "fast"
    status, doc, err = check(tmp_path, data)
    assert status == 1 and err == ""
    assert set(doc) == TOP_KEYS and not doc["ok"] and not doc["valid"] and doc["robot"] is None
    assert "backend.baudrate" in doc["error"] and doc["problems"] == [doc["error"]]

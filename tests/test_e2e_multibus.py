"""Several buses in one robot (issue 8 item 5): profiles/bimanual_so101.yaml, two SO-101 arms on two
Feetech buses, run with --sim (one simulator per bus). One operating state covers both arms: one
enable powers both buses; each arm moves on its own bus with move_jp; a fault on one bus faults the
robot, names the bus and the joint, and switches torque off on both. Plus the profile rules of
``backends`` (each namespace on one named bus) and key paths of a bus's backend errors."""

from __future__ import annotations

import copy
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml

from crtk_bridge.backends import create_backend
from crtk_bridge.backends.composite import CompositeActuator
from crtk_bridge.client import connect
from crtk_bridge.errors import ProfileError
from crtk_bridge.profile import load_profile, parse_profile
from crtk_bridge.sim.control import control_request

from .conftest import ROOT, DaemonProcess, wait_until

BIMANUAL = ROOT / "profiles" / "bimanual_so101.yaml"
LEFT_GOAL = np.array([0.4, 0.3, -0.3, 0.2, 0.0])
RIGHT_GOAL = np.array([-0.5, -0.2, 0.4, 0.0, 0.3])


def ticks(rad: np.ndarray) -> np.ndarray:
    return 2048 + rad * 4096 / (2 * math.pi)  # STS3215, offset 2048, direction +1 (the profile's)


class Buses:
    """The simulators of a several-bus daemon, by bus name (from the lines --sim prints)."""

    def __init__(self, daemon: DaemonProcess, names: set[str]):
        self.sims = {}
        for line in daemon.output().splitlines():
            if "simulator control socket" in line:
                bus = line.split("bus '", 1)[1].split("'", 1)[0]
                self.sims[bus] = line.rsplit(" ", 1)[-1].rstrip(")")
        assert set(self.sims) == names, daemon.output()

    def servos(self, bus: str) -> dict:
        reply = control_request(self.sims[bus], {"cmd": "dump"})
        assert reply.get("ok"), reply
        return reply["servos"]

    def torque(self, bus: str) -> list[int]:
        return [s["torque_enable"] for _, s in sorted(self.servos(bus).items())]

    def arm_ticks(self, bus: str) -> np.ndarray:
        s = self.servos(bus)
        return np.array([s[str(i)]["present_position"] for i in range(1, 6)], dtype=float)


@pytest.fixture(scope="module")
def bimanual_daemon():
    """One bimanual daemon for the module's two tests, in file order: the first starts from it
    fresh (DISABLED) and leaves it DISABLED; the second enables it and faults it."""
    tmp = Path(tempfile.mkdtemp(prefix="crtk-"))
    d = DaemonProcess(["--profile", str(BIMANUAL), "--sim"], tmp / "bimanual.sock", tmp / "daemon.log")
    try:
        yield d
    finally:
        d.stop()
        shutil.rmtree(tmp, ignore_errors=True)


@pytest.fixture
def bimanual(bimanual_daemon):
    robot = connect(socket=str(bimanual_daemon.socket_path))
    try:
        yield Buses(bimanual_daemon, {"left", "right"}), robot
    finally:
        robot.close()


def test_both_arms_enable_together_move_independently_share_one_state(bimanual):
    sims, robot = bimanual
    listed = robot.list()["namespaces"]
    assert [(ns["name"], ns["bus"]) for ns in listed] == [
        ("left", "left"), ("left/gripper", "left"), ("right", "right"), ("right/gripper", "right")]
    left, right = robot.device("left"), robot.device("right")
    assert sims.torque("left") == [0] * 6 and sims.torque("right") == [0] * 6  # starts DISABLED
    assert left.enable(5.0)  # ONE enable: the whole robot, both buses
    wait_until(lambda: sims.torque("left") == [1] * 6 and sims.torque("right") == [1] * 6, 3,
               what="torque on every servo of both buses")
    assert right.operating_state() == "ENABLED" and robot.device("right/gripper").operating_state() == "ENABLED"
    # common stamps: both arms' samples come from the same cycle
    assert left.measured_js()[3] > 0
    wait_until(lambda: left.measured_js()[3] == right.measured_js()[3], 2, what="one stamp for both buses")
    # independent motion, at the same time, each on its own bus
    hl, hr = left.move_jp(LEFT_GOAL), right.move_jp(RIGHT_GOAL)
    assert hl.wait(timeout=15.0) and hr.wait(timeout=15.0)
    wait_until(lambda: np.allclose(left.measured_js()[0], LEFT_GOAL, atol=0.02)
               and np.allclose(right.measured_js()[0], RIGHT_GOAL, atol=0.02), 5, what="both arms at their goals")
    # ... and the right servos really moved on the right bus, the left on the left
    assert np.allclose(sims.arm_ticks("left"), ticks(LEFT_GOAL), atol=15)
    assert np.allclose(sims.arm_ticks("right"), ticks(RIGHT_GOAL), atol=15)
    # one operating state: disabling from the right arm disables the left too, both buses off
    assert right.disable(5.0)
    assert left.operating_state() == "DISABLED"
    wait_until(lambda: sims.torque("left") == [0] * 6 and sims.torque("right") == [0] * 6, 3,
               what="torque off on both buses")


def test_a_fault_on_one_bus_faults_the_robot_naming_bus_and_joint(bimanual):
    sims, robot = bimanual
    left, right = robot.device("left"), robot.device("right")
    assert left.enable(5.0)
    mark = robot.connection.event_count
    reply = control_request(sims.sims["right"], {"cmd": "fault", "id": 3, "kind": "silent"})
    assert reply.get("ok"), reply
    ev = robot.wait_for_event("bus_timeout", 5.0, kind="error", since=mark)
    assert ev is not None, list(robot.connection.events_since(mark))
    # the bus that went silent leads (another bus missing one reply in the same cycle is said after it)
    assert ev.data["message"].startswith("bimanual_so101: bus 'right': "), ev.data
    assert ev.data["joint"] in ("right_shoulder_pan", "right_shoulder_lift", "right_elbow_flex"), ev.data
    wait_until(left.is_fault, 3, what="the LEFT arm in FAULT too (one operating state)")
    assert right.is_fault()
    wait_until(lambda: sims.torque("left") == [0] * 6, 3, what="torque off on the healthy bus")


# ---------------------------------------------------------------- profile rules


def bimanual_data() -> dict:
    return yaml.safe_load(BIMANUAL.read_text())


def test_profile_builds_one_backend_per_bus():
    p = load_profile(BIMANUAL)
    assert p.bus_names == ["left", "right"] and p.backend_type == "feetech"
    right = p.bus_profile("right")
    assert right.backend["port"] == p.backends["right"]["port"]
    assert right.joint_names == [f"right_{n}" for n in ("shoulder_pan", "shoulder_lift", "elbow_flex",
                                                         "wrist_flex", "wrist_roll", "gripper")]
    b = create_backend(p)
    assert isinstance(b, CompositeActuator) and b.bus_names == ["left", "right"] and b.n == 12
    assert [part.joint_keys[0].id for part in b.parts] == [1, 1]  # servo ids are per bus


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["namespaces"][0].pop("backend"),
     "namespaces[0] (left).backend: required with several buses, one of left, right"),
    (lambda d: d["namespaces"][2].update(backend="middle"),
     "namespaces[2] (right).backend: unknown bus 'middle' (backends: left, right)"),
    (lambda d: d.update(backend={"type": "feetech", "port": "/dev/x"}),
     "backend: required: `backend` for a robot on one bus, or `backends`"),
    (lambda d: d["backends"].update(spare={"type": "feetech", "port": "/dev/y"}),
     "backends.spare: no namespace lives on this bus"),
    (lambda d: d["backends"]["left"].pop("type"), "backends.left.type: required"),
])
def test_bus_rules_name_the_key(edit, message):
    data = bimanual_data()
    edit(data)
    with pytest.raises(ProfileError) as info:
        parse_profile(data, "bimanual.yaml")
    assert message in str(info.value)


def test_a_bus_backend_error_names_the_robot_profile_key():
    data = bimanual_data()
    del data["backends"]["right"]["port"]
    data["joints"][8]["calibration"]["direction"] = 3  # right_elbow_flex: the robot's joints[8]
    with pytest.raises(ProfileError) as info:
        create_backend(parse_profile(copy.deepcopy(data), "bimanual.yaml"), source="bimanual.yaml")
    assert "backends.right.port: required" in str(info.value)
    del data["backends"]["right"]
    data["backends"]["right"] = {"type": "feetech", "port": "/dev/ttyACM1"}
    with pytest.raises(ProfileError) as info:
        create_backend(parse_profile(data, "bimanual.yaml"), source="bimanual.yaml")
    assert "joints[8] (right_elbow_flex).calibration.direction: must be 1 or -1" in str(info.value)


def test_a_one_bus_profile_cannot_name_a_bus():
    data = yaml.safe_load((ROOT / "profiles" / "so101.yaml").read_text())
    data["namespaces"][0]["backend"] = "left"
    with pytest.raises(ProfileError, match=r"namespaces\[0\] \(so101\)\.backend: only with `backends`"):
        parse_profile(data, "so101.yaml")


def test_buses_of_different_backends_with_capabilities_per_namespace(short_tmp):
    """An SO-101 arm on a Feetech bus with an XL330 gripper on a Dynamixel bus: each bus gets its
    own simulator, and each namespace offers what its own joints can do (effort on the gripper)."""
    so101 = yaml.safe_load((ROOT / "profiles" / "so101.yaml").read_text())
    gripper = dict(so101["joints"][5], model="xl330-m288", effort_per_amp=0.35)
    data = {
        "name": "mixed", "backends": {"arm": {"type": "feetech", "port": "/dev/null"},
                                      "hand": {"type": "dynamixel", "port": "/dev/null",
                                               "joint_position_modes": {"gripper": "current_based_position"}}},
        "loop": so101["loop"], "joints": so101["joints"][:5] + [gripper],
        "namespaces": [{"name": "mixed", "backend": "arm", "joints": so101["namespaces"][0]["joints"]},
                       {"name": "mixed/gripper", "backend": "hand", "joints": ["gripper"]}],
    }
    path = short_tmp / "mixed.yaml"
    path.write_text(yaml.safe_dump(data))
    d = DaemonProcess(["--profile", str(path), "--sim"], short_tmp / "mixed.sock", short_tmp / "daemon.log")
    try:
        sims = Buses(d, {"arm", "hand"})
        robot = connect(socket=str(d.socket_path))
        try:
            info = robot.list()
            assert info["backend"] == "feetech+dynamixel"
            cmds = {ns["name"]: ns["commands"] for ns in info["namespaces"]}
            assert "servo_jf" in cmds["mixed/gripper"] and "servo_jf" not in cmds["mixed"]
            arm, hand = robot.device("mixed"), robot.device("mixed/gripper")
            assert arm.enable(5.0)
            assert arm.move_jp(LEFT_GOAL).wait(timeout=15.0)
            hand.servo_jf([0.035])  # 0.1 A = 100 XL330 units
            wait_until(lambda: sims.servos("hand")["6"]["operating_mode"] == 0
                       and sims.servos("hand")["6"]["goal_current"] == 100, 3, what="gripper in current mode")
            wait_until(lambda: np.allclose(sims.arm_ticks("arm"), ticks(LEFT_GOAL), atol=15), 5,
                       what="the Feetech arm at its goal")
            assert arm.disable(5.0)
        finally:
            robot.close()
    finally:
        d.stop()

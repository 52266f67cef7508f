"""What ``list`` and a new session tell a client that adapts commands to the robot (the LeRobot
plugin, issue 21): each joint's position limits and the servo step bound (so the client can say
what it really sent), LeRobot's numbers as affine maps of each joint's value (docs/protocol.md,
"LeRobot units"; the arithmetic is tests/test_calibrate_import.py's), and, for a session that
joins a robot already in FAULT, the error event that caused it."""

from __future__ import annotations

import math

import pytest

from crtk_bridge.backends.calibration import lerobot_maps
from crtk_bridge.client import connect
from crtk_bridge.profile import load_profile

from .conftest import ROOT, only_on, wait_until


@only_on("so101-feetech")
@pytest.mark.reuse_daemon
def test_list_carries_limits_step_bound_and_lerobot_maps_from_the_profile(sim_daemon):
    profile = load_profile(ROOT / "profiles" / "so101.yaml")
    joints = {j.name: j for j in profile.joints}
    with connect(socket=str(sim_daemon.socket_path), timeout=5.0) as robot:
        info = robot.list()
    assert info["servo_step_max"] == profile.safety.servo_step_max
    for ns in info["namespaces"]:
        assert len(ns["position_limits"]) == len(ns["lerobot"]) == len(ns["joints"])
        for name, limits, maps in zip(ns["joints"], ns["position_limits"], ns["lerobot"]):
            j = joints[name]
            assert limits == [j.limits.position_min, j.limits.position_max]
            cal = j.backend["calibration"]
            assert maps == lerobot_maps(cal["offset"], cal["direction"], cal["range"], 4096)
    # by hand, the shipped gripper (offset 2048, range [1900, 3300]): 0 rad is 2048 ticks, LeRobot's
    # (2048 - 1900) / 1400 * 100; one radian more is 4096 / (2 pi) ticks more
    grip = next(ns for ns in info["namespaces"] if ns["name"] == "so101/gripper")["lerobot"][0]
    scale, bias = grip["range_0_100"]
    assert bias == pytest.approx(148 / 1400 * 100) and scale == pytest.approx(4096 / (2 * math.pi) / 1400 * 100)


@only_on("ur5e")
@pytest.mark.reuse_daemon
def test_a_robot_without_servo_calibration_has_no_lerobot_numbers(sim_daemon):
    with connect(socket=str(sim_daemon.socket_path), timeout=5.0) as robot:
        info = robot.list()
    assert all(m is None for ns in info["namespaces"] for m in ns["lerobot"])
    assert all(len(lim) == 2 for ns in info["namespaces"] for lim in ns["position_limits"])


@only_on("so101-feetech")
def test_a_session_joining_a_fault_gets_its_reason(sim_daemon):
    with connect(socket=str(sim_daemon.socket_path), timeout=5.0) as robot:
        arm = robot.device(sim_daemon.robot.arm)
        assert arm.enable(5.0)
        sim = sim_daemon.robot.sim(sim_daemon.sim_control_path())
        sim.set_unplugged(True)
        wait_until(arm.is_fault, 10, what="the FAULT of an unplugged bus")
        cause = [e for e in robot.connection.events if e.kind == "error"][-1]
        with connect(socket=str(sim_daemon.socket_path), timeout=5.0) as late:
            assert late.device().is_fault()
            wait_until(lambda: any(e.kind == "error" for e in late.connection.events), 5,
                       what="the error event replayed to a late session")
            told = [e for e in late.connection.events if e.kind == "error"]
        assert [e.data for e in told] == [cause.data] and "no reply" in cause.data["message"]
        sim.set_unplugged(False)

"""The LeRobot plugin's daemon side (lerobot_robot_crtk/lerobot_robot_crtk/arm.py, issue 21),
without LeRobot: the plugin's package registers LeRobot configs at import, so its LeRobot-free
module is loaded here from its file. What LeRobot itself does with the plugin (record, replay,
teleoperate in the real LeRobot) is tests/lerobot/'s.

Against a simulated SO-101: the joints are known before connecting (LeRobot reads its features
first); readings in ``lerobot`` units are list's maps applied to the daemon's radians (the maps
themselves are checked against LeRobot's formulas in test_calibrate_import.py); an action is
clipped by ``max_relative_target`` (LeRobot's semantics), the joint limits and ``servo_step_max``,
and the returned action is what the daemon got (its goal_jp); a FAULT at connect or mid-episode
raises one line with the daemon's reason; disconnecting holds and releases control."""

from __future__ import annotations

import importlib.util
import math
import sys
import time

import numpy as np
import pytest
import yaml

from crtk_bridge.backends.calibration import lerobot_maps
from crtk_bridge.client import connect
from crtk_bridge.profile import load_profile

from .conftest import ROOT, DaemonProcess, only_on, so101_data, wait_until

_spec = importlib.util.spec_from_file_location("crtk_lerobot_arm", ROOT / "lerobot_robot_crtk" / "lerobot_robot_crtk"
                                               / "arm.py")
arm_module = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = arm_module  # dataclasses look their module up there
_spec.loader.exec_module(arm_module)
DaemonArm, CrtkFaultError, ConfigError = arm_module.DaemonArm, arm_module.CrtkFaultError, arm_module.ConfigError

PROFILE = load_profile(ROOT / "profiles" / "so101.yaml")
JOINTS = {j.name: j for j in PROFILE.joints}
KEYS = [f"{j.name}.pos" for j in PROFILE.joints]


def by_hand(name: str, rad: float, use_degrees: bool = True) -> float:
    """LeRobot's number of joint ``name`` at ``rad``, from the profile's calibration."""
    cal = JOINTS[name].backend["calibration"]
    mode = "range_0_100" if name == "gripper" else "degrees" if use_degrees else "range_m100_100"
    scale, bias = lerobot_maps(cal["offset"], cal["direction"], cal["range"], 4096)[mode]
    v = scale * rad + bias
    return v if mode == "degrees" else min(100.0, max(-100.0 if mode == "range_m100_100" else 0.0, v))


def robot_settled(sock: str) -> bool:
    """The arm's setpoint no longer moves (its interpolation reached the goal)."""
    with connect(socket=sock) as robot:
        dev = robot.device("so101")
        return bool(np.allclose(dev.setpoint_jp()[0], dev.goal_jp()[0], atol=1e-6))


def rad_of(robot) -> dict[str, float]:
    info = {ns["name"]: ns["joints"] for ns in robot.list()["namespaces"]}
    out = {}
    for ns, names in info.items():
        out.update(zip(names, (float(x) for x in robot.device(ns).measured_jp()[0])))
    return out


@only_on("so101-feetech")
@pytest.mark.reuse_daemon
def test_joints_known_before_connecting_and_readings_in_lerobot_units(sim_daemon):
    sock = str(sim_daemon.socket_path)
    arm = DaemonArm(socket=sock)
    assert arm.keys() == KEYS and not arm.is_open  # one list query, nothing enabled
    arm.open()
    try:
        with connect(socket=sock) as robot:
            assert robot.operating_state() == "DISABLED"
            rad = rad_of(robot)
        got = arm.read()
        for key in KEYS:
            name = key[:-4]
            assert got[key] == pytest.approx(by_hand(name, rad[name]), abs=1e-6), key
        arm_m100 = DaemonArm(socket=sock, use_degrees=False)
        arm_m100.open()
        try:
            got = arm_m100.read()
            assert got["elbow_flex.pos"] == pytest.approx(by_hand("elbow_flex", rad["elbow_flex"], False), abs=1e-6)
        finally:
            arm_m100.close()
        si = DaemonArm(socket=sock, units="si")
        si.open()
        try:
            assert si.read() == pytest.approx({f"{n}.pos": v for n, v in rad.items()}, abs=1e-9)
        finally:
            si.close()
    finally:
        arm.close()


@only_on("so101-feetech")
@pytest.mark.reuse_daemon  # ends ENABLED, no fault: the module's daemon, restored
def test_an_action_is_clipped_and_the_return_is_what_the_daemon_got(sim_daemon):
    sock = str(sim_daemon.socket_path)
    arm = DaemonArm(socket=sock)
    arm.describe()
    arm.open()
    try:
        arm.enable()
        now = arm.read()
        # LeRobot's max_relative_target: each joint within 5 of its measured value; 0-dim arrays
        # (what a dataset's tensors are) taken with float()
        action = {k: np.array(v + 20.0) for k, v in now.items()}
        sent = arm.send(action, max_relative_target=5.0)
        assert sent == pytest.approx({k: v + 5.0 for k, v in now.items()}, abs=0.2)
        with connect(socket=sock) as robot:
            goal = robot.device("so101").goal_jp()[0]
            names = robot.list()["namespaces"][0]["joints"]
        for name, g in zip(names, goal):  # the daemon's goal is exactly the returned action
            assert by_hand(name, float(g)) == pytest.approx(sent[f"{name}.pos"], abs=1e-6)
        # far beyond the joint limit and the step bound (si): one step of servo_step_max toward the
        # limit, never the refusal a far goal would get
        si = DaemonArm(socket=sock, units="si")
        arm.close()
        wait_until(lambda: robot_settled(sock), 10, what="the interpolation at its goal")
        si.open()
        si.enable()
        with connect(socket=sock) as robot:  # the step bound counts from the daemon's setpoint
            setpoint = robot.device("so101").setpoint_jp()[0]
            start = float(setpoint[0]) if len(setpoint) else si.read()["shoulder_pan.pos"]
        step = si.info["servo_step_max"] * arm_module.STEP_MARGIN
        first = si.send({"shoulder_pan.pos": 10.0})
        assert first == {"shoulder_pan.pos": pytest.approx(start + step)}
        hi = JOINTS["shoulder_pan"].limits.position_max
        for _ in range(40):
            last = si.send({"shoulder_pan.pos": 10.0})
        assert last == {"shoulder_pan.pos": pytest.approx(hi)}  # clipped to the limit, as the daemon would
        wait_until(lambda: abs(si.read()["shoulder_pan.pos"] - hi) < 0.02, 10, what="the arm at its limit")
        si.release("hold")
        with connect(socket=sock) as other:  # control released, the arm still held
            assert other.operating_state() == "ENABLED"
            other.device("so101").hold()
        si.close()
    finally:
        arm.close()


@only_on("so101-feetech")
@pytest.mark.reuse_daemon  # ends ENABLED, no fault: the module's daemon, restored
def test_disconnect_holds_at_the_last_action_not_short_of_it(sim_daemon):
    """LeRobot disconnects right after its last ``send_action``: the arm ends at that action, not
    where its interpolation was when the hold came (a replay ended off its recorded path)."""
    sock = str(sim_daemon.socket_path)
    arm = DaemonArm(socket=sock)
    arm.open()
    try:
        arm.enable()
        now = arm.read()
        sent = arm.send({k: v + (4.0 if v < 0 else -4.0) for k, v in now.items() if k != "gripper.pos"})
        assert max(abs(sent[k] - now[k]) for k in sent) > 2.0  # a step the interpolation takes a while over
        arm.release("hold")
        wait_until(lambda: robot_settled(sock), 5, what="the hold at the last action (setpoint == its goal)")
        wait_until(lambda: all(abs(arm.read()[k] - sent[k]) < 0.5 for k in sent), 5,
                   what=f"the arm at the last action {sent}, read {arm.read()}")
    finally:
        arm.close()


def test_disconnect_of_a_slow_predicted_stream_holds_exactly_at_the_last_action(tmp_path):
    """``loop.interpolation: predict`` passes the last action by up to a step, then returns to it
    over about 4 action periods: at 2.5 Hz that is longer than the plugin's 1 s floor, and a
    disconnect held the arm off its last action. The wait scales with the action interval."""
    data = so101_data()
    data["loop"]["interpolation"] = "predict"
    (tmp_path / "predict.yaml").write_text(yaml.safe_dump(data))
    d = DaemonProcess(["--profile", str(tmp_path / "predict.yaml"), "--sim"], tmp_path / "d.sock", tmp_path / "d.log")
    try:
        arm = DaemonArm(socket=str(d.socket_path), units="si")
        arm.open()
        try:
            arm.enable()
            start = arm.read()["shoulder_pan.pos"]
            direction = 1.0 if start < 0 else -1.0
            period = 0.5  # 2 Hz: predict settles ~1.7 s after the last action
            due = time.monotonic()
            for k in range(1, 7):
                time.sleep(max(0.0, due - time.monotonic()))
                last = arm.send({"shoulder_pan.pos": start + direction * 0.04 * k})["shoulder_pan.pos"]
                due += period
            assert arm.settle_s() >= 4 * period
            arm.release("hold")  # LeRobot disconnects right after its last action
            with connect(socket=str(d.socket_path)) as robot:
                held = float(robot.device("so101").setpoint_jp()[0][0])
            assert held == pytest.approx(last, abs=1e-6), f"held at {held}, last action {last}"
        finally:
            arm.close()
    finally:
        d.stop()


@only_on("so101-feetech")
def test_a_fault_mid_episode_raises_its_reason_and_connect_refuses_a_faulted_robot(sim_daemon):
    sock = str(sim_daemon.socket_path)
    arm = DaemonArm(socket=sock)
    arm.open()
    try:
        arm.enable()
        now = arm.read()
        arm.send(now)
        sim_daemon.robot.sim(sim_daemon.sim_control_path()).set_unplugged(True)
        with connect(socket=sock) as robot:
            wait_until(lambda: robot.operating_state() == "FAULT", 10, what="the FAULT of an unplugged bus")
        with pytest.raises(CrtkFaultError) as err:
            for _ in range(5):  # the FAULT event may reach this connection a moment later
                arm.send(now)
                arm.read()
        message = str(err.value)
        assert "so101 is in FAULT" in message and "no reply" in message and "\n" not in message
        late = DaemonArm(socket=sock)
        with pytest.raises(CrtkFaultError, match=r"so101 is in FAULT \(.*no reply.*\); connect refused"):
            late.open()
        assert not late.is_open
        arm.release("hold")  # LeRobot's finally: disconnect: never raises, in FAULT nor with the daemon gone
        sim_daemon.proc.kill()
        sim_daemon.proc.wait(15)
        arm.release("hold")
        arm.release("disable")
    finally:
        arm.close()


@pytest.mark.parametrize("kw, words", [
    ({"units": "degrees"}, "units must be one of lerobot, si"),
    ({"command": "move"}, "command must be one of interpolate, servo"),
    ({"on_disconnect": "drop"}, "on_disconnect must be one of hold, disable"),
    ({"max_relative_target": math.nan}, "max_relative_target must be a finite number > 0"),
    ({"max_relative_target": -5.0}, "got -5.0"),
    ({"max_relative_target": 0}, "got 0"),
    ({"max_relative_target": {"gripper": math.inf}}, "got inf"),
])
def test_settings_lerobot_lets_through_are_refused_in_one_line(kw, words):
    """LeRobot's own max_relative_target check lets nan (no clamp), a negative cap (inverted) and
    0 (no motion) through."""
    settings = {"units": "lerobot", "command": "interpolate", "on_disconnect": "hold", "max_relative_target": None}
    with pytest.raises(ConfigError, match=words.replace("(", r"\(")):
        arm_module.check_settings(**{**settings, **kw})

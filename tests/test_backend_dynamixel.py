"""DynamixelBackend against the Protocol 2.0 simulator (real dynamixel_sdk packets on a pty).

Dynamixel specifics: capabilities per model mix, current mode (effort), operating-mode switches
without a jump, hardware-error FAULT and recovery by reboot on enable, fast vs plain sync read,
bytes per cycle. Every wait is a poll with a deadline."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import yaml

from crtk_bridge.backends import create_backend
from crtk_bridge.backends.dynamixel import tables as T
from crtk_bridge.backends.dynamixel.backend import DynamixelBackend
from crtk_bridge.core.actuator import CommandMode, effective_period_s
from crtk_bridge.errors import BackendError
from crtk_bridge.errors import ProfileError
from crtk_bridge.profile import parse_profile
from crtk_bridge.sim.dynamixel import DynamixelSimulator

from .conftest import wait_until

with open("profiles/koch.yaml") as f:
    KOCH = yaml.safe_load(f)
TICK = 2 * math.pi / 4096


def koch(**backend) -> dict:
    data = copy.deepcopy(KOCH)
    data["backend"].update(backend)
    return data


def all_xl330(**backend) -> dict:
    """A Koch whose shoulders are XL330s too, every joint with effort_per_amp: effort capable."""
    data = koch(**backend)
    for j in data["joints"]:
        j["model"] = "xl330-m288"
        j["effort_per_amp"] = 0.35
    return data


def start_sim(data):
    s = DynamixelSimulator.from_profile(parse_profile(data))
    s.start()
    return s


@pytest.fixture
def rig(request):
    data = getattr(request, "param", None) or koch()
    sim = start_sim(data)
    data = copy.deepcopy(data)
    data["backend"]["port"] = sim.port
    b = DynamixelBackend(parse_profile(data, "koch.yaml"), source="koch.yaml")
    b.open()
    b.configure()
    yield sim, b
    b.close()
    sim.stop()


def ok(fault):
    assert fault is None, fault


def reg(sim, sid, name):
    return sim.servo(sid).read(name)


def switch(b, cmd, fb=None):
    """The operating-mode switch ``cmd`` needs (mode_switch_steps), run over cycles as core runs
    it (the cycle's read, one step); nothing when none is needed. Returns the cycles it took."""
    steps = b.mode_switch_steps(cmd.mode)
    fb = fb if fb is not None else b.new_feedback()
    cycles = 0
    for _ in steps or ():
        ok(b.read(fb))
        cycles += 1
    return cycles


# ---------------------------------------------------------------- profile and capabilities

def test_koch_capabilities_effort_per_joint():
    b = create_backend(parse_profile(koch()))
    t = b._traits_hook()  # what open() declares: per joint from the profile alone, no bus needed
    c = t.capabilities  # the whole robot: only what every joint can do
    assert isinstance(b, DynamixelBackend)
    assert (c.position, c.velocity, c.effort, c.measures_effort, c.can_free) == (True, True, False, False, True)
    # per joint: the XL430 shoulders have no current sensing; the XL330s with effort_per_amp have it
    assert [t.joints[i].effort for i in range(6)] == [False, False, True, True, True, True]
    assert [t.joints[i].measures_effort for i in range(6)] == [False, False, True, True, True, True]
    assert t.capabilities_of([5]).effort and not t.capabilities_of([0, 1, 2, 3, 4]).effort
    c = DynamixelBackend(parse_profile(all_xl330()))._traits_hook().capabilities
    assert c.effort and c.measures_effort
    data = all_xl330()
    del data["joints"][0]["effort_per_amp"]
    assert not DynamixelBackend(parse_profile(data))._traits_hook().capabilities.effort


def test_profile_errors_name_the_key():
    with pytest.raises(ProfileError, match=r"backend\.joint_position_modes\.shoulder_pan: "
                                           r"current_based_position mode is not available .* xl430-w250"):
        DynamixelBackend(parse_profile(koch(joint_position_modes={"shoulder_pan": "current_based_position"})))
    with pytest.raises(ProfileError, match=r"backend\.joint_position_modes\.elbow: unknown joint"):
        DynamixelBackend(parse_profile(koch(joint_position_modes={"elbow": "position"})))
    with pytest.raises(ProfileError, match=r"backend\.baudrate: 1234 is not supported"):
        DynamixelBackend(parse_profile(koch(baudrate=1234)))
    data = koch()
    data["joints"][1]["model"] = "xl320"
    with pytest.raises(ProfileError, match=r"joints\[1\] \(shoulder_lift\)\.model: unknown model 'xl320'"):
        DynamixelBackend(parse_profile(data))


# ---------------------------------------------------------------- against the simulator

def test_configure_sets_modes_and_read_applies_calibration(rig):
    sim, b = rig
    assert [reg(sim, i, "Operating_Mode") for i in range(1, 7)] == [4, 4, 4, 4, 4, 5]
    assert all(reg(sim, i, "Return_Delay_Time") == 0 for i in range(1, 7))
    sim.servo(2).write("Present_Position", 2048 + 300)
    sim.servo(6).write("Present_Position", 2048 - 100)
    fb = b.new_feedback()
    ok(b.read(fb))
    assert fb.position[1] == pytest.approx(300 * TICK) and fb.position[5] == pytest.approx(-100 * TICK)
    assert fb.stamp > 0 and b.info().details["fast_sync_read"] is True


def test_enable_holds_and_position_command_converges(rig):
    sim, b = rig
    sim.servo(3).write("Present_Position", 2500)
    sim.servo(3).write("Goal_Position", 0)  # stale goal: enabling must not jump to it
    fb = b.new_feedback()
    b.enable(fb)
    assert reg(sim, 3, "Goal_Position") == 2500 and reg(sim, 3, "Torque_Enable") == 1
    cmd = b.new_command()
    cmd.mode[:] = CommandMode.POSITION
    cmd.position[:] = 0.2

    def there():
        ok(b.read(fb))
        ok(b.write(cmd))
        return np.all(np.abs(fb.position - 0.2) < 3 * TICK)

    wait_until(there, 10.0, what="joints at 0.2 rad")


@pytest.mark.parametrize("rig", [all_xl330()], indirect=True)
def test_current_mode_effort_command_and_measured_effort(rig):
    sim, b = rig
    fb = b.new_feedback()
    b.enable(fb)
    cmd = b.new_command()
    cmd.mode[:] = CommandMode.NONE
    cmd.mode[2] = CommandMode.EFFORT
    cmd.effort[2] = 0.0175  # N*m = 50 mA at 0.35 N*m/A
    switch(b, cmd)
    ok(b.write(cmd))
    assert reg(sim, 3, "Operating_Mode") == 0 and reg(sim, 3, "Torque_Enable") == 1
    wait_until(lambda: reg(sim, 3, "Goal_Current") == 50, 2.0, what="Goal_Current 50 mA")
    ok(b.read(fb))
    assert fb.effort[2] == pytest.approx(0.0175)
    start = fb.position[2]
    wait_until(lambda: b.read(fb) is None and fb.position[2] > start + 0.1, 5.0, what="current mode motion")


def test_mode_switch_velocity_then_position_without_a_jump(rig):
    sim, b = rig
    fb = b.new_feedback()
    b.enable(fb)
    cmd = b.new_command()
    cmd.mode[:] = CommandMode.NONE
    cmd.mode[0] = CommandMode.VELOCITY
    cmd.velocity[0] = 1.0
    ok(b.write(cmd))  # not in velocity mode yet: nothing sent, the joint holds
    assert reg(sim, 1, "Operating_Mode") == 4 and reg(sim, 1, "Goal_Velocity") == 0
    switch(b, cmd)
    ok(b.write(cmd))
    assert reg(sim, 1, "Operating_Mode") == 1
    wait_until(lambda: b.read(fb) is None and fb.position[0] > 0.3, 5.0, what="velocity mode motion")
    # back to position where the joint is (the motion layer's position setpoint follows the joint
    # under velocity control): the switch holds it, nothing jumps while torque goes off and on
    cmd.mode[0] = CommandMode.POSITION
    cmd.position[0] = fb.position[0]
    switch(b, cmd, fb)
    ok(b.write(cmd))
    assert reg(sim, 1, "Operating_Mode") == 4 and reg(sim, 1, "Torque_Enable") == 1
    ok(b.read(fb))
    held = fb.position[0]
    for _ in range(20):
        ok(b.read(fb))
        ok(b.write(cmd))
        assert abs(fb.position[0] - held) < 0.05
    # the gripper's position flavour is current-based position; a FREE joint is torque off
    cmd.mode[5] = CommandMode.FREE
    ok(b.write(cmd))
    wait_until(lambda: reg(sim, 6, "Torque_Enable") == 0, 2.0, what="gripper free")
    cmd.mode[5] = CommandMode.POSITION
    cmd.position[5] = fb.position[5]
    assert b.mode_switch_steps(cmd.mode) is None  # leaving FREE in its own mode: no switch
    ok(b.write(cmd))  # the goal, then torque on (one sync write each, no acknowledgement)
    wait_until(lambda: reg(sim, 6, "Torque_Enable") == 1, 2.0, what="gripper torque on after free")
    assert reg(sim, 6, "Operating_Mode") == 5


def test_hardware_error_is_a_fault_and_enable_reboots(rig):
    sim, b = rig
    fb = b.new_feedback()
    b.enable(fb)
    sim.set_fault(4, "error_bits", T.HW_OVERLOAD | T.HW_OVERHEATING)
    fault = b.read(fb)
    assert fault is not None and fault.code == "servo_error" and not fault.transient
    assert fault.joint == "wrist_flex" and fault.register == "Hardware_Error_Status" and fault.value == 0x24
    assert fault.message == ("koch: joint 'wrist_flex' (id 4) reports overheating error, overload error "
                             "(Hardware_Error_Status=0x24)")
    assert reg(sim, 4, "Torque_Enable") == 0
    b.disable()
    b.enable(fb)  # the way out of FAULT: reboot, wait, reconfigure, hold, torque on
    assert reg(sim, 4, "Hardware_Error_Status") == 0 and reg(sim, 4, "Torque_Enable") == 1
    assert reg(sim, 4, "Operating_Mode") == 4
    ok(b.read(fb))


@pytest.mark.parametrize("kind", ["silent", "corrupt"])
def test_silent_or_corrupt_servo_named_by_the_plain_retry_of_a_fast_read(rig, kind):
    # corrupt: in a Fast Sync Read only this servo's own (cumulative) CRC is bad; the packet's
    # last CRC, the only one the SDK checks, is good
    sim, b = rig
    fb = b.new_feedback()
    ok(b.read(fb))
    assert b.info().details["fast_sync_read"] is True
    sim.set_fault(5, kind)
    fault = b.read(fb)
    assert fault is not None and fault.code in ("bus_timeout", "bus_corrupt") and fault.transient
    assert fault.joint == "wrist_roll" and "joint 'wrist_roll' (id 5)" in fault.message
    sim.clear_faults()
    ok(b.read(fb))


@pytest.mark.parametrize("fast, reply", [("on", 8 + 6 * 14), ("off", 6 * (11 + 10))])
def test_one_cycle_is_the_protocol_minimum_of_bytes(fast, reply):
    data = koch(fast_sync_read=fast)
    sim = start_sim(data)
    data["backend"]["port"] = sim.port
    b = DynamixelBackend(parse_profile(data))
    try:
        b.open()
        b.configure()
        fb = b.new_feedback()
        b.enable(fb)
        cmd = b.new_command()
        cmd.mode[:] = CommandMode.POSITION
        ok(b.read(fb))
        ok(b.write(cmd))
        ok(b.read(fb))  # answered, so the simulator has consumed everything sent before it
        rx0, tx0 = sim.rx_bytes, sim.tx_bytes
        ok(b.write(cmd))
        ok(b.read(fb))  # one cycle's worth: a sync write of goals and a sync read, in either order
        assert sim.rx_bytes - rx0 == (14 + 6) + (14 + 6 * 5)  # sync read request + sync write of goals
        assert sim.tx_bytes - tx0 == reply
    finally:
        b.close()
        sim.stop()



@pytest.mark.parametrize("silent_after, failed", [("Torque_Enable", "Operating_Mode"),
                                                  ("Goal_Velocity", "Torque_Enable")])
def test_failed_mode_switch_after_torque_off_names_joint_and_register(rig, silent_after, failed):
    # the servo acknowledges Torque_Enable=0 (and maybe more) and then goes silent: the joint is
    # limp, so the switch fails at once (core faults the robot), naming the joint and register
    sim, b = rig
    fb = b.new_feedback()
    b.enable(fb)
    real = b._write_register

    def write_then_go_silent(i, name, value, check_error=False):
        real(i, name, value, check_error)
        if i == 0 and name == silent_after and (name != "Torque_Enable" or value == 0):
            sim.set_fault(1, "silent")  # from here on servo 1 answers nothing

    b._write_register = write_then_go_silent
    cmd = b.new_command()
    cmd.mode[:] = CommandMode.NONE
    cmd.mode[0] = CommandMode.VELOCITY
    cmd.velocity[0] = 0.5
    with pytest.raises(BackendError) as exc:
        switch(b, cmd)
    message = str(exc.value)
    assert "joint 'shoulder_pan'" in message and "velocity mode" in message
    assert f"register {failed}" in message and "torque may be off" in message
    if failed == "Operating_Mode":
        assert reg(sim, 1, "Torque_Enable") == 0  # limp: which is why core must go to FAULT now
    # (a lost ack of Torque_Enable=1: the servo may or may not be torqued; unknown, so FAULT too)


def test_failed_mode_switch_puts_the_robot_in_fault_at_once_torque_off_everywhere(rig):
    # the controller's side of the test above: one cycle with the failed switch, and the robot is
    # in FAULT (not ENABLED for bus_errors_max cycles with a limp joint); then torque off everywhere
    import time

    from crtk_bridge.core.control import Controller
    from crtk_bridge.core.cycle import CycleRunner

    sim, b = rig
    c = Controller(b.profile, b, time.time, effective_period_s(b.profile, b))
    runner = CycleRunner(b, c.dt)

    def cycle():  # the loop's (core/cycle.py)
        runner.cycle(c)

    c.handle({"id": 1, "cmd": "enable"})
    wait_until(lambda: cycle() or any(m.get("id") == 1 for m in c.outbox), 10.0, what="enable reply")
    assert c.state.value == "ENABLED"
    real = b._write_register

    def write_then_go_silent(i, name, value, check_error=False):
        real(i, name, value, check_error)
        if i == 0 and name == "Torque_Enable" and value == 0:
            sim.set_fault(1, "silent")

    b._write_register = write_then_go_silent
    c.outbox.clear()
    # the switch to velocity mode starts with the command (its first step: joint 0) and fails
    # after torque off: FAULT at once, and the command's reply says so
    c.handle({"id": 2, "cmd": "servo_jv", "ns": "koch", "data": {"velocity": [0.3, 0, 0, 0, 0]}})
    assert c.state.value == "FAULT"
    (reply,) = [m for m in c.outbox if m.get("id") == 2]
    assert not reply["ok"] and reply["error"]["code"] == "fault", reply
    errors = [m["data"] for m in c.outbox if m.get("event") == "error"]
    assert errors and errors[0]["code"] == "mode_switch_failed"
    assert "joint 'shoulder_pan'" in errors[0]["message"] and "register Operating_Mode" in errors[0]["message"]
    b._write_register = real
    sim.clear_faults()  # the servo answers again: the fault's torque off is confirmed
    wait_until(lambda: cycle() or all(reg(sim, sid, "Torque_Enable") == 0 for sid in range(1, 7)), 5.0,
               what="torque off on every servo")

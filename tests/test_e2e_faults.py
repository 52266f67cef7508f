"""End to end, faults and safety (issue 3): faults injected through the simulator's control socket
under a real daemon on each simulated robot (SO-101 on Feetech, Koch on Dynamixel); each must put
the robot in FAULT with an error event naming its cause, switch torque off, refuse ``enable`` while
it persists and recover with ``enable`` once cleared (a latched Dynamixel hardware error: enable
REBOOTs the servo, see SERVO_ERROR). Plus: a controlling client killed mid-stream, and the FAULT
row of the CRTK transition table."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from crtk_bridge.client import CommandError, connect
from crtk_bridge.sim.control import control_request

from .conftest import ROOT, wait_until

# What legitimately differs per backend (keyed by the profile's backend type):
# - register: the error register a servo_error event names, and (lower-cased) the simulator's
#   dump key for it: the STS3215's Status byte, the Dynamixel Hardware_Error_Status. The bits
#   tested mean the same on both: 0x20 overload, 0x04 overheating, 0x01 input voltage.
# - latched: the STS3215's Status bits are live conditions, so enable is refused while they are
#   set. A Dynamixel hardware error is latched until a REBOOT (or power cycle), so the simulator's
#   clear_faults leaves it set; enable REBOOTs the servos in error, so it succeeds and clears it.
SERVO_ERROR = {
    "feetech": {"register": "Status", "latched": False},
    "dynamixel": {"register": "Hardware_Error_Status", "latched": True},
}


@pytest.fixture
def rig(sim_daemon):
    robot = connect(socket=str(sim_daemon.socket_path))
    arm = robot.device(sim_daemon.robot.arm)
    try:
        assert arm.enable(5.0)
        yield robot, arm, sim_daemon.sim_control_path()
    finally:
        robot.close()


def sim_req(sim: str, **req) -> dict:
    reply = control_request(sim, req)
    assert reply.get("ok"), reply
    return reply


def torque(sim: str) -> dict[str, int]:
    return {sid: s["torque_enable"] for sid, s in sim_req(sim, cmd="dump")["servos"].items()}


def all_torque(sim: str, value: int) -> bool:
    t = torque(sim)
    return len(t) == 6 and all(v == value for v in t.values())


def expect_fault(robot, arm, mark: int, code: str, joint: str | None, timeout: float = 3.0):
    """The error event with ``code`` (naming ``joint``) arrives and the robot is in FAULT."""
    ev = robot.wait_for_event(code, timeout, kind="error", since=mark)
    assert ev is not None, [e for e in robot.connection.events_since(mark)]
    if joint is not None:
        assert ev.data.get("joint") == joint, ev.data
        assert joint in ev.data["message"] or f"id {SERVO_ID[joint]}" in ev.data["message"], ev.data
    wait_until(arm.is_fault, 2, what="FAULT state")
    return ev


SERVO_ID = {"shoulder_pan": 1, "shoulder_lift": 2, "elbow_flex": 3, "wrist_flex": 4, "wrist_roll": 5}  # both robots


def error_bits(sim: str, backend: str, sid: int) -> int:
    """The simulated servo's error register (Status / Hardware_Error_Status)."""
    return sim_req(sim, cmd="dump")["servos"][str(sid)][SERVO_ERROR[backend]["register"].lower()]


def clear_error_bits_and_enable(arm, sim: str, backend: str, sid: int, bits: int) -> None:
    """Enable out of a servo_error FAULT: refused while live Status bits persist (STS3215), or
    REBOOTing the servo whose hardware error is latched (Dynamixel)."""
    if SERVO_ERROR[backend]["latched"]:
        sim_req(sim, cmd="clear_faults")
        assert error_bits(sim, backend, sid) == bits  # latched: only a REBOOT clears it
        assert arm.enable(5.0) and arm.is_enabled()  # enable REBOOTs the servo in error
        assert error_bits(sim, backend, sid) == 0
    else:
        enable_refused_while_fault_persists(arm)
        assert error_bits(sim, backend, sid) == bits
        sim_req(sim, cmd="clear_faults")
        assert arm.enable(5.0) and arm.is_enabled()
    assert all_torque(sim, 1)


def enable_refused_while_fault_persists(arm) -> None:
    with pytest.raises(CommandError) as err:
        arm.enable(3.0)
    assert err.value.code == "fault"
    assert arm.is_fault()


def recover(arm, sim: str) -> None:
    sim_req(sim, cmd="clear_faults")
    assert arm.enable(5.0) and arm.is_enabled()
    assert all_torque(sim, 1)
    p, ts = arm.measured_jp()
    assert ts > 0
    step = np.zeros(len(p))
    step[0] = 0.05
    assert arm.move_jr(step).wait(timeout=5.0) and arm.is_enabled()


@pytest.mark.parametrize("kind,code", [("silent", "bus_timeout"), ("corrupt", "bus_corrupt")])
def test_bus_fault_on_one_servo(rig, sim_robot, kind, code):
    robot, arm, sim = rig
    mark = robot.connection.event_count
    sim_req(sim, cmd="fault", id=3, kind=kind)
    ev = expect_fault(robot, arm, mark, code, "elbow_flex")
    assert sim_robot.arm in ev.data["ns"]
    wait_until(lambda: all_torque(sim, 0), 2, what="torque off on every servo")
    assert arm.measured_jp()[1] == 0.0  # measured data invalid while the bus fails
    enable_refused_while_fault_persists(arm)
    recover(arm, sim)


@pytest.mark.parametrize("bits,what", [(0x20, "overload"), (0x04, "overheat"), (0x01, "voltage")])
def test_servo_error_bit(rig, sim_robot, bits, what):
    robot, arm, sim = rig
    mark = robot.connection.event_count
    sim_req(sim, cmd="fault", id=4, kind="error_bits", bits=bits)
    ev = expect_fault(robot, arm, mark, "servo_error", "wrist_flex")
    assert ev.data["register"] == SERVO_ERROR[sim_robot.backend]["register"] and ev.data["value"] == bits
    assert what in ev.data["message"]
    wait_until(lambda: all_torque(sim, 0), 2, what="torque off on every servo")
    clear_error_bits_and_enable(arm, sim, sim_robot.backend, 4, bits)
    recover(arm, sim)


def test_frozen_joint_during_a_move_is_a_tracking_error(rig, sim_robot):
    robot, arm, sim = rig
    mark = robot.connection.event_count
    sim_req(sim, cmd="fault", id=2, kind="freeze")
    h = arm.move_jp(sim_robot.vec(shoulder_lift=1.2))
    ev = expect_fault(robot, arm, mark, "tracking_error", "shoulder_lift")
    assert ev.data["value"] > 0.6  # the error, beyond safety.tracking_error_max
    assert h.wait(timeout=1.0)  # the move ended with the FAULT: nobody waits on it forever
    wait_until(lambda: all_torque(sim, 0), 2, what="torque off on every servo")
    assert abs(arm.measured_jp()[0][1]) < 0.05  # it never moved
    recover(arm, sim)


def test_unplugged_bus(rig):
    robot, arm, sim = rig
    mark = robot.connection.event_count
    sim_req(sim, cmd="unplug", on=True)
    ev = expect_fault(robot, arm, mark, "bus_timeout", "shoulder_pan")  # the first servo asked
    assert "no reply" in ev.data["message"]
    assert arm.measured_jp()[1] == 0.0
    enable_refused_while_fault_persists(arm)
    sim_req(sim, cmd="unplug", on=False)
    assert arm.disable(3.0) and all_torque(sim, 0)  # disable reaches the servos again
    recover(arm, sim)


def test_unplugged_bus_torque_off_confirmed_or_reported(rig):
    robot, arm, sim = rig
    mark = robot.connection.event_count
    sim_req(sim, cmd="unplug", on=True)
    expect_fault(robot, arm, mark, "bus_timeout", "shoulder_pan")
    time.sleep(0.1)  # unplugged for a while, as a pulled cable would be
    sim_req(sim, cmd="unplug", on=False)
    # torque off could not reach the servos while unplugged: the daemon says so, and switches
    # them off once the bus is back
    errors = [e for e in robot.connection.events_since(mark) if e.data.get("code") == "bus_timeout"]
    assert errors and "torque off not confirmed" in errors[0].data["message"]
    wait_until(lambda: all_torque(sim, 0), 2, what="torque off after replugging")
    wait_until(lambda: any(e.data.get("code") == "torque_off_confirmed" for e in robot.connection.events_since(mark)),
               2, what="torque_off_confirmed status event")


def test_fault_row_of_the_transition_table(rig, sim_robot):
    robot, arm, sim = rig
    mark = robot.connection.event_count
    sim_req(sim, cmd="fault", id=1, kind="error_bits", bits=0x20)
    expect_fault(robot, arm, mark, "servo_error", "shoulder_pan")
    for cmd in ("pause", "resume"):
        with pytest.raises(CommandError) as err:
            getattr(arm, cmd)(1.0)
        assert err.value.code == "invalid_state" and "FAULT" in err.value.message
        assert arm.is_fault()
    with pytest.raises(CommandError) as err:
        arm.move_jp([0.0] * sim_robot.n)
    assert err.value.code == "invalid_state" and "FAULT" in err.value.message
    assert arm.disable(3.0) and arm.is_disabled()  # FAULT -> DISABLED
    assert all_torque(sim, 0)
    # enable from DISABLED with a live error bit still set fails into FAULT; once the cause is
    # gone, enable retries straight to ENABLED (FAULT -> ENABLED). A latched Dynamixel error: enable
    # REBOOTs the servo, DISABLED -> ENABLED.
    clear_error_bits_and_enable(arm, sim, sim_robot.backend, 1, 0x20)


STREAMER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from crtk_bridge.client import connect
    arm = connect(socket=sys.argv[1]).device(sys.argv[2])
    assert arm.enable(5.0)
    p = arm.measured_jp()[0]
    step = np.zeros(len(p))
    step[0] = 0.004  # 0.4 rad/s on shoulder_pan
    k = 0
    while True:
        k += 1
        arm.servo_jp(p + k * step)
        if k == 20:
            print("streaming", flush=True)
        time.sleep(0.01)
""")


def test_killed_controlling_client_makes_the_arm_hold(sim_daemon):
    watcher = connect(socket=str(sim_daemon.socket_path))
    arm = watcher.device(sim_daemon.robot.arm)
    servo_timeout = sim_daemon.robot.servo_timeout_s
    proc = subprocess.Popen([sys.executable, "-c", STREAMER, str(sim_daemon.socket_path), sim_daemon.robot.arm],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "streaming", proc.stderr.read()
        start = arm.measured_jp()[0][0]
        wait_until(lambda: arm.measured_jp()[0][0] - start > 0.05, 5, what="arm following the stream")
        mark = watcher.connection.event_count
        proc.send_signal(signal.SIGKILL)
        proc.wait(5)
        t_kill = time.monotonic()
        ev = [None]

        def released():
            for code in ("control_released", "servo_timeout"):
                e = arm.wait_for_event(code, 0.0, kind="warning", since=mark)
                if e is not None:
                    ev[0] = e
            return ev[0] is not None

        wait_until(released, servo_timeout + 1.0, what="control_released or servo_timeout warning")

        # measured position stops changing within one watchdog period (plus the servo settling)
        def still():
            a = arm.measured_jp()[0][0]
            time.sleep(0.05)  # observation window
            return abs(arm.measured_jp()[0][0] - a) < 0.002

        wait_until(still, servo_timeout + 0.3, what="arm holding")
        assert time.monotonic() - t_kill < servo_timeout + 0.35
        held = arm.measured_jp()[0][0]
        time.sleep(0.3)  # the observation window of "it stays there"
        assert abs(arm.measured_jp()[0][0] - held) < 0.005
        assert arm.is_enabled(), (arm.operating_state(), watcher.connection.events_since(mark))  # not a fault
        # and control is free for the watcher
        assert arm.move_jr(sim_daemon.robot.vec(shoulder_pan=-0.05)).wait(timeout=5.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        watcher.close()

"""End to end, faults and safety (issue 3): faults injected through the simulator's control socket
under a real daemon on each simulated robot (SO-101 on Feetech, Koch on Dynamixel, the CANopen
pan / tilt unit where its simulator offers the fault: ``fault:<kind>`` capabilities, the
conformance row's hooks and codes); each must put
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

from .conftest import ROOT, wait_until

# every simulated robot, unless a test says what it needs. One daemon per robot serves the module
# (reuse_daemon): each test ends recovered (ENABLED, no fault: recover() or its own enable, which
# the test asserts) and SharedDaemons puts it back DISABLED at its start pose (a test that fails
# in FAULT: a fresh daemon for the next). Every fault is still injected into an ENABLED robot and
# seen on a connection of the test's own.
pytestmark = [pytest.mark.requires(), pytest.mark.reuse_daemon]

# What legitimately differs between the serial servo buses (keyed by the profile's backend type;
# the tests using it need fault:error_bits):
# - register: the error register a servo_error event names, read back from the simulated servo:
#   the STS3215's Status byte, the Dynamixel Hardware_Error_Status. The bits
#   tested mean the same on both: 0x20 overload, 0x04 overheating, 0x01 input voltage.
# - latched: the STS3215's Status bits are live conditions, so enable is refused while they are
#   set. A Dynamixel hardware error is latched until a REBOOT (or power cycle), so the simulator's
#   clear_faults leaves it set; enable REBOOTs the servos in error, so it succeeds and clears it.
SERVO_ERROR = {
    "feetech": {"register": "Status", "latched": False},
    "dynamixel": {"register": "Hardware_Error_Status", "latched": True},
}


@pytest.fixture
def offered(request, sim_robot):
    """Skip (before a daemon starts) where the robot's simulator cannot inject the ``kind``
    parameter's fault."""
    kind = request.node.callspec.params.get("kind")
    if kind is not None and f"fault:{kind}" not in sim_robot.capabilities:
        pytest.skip(f"{sim_robot.profile.name}: its simulator offers no {kind!r} fault")


@pytest.fixture
def rig(sim_daemon):
    robot = connect(socket=str(sim_daemon.socket_path))
    arm = robot.device(sim_daemon.robot.arm)
    try:
        assert arm.enable(5.0)
        yield robot, arm, sim_daemon.robot.sim(sim_daemon.sim_control_path())
    finally:
        robot.close()


def all_torque(bot, sim, value: int) -> bool:
    t = bot.torque(sim)
    return len(t) == len(bot.servo_ids) and all(v == bool(value) for v in t.values())


def expect_fault(robot, arm, mark: int, code: str, joint: str | None, bot=None, timeout: float = 3.0):
    """The error event with ``code`` (naming ``joint``, or its device id) arrives and the robot
    is in FAULT."""
    ev = robot.wait_for_event(code, timeout, kind="error", since=mark)
    assert ev is not None, [e for e in robot.connection.events_since(mark)]
    if joint is not None:
        assert ev.data.get("joint") == joint, ev.data
        dev = bot.servo_id[joint]
        assert joint in ev.data["message"] or any(f"{w} {dev}" in ev.data["message"] for w in ("id", "node")), ev.data
    wait_until(arm.is_fault, 2, what="FAULT state")
    return ev


def error_bits(sim, backend: str, sid: int) -> int:
    """The simulated servo's error register (Status / Hardware_Error_Status)."""
    return sim.servo(sid).read(SERVO_ERROR[backend]["register"])


def clear_error_bits_and_enable(arm, sim, bot, sid: int, bits: int) -> None:
    """Enable out of a servo_error FAULT: refused while live Status bits persist (STS3215), or
    REBOOTing the servo whose hardware error is latched (Dynamixel)."""
    backend = bot.backend
    if SERVO_ERROR[backend]["latched"]:
        sim.clear_faults()
        assert error_bits(sim, backend, sid) == bits  # latched: only a REBOOT clears it
        assert arm.enable(5.0) and arm.is_enabled()  # enable REBOOTs the servo in error
        assert error_bits(sim, backend, sid) == 0
    else:
        enable_refused_while_fault_persists(arm)
        assert error_bits(sim, backend, sid) == bits
        sim.clear_faults()
        assert arm.enable(5.0) and arm.is_enabled()
    assert all_torque(bot, sim, 1)


def clear_device_error_and_enable(arm, sim, bot) -> None:
    """Enable out of the FAULT the row's ``inject_error`` caused: refused while a live error
    persists, or resetting a latched one (a Dynamixel REBOOT, a CiA 402 fault reset)."""
    if bot.row.error_latched:
        bot.row.clear_errors(sim)
        assert arm.enable(5.0) and arm.is_enabled()
    else:
        enable_refused_while_fault_persists(arm)
        bot.row.clear_errors(sim)
        assert arm.enable(5.0) and arm.is_enabled()
    assert all_torque(bot, sim, 1)


def enable_refused_while_fault_persists(arm) -> None:
    with pytest.raises(CommandError) as err:
        arm.enable(3.0)
    assert err.value.code == "fault"
    assert arm.is_fault()


def recover(arm, sim, bot) -> None:
    sim.clear_faults()
    assert arm.enable(5.0) and arm.is_enabled()
    assert all_torque(bot, sim, 1)
    p, ts = arm.measured_jp()
    assert ts > 0
    step = np.zeros(len(p))
    step[0] = 0.05
    assert arm.move_jr(step).wait(timeout=5.0) and arm.is_enabled()


@pytest.mark.parametrize("kind", ["silent", "corrupt"])
def test_bus_fault_on_one_device(offered, rig, sim_robot, kind):
    robot, arm, sim = rig
    bot = sim_robot
    joint = bot.joint_names[bot.j(2)]  # elbow_flex on the five-joint arms
    code = {"silent": bot.row.silent_code, "corrupt": "bus_corrupt"}[kind]
    mark = robot.connection.event_count
    sim.set_fault(bot.servo_id[joint], kind)
    ev = expect_fault(robot, arm, mark, code, joint, bot)
    assert ev.data["ns"] == bot.name  # a FAULT is robot-wide
    deaf = kind == "silent" and not bot.row.silent_hears  # a node off the bus hears nothing either
    dev = str(bot.servo_id[joint])
    hearing = [i for i in bot.servo_ids if not (deaf and i == dev)]
    wait_until(lambda: not any(bot.torque(sim, hearing).values()), 2, what="torque off on every device that hears")
    assert arm.measured_jp()[1] == 0.0  # measured data invalid while the bus fails
    if deaf:  # the daemon says torque off did not reach it (once its disable gave up)...
        wait_until(lambda: robot.wait_for_event("torque_off_unconfirmed", 0.0, kind="error", since=mark), 5,
                   what="torque_off_unconfirmed error event")
    enable_refused_while_fault_persists(arm)
    if deaf:  # ...and switches it off once it hears again
        sim.clear_faults()
        wait_until(lambda: all_torque(bot, sim, 0), 3, what="torque off on every device once it hears")
        wait_until(lambda: not arm.is_busy(), 3, what="the retried torque off ended")
    else:
        assert all_torque(bot, sim, 0)
    recover(arm, sim, bot)


@pytest.mark.requires("fault:error_bits")
@pytest.mark.parametrize("bits,what", [(0x20, "overload"), (0x04, "overheat"), (0x01, "voltage")])
def test_servo_error_bit(rig, sim_robot, bits, what):
    robot, arm, sim = rig
    mark = robot.connection.event_count
    sim.set_fault(4, "error_bits", bits)
    ev = expect_fault(robot, arm, mark, "servo_error", "wrist_flex", sim_robot)
    assert ev.data["register"] == SERVO_ERROR[sim_robot.backend]["register"] and ev.data["value"] == bits
    assert what in ev.data["message"]
    wait_until(lambda: all_torque(sim_robot, sim, 0), 2, what="torque off on every servo")
    clear_error_bits_and_enable(arm, sim, sim_robot, 4, bits)
    recover(arm, sim, sim_robot)


@pytest.mark.requires("fault:freeze")
def test_frozen_joint_during_a_move_is_a_tracking_error(rig, sim_robot):
    robot, arm, sim = rig
    mark = robot.connection.event_count
    sim.set_fault(2, "freeze")
    h = arm.move_jp(sim_robot.vec(shoulder_lift=1.2))
    ev = expect_fault(robot, arm, mark, "tracking_error", "shoulder_lift", sim_robot)
    assert ev.data["value"] > 0.6  # the error, beyond safety.tracking_error_max
    assert h.wait(timeout=1.0)  # the move ended with the FAULT: nobody waits on it forever
    wait_until(lambda: all_torque(sim_robot, sim, 0), 2, what="torque off on every servo")
    assert abs(arm.measured_jp()[0][1]) < 0.05  # it never moved
    recover(arm, sim, sim_robot)


# an unplugged serial bus: no reply from the first servo asked (the CANopen adapter's bus-off is
# tests/test_backend_canopen_e2e.py::test_adapter_bus_off_faults_and_enable_recovers_once_it_passes_again)
@pytest.mark.requires("servo_bus")
def test_unplugged_bus(rig, sim_robot):
    robot, arm, sim = rig
    mark = robot.connection.event_count
    sim.set_unplugged(True)
    ev = expect_fault(robot, arm, mark, "bus_timeout", "shoulder_pan", sim_robot)  # the first servo asked
    assert "no reply" in ev.data["message"]
    assert arm.measured_jp()[1] == 0.0
    enable_refused_while_fault_persists(arm)
    sim.set_unplugged(False)
    assert arm.disable(3.0) and all_torque(sim_robot, sim, 0)  # disable reaches the servos again
    recover(arm, sim, sim_robot)


@pytest.mark.requires("servo_bus")
def test_unplugged_bus_torque_off_confirmed_or_reported(rig, sim_robot):
    robot, arm, sim = rig
    mark = robot.connection.event_count
    sim.set_unplugged(True)
    expect_fault(robot, arm, mark, "bus_timeout", "shoulder_pan", sim_robot)
    time.sleep(0.1)  # unplugged for a while, as a pulled cable would be
    sim.set_unplugged(False)
    # torque off could not reach the servos while unplugged: the daemon says so, and switches
    # them off once the bus is back
    errors = [e for e in robot.connection.events_since(mark) if e.data.get("code") == "bus_timeout"]
    assert errors and "torque off not confirmed" in errors[0].data["message"]
    wait_until(lambda: all_torque(sim_robot, sim, 0), 2, what="torque off after replugging")
    wait_until(lambda: any(e.data.get("code") == "torque_off_confirmed" for e in robot.connection.events_since(mark)),
               2, what="torque_off_confirmed status event")
    recover(arm, sim, sim_robot)  # and enable recovers from it (the module's next test reuses the daemon)


def test_fault_row_of_the_transition_table(rig, sim_robot):
    robot, arm, sim = rig
    bot = sim_robot
    mark = robot.connection.event_count
    first = bot.joint_names[0]
    bot.row.inject_error(sim, bot.servo_id[first])  # a device error (the conformance row's)
    # naming the joint, unless the device's error is the whole arm's (a UR protective stop)
    expect_fault(robot, arm, mark, bot.row.error_code, first if bot.row.error_names_joint else None, bot)
    for cmd in ("pause", "resume"):
        with pytest.raises(CommandError) as err:
            getattr(arm, cmd)(1.0)
        assert err.value.code == "invalid_state" and "FAULT" in err.value.message
        assert arm.is_fault()
    with pytest.raises(CommandError) as err:
        arm.move_jp([0.0] * bot.n)
    assert err.value.code == "invalid_state" and "FAULT" in err.value.message
    assert arm.disable(3.0) and arm.is_disabled()  # FAULT -> DISABLED
    assert all_torque(bot, sim, 0)
    # enable from DISABLED with a live error still set fails into FAULT; once the cause is gone,
    # enable retries straight to ENABLED (FAULT -> ENABLED). A latched error (a Dynamixel
    # hardware error: enable REBOOTs the servo; a CiA 402 fault: enable resets it),
    # DISABLED -> ENABLED.
    if "fault:error_bits" in bot.capabilities:  # the servo's error register, read back
        clear_error_bits_and_enable(arm, sim, bot, bot.servo_id[first], 0x20)
    else:
        clear_device_error_and_enable(arm, sim, bot)


STREAMER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from crtk_bridge.client import connect
    arm = connect(socket=sys.argv[1]).device(sys.argv[2])
    assert arm.enable(5.0)
    p = arm.measured_jp()[0]
    step = np.zeros(len(p))
    step[0] = 0.004  # 0.4 rad/s on the first joint
    k = 0
    while True:
        k += 1
        arm.servo_jp(p + k * step)
        if k == 20:
            print("streaming", flush=True)
        time.sleep(0.01)
""")


@pytest.mark.requires("arm")  # a stream of rad-sized steps
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
        assert arm.move_jr(sim_daemon.robot.vec((0, -0.05))).wait(timeout=5.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        watcher.close()

"""The UR controller simulator driven by ur_rtde's own interfaces, unmodified (independent clients).

One simulator subprocess for the module on a free 127.0.0.N (its ports are fixed, so other
tests may run beside it on other addresses), one RTDEReceiveInterface, one DashboardClient and
one RTDEControlInterface reused across tests (each disconnect costs ur_rtde 0.5 s). The tests
run in file order: power on first, then the control script, motion, then the faults. Every wait
is a poll with a deadline.
"""

from __future__ import annotations

import math
import os
import re
import socket
import time

import numpy as np
import pinocchio as pin
import pytest

from crtk_bridge.profile import parse_profile
from crtk_bridge.sim import SimulatorError, simulator_class
from crtk_bridge.sim.ur_robot import UR5E_URDF

from .conftest import wait_until

# ur_rtde runs in-process and can abort it after a link breaks: a child pytest runs these (tests/in_child.py)
pytestmark = pytest.mark.in_child

rtde_receive = pytest.importorskip("rtde_receive")
rtde_control = pytest.importorskip("rtde_control")
dashboard_client = pytest.importorskip("dashboard_client")
rtde_io = pytest.importorskip("rtde_io")

HOME = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]
NAMES = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
         "wrist_3_joint"]
ELBOW_LIMIT = 3.0  # the profile's safety limit on the elbow (the others: +-6.2)

# Universal Robots' published UR5e DH parameters, written out independently of the URDF
DH_A = [0, -0.425, -0.3922, 0, 0, 0]
DH_D = [0.1625, 0, 0, 0.1333, 0.0997, 0.0996]
DH_ALPHA = [math.pi / 2, 0, 0, math.pi / 2, -math.pi / 2, 0]


def ur_profile(n_joints: int = 6, **backend):
    joints = []
    for name, home in list(zip(NAMES, HOME))[:n_joints]:
        lim = ELBOW_LIMIT if name == "elbow_joint" else 6.2
        joints.append({"name": name, "home": home, "limits": {
            "position_min": -lim, "position_max": lim, "velocity_max": 3.1, "acceleration_max": 10.0,
            "jerk_max": 100.0}})
    return parse_profile({
        "name": "ur5e_test", "backend": {"type": "ur", "host": "127.0.0.1", **backend},
        "joints": joints, "namespaces": [{"name": "ur5e", "joints": [j["name"] for j in joints]}],
    }, "<test_sim_ur>")


def dh_fk(q) -> np.ndarray:
    t = np.eye(4)
    for th, a, d, al in zip(q, DH_A, DH_D, DH_ALPHA):
        ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
        t = t @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
                          [0, sa, ca, d], [0, 0, 0, 1]])
    return t


def pose_matrix(pose) -> np.ndarray:
    return pin.SE3(pin.exp3(np.asarray(pose[3:])), np.asarray(pose[:3])).homogeneous


@pytest.fixture(scope="module")
def sim():
    s = simulator_class("ur").from_profile(ur_profile(), power_on_s=0.2, brake_release_s=0.3, unlock_delay_s=5.0)
    s.start()
    yield s
    s.stop()


@pytest.fixture(scope="module")
def recv(sim):
    r = rtde_receive.RTDEReceiveInterface(sim.host)
    yield r
    r.disconnect()


@pytest.fixture(scope="module")
def dash(sim):
    d = dashboard_client.DashboardClient(sim.host)
    d.connect()
    yield d
    d.disconnect()


@pytest.fixture(scope="module")
def powered(sim, recv, dash):
    """Power on + brake release (idempotent): the arm is RUNNING."""
    def ensure():
        if recv.getRobotMode() != 7:
            dash.powerOn()
            wait_until(lambda: recv.getRobotMode() == 5, 5, what="robot mode IDLE after power on")
            dash.brakeRelease()
            wait_until(lambda: recv.getRobotMode() == 7, 5, what="robot mode RUNNING after brake release")
    ensure()
    return ensure


@pytest.fixture(scope="module")
def control(sim, powered):
    c = rtde_control.RTDEControlInterface(sim.host)
    yield c
    c.disconnect()


@pytest.fixture
def ready(control, recv, powered, sim):
    """The arm RUNNING with the control script playing (re-uploaded if a test stopped it)."""
    powered()
    if not control.isProgramRunning():
        control.reuploadScript()
        wait_until(control.isProgramRunning, 5, what="the control script running again")
    return control


def test_receive_getters_before_power_on(sim, recv):
    assert recv.isConnected()
    assert recv.getRobotMode() == 3  # POWER_OFF
    assert recv.getSafetyMode() == 1  # NORMAL
    assert recv.getRuntimeState() == 1  # STOPPED
    assert recv.getSafetyStatusBits() == 1  # bit 0: normal
    assert recv.getRobotStatus() == 0  # not powered, no program
    assert recv.getTargetSpeedFraction() == 1.0
    np.testing.assert_allclose(recv.getActualQ(), HOME, atol=1e-12)  # rests at the profile's home
    t0 = recv.getTimestamp()
    wait_until(lambda: recv.getTimestamp() >= t0 + 0.1, 3, what="the RTDE timestamp advancing")


def test_tcp_pose_is_the_published_dh_forward_kinematics(sim, recv):
    q = recv.getActualQ()
    dh = dh_fk(q)
    np.testing.assert_allclose(pose_matrix(recv.getActualTCPPose()), dh, atol=1e-6)
    # and the URDF written from the same table gives the same flange pose
    model = pin.buildModelFromUrdf(str(UR5E_URDF))
    data = model.createData()
    pin.framesForwardKinematics(model, data, np.asarray(q))
    np.testing.assert_allclose(data.oMf[model.getFrameId("tool0")].homogeneous, dh, atol=1e-6)
    # at joint zero the controller's documented pose: x = a2 + a3, y = -(d4 + d6), z = d1 - d5
    np.testing.assert_allclose(dh_fk([0.0] * 6)[:3, 3], [-0.8172, -0.2329, 0.0628], atol=1e-9)


def test_dashboard_power_on_and_brake_release(sim, recv, dash, powered):
    assert re.fullmatch(r"\d+\.\d+\.\d+\.\d+", dash.polyscopeVersion())
    assert dash.getSerialNumber().isdigit()
    assert dash.isInRemoteControl()
    powered()  # power on -> IDLE -> brake release -> RUNNING, seen over RTDE
    assert dash.robotmode() == "Robotmode: RUNNING"
    assert recv.getRobotStatus() & 1  # powered
    assert dash.safetystatus() == "Safetystatus: NORMAL"
    assert not dash.running()


def test_brake_release_from_power_off_powers_on_and_proceeds_to_running(sim, recv, dash, powered):
    """As the controller: ``brake release`` from POWER_OFF powers the arm on and releases the
    brakes once powered; ``power on`` and ``brake release`` sent back to back end RUNNING too."""
    for sequence in ((dash.brakeRelease,), (dash.powerOn, dash.brakeRelease)):
        dash.powerOff()
        wait_until(lambda: recv.getRobotMode() == 3, 5, what="robot mode POWER_OFF after power off")
        seen = set()
        for command in sequence:
            command()

        def running() -> bool:
            seen.add(recv.getRobotMode())
            return 7 in seen

        wait_until(running, 5, what=f"robot mode RUNNING after {[c.__name__ for c in sequence]}")
        assert dash.robotmode() == "Robotmode: RUNNING" and recv.getRobotStatus() & 1
    powered()


def test_control_interface_uploads_its_script(ready, recv, dash):
    assert ready.isProgramRunning()
    # (isProgramRunning reads the control interface's own RTDE link; this receive interface is a
    # second link whose packet may come a cycle later)
    wait_until(lambda: recv.getRuntimeState() == 2, 2, what="runtime state PLAYING")
    assert dash.running()
    assert recv.getRobotStatus() & 2  # program running bit


def test_movej_arrives_along_a_trajectory(ready, recv):
    start = np.array(recv.getActualQ())
    goal = start + [0.4, -0.2, 0.3, 0.1, -0.1, 0.2]
    assert ready.moveJ(goal.tolist(), 1.5, 4.0, True)  # asynchronous: watch it move
    mid = wait_until(lambda: 0.05 < abs(recv.getActualQ()[0] - start[0]) < 0.35 and recv.getActualQ(), 3,
                     interval=0.002, what="the arm part way")
    assert ready.getAsyncOperationProgress() >= 0  # still running
    wait_until(lambda: ready.getAsyncOperationProgress() < 0, 5, what="the async moveJ to finish")
    # (the control interface's own link said so; this receive link's packet may come a cycle later)
    wait_until(lambda: np.allclose(recv.getActualQ(), goal, atol=1e-6), 1, what="the arm at the goal")
    # phase-synchronised (a line in joint space): every joint was the same fraction of the way when joint 0 was
    frac = (np.array(mid) - start) / (goal - start)
    np.testing.assert_allclose(frac, frac[0], atol=0.03)
    goal2 = goal - [0.2, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert ready.moveJ(goal2.tolist(), 2.0, 8.0)  # synchronous: returns on arrival
    wait_until(lambda: np.allclose(recv.getActualQ(), goal2, atol=1e-6), 1, what="the arm at the second goal")
    wait_until(ready.isSteady, 1, what="isSteady after the synchronous moveJ")


def test_servoj_streaming_tracks(ready, recv):
    q0 = np.array(recv.getActualQ())
    errors, reached = [], []
    for k in range(250):  # 0.5 s at 500 Hz: half a period of a 1 Hz sine
        t = ready.initPeriod()
        target = q0 + [0.1 * math.sin(2 * math.pi * k / 500), 0, 0, 0, 0.1 * k / 250, 0]
        assert ready.servoJ(target.tolist(), 0.5, 0.5, 0.002, 0.05, 300)
        if k > 50:
            errors.append(abs(recv.getActualQ()[0] - target[0]))
            reached.append(recv.getActualQ()[0] - q0[0])
        ready.waitPeriod(t)
    # the servo thread keeps chasing the last target until servoStop
    wait_until(lambda: abs(recv.getActualQ()[4] - (q0[4] + 0.1 * 249 / 250)) < 1e-4, 2,
               what="wrist 2 at the last servoJ target")
    assert ready.servoStop(10.0)
    # first order with the 50 ms lookahead on a 0.1 rad, 1 Hz sine: lag error < 0.1 * 0.3 rad
    assert max(errors) < 0.05
    assert max(reached) > 0.08  # it did follow the sine up
    wait_until(lambda: not any(recv.getActualQd()), 2, what="the arm at rest after servoStop")


def test_speedj_reaches_the_velocity_and_speedstop_stops(ready, recv):
    assert ready.speedJ([0.3, 0, 0, 0, 0, -0.2], 2.0, 0.0)
    wait_until(lambda: abs(recv.getActualQd()[0] - 0.3) < 1e-6 and abs(recv.getActualQd()[5] + 0.2) < 1e-6, 3,
               what="speedJ velocity reached")
    q = recv.getActualQ()[0]
    wait_until(lambda: recv.getActualQ()[0] > q + 0.03, 3, what="joint 0 moving at 0.3 rad/s")
    assert ready.speedStop(5.0)
    # speedStop returns when the script has taken the stop; this receive link sees the last
    # decelerating packet up to a cycle later (0.3 rad/s at 5 rad/s^2 takes 60 ms)
    wait_until(lambda: not any(recv.getActualQd()), 1, what="the arm at rest after speedStop")
    q = recv.getActualQ()
    time.sleep(0.05)
    assert recv.getActualQ() == q  # and it stays at rest: speedJ is over


def test_movel_goes_straight_and_servol_follows(ready, recv):
    start = np.array(recv.getActualTCPPose())
    goal = start + [0.0, 0.05, -0.08, 0, 0, 0]
    assert ready.moveL(goal.tolist(), 0.2, 1.0, True)
    worst = 0.0
    deadline = time.monotonic() + 5
    while ready.getAsyncOperationProgress() >= 0 and time.monotonic() < deadline:
        p = np.array(recv.getActualTCPPose()[:3])
        d = goal[:3] - start[:3]
        off = (p - start[:3]) - d * np.dot(p - start[:3], d) / np.dot(d, d)
        worst = max(worst, float(np.linalg.norm(off)))
        time.sleep(0.005)
    wait_until(lambda: np.allclose(recv.getActualTCPPose()[:3], goal[:3], atol=1e-4), 1, what="the TCP at the moveL goal")
    assert worst < 1e-3  # a straight line, not a joint-space arc
    # servoL: a stream of poses along x; the TCP follows
    p0 = np.array(recv.getActualTCPPose())
    for k in range(100):
        t = ready.initPeriod()
        assert ready.servoL((p0 + [0.0004 * k, 0, 0, 0, 0, 0]).tolist(), 0.5, 0.5, 0.002, 0.05, 300)
        ready.waitPeriod(t)
    wait_until(lambda: np.allclose(recv.getActualTCPPose(), p0 + [0.0396, 0, 0, 0, 0, 0], atol=1e-5), 2,
               what="TCP at the servoL goal")
    assert ready.servoStop(10.0)


def test_kinematics_queries_and_safety_limit_checks(ready, recv):
    q = recv.getActualQ()
    # (ur_rtde 1.6.5's getForwardKinematics(q, tcp_offset) sends 12 values on a 6-value recipe,
    # which a controller drops: the call would wait 300 s; the default form is sound)
    fk = ready.getForwardKinematics()
    np.testing.assert_allclose(pose_matrix(fk), dh_fk(q), atol=1e-6)
    ik = ready.getInverseKinematics(fk, (np.array(q) + 0.05).tolist())
    np.testing.assert_allclose(dh_fk(ik), dh_fk(q), atol=1e-5)
    assert ready.isJointsWithinSafetyLimits(q)
    outside = list(q)
    outside[2] = ELBOW_LIMIT + 0.1  # the profile's elbow limit
    assert not ready.isJointsWithinSafetyLimits(outside)
    assert ready.isPoseWithinSafetyLimits(fk)
    assert not ready.isPoseWithinSafetyLimits([2.0, 0.0, 0.5, 0.0, 3.14, 0.0])  # beyond the reach
    # realtime queries: ur_rtde reads the result registers right after sending, so (as on a real
    # controller) a value is one controller tick late: poll until it is there
    model = pin.buildModelFromUrdf(str(UR5E_URDF))
    gravity = pin.computeGeneralizedGravity(model, model.createData(), np.asarray(q))
    assert abs(gravity[1]) > 1.0  # the shoulder holds the arm up
    wait_until(lambda: np.allclose(ready.getJointTorques(), gravity, atol=1e-9), 2, what="gravity torques")
    wait_until(lambda: np.allclose(pose_matrix(ready.getActualToolFlangePose()), dh_fk(q), atol=1e-6), 2,
               what="the flange pose")


def test_speed_slider_scales_motion(sim, ready, recv):
    sim.set_speed_slider(0.5)
    try:
        wait_until(lambda: recv.getTargetSpeedFraction() == 0.5, 2, what="target_speed_fraction 0.5")
        q = np.array(recv.getActualQ())
        assert ready.moveJ((q + [0.6, 0, 0, 0, 0, 0]).tolist(), 1.0, 10.0, True)
        peak = 0.0
        deadline = time.monotonic() + 5
        while ready.getAsyncOperationProgress() >= 0 and time.monotonic() < deadline:
            peak = max(peak, abs(recv.getActualQd()[0]))
            time.sleep(0.002)
        assert 0.3 < peak <= 0.5 + 1e-9  # 1.0 rad/s asked, half of it allowed
        wait_until(lambda: abs(recv.getActualQ()[0] - (q[0] + 0.6)) < 1e-6, 1, what="joint 0 at the slowed moveJ's goal")
    finally:
        sim.set_speed_slider(1.0)


def test_teach_mode_lets_the_hand_move_the_arm(sim, ready, recv):
    q = np.array(recv.getActualQ())
    with pytest.raises(SimulatorError, match="not in teach mode"):
        sim.control({"cmd": "hand", "q": (q + 0.1).tolist()})
    assert ready.teachMode()
    sim.control({"cmd": "hand", "q": (q + [0, 0, 0, 0, 0, 0.1]).tolist(), "speed": 1.0})
    wait_until(lambda: abs(recv.getActualQ()[5] - (q[5] + 0.1)) < 1e-6, 2, what="the hand moving wrist 3")
    assert ready.endTeachMode()
    assert not sim.state()["teach_mode"]


def test_protective_stop_seen_and_movej_refused_until_unlocked(sim, ready, recv, dash):
    sim.control({"cmd": "timings", "unlock_delay_s": 60.0})  # (so a loaded host cannot outlast it)
    sim.inject_stop("protective", cause="collision on the test bench")
    wait_until(recv.isProtectiveStopped, 2, what="isProtectiveStopped")
    assert recv.getSafetyMode() == 3
    assert recv.getSafetyStatusBits() & (1 << 2)
    assert recv.getRobotMode() == 7  # still powered, brakes released
    # the program stopped: as the control interface's own RTDE stream says, which may be a package
    # behind the receive interface's on a loaded host
    wait_until(lambda: not ready.isProgramRunning(), 2, what="the program stopped")
    q = recv.getActualQ()
    t0 = time.monotonic()
    assert not ready.moveJ((np.array(q) + 0.1).tolist())  # refused at once
    assert time.monotonic() - t0 < 3.0  # (not ur_rtde's 300 s wait for a program that runs)
    np.testing.assert_allclose(recv.getActualQ(), q, atol=1e-12)
    with pytest.raises(RuntimeError, match="Cannot unlock protective stop until 60s after occurrence"):
        dash.unlockProtectiveStop()  # a real controller refuses within 5 s of the stop
    sim.control({"cmd": "timings", "unlock_delay_s": 0.0})
    dash.unlockProtectiveStop()
    wait_until(lambda: recv.getSafetyMode() == 1, 2, what="safety NORMAL after unlock")
    ready.reuploadScript()
    wait_until(ready.isProgramRunning, 5, what="the script running again")
    assert ready.moveJ((np.array(q) + [0.05, 0, 0, 0, 0, 0]).tolist())


def test_motion_beyond_a_joint_limit_is_a_protective_stop(sim, ready, recv, dash):
    q = np.array(recv.getActualQ())
    assert ready.speedJ([0, 0, 1.0, 0, 0, 0], 5.0, 0.0)  # the elbow runs into its limit
    wait_until(recv.isProtectiveStopped, 5, what="a protective stop at the elbow's limit")
    assert recv.getActualQ()[2] == pytest.approx(ELBOW_LIMIT)
    assert "joint 2" in sim.state()["stop_cause"]
    dash.unlockProtectiveStop()
    # the input register still says speedJ: a re-uploaded script would play it again (as the
    # controller's would); any command while the program is stopped makes ur_rtde clear it, over
    # RTDE, while the script goes over port 30003: wait for the clear before uploading
    assert sim.state()["command"] == 9
    assert not ready.speedStop(5.0)
    wait_until(lambda: sim.state()["command"] == 0, 2, what="the command register cleared")
    ready.reuploadScript()
    wait_until(ready.isProgramRunning, 5, what="the script running again")
    assert ready.moveJ(q.tolist(), 3.0, 10.0)


def test_safeguard_stop_pauses_and_resumes(sim, ready, recv):
    sim.inject_stop("safeguard")
    wait_until(lambda: recv.getSafetyMode() == 5 and recv.getRuntimeState() == 4, 2,
               what="safeguard stop: runtime PAUSED")
    q = np.array(recv.getActualQ())
    assert not ready.moveJ((q + 0.1).tolist())  # the program cannot run a move while paused
    sim.release("safeguard")
    wait_until(lambda: recv.getSafetyMode() == 1 and recv.getRuntimeState() == 2, 2, what="resumed")
    # the control interface learns it from its own RTDE link, a package after the receive link
    wait_until(ready.isProgramRunning, 2, what="the control interface seeing the program run")


def test_safeguard_release_resumes_the_interrupted_servo_stream(sim, ready, recv):
    # what UR users report as "a fast jump on resume": the program continues the servoj it was
    # in, toward the last target streamed before the stop
    q = np.array(recv.getActualQ())
    target = q + [0.4, 0, 0, 0, 0, 0]
    sim.set_speed_slider(0.1)  # a slow chase (0.31 rad/s), so the stop surely lands part way
    try:
        assert ready.servoJ(target.tolist(), 0.5, 0.5, 0.002, 0.1, 300)
        sim.inject_stop("safeguard")
        wait_until(lambda: recv.getRuntimeState() == 4, 2, what="paused by the safeguard stop")
        held = recv.getActualQ()[0]
        assert held < target[0] - 0.1  # stopped part way
        with pytest.raises(AssertionError):
            wait_until(lambda: recv.getActualQ()[0] != held, 0.3, what="no motion while paused")
        sim.release("safeguard")
        wait_until(lambda: abs(recv.getActualQ()[0] - target[0]) < 1e-3, 4, what="the old target reached on resume")
        assert ready.servoStop(10.0)
    finally:
        sim.set_speed_slider(1.0)


def test_emergency_stop_powers_off_until_released_and_powered_on(sim, ready, recv, dash, powered):
    sim.inject_stop("robot_estop")
    wait_until(recv.isEmergencyStopped, 2, what="isEmergencyStopped")
    assert recv.getRobotMode() == 3  # POWER_OFF
    assert recv.getSafetyStatusBits() & (1 << 6 | 1 << 7) == (1 << 6 | 1 << 7)
    dash.powerOn()  # refused while the button is pressed
    with pytest.raises(AssertionError):
        wait_until(lambda: recv.getRobotMode() != 3, 0.4, what="no power while e-stopped")
    sim.release("robot_estop")
    powered()
    assert recv.getSafetyMode() == 1


def test_fault_needs_restart_safety(sim, recv, dash, powered):
    sim.inject_stop("fault", cause="joint 3 encoder mismatch")
    wait_until(lambda: recv.getSafetyMode() == 9, 2, what="safety mode FAULT")
    assert recv.getRobotMode() == 3  # powered off
    assert recv.getSafetyStatusBits() & (1 << 9)
    assert dash.safetystatus() == "Safetystatus: FAULT"
    with pytest.raises(SimulatorError, match="'restart safety' clears it"):
        sim.release("fault")  # no button clears a fault
    dash.restartSafety()
    wait_until(lambda: recv.getSafetyMode() == 1, 2, what="safety NORMAL after restart safety")
    powered()


def test_io_interface_sets_outputs_and_the_speed_slider(sim, recv):
    io = rtde_io.RTDEIOInterface(sim.host)
    try:
        assert io.setStandardDigitalOut(3, True)
        wait_until(lambda: recv.getActualDigitalOutputBits() == 1 << 3, 2, what="digital output 3 on")
        assert io.setSpeedSlider(0.25)
        wait_until(lambda: recv.getTargetSpeedFraction() == 0.25, 2, what="the speed slider at 25 %")
        assert io.setSpeedSlider(1.0)
        wait_until(lambda: recv.getTargetSpeedFraction() == 1.0, 2, what="the speed slider back at 100 %")
    finally:
        io.disconnect()


def test_watchdog_stops_the_program_when_inputs_stop(ready, recv):
    # a command-register write at least every 500 ms, or it stops (2 Hz: a loaded host's scheduling
    # hiccup between two kicks must not stop it; 4 Hz did once at load 10)
    assert ready.setWatchdog(2.0)
    for _ in range(25):
        assert ready.kickWatchdog()
        time.sleep(0.02)
    assert ready.isProgramRunning()  # kicked every 20 ms: still running
    t0 = time.monotonic()
    wait_until(lambda: not ready.isProgramRunning(), 3, what="the watchdog stopping the program")
    assert time.monotonic() - t0 > 0.4  # not before its 500 ms
    wait_until(lambda: recv.getRuntimeState() == 1, 1, what="runtime state STOPPED on the receive link")
    ready.reuploadScript()
    wait_until(ready.isProgramRunning, 5, what="the script running again, without a watchdog")
    time.sleep(0.1)
    assert ready.isProgramRunning()


def test_link_loss_seen_by_isconnected_then_reconnect(sim, control, recv):
    # (last tests of the module: the control interface is not reconnected in this process; its
    # reconnect() after a link loss was seen to corrupt the heap of ur_rtde 1.6.5, see report)
    assert recv.isConnected() and control.isConnected()
    sim.link_loss(1.5)
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection((sim.host, 30004), timeout=1).close()  # refused while down
    socket.create_connection((sim.host, 29999), timeout=1).close()  # only RTDE was cut
    wait_until(lambda: not recv.isConnected(), 2, what="receive isConnected() False after the link loss")
    wait_until(lambda: not control.isConnected(), 2, what="control isConnected() False after the link loss")
    wait_until(lambda: _try(recv.reconnect), 5, interval=0.1, what="reconnect after the link is back")
    assert recv.isConnected()
    t0 = recv.getTimestamp()
    wait_until(lambda: recv.getTimestamp() > t0, 2, what="data flowing again")
    assert recv.getRuntimeState() == 2  # the program kept running on the controller


def test_controller_restart_drops_everything_and_comes_back_powered_off(sim, recv):
    sim.restart(0.3)
    wait_until(lambda: not recv.isConnected(), 2, what="the link dropped by the restart")
    wait_until(lambda: _try(recv.reconnect), 5, interval=0.1, what="reconnect after the reboot")
    t0 = recv.getTimestamp()
    wait_until(lambda: recv.getTimestamp() > t0, 2, what="data flowing after the reboot")
    assert recv.getRobotMode() == 3  # POWER_OFF
    assert recv.getRuntimeState() == 1  # no program
    assert recv.getSafetyMode() == 1


def test_cb3_streams_at_125_hz():
    sim = simulator_class("ur").from_profile(ur_profile(series="cb3"))
    sim.start()
    try:
        r = rtde_receive.RTDEReceiveInterface(sim.host)
        try:
            stamps = set()
            wait_until(lambda: stamps.add(round(r.getTimestamp(), 4)) or len(stamps) >= 6, 3, interval=0.001,
                       what="six data packages")
            steps = np.diff(sorted(stamps))
            assert np.min(steps) == pytest.approx(0.008, abs=1e-6)  # one package per 8 ms tick
        finally:
            r.disconnect()
    finally:
        sim.stop()
    assert not sim.running


def test_an_address_in_use_is_refused_naming_it(sim):
    other = simulator_class("ur").from_profile(ur_profile(), host=sim.host)
    with pytest.raises(SimulatorError, match=rf"cannot bind {re.escape(sim.host)}:\d+"):
        other.start(timeout_s=10)
    assert not other.running


def test_a_profile_without_six_joints_is_refused():
    with pytest.raises(SimulatorError, match="has 6 joints, the profile has 5"):
        simulator_class("ur").from_profile(ur_profile(n_joints=5))


def _try(fn) -> bool:
    try:
        return bool(fn())
    except RuntimeError:
        return False


def test_the_tool_port_relays_raw_bytes_to_the_serial_line_behind_the_flange(tmp_path):
    """``tool_link``: TCP 54321 (UR's tool communication) carries raw bytes both ways to the serial
    device behind the tool connector (here a bare pty, where a Robotiq simulator sits under
    --sim), reached with pyserial's ``socket://`` URL as the gripper's backend does; one client
    at a time; a link loss of the port ``tool`` drops it."""
    import select as _select

    import serial

    from crtk_bridge.sim.loopback import free_loopback_host
    from crtk_bridge.sim.pty import PtyPort, line_baud
    from crtk_bridge.sim.ur import PORTS, TOOL_PORT, URController

    line = PtyPort(link=tmp_path / "ttyTOOL")
    line.open()
    ctl = URController(free_loopback_host([*PORTS.values(), TOOL_PORT]), tool_link=line.path,
                       control=str(tmp_path / "ur.ctl"))
    ctl.start()
    try:
        def on_line(n: int) -> bytes:
            got = b""
            deadline = time.monotonic() + 5
            while len(got) < n and time.monotonic() < deadline:
                if _select.select([line.master_fd], [], [], 0.1)[0]:
                    got += os.read(line.master_fd, 256)
            return got

        port = serial.serial_for_url(f"socket://{ctl.host}:{TOOL_PORT}", timeout=2)
        request = bytes.fromhex("0904 07d0 0003 b1ee".replace(" ", ""))  # an FC4 read, as on RS-485
        port.write(request)
        assert on_line(len(request)) == request
        assert line_baud(line.master_fd) == 115200  # the tool's serial rate
        reply = bytes(range(256)) * 2  # every byte value, unchanged
        os.write(line.master_fd, reply)
        assert port.read(len(reply)) == reply
        wait_until(lambda: ctl.state()["tool_clients"] == 1, 5, what="the tool client counted")
        second = socket.create_connection((ctl.host, TOOL_PORT), timeout=2)
        assert second.recv(16) == b""  # one client at a time: the second is closed
        second.close()
        assert ctl.control({"cmd": "link_loss", "duration_s": 0.3, "ports": ["tool"]})["ok"]
        wait_until(lambda: ctl.state()["tool_clients"] == 0, 5, what="the tool client dropped")
        port.close()
        def reconnected():
            try:
                p = serial.serial_for_url(f"socket://{ctl.host}:{TOOL_PORT}", timeout=2)
            except serial.SerialException:
                return None
            return p
        port = wait_until(reconnected, 5, what="the tool port back after the link loss")
        port.write(b"\x09\x10")
        assert on_line(2) == b"\x09\x10"
        port.close()
    finally:
        ctl.stop()
        line.close()


def test_the_arms_tcp_pose_and_speed_are_recomputed_only_when_their_inputs_change():
    """Every tick publishes the TCP pose and twist; an arm at rest (powered off, or holding) does
    not redo the kinematics each tick (the simulator's largest share of a tick, and every test on
    the UR pays it): they are made again only when the joints, their speeds or the TCP offset
    changed, and are then exactly what the kinematics give."""
    from crtk_bridge.sim.ur_robot import Limits, Timings, URRobot, se3_to_pose

    q0 = np.array([0.1, -1.4, 1.5, -1.6, -1.5, 0.3])
    r = URRobot(q0, Limits(), Timings(), clock=time.monotonic)
    calls = {"fk": 0, "jacobian": 0}
    fk, jacobian = r.kin.fk, r.kin.jacobian

    def counting(name, f):
        def call(*args):
            calls[name] += 1
            return f(*args)
        return call

    r.kin.fk, r.kin.jacobian = counting("fk", fk), counting("jacobian", jacobian)
    first = r.tcp_pose()
    for _ in range(10):  # at rest: ten ticks, one forward kinematics, no Jacobian
        r.step(0.002)
        assert r.tcp_pose() == first and r.tcp_speed() == [0.0] * 6
    assert calls == {"fk": 1, "jacobian": 0}, calls
    r.set_joints(q0 + 0.01, np.full(6, 0.5))  # moved, moving
    pose, speed = r.tcp_pose(), r.tcp_speed()
    assert pose == se3_to_pose(fk(q0 + 0.01)) and pose != first
    assert np.allclose(speed, jacobian(q0 + 0.01) @ np.full(6, 0.5))
    assert r.tcp_speed() == speed and calls == {"fk": 2, "jacobian": 1}, calls
    r.kin.tcp = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.1]))  # set_tcp: the same joints, another TCP
    assert r.tcp_pose() == se3_to_pose(fk(q0 + 0.01)) != pose
    assert calls["fk"] == 3
    r.tcp_pose().append(1.0)  # a caller's list is its own
    assert len(r.tcp_pose()) == 6

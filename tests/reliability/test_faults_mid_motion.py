"""Reliability: every fault the simulators inject, injected mid-motion on every simulated robot
that offers it (``fault:<kind>`` capabilities; the device error is the conformance row's).

For each fault kind (``crtk_bridge/sim/bus.py``: silent, corrupt, error_bits, freeze; the row's
device error (a servo's overload bit, a CiA 402 drive's EMCY); and unplug of a serial bus) while a
move runs: the robot goes to FAULT with an error event naming the right cause (code, joint,
register), torque goes off on every device (for an unplugged bus: once the bus is back, with
``torque_off_confirmed``), the interrupted move ends (its idle edge comes), and after recovery
(clear the fault, ``enable``) nothing moves until a new command: the arm holds where it is, with
no goal, and only a new move makes it move again.

One daemon per robot serves all fault kinds (module scope): each test starts from a recovered,
ENABLED robot and leaves one, so the faults do not depend on each other's order.
"""

from __future__ import annotations

import shutil
import time
import tempfile
from pathlib import Path

import numpy as np
import pytest

from crtk_bridge.client import CommandError, connect
from crtk_bridge.profile import load_profile

from ..conftest import DaemonProcess, start_sim_daemon, wait_until

pytestmark = pytest.mark.requires()  # every simulated robot, each fault where it is offered

FAULT_JOINT = 2  # the five-joint arms' elbow_flex (id 3 on both); an arm's last if it has fewer
# the STS3215's Status bits are live (clear_faults clears them); a Dynamixel hardware error is
# latched until a REBOOT, which enable performs (see tests/test_e2e_faults.py)
SERVO_ERROR_REGISTER = {"feetech": "Status", "dynamixel": "Hardware_Error_Status"}
# fault kind -> the capability it needs (None: every robot's row has it)
FAULTS = {"silent": "fault:silent", "corrupt": "fault:corrupt", "device_error": None,
          "freeze": "fault:freeze", "unplug": "servo_bus"}


class Rig:
    def __init__(self, daemon: DaemonProcess):
        self.daemon = daemon
        self.bot = daemon.robot
        self.sim = self.bot.sim(daemon.sim_control_path())
        self.robot = connect(socket=str(daemon.socket_path))
        self.arm = self.robot.device(self.bot.arm)

    def torque(self, value: int) -> bool:
        return all(v == bool(value) for v in self.bot.torque(self.sim).values())

    def recover(self) -> None:
        """Clear every injected fault and enable (FAULT -> ENABLED retries; a latched Dynamixel
        error is cleared by the REBOOT enable performs)."""
        def attempt() -> bool:
            self.sim.set_unplugged(False)
            self.sim.clear_faults()
            if not self.arm.is_enabled():
                try:
                    self.arm.enable(5.0)
                except CommandError:  # a loaded host: a bus_timeout right after enable; again
                    return False
            return self.arm.is_enabled() and self.torque(1)

        wait_until(attempt, 20, interval=0.1, what="recovered: ENABLED, torque on every servo")


@pytest.fixture(scope="module")
def rig(sim_robot):
    tmp = Path(tempfile.mkdtemp(prefix="crtk-rel-"))
    bot = sim_robot
    daemon = start_sim_daemon(bot, tmp)
    try:
        r = Rig(daemon)
        yield r
        r.robot.close()
    finally:
        daemon.stop()
        shutil.rmtree(tmp, ignore_errors=True)


def still(r: Rig, window_s: float = 0.3) -> np.ndarray:
    """Every device's goal and present position over an observation window; asserts that none
    changed by more than a 4096-tick servo's tick (quantisation; in the device's own units) and
    returns the measured arm position."""
    bot, row = r.bot, r.bot.row
    ids = list(bot.servo_ids)
    tick = {i: max(1, round(abs(bot.counts_per_rad[i]) * 2 * np.pi / 4096)) for i in ids}

    def sample() -> dict:
        return {i: (row.goal(r.sim, int(i)), row.present(r.sim, int(i))) for i in ids}

    first = sample()
    samples = [first]
    end = time.monotonic() + window_s
    while time.monotonic() < end:  # the observation window of "nothing moves"
        samples.append(sample())
        time.sleep(0.02)
    for s in samples:
        for i in ids:
            assert abs(s[i][0] - first[i][0]) <= tick[i], (i, first[i], s[i])
            assert abs(s[i][1] - first[i][1]) <= 2 * tick[i], (i, first[i], s[i])
    return r.arm.measured_jp()[0]


@pytest.mark.parametrize("kind", list(FAULTS))
def test_fault_mid_motion(rig, kind):
    r = rig
    bot = r.bot
    need = FAULTS[kind]
    if need is not None and need not in bot.capabilities:
        pytest.skip(f"{bot.profile.name}: lacks {need}")
    r.recover()
    e = bot.j(FAULT_JOINT)
    sid = int(bot.arm_ids[e])
    joint = bot.joint_names[e]
    inject, code = {
        "silent": (lambda: r.sim.set_fault(sid, "silent"), bot.row.silent_code),
        "corrupt": (lambda: r.sim.set_fault(sid, "corrupt"), "bus_corrupt"),
        "device_error": (lambda: bot.row.inject_error(r.sim, sid), bot.row.error_code),
        "freeze": (lambda: r.sim.set_fault(sid, "freeze"), "tracking_error"),
        "unplug": (lambda: r.sim.set_unplugged(True), "bus_timeout"),
    }[kind]
    if kind == "unplug":
        joint = bot.joint_names[0]  # the first servo asked
    if kind == "device_error" and not bot.row.error_names_joint:
        joint = None  # the whole arm's error (a UR protective stop)

    # 0.1 rad on an arm; on a gripper alone (one joint in metres) the same share of its range as
    # the suite's goals are (SimRobot.load: a third of the range per rad)
    if "arm" in bot.capabilities:
        step, tol = 0.1, 0.02
    else:
        lim = load_profile(bot.profile).joints[e].limits
        step = 0.1 * (lim.position_max - lim.position_min) / 3.0
        tol = 0.5 * step

    # a move that takes the joint far (from wherever the previous test left it)
    here = r.arm.measured_jp()[0]
    goal = max((bot.goals["wide"], bot.goals["far"]), key=lambda g: abs(g[e] - here[e]))
    mark = r.robot.connection.event_count
    h = r.arm.move_jp(goal)
    start = bot.row.present(r.sim, sid)
    wait_until(lambda: bot.row.present(r.sim, sid) != start, 5, what="joint moving in the simulator")
    inject()

    # FAULT, with the cause
    ev = r.robot.wait_for_event(code, 5.0, kind="error", since=mark)
    assert ev is not None, r.robot.connection.events_since(mark)
    assert ev.data["ns"] == bot.name and ev.data.get("joint") == joint, ev.data  # a FAULT is robot-wide
    if kind == "device_error" and "fault:error_bits" in bot.capabilities:  # the servos' overload bit
        assert ev.data["register"] == SERVO_ERROR_REGISTER[bot.backend] and ev.data["value"] == 0x20
        assert "overload" in ev.data["message"]
    wait_until(r.arm.is_fault, 2, what="FAULT state")
    assert h.wait(timeout=2.0)  # the interrupted move ended: nobody waits on it
    with pytest.raises(CommandError) as err:
        r.arm.move_jp(goal)
    assert err.value.code == "invalid_state"

    # torque off on every device (an unplugged bus, a node off the bus that hears nothing: once it
    # answers again, and the daemon says so)
    deaf = kind == "silent" and not bot.row.silent_hears
    if kind == "unplug":
        assert "torque off not confirmed" in ev.data["message"]
        r.sim.set_unplugged(False)
    if deaf:
        wait_until(lambda: r.robot.wait_for_event("torque_off_unconfirmed", 0.0, kind="error", since=mark), 5,
                   what="torque_off_unconfirmed")
        r.sim.clear_faults()
    if kind == "unplug" or deaf:
        wait_until(lambda: r.robot.wait_for_event("torque_off_confirmed", 0.0, kind="status", since=mark), 3,
                   what="torque_off_confirmed")
    wait_until(lambda: r.torque(0), 3, what="torque off on every device")
    stopped = r.arm.measured_jp()[0]
    assert np.abs(stopped - goal).max() > step  # it was stopped on the way, not at the goal

    # recovery: nothing moves until commanded; the old move does not resume
    r.recover()
    assert r.arm.is_enabled() and not r.arm.is_busy()
    held = still(r)
    assert r.arm.goal_js()[3] == 0.0  # no goal after enable
    sp, ts = r.arm.setpoint_jp()
    assert ts == 0.0 or np.allclose(sp, held, atol=tol)  # holding where it is
    assert np.abs(held - goal).max() > step
    # ...until a command: a small move is followed
    target = held + bot.vec((0, step if held[0] < 0 else -step))
    assert r.arm.move_jp(target).wait(timeout=5.0)
    wait_until(lambda: abs(r.arm.measured_jp()[0][0] - target[0]) < tol, 3, what="small move after recovery")
    assert r.arm.is_enabled()

"""Reliability: every fault the simulators inject, injected mid-motion on both simulated robots.

For each fault kind (``crtk_bridge/sim/bus.py``: silent, corrupt, error_bits, freeze; and unplug of
the whole bus) while a move runs: the robot goes to FAULT with an error event naming the right
cause (code, joint, register), torque goes off on every servo (for an unplugged bus: once the bus
is back, with ``torque_off_confirmed``), the interrupted move ends (its idle edge comes), and after
recovery (clear the fault, ``enable``) nothing moves until a new command: the arm holds where it
is, with no goal, and only a new move makes it move again.

One daemon per robot serves all fault kinds (module scope): each test starts from a recovered,
ENABLED robot and leaves one, so the faults do not depend on each other's order.
"""

from __future__ import annotations

import math
import shutil
import time
import tempfile
from pathlib import Path

import numpy as np
import pytest

from crtk_bridge.client import CommandError, connect
from crtk_bridge.sim.control import control_request

from ..conftest import DaemonProcess, wait_until

RAD_PER_TICK = 2 * math.pi / 4096
FAULT_SERVO = "elbow_flex"  # id 3 on both robots
# the STS3215's Status bits are live (clear_faults clears them); a Dynamixel hardware error is
# latched until a REBOOT, which enable performs (see tests/test_e2e_faults.py)
SERVO_ERROR_REGISTER = {"feetech": "Status", "dynamixel": "Hardware_Error_Status"}

# fault kind -> (control request to inject it, error code expected, joint the event names)
FAULTS = {
    "silent": ({"cmd": "fault", "kind": "silent"}, "bus_timeout", FAULT_SERVO),
    "corrupt": ({"cmd": "fault", "kind": "corrupt"}, "bus_corrupt", FAULT_SERVO),
    "error_bits": ({"cmd": "fault", "kind": "error_bits", "bits": 0x20}, "servo_error", FAULT_SERVO),
    "freeze": ({"cmd": "fault", "kind": "freeze"}, "tracking_error", FAULT_SERVO),
    "unplug": ({"cmd": "unplug", "on": True}, "bus_timeout", "shoulder_pan"),  # the first servo asked
}


class Rig:
    def __init__(self, daemon: DaemonProcess):
        self.daemon = daemon
        self.bot = daemon.robot
        self.sim = daemon.sim_control_path()
        self.robot = connect(socket=str(daemon.socket_path))
        self.arm = self.robot.device(self.bot.arm)

    def req(self, **request) -> dict:
        reply = control_request(self.sim, request)
        assert reply.get("ok"), reply
        return reply

    def servos(self) -> dict:
        return self.req(cmd="dump")["servos"]

    def torque(self, value: int) -> bool:
        return all(s["torque_enable"] == value for s in self.servos().values())

    def recover(self) -> None:
        """Clear every injected fault and enable (FAULT -> ENABLED retries; a latched Dynamixel
        error is cleared by the REBOOT enable performs)."""
        def attempt() -> bool:
            self.req(cmd="unplug", on=False)
            self.req(cmd="clear_faults")
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
    daemon = DaemonProcess(["--profile", str(bot.profile), "--sim"], tmp / "d.sock", tmp / "d.log", robot=bot)
    try:
        r = Rig(daemon)
        yield r
        r.robot.close()
    finally:
        daemon.stop()
        shutil.rmtree(tmp, ignore_errors=True)


def still(r: Rig, window_s: float = 0.3) -> np.ndarray:
    """Every servo's Goal_Position and Present_Position over an observation window; asserts that
    none changed by more than a tick (quantisation) and returns the measured arm position."""
    ids = list(r.bot.servo_ids)
    first = r.servos()
    samples = [first]
    end = time.monotonic() + window_s
    while time.monotonic() < end:  # the observation window of "nothing moves"
        samples.append(r.servos())
        time.sleep(0.02)
    for s in samples:
        for i in ids:
            assert abs(s[i]["goal_position"] - first[i]["goal_position"]) <= 1, (i, first[i], s[i])
            assert abs(s[i]["present_position"] - first[i]["present_position"]) <= 2, (i, first[i], s[i])
    return r.arm.measured_jp()[0]


@pytest.mark.parametrize("kind", list(FAULTS))
def test_fault_mid_motion(rig, kind):
    r = rig
    bot = r.bot
    r.recover()
    inject, code, joint = FAULTS[kind]
    sid = bot.servo_id[FAULT_SERVO]
    elbow = bot.joint_names.index(FAULT_SERVO)

    # a move that takes the elbow far (from wherever the previous test left it)
    here = r.arm.measured_jp()[0]
    goal = max((bot.goals["wide"], bot.goals["far"]), key=lambda g: abs(g[elbow] - here[elbow]))
    mark = r.robot.connection.event_count
    h = r.arm.move_jp(goal)
    wait_until(lambda: r.servos()[str(sid)]["present_velocity"] != 0, 5, what="elbow moving in the simulator")
    r.req(**(dict(inject, id=sid) if inject["cmd"] == "fault" else inject))

    # FAULT, with the cause
    ev = r.robot.wait_for_event(code, 5.0, kind="error", since=mark)
    assert ev is not None, r.robot.connection.events_since(mark)
    assert ev.data["ns"] == bot.arm.split("/")[0] and ev.data.get("joint") == joint, ev.data
    if kind == "error_bits":
        assert ev.data["register"] == SERVO_ERROR_REGISTER[bot.backend] and ev.data["value"] == 0x20
        assert "overload" in ev.data["message"]
    wait_until(r.arm.is_fault, 2, what="FAULT state")
    assert h.wait(timeout=2.0)  # the interrupted move ended: nobody waits on it
    with pytest.raises(CommandError) as err:
        r.arm.move_jp(goal)
    assert err.value.code == "invalid_state"

    # torque off on every servo (an unplugged bus: once it answers again, and the daemon says so)
    if kind == "unplug":
        assert "torque off not confirmed" in ev.data["message"]
        r.req(cmd="unplug", on=False)
        wait_until(lambda: r.robot.wait_for_event("torque_off_confirmed", 0.0, kind="status", since=mark), 3,
                   what="torque_off_confirmed")
    wait_until(lambda: r.torque(0), 3, what="torque off on every servo")
    stopped = r.arm.measured_jp()[0]
    assert np.abs(stopped - goal).max() > 0.1  # it was stopped on the way, not at the goal

    # recovery: nothing moves until commanded; the old move does not resume
    r.recover()
    assert r.arm.is_enabled() and not r.arm.is_busy()
    held = still(r)
    assert r.arm.goal_js()[3] == 0.0  # no goal after enable
    sp, ts = r.arm.setpoint_jp()
    assert ts == 0.0 or np.allclose(sp, held, atol=0.02)  # holding where it is
    assert np.abs(held - goal).max() > 0.1
    # ...until a command: a small move is followed
    target = held + bot.vec(shoulder_pan=0.1 if held[0] < 0 else -0.1)
    assert r.arm.move_jp(target).wait(timeout=5.0)
    wait_until(lambda: abs(r.arm.measured_jp()[0][0] - target[0]) < 0.02, 3, what="small move after recovery")
    assert r.arm.is_enabled()

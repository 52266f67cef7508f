"""Lifecycle transitions across cycles and the device-status table, on the controller with a
fake actuator whose enable takes as many cycles as a test says."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from crtk_bridge.core.actuator import (
    Actuator,
    Capabilities,
    CommandMode,
    DeviceStatus,
    Clock as TraitClock,
    Fault,
    Lifecycle,
    Traits,
    effective_period_s,
)
from crtk_bridge.core.control import Controller
from crtk_bridge.core.cycle import CycleRunner
from crtk_bridge.core.state import DEVICE_STATUS, OperatingState
from crtk_bridge.errors import BackendError
from crtk_bridge.profile import load_profile

from .test_controller import Clock, make_rig

PROFILE = load_profile("profiles/so101.yaml")


class SlowActuator(Actuator):
    """Enable takes ``enable_cycles`` steps; every bus action is logged in ``bus``."""

    CAPS = Capabilities(position=True)

    def __init__(self, profile, enable_cycles=5, **traits):
        super().__init__(profile)
        self.enable_cycles = enable_cycles
        self.bus: list[str] = []
        self.torque = False
        self.pos = np.linspace(-0.2, 0.2, self.n)
        self.fail_at: int | None = None
        self._traits_kw = {"transition_timeouts_s": {Lifecycle.ENABLE: 1.0, Lifecycle.DISABLE: 1.0}, **traits}
        self.open()  # no bus: open (its traits final) once built

    def _open_hook(self):
        pass

    def _traits_hook(self):
        return Traits(joints=(self.CAPS,) * self.n, **self._traits_kw)

    def _close_hook(self):
        pass

    def _enable_steps(self, feedback):
        try:
            for k in range(self.enable_cycles):
                if self.fail_at == k:
                    raise BackendError("so101: joint 'gripper' (id 6) did not confirm Torque_Enable")
                self.bus.append(f"enable-step-{k}")
                yield
            self.torque = True
        finally:
            self.bus.append("enable-finally")

    def _pause_steps(self):
        for _ in range(3):
            self.bus.append("pause-step")
            yield

    disable_cycles = 0  # DISABLE's confirmation steps after its torque off (a serial bus: one per servo)

    disable_fails = False  # DISABLE's first step raises (the bus does not answer)

    def _disable_steps(self):
        if self.disable_fails:
            raise BackendError("so101: joint 'gripper' (id 6) did not confirm Torque_Enable = 0")
        self.bus.append("torque-off")
        self.torque = False
        for _ in range(self.disable_cycles):
            self.bus.append("torque-off-confirmed")
            yield

    def _read(self, fb):
        self.bus.append("read")
        fb.position[:] = self.pos
        fb.stamp += 0.005
        return None

    def _write(self, cmd):
        self.bus.append("write")
        return None


@pytest.fixture
def rig():
    return make_slow_rig(SlowActuator(PROFILE))


def make_slow_rig(act):
    """(controller, actuator, clock, cycle(n), send(cmd, ns, **data) -> id, replies(id)) around
    ``act``; unlike test_controller's rig, replies may come cycles after the request."""
    clock = Clock()
    c = Controller(PROFILE, act, clock, effective_period_s(PROFILE, act))
    ids = itertools.count(1)
    fb = act.new_feedback()

    runner = CycleRunner(act, c.dt, clock=clock, sleep=clock.sleep)  # the loop's cycle, on the fake clock

    def cycle(n=1):
        for _ in range(n):
            runner.cycle(c)

    def send(cmd, ns=None, **data):
        rid = next(ids)
        c.handle({"id": rid, "cmd": cmd, "ns": ns, "data": data})
        return rid

    def replies(rid):
        return [m for m in c.outbox if m.get("id") == rid]

    cycle()
    return c, act, clock, cycle, send, replies


def test_enable_over_cycles_keeps_reading_stays_disabled_busy_and_replies_once(rig):
    c, act, clock, cycle, send, replies = rig
    rid = send("enable")
    assert replies(rid) == [] and c.state is OperatingState.DISABLED and c.is_busy
    busy = [m["data"] for m in c.outbox if m.get("event") == "operating_state"][-1]
    assert busy["is_busy"] and busy["state"] == "DISABLED"
    for _ in range(3):
        act.bus.clear()
        cycle()
        # every cycle reads first, then advances the transition by exactly one step; no writes
        assert act.bus[0] == "read" and sum(b.startswith("enable-step") for b in act.bus) == 1
        assert "write" not in act.bus
        assert c.state is OperatingState.DISABLED and replies(rid) == []
    cycle(3)
    (reply,) = replies(rid)
    assert reply["ok"] and reply["data"]["state"] == "ENABLED" and not reply["data"]["is_busy"]
    assert c.state is OperatingState.ENABLED and not c.is_busy and act.torque
    np.testing.assert_allclose(c.command.position, act.pos)  # holds where it is
    cycle(10)
    assert len(replies(rid)) == 1


def test_one_bus_read_per_cycle_around_an_enable(rig):
    """The pose an enable holds is the cycle's own read after torque on (the backend's ENABLE
    ends in that cycle): the controller reads nothing itself, so every cycle, the one the enable
    ends in too, has exactly one read (on CANopen each read is a SYNC's worth: one per cycle)."""
    c, act, clock, cycle, send, replies = rig
    rid = send("enable")
    reads = []
    for _ in range(20):
        act.bus.clear()
        cycle()
        reads.append(act.bus.count("read"))
        if replies(rid):
            break
    for _ in range(3):
        act.bus.clear()
        cycle()
        reads.append(act.bus.count("read"))
    (reply,) = replies(rid)
    assert reply["ok"] and reads == [1] * len(reads)


def test_second_enable_joins_and_both_get_one_reply(rig):
    c, act, clock, cycle, send, replies = rig
    a, b = send("enable"), send("enable")
    cycle(8)
    assert len(replies(a)) == 1 and len(replies(b)) == 1 and replies(b)[0]["ok"]


def test_disable_aborts_a_running_enable(rig):
    c, act, clock, cycle, send, replies = rig
    rid = send("enable")
    cycle(2)
    d = send("disable")
    (r,) = replies(rid)
    assert not r["ok"] and r["error"]["code"] == "aborted" and "aborted by disable" in r["error"]["message"]
    assert "enable-finally" in act.bus and not act.torque  # the steps' finally ran; torque off
    assert replies(d)[0]["ok"] and c.state is OperatingState.DISABLED and not c.is_busy


def test_enable_during_a_faults_torque_off_is_handled_when_it_ends(rig):
    """The torque off of a fault confirms one servo per cycle (nobody waits on it): an enable
    sent meanwhile (the fault was cleared) is not refused as "disable in progress"; it runs when
    the torque off has ended, and its one reply comes then."""
    c, act, clock, cycle, send, replies = rig
    act.disable_cycles = 6
    send("enable")
    cycle(8)
    assert c.state is OperatingState.ENABLED
    c.enter_fault(Fault("bus_timeout", "so101: no reply", transient=False))
    assert c.is_busy and not act.torque  # the torque off confirms over the next cycles
    rid = send("enable")
    assert replies(rid) == [] and c.state is OperatingState.FAULT
    cycle(6)
    assert act.bus.count("torque-off-confirmed") == 6
    cycle(8)
    (r,) = replies(rid)
    assert r["ok"] and c.state is OperatingState.ENABLED and act.torque, r
    enables = [i for i, b in enumerate(act.bus) if b == "enable-step-0"]
    assert enables[-1] > max(i for i, b in enumerate(act.bus) if b == "torque-off-confirmed")


def test_a_client_disable_that_aborts_a_faults_torque_off_then_fails_keeps_it_unconfirmed_and_retries(rig):
    """A client's disable in FAULT aborts the fault's own torque off (still confirming servos);
    when that DISABLE fails, the robot says torque off is unconfirmed (error event, the
    ``torque_unconfirmed`` flag) and retries it once the bus answers, as after the fault's own
    failure; it said nothing and never retried (session 7's review)."""
    c, act, clock, cycle, send, replies = rig
    act.disable_cycles = 6
    send("enable")
    cycle(8)
    c.enter_fault(Fault("bus_timeout", "so101: no reply", transient=False))
    cycle(2)
    assert c.is_busy and not c.torque_unconfirmed  # confirming, one servo a cycle
    act.disable_fails = True
    rid = send("disable")
    (r,) = replies(rid)
    assert not r["ok"] and "disable failed, still FAULT" in r["error"]["message"], r
    assert c.state is OperatingState.FAULT and c.torque_unconfirmed
    (unconfirmed,) = [m["data"] for m in c.outbox if m.get("event") == "error"
                      and m["data"]["code"] == "torque_off_unconfirmed"]
    assert unconfirmed["message"].startswith(f"{c.robot}: torque off not confirmed (") and "gripper" in unconfirmed["message"]
    act.disable_fails = False  # the bus answers again: the retry (at most once a second) confirms
    act.bus.clear()
    clock.t += 1.1
    cycle(10)
    assert act.bus.count("torque-off-confirmed") == 6 and not c.torque_unconfirmed
    assert [m["data"]["code"] for m in c.outbox if m.get("event") == "status"][-1] == "torque_off_confirmed"
    assert c.state is OperatingState.FAULT  # still FAULT: only torque off was retried


def test_transition_beyond_its_time_limit_faults_naming_it(rig):
    c, act, clock, cycle, send, replies = rig
    act.enable_cycles = 10_000
    rid = send("enable")
    cycle(int(1.0 / c.dt) + 5)
    (r,) = replies(rid)
    assert not r["ok"] and r["error"]["code"] == "fault"
    assert "so101: enable did not finish within 1 s" in r["error"]["message"]
    assert c.state is OperatingState.FAULT and not act.torque and "torque-off" in act.bus
    err = [m["data"] for m in c.outbox if m.get("event") == "error"][-1]
    assert err["code"] == "enable_failed" and "enable did not finish" in err["message"]


def test_failed_step_faults_with_the_backends_reason(rig):
    c, act, clock, cycle, send, replies = rig
    act.fail_at = 2
    rid = send("enable")
    cycle(4)
    (r,) = replies(rid)
    assert not r["ok"] and "gripper" in r["error"]["message"] and c.state is OperatingState.FAULT


def test_motion_refused_while_a_transition_runs_and_state_changes_at_its_end(rig):
    c, act, clock, cycle, send, replies = rig
    act.enable_cycles = 0
    send("enable")
    cycle()
    p = send("pause")
    assert c.state is OperatingState.ENABLED and c.is_busy and replies(p) == []
    m = send("servo_jp", "so101", position=[0.0] * 5)
    assert replies(m)[0]["error"]["code"] == "invalid_state" and "pause in progress" in replies(m)[0]["error"]["message"]
    r = send("resume")
    assert replies(r)[0]["error"]["code"] == "invalid_state"  # not valid in ENABLED
    cycle(3)
    assert replies(p)[0]["ok"] and c.state is OperatingState.PAUSED and not c.is_busy


def test_device_status_table_is_total():
    assert set(DEVICE_STATUS) == {(s, d) for s in OperatingState for d in DeviceStatus}


@pytest.mark.parametrize("status,target,code", [
    (DeviceStatus.PAUSED, OperatingState.PAUSED, "device_paused"),
    (DeviceStatus.POWERED_OFF, OperatingState.DISABLED, "device_powered_off"),
    (DeviceStatus.FAULT, OperatingState.FAULT, "servo_error"),
])
def test_device_status_maps_onto_crtk_states(rig, status, target, code):
    c, act, clock, cycle, send, replies = rig
    act.enable_cycles = 0
    send("enable")
    cycle()
    assert c.state is OperatingState.ENABLED
    c.outbox.clear()
    act.report_status(status, Fault("servo_error", "so101: joint 'gripper' reports Overload", joint="gripper",
                                    transient=False) if status is DeviceStatus.FAULT else None)
    cycle()
    assert c.state is target
    ev = [m["data"] for m in c.outbox if m.get("event") in ("error", "warning")]
    assert ev and ev[0]["code"] == code
    if status is DeviceStatus.FAULT:
        assert ev[0]["joint"] == "gripper"
        act.report_status(DeviceStatus.FAULT_CLEARED)
        cycle()
        assert c.state is OperatingState.FAULT  # never leaves FAULT by itself
        assert [m["data"]["code"] for m in c.outbox if m.get("event") == "status"][-1] == "fault_cleared"


def test_a_device_fault_switches_torque_off(rig):
    c, act, clock, cycle, send, replies = rig
    act.enable_cycles = 0
    send("enable")
    cycle()
    act.report_status(DeviceStatus.FAULT, Fault("drive_fault", "so101: drive fault", transient=False))
    cycle()
    assert c.state is OperatingState.FAULT and not act.torque and "torque-off" in act.bus


def test_cyclic_write_backend_is_written_every_cycle_in_every_state():
    c, act, clock, cycle, send, replies = make_slow_rig(SlowActuator(PROFILE, cyclic_write=True))
    act.bus.clear()
    cycle(3)
    assert act.bus.count("write") == 3 and c.state is OperatingState.DISABLED
    assert np.all(c.command.mode == CommandMode.NONE)


def test_effective_period_is_the_hardwares_when_it_paces():
    class Paced(SlowActuator):
        def cycle_period_s(self):
            return 0.002

    assert effective_period_s(PROFILE, SlowActuator(PROFILE)) == pytest.approx(1.0 / PROFILE.loop.rate_hz)
    paced = Paced(PROFILE, clock=TraitClock.DEVICE)
    assert effective_period_s(PROFILE, paced) == pytest.approx(0.002)
    assert Controller(PROFILE, paced, Clock(), effective_period_s(PROFILE, paced)).dt == pytest.approx(0.002)


class HookedActuator(SlowActuator):
    """Logs which lifecycle hooks reached the backend; homes natively over a few cycles."""

    CAPS = Capabilities(position=True, needs_homing=True)

    def __init__(self, profile, enable_cycles=5):
        super().__init__(profile, enable_cycles, native_homing=True)

    def _resume_steps(self):
        self.bus.append("resume")
        yield from ()

    def _fault_reset_steps(self):
        self.bus.append("fault-reset")
        yield

    def _home_steps(self):
        for _ in range(4):
            self.bus.append("home-step")
            yield


def test_pause_resume_fault_reset_and_native_home_reach_the_backend():
    c, act, clock, cycle, req = make_rig(HookedActuator(PROFILE, enable_cycles=1))
    assert not c.is_homed and act.traits.native_homing
    c.handle({"id": 1, "cmd": "enable"})
    cycle(3)
    assert c.state is OperatingState.ENABLED and "fault-reset" not in act.bus
    c.handle({"id": 2, "cmd": "home"})
    assert c.is_busy and not c.is_homed and act.bus.count("home-step") == 1
    cycle(6)
    assert c.is_homed and not c.is_busy and [m for m in c.outbox if m.get("id") == 2][0]["ok"]
    assert act.bus.count("home-step") == 4
    c.handle({"id": 3, "cmd": "pause"})
    cycle(4)
    assert c.state is OperatingState.PAUSED and act.bus.count("pause-step") == 3
    c.handle({"id": 4, "cmd": "resume"})
    assert c.state is OperatingState.ENABLED and "resume" in act.bus
    act.report_status(DeviceStatus.FAULT, Fault("drive_fault", "so101: drive fault", transient=False))
    cycle()
    assert c.state is OperatingState.FAULT
    act.bus.clear()
    c.handle({"id": 5, "cmd": "enable"})
    cycle(4)
    # leaving FAULT: the backend's fault reset first, then its enable
    assert act.bus.index("fault-reset") < act.bus.index("enable-step-0")
    assert c.state is OperatingState.ENABLED


class _MissesReadsAfterTorqueOn(SlowActuator):
    """Misses ``misses`` replies right after torque on (a loaded host), then answers."""

    def __init__(self, profile, misses):
        super().__init__(profile, enable_cycles=2)
        self.misses = misses

    def _read(self, fb):
        if self.torque and self.misses > 0:
            self.misses -= 1
            return Fault("bus_timeout", "so101: no reply from joint 'gripper' (id 6)")
        return super()._read(fb)


@pytest.mark.parametrize("misses, enabled", [(1, True), (2, True), (3, False)])
def test_enable_tolerates_a_missed_read_after_torque_on(misses, enabled):
    """One late reply right after torque on must not fault the robot: the pose it holds comes
    from the next good read; a bus that keeps failing still faults, torque off."""
    c, act, clock, cycle, send, replies = make_slow_rig(_MissesReadsAfterTorqueOn(PROFILE, misses))
    rid = send("enable")
    for _ in range(10):
        if replies(rid):
            break
        cycle()
    (reply,) = replies(rid)
    assert reply["ok"] is enabled
    if enabled:
        assert c.state is OperatingState.ENABLED and act.torque
        cycle()
        np.testing.assert_allclose(c.command.position, act.pos)  # holds where it is
    else:
        assert c.state is OperatingState.FAULT and not act.torque
        assert "no fresh position after torque on" in reply["error"]["message"]


class SwitchingActuator(SlowActuator):
    """Velocity capable; a change of a joint's command mode takes ``switch_cycles`` steps per
    switching joint (a Dynamixel's operating-mode switch), logged in ``bus``."""

    CAPS = Capabilities(position=True, velocity=True)

    def __init__(self, profile, **kw):
        super().__init__(profile, enable_cycles=1, **kw)
        self.device_modes = np.full(self.n, int(CommandMode.POSITION), dtype=np.uint8)
        self.written: list[np.ndarray] = []

    def mode_switch_steps(self, modes):
        todo = [i for i in range(self.n)
                if modes[i] in (CommandMode.POSITION, CommandMode.VELOCITY) and modes[i] != self.device_modes[i]]
        if not todo:
            return None
        self.bus.append("prepare")
        wanted = modes.copy()

        def steps():
            for k, i in enumerate(todo):
                if k:
                    yield
                self.bus.append(f"switch-{i}")
                self.device_modes[i] = wanted[i]
        return steps()

    def _write(self, cmd):
        self.bus.append("write")
        self.written.append(cmd.mode.copy())
        return None


def test_mode_switch_runs_over_cycles_replies_at_its_end_and_refuses_motion_meanwhile():
    """A command that needs another device mode (servo_jv on a velocity-capable backend) starts
    the backend's MODE_SWITCH transition: one joint per cycle (is_busy stays false); the command's reply
    comes when it ends; another motion command meanwhile is refused naming the switch; a hold is
    not refused; when the stop needs position mode again, core switches back by itself."""
    c, act, clock, cycle, send, replies = make_slow_rig(SwitchingActuator(PROFILE))
    send("enable")
    cycle(3)
    assert c.state is OperatingState.ENABLED and act.bus.count("prepare") == 0
    arm = [0.1, 0.0, 0.0, 0.0, 0.0]
    rid = send("servo_jv", "so101", velocity=arm)
    seq = c.busy_seq
    assert replies(rid) == [] and act.bus.count("switch-0") == 1  # first step at once
    assert not c.is_busy  # servo commands never raise is_busy, nor does their mode switch
    other = send("servo_jv", "so101", velocity=arm)
    (r,) = replies(other)
    assert not r["ok"] and r["error"]["code"] == "invalid_state" and "mode_switch in progress" in r["error"]["message"]
    cycle(3)
    assert replies(rid) == []  # 5 arm joints, one per cycle
    cycle(1)
    (r,) = replies(rid)
    assert r["ok"] and not c.is_busy and c.busy_seq == seq
    assert [b for b in act.bus if b.startswith("switch")] == [f"switch-{i}" for i in range(5)]
    cycle(2)
    assert list(act.written[-1][:5]) == [CommandMode.VELOCITY] * 5
    # a stop is never refused; it needs position mode again: its reply when the switch back ends
    h = send("hold", "so101")
    assert replies(h) == []
    cycle(5)
    assert replies(h)[0]["ok"] and list(act.device_modes[:5]) == [CommandMode.POSITION] * 5
    assert not c.is_busy and c.state is OperatingState.ENABLED
    # a hold during a switch is not refused either (the switch goes on, then core switches back)
    rid = send("servo_jv", "so101", velocity=arm)
    h = send("hold", "so101")
    assert replies(h)[0]["ok"] and replies(rid) == []
    cycle(12)
    assert replies(rid)[0]["ok"] and list(act.device_modes[:5]) == [CommandMode.POSITION] * 5
    assert list(act.written[-1][:5]) == [CommandMode.POSITION] * 5 and not c.is_busy

"""The composite actuator (several buses in one robot) on fake buses: joints gathered and scattered
by index, one stamp, faults and statuses naming the bus, lifecycle transitions stepped on every bus
together, enable all-or-none, disable on every bus, and each bus's I/O on its own persistent thread."""

from __future__ import annotations

import dataclasses
import math
import threading
import time

import numpy as np
import pytest

from crtk_bridge.backends import create_backend
from crtk_bridge.backends.composite import TRAIT_RULES, CompositeActuator, combine_traits
from crtk_bridge.core.actuator import (
    Actuator,
    Capabilities,
    Clock as TraitClock,
    CommandMode,
    DeviceStatus,
    Fault,
    Lifecycle,
    Traits,
    effective_period_s,
)
from crtk_bridge.core.control import Controller
from crtk_bridge.core.cycle import CycleRunner, run_transition
from crtk_bridge.core.state import OperatingState
from crtk_bridge.errors import BackendError, ProfileError
from crtk_bridge.profile import load_profile

from .conftest import wait_until
from .test_controller import Clock

PROFILE = load_profile("profiles/bimanual_so101.yaml")


class FakeBus(Actuator):
    """A bus whose enable takes ``enable_cycles`` steps; records which thread did its I/O."""

    CAPS = Capabilities(position=True)
    #: Traits fields beside the joints' CAPS
    TRAITS: dict = {"transition_timeouts_s": {Lifecycle.ENABLE: 1.0, Lifecycle.DISABLE: 1.0}}

    def __init__(self, profile, base: float, stamp: float, enable_cycles: int = 1):
        super().__init__(profile)
        self.base, self.stamp = base, stamp
        self.enable_cycles = enable_cycles
        self.steps = 0
        self.fail_enable = self.fail_disable = False
        self.fault: Fault | None = None
        self.threads: set[int] = set()
        self.written: np.ndarray | None = None
        self.torque = False

    def _open_hook(self):
        pass

    def _traits_hook(self):
        return Traits(joints=(self.CAPS,) * self.n, **self.TRAITS)

    def _close_hook(self):
        pass

    def _enable_steps(self, feedback):
        for _ in range(self.enable_cycles):
            self.steps += 1
            if self.fail_enable:
                raise BackendError(f"{self.robot}: joint {self.joint_names[0]!r} did not confirm Torque_Enable")
            yield
        self.torque = True

    def _disable_steps(self):
        if self.fail_disable:
            raise BackendError(f"{self.robot}: torque off not confirmed on {self.joint_names[2]!r}")
        self.torque = False
        yield from ()

    def _read(self, fb):
        self.threads.add(threading.get_ident())
        fb.position[:] = self.base + np.arange(self.n)
        fb.stamp = self.stamp
        return self.fault

    def _write(self, cmd):
        self.threads.add(threading.get_ident())
        self.written = cmd.position.copy()
        return None


def composite(**left_kw) -> tuple[CompositeActuator, FakeBus, FakeBus]:
    left = FakeBus(PROFILE.bus_profile("left"), base=0.0, stamp=100.0, **left_kw)
    right = FakeBus(PROFILE.bus_profile("right"), base=10.0, stamp=99.5)
    c = CompositeActuator(PROFILE, {"left": left, "right": right})
    c.open()
    return c, left, right


def run_steps(t, limit=50) -> int:
    for k in range(1, limit):
        if t.step():
            return k
    raise AssertionError("transition did not end")


def test_the_registry_builds_one_backend_per_bus():
    b = create_backend(PROFILE)
    assert isinstance(b, CompositeActuator) and [type(p).__name__ for p in b.parts] == ["FeetechBackend"] * 2


def test_read_gathers_every_bus_with_one_stamp_on_persistent_threads():
    c, left, right = composite()
    fb = c.new_feedback()
    for _ in range(3):
        assert c.read(fb) is None
    assert np.array_equal(fb.position, np.r_[np.arange(6.0), 10 + np.arange(6.0)])
    assert fb.stamp == 99.5  # the earliest bus's: the sample is at least that old
    assert left.threads == {threading.get_ident()}  # the first bus on the calling thread
    (worker,) = right.threads
    assert worker != threading.get_ident()  # the second on its own thread, the same every cycle
    cmd = c.new_command()
    cmd.position[:] = np.arange(12.0)
    assert c.write(cmd) is None  # not enabled, not cyclic_write: the buses are not written
    assert left.written is None and right.written is None
    c.close()


def test_write_scatters_each_bus_its_own_joints():
    c, left, right = composite()
    c.enable(c.new_feedback())
    cmd = c.new_command()
    cmd.mode[:] = CommandMode.POSITION
    cmd.position[:] = np.arange(12.0)
    assert c.write(cmd) is None
    assert np.array_equal(left.written, np.arange(6.0)) and np.array_equal(right.written, 6 + np.arange(6.0))
    c.close()


def test_closed_buses_fault_and_start_no_thread():
    c, left, right = composite()
    c.close()
    threads = threading.active_count()
    assert c.read(c.new_feedback()).message == "bimanual_so101: read on closed buses"
    assert c.write(c.new_command()) is not None and threading.active_count() == threads


def test_a_bus_fault_names_the_bus_and_keeps_the_joint():
    c, left, right = composite()
    right.fault = Fault("bus_timeout", "bimanual_so101: no reply from joint 'right_elbow_flex' (id 3)",
                        joint="right_elbow_flex")
    f = c.read(c.new_feedback())
    assert f.code == "bus_timeout" and f.joint == "right_elbow_flex" and f.transient
    assert f.message == "bimanual_so101: bus 'right': no reply from joint 'right_elbow_flex' (id 3)"
    left.fault = Fault("servo_error", "bimanual_so101: joint 'left_gripper' overload", joint="left_gripper",
                       transient=False)
    f = c.read(c.new_feedback())  # the non-transient one leads, the other is said too
    assert f.code == "servo_error" and f.joint == "left_gripper" and not f.transient
    assert "bus 'left': joint 'left_gripper' overload; bus 'right': no reply" in f.message
    # both transient: the bus failing for the most cycles in a row leads (the likely cause), not
    # the one that missed a single reply in the same cycle
    left.fault = Fault("bus_timeout", "bimanual_so101: no reply from joint 'left_shoulder_pan' (id 1)",
                       joint="left_shoulder_pan")
    f = c.read(c.new_feedback())
    assert f.joint == "right_elbow_flex" and f.message.startswith("bimanual_so101: bus 'right': no reply")
    assert "; bus 'left': no reply from joint 'left_shoulder_pan'" in f.message
    c.close()


def test_transitions_step_every_bus_together_until_the_slowest_ends():
    c, left, right = composite(enable_cycles=5)
    right.enable_cycles = 2
    t = c.begin(Lifecycle.ENABLE, c.new_feedback())
    # the slowest bus's 5 steps, the cycle of its fresh read after torque on (Actuator's), and
    # the step that sees it end
    assert run_steps(t) == 7
    assert left.steps == 5 and right.steps == 2 and left.torque and right.torque
    assert c.is_enabled and left.is_enabled and right.is_enabled
    # the buses' limits add up, and an enable may end in a rollback (every bus's disable)
    assert c.traits.timeout_s(Lifecycle.ENABLE) == 2.0 + 2.0
    c.close()


def test_enable_is_all_or_none_and_names_the_bus():
    c, left, right = composite(enable_cycles=4)
    right.enable_cycles = 1
    t = c.begin(Lifecycle.ENABLE, c.new_feedback())
    # right done after its one step and its fresh read, left still going
    assert not t.step() and not t.step() and not t.step()
    assert right.torque and right.is_enabled and not left.torque
    left.fail_enable = True
    with pytest.raises(BackendError, match=r"^bimanual_so101: bus 'left': joint 'left_shoulder_pan' did not"):
        t.step()
    assert not right.torque and not right.is_enabled  # switched off again: nothing stays powered
    c.close()


def test_disable_goes_on_on_every_bus_and_names_those_that_failed():
    c, left, right = composite()
    c.enable(c.new_feedback())
    left.fail_disable = True
    with pytest.raises(BackendError) as info:
        c.disable()
    assert str(info.value) == ("bimanual_so101: bus 'left': torque off not confirmed on 'left_elbow_flex'")
    assert not right.torque  # the healthy bus was still switched off
    left.fail_disable = False
    c.close()


def test_device_status_is_the_most_severe_buss():
    c, left, right = composite()
    fb = c.new_feedback()
    right.report_status(DeviceStatus.PAUSED)
    c.read(fb)
    assert c.take_status() == (DeviceStatus.PAUSED, None)
    cause = Fault("servo_error", "bimanual_so101: joint 'left_gripper' overload", joint="left_gripper")
    left.report_status(DeviceStatus.FAULT, cause)
    c.read(fb)
    status, why = c.take_status()
    assert status is DeviceStatus.FAULT and why.message.startswith("bimanual_so101: bus 'left': ")
    left.report_status(DeviceStatus.FAULT_CLEARED)
    c.read(fb)
    assert c.take_status() == (DeviceStatus.PAUSED, None)  # the right bus is still paused
    right.report_status(DeviceStatus.OK)
    c.read(fb)
    assert c.take_status() == (DeviceStatus.OK, None)
    c.close()


def test_device_news_pass_through_in_order_beside_the_status():
    """A bus's WARNING / NOTICE reports (a gripper's minor fault, its grasp) are news, not a
    status: each reaches the robot in order, naming its bus, and none hides a FAULT reported in
    the same cycle (the robot's status is still the most severe bus's). Also from a bus served at
    its own rate."""
    for make in (composite, slow_composite):
        c, left, right = make()
        fb = c.new_feedback()
        grasp = Fault("device_status", "bimanual_so101: gOBJ 2", joint="right_gripper", register="gOBJ", value=2)
        heat = Fault("device_warning", "bimanual_so101: gFLT 0x08", joint="right_gripper", register="gFLT", value=8)
        right.report_status(DeviceStatus.NOTICE, grasp)
        right.report_status(DeviceStatus.FAULT, Fault("servo_error", "bimanual_so101: overload", joint="right_gripper"))
        right.report_status(DeviceStatus.WARNING, heat)
        got = []

        def three() -> bool:
            c.read(fb)
            news = c.take_status()
            if news is not None:
                got.append(news)
            return len(got) >= 3

        wait_until(three, 5, interval=0.005, what="three reports")
        assert {g[0] for g in got} == {DeviceStatus.NOTICE, DeviceStatus.WARNING, DeviceStatus.FAULT}
        notice = next(g[1] for g in got if g[0] is DeviceStatus.NOTICE)
        assert notice.message.startswith("bimanual_so101: bus 'right': ") and notice.register == "gOBJ"
        assert [g[0] for g in got if g[0] in (DeviceStatus.NOTICE, DeviceStatus.WARNING)] == \
            [DeviceStatus.NOTICE, DeviceStatus.WARNING]
        assert c.device_status is DeviceStatus.FAULT
        c.close()


def test_every_traits_field_has_a_combining_rule():
    """A field added to Traits without a rule in the composite's one combining function fails
    here (and combine_traits raises KeyError): a bus's declaration is never silently dropped."""
    assert set(TRAIT_RULES) == {f.name for f in dataclasses.fields(Traits)}


class Device(FakeBus):
    """A bus whose device does what a UR controller or a CiA 402 drive does: paces the loop,
    written every cycle, stops itself on pause, checks goals, homes itself, has a speed slider."""

    CAPS = Capabilities(position=True, velocity=True, measures_effort=True, needs_homing=True, can_free=False)
    TRAITS = {"clock": TraitClock.DEVICE, "cyclic_write": True, "stops_itself_on_pause": True, "goal_check": True,
              "native_homing": True, "speed_scaling": True,
              "transition_timeouts_s": {Lifecycle.ENABLE: 3.0, Lifecycle.DISABLE: 2.0, Lifecycle.HOME: 30.0}}

    def cycle_period_s(self):
        return 0.002

    def wait_cycle(self, deadline):
        self.waited = deadline
        return True

    def _read(self, fb):
        self.speed_fraction = 0.25
        return super()._read(fb)

    def goal_check_steps(self, ns, cmd, goal):
        self.checked = (ns, cmd, list(goal))
        yield

    def _home_steps(self):
        self.homed = True
        yield


def device_and_servos():
    """Bus 'left': plain servos (FakeBus); bus 'right': a Device."""
    left = FakeBus(PROFILE.bus_profile("left"), 0.0, 1.0)
    right = Device(PROFILE.bus_profile("right"), 10.0, 1.0)
    c = CompositeActuator(PROFILE, {"left": left, "right": right})
    c.open()
    return c, left, right


def test_the_robot_declares_exactly_what_its_buses_do():
    """Every field, by its rule: per joint (capabilities, pause behaviour) each joint its own bus's;
    the device's clock; written every cycle; goal check, native homing and the speed slider
    offered through the bus that has them; time limits added up."""
    c, left, right = device_and_servos()
    t, lt, rt = c.traits, left.traits, right.traits
    assert t.joints == lt.joints + rt.joints  # bimanual_so101: the left arm's joints first
    assert t.stops_itself_on_pause == (False,) * left.n + (True,) * right.n
    assert t.capabilities_of(range(left.n)) == FakeBus.CAPS and t.capabilities_of(range(6, 12)) == Device.CAPS
    assert t.capabilities.needs_homing and not t.capabilities.velocity  # the robot: every joint together
    assert t.clock is TraitClock.DEVICE and t.cyclic_write and t.goal_check and t.native_homing and t.speed_scaling
    assert c.cycle_period_s() == 0.002
    runner = CycleRunner(c, c.cycle_period_s())  # the cycle starts on the device bus's clock
    deadline = runner.next_t
    runner.wait()
    assert right.waited == deadline
    assert t.timeout_s(Lifecycle.DISABLE) == 1.0 + 2.0
    assert t.timeout_s(Lifecycle.ENABLE) == 1.0 + 3.0 + 3.0  # and the rollback's disables
    assert t.timeout_s(Lifecycle.HOME) == 30.0  # only the bus that homes
    # the speed slider: the device bus's, NaN until it reported one
    assert math.isnan(c.speed_fraction)
    assert c.read(c.new_feedback()) is None and c.speed_fraction == 0.25
    # the goal check: a namespace's own bus's; none on the servo bus's namespace
    assert c.goal_check_steps("left", "move_jp", np.zeros(6)) is None
    steps = c.goal_check_steps("right", "move_jp", np.ones(6))
    assert list(steps) == [None] and right.checked == ("right", "move_jp", [1.0] * 6)
    # native homing: HOME runs on the bus that homes itself, the other is not touched
    c.enable(c.new_feedback())
    run_transition(c, c.begin(Lifecycle.HOME))
    assert right.homed and not hasattr(left, "homed")
    c.close()
    # and nothing of it when no bus has it
    c, left, right = composite()
    t = c.traits
    assert t.clock is TraitClock.LOOP and not (t.cyclic_write or t.goal_check or t.native_homing or t.speed_scaling)
    assert t.stops_itself_on_pause == (False,) * 12 and c.cycle_period_s() is None
    with pytest.raises(BackendError, match="does not home natively"):
        c.begin(Lifecycle.HOME)
    c.close()


def test_traits_are_final_only_once_open():
    """Read before open, a backend's traits raise naming the robot: a composite (or core) cannot
    combine a CiA 402 bus's capabilities before the drives said what they support."""
    left = FakeBus(PROFILE.bus_profile("left"), 0.0, 1.0)
    right = Device(PROFILE.bus_profile("right"), 10.0, 1.0)
    c = CompositeActuator(PROFILE, {"left": left, "right": right})
    for b in (left, c):
        with pytest.raises(BackendError, match=r"bimanual_so101: the \w+ traits were read before open\(\)"):
            b.traits
    c.open()
    assert c.traits.native_homing and right.traits.native_homing
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.traits.native_homing = False
    c.close()


def test_buses_that_cannot_be_one_robot_are_refused_at_open_naming_them():
    two = CompositeActuator(PROFILE, {"left": Device(PROFILE.bus_profile("left"), 0.0, 1.0),
                                      "right": Device(PROFILE.bus_profile("right"), 0.0, 1.0)})
    with pytest.raises(ProfileError, match="buses 'left', 'right' both pace the control loop"):
        two.open()
    assert not two.parts[0]._open and not two.parts[1]._open  # the buses opened are closed again

    class Unhomed(FakeBus):  # needs homing, cannot home itself
        CAPS = Capabilities(position=True, needs_homing=True)

    class Homing(FakeBus):
        CAPS = Capabilities(position=True, needs_homing=True)
        TRAITS = {"native_homing": True}

    mixed = CompositeActuator(PROFILE, {"left": Unhomed(PROFILE.bus_profile("left"), 0.0, 1.0),
                                        "right": Homing(PROFILE.bus_profile("right"), 0.0, 1.0)})
    with pytest.raises(ProfileError, match="bus 'left' needs homing but does not home itself, beside bus 'right'"):
        mixed.open()


def test_combine_traits_handles_every_field_by_its_rule():
    """combine_traits straight: one bus's traits come back as they are (every rule is the
    identity on one bus)."""
    one = Traits(joints=(Capabilities(position=True, effort=True),) * 3, clock=TraitClock.DEVICE, cyclic_write=True,
                 stops_itself_on_pause=(True, False, True), goal_check=True, native_homing=True, speed_scaling=True,
                 transition_timeouts_s={Lifecycle.HOME: 9.0})
    again = combine_traits([one], [(0, 0), (0, 1), (0, 2)], ["only"], "x.yaml")
    expected = dataclasses.replace(one, transition_timeouts_s={
        **one.transition_timeouts_s, Lifecycle.ENABLE: one.timeout_s(Lifecycle.ENABLE) + one.timeout_s(Lifecycle.DISABLE)})
    assert again == expected


def test_on_resume_each_bus_resumes_from_where_it_stopped():
    """A device that stops itself on pause (a UR arm's safeguard stop) beside servos that core's
    braking ramp stops: on resume the device's namespace holds where the device stopped (the
    measured position), the servos' where core's ramp ended."""
    c, left, right = device_and_servos()
    clock = Clock()
    ctl = Controller(PROFILE, c, clock, effective_period_s(PROFILE, c))
    runner = CycleRunner(c, ctl.dt, clock=clock, sleep=clock.sleep)  # the loop's cycle, on the fake clock

    def cycle(n=1):
        for _ in range(n):
            runner.cycle(ctl)

    cycle()
    ctl.handle({"id": 1, "cmd": "enable"})
    cycle(3)
    assert ctl.state is OperatingState.ENABLED
    ctl.handle({"id": 2, "cmd": "pause"})
    cycle(3)
    assert ctl.state is OperatingState.PAUSED
    held = ctl.command.position.copy()
    left.base, right.base = 0.05, 10.05  # both buses measure somewhere else than core's hold
    cycle()
    ctl.handle({"id": 3, "cmd": "resume"})
    cycle(3)
    assert ctl.state is OperatingState.ENABLED
    np.testing.assert_allclose(ctl.command.position[6:], 10.05 + np.arange(6.0))  # where the device stopped
    np.testing.assert_allclose(ctl.command.position[:6], held[:6])  # core's own hold
    c.close()


def test_native_cartesian_rows_go_to_and_come_from_their_bus():
    """A natively cartesian bus (a UR arm) beside a joint-only one (a servo gripper): the robot's
    cartesian rows are that bus's, its measured pose gathered, its setpoints scattered."""

    class Native(FakeBus):
        CAPS = Capabilities(position=True, native_cartesian=True)

        def cartesian_namespaces(self):
            return ["right"]

        def _read(self, fb):
            fb.cartesian.position[0] = (0.1, 0.2, 0.3)
            fb.cartesian.done_seq[0] = 7
            fb.cartesian.stamp = 42.0
            return super()._read(fb)

        def _write(self, cmd):
            self.pose = (int(cmd.cartesian.mode[0]), cmd.cartesian.position[0].copy(), int(cmd.cartesian.seq[0]))
            return super()._write(cmd)

    left = FakeBus(PROFILE.bus_profile("left"), 0.0, 1.0)
    right = Native(PROFILE.bus_profile("right"), 0.0, 1.0)
    c = CompositeActuator(PROFILE, {"left": left, "right": right})
    c.open()
    assert c.cartesian_namespaces() == ["right"]
    fb = c.new_feedback()
    assert c.read(fb) is None
    assert np.array_equal(fb.cartesian.position[0], [0.1, 0.2, 0.3]) and fb.cartesian.done_seq[0] == 7
    assert fb.cartesian.stamp == 42.0
    c.enable(fb)
    cmd = c.new_command()
    cmd.cartesian.mode[0], cmd.cartesian.position[0], cmd.cartesian.seq[0] = 3, (0.3, 0.0, 0.2), 8
    assert c.write(cmd) is None
    mode, position, seq = right.pose
    assert mode == 3 and np.array_equal(position, [0.3, 0.0, 0.2]) and seq == 8
    c.close()


class ServoBus(FakeBus):
    """A bus of servos each with its own torque: enable switches one servo on per step (failing at
    step ``fail_at`` when set), disable one servo off per step. ``log`` (shared by the buses)
    records every read and every torque-off step, so a test sees what happened in which cycle."""

    def __init__(self, profile, name, log, enable_cycles=None):
        super().__init__(profile, base=0.0, stamp=1.0)
        self.name, self.log = name, log
        self.servo_torque = np.zeros(self.n, dtype=bool)
        self.enable_cycles = self.n if enable_cycles is None else enable_cycles
        self.fail_at: int | None = None
        self.goal = np.zeros(self.n)

    def _enable_steps(self, feedback):
        self.goal[:] = feedback.position  # hold where the joints are
        for k in range(self.enable_cycles):
            if self.fail_at == k:
                raise BackendError(f"{self.robot}: joint {self.joint_names[k]!r} did not confirm Torque_Enable")
            self.servo_torque[k % self.n] = True
            yield

    def _disable_steps(self):
        for k in range(self.n):
            self.servo_torque[k] = False
            self.log.append(("off", self.name))
            if k < self.n - 1:
                yield

    def _read(self, fb):
        self.log.append(("read", self.name))
        fb.position[:] = 0.1 * np.arange(self.n)
        fb.stamp += 0.005
        return self.fault

    def _write(self, cmd):
        on = cmd.mode == CommandMode.POSITION
        self.goal[on] = cmd.position[on]
        return None


def controller_rig(left_enable_cycles=None):
    log: list = []
    left = ServoBus(PROFILE.bus_profile("left"), "left", log, left_enable_cycles)
    right = ServoBus(PROFILE.bus_profile("right"), "right", log)
    act = CompositeActuator(PROFILE, {"left": left, "right": right})
    act.open()
    clock = Clock()
    c = Controller(PROFILE, act, clock, effective_period_s(PROFILE, act))
    runner = CycleRunner(act, c.dt, clock=clock, sleep=clock.sleep)  # the loop's cycle, on the fake clock
    cycles: list[list] = []  # the log of each cycle

    def cycle(n=1):
        for _ in range(n):
            start = len(log)
            runner.cycle(c)
            cycles.append(log[start:])

    cycle()
    return c, act, left, right, cycle, cycles


def run_until(cycle, cond, limit=200):
    for _ in range(limit):
        if cond():
            return
        cycle()
    raise AssertionError("condition not reached")


@pytest.mark.parametrize("faulty", ["left", "right"])
def test_a_fault_switches_every_bus_off_in_steps(faulty):
    """A fault on either bus switches torque off on every bus, in one transition stepping the
    buses together, one step per cycle; the robot is FAULT naming the bus that faulted."""
    c, act, left, right, cycle, cycles = controller_rig()
    c.handle({"id": 1, "cmd": "enable", "ns": None, "data": {}})
    run_until(cycle, lambda: c.state is OperatingState.ENABLED)
    cycle(3)
    assert left.servo_torque.all() and right.servo_torque.all()
    bus = left if faulty == "left" else right
    bus.fault = Fault("servo_error", f"bimanual_so101: joint '{faulty}_gripper' overload",
                      joint=f"{faulty}_gripper", transient=False)
    cycle()
    bus.fault = None
    assert c.state is OperatingState.FAULT
    assert c.fault_cause.message == f"bimanual_so101: bus '{faulty}': joint '{faulty}_gripper' overload"
    mark = len(cycles)
    run_until(cycle, lambda: not c.is_busy)
    cycle(3)
    assert not left.servo_torque.any() and not left.is_enabled
    assert not right.servo_torque.any() and not right.is_enabled
    # one step of each bus's torque off per cycle, each cycle reading both buses first
    for bus in (left, right):
        offs = [log.count(("off", bus.name)) for log in cycles[mark - 1:] if ("off", bus.name) in log]
        assert offs == [1] * bus.n
    assert all(set(log[:2]) == {("read", "left"), ("read", "right")} for log in cycles[mark - 1:])
    assert not act.is_enabled and c.state is OperatingState.FAULT


def test_a_fault_on_one_bus_names_it():
    c, act, left, right, cycle, cycles = controller_rig()
    c.handle({"id": 1, "cmd": "enable", "ns": None, "data": {}})
    run_until(cycle, lambda: c.state is OperatingState.ENABLED)
    right.fault = Fault("servo_error", "bimanual_so101: joint 'right_gripper' overload", transient=False)
    cycle()
    run_until(cycle, lambda: not c.is_busy)
    assert c.state is OperatingState.FAULT and c.fault_cause.message.startswith("bimanual_so101: bus 'right': ")
    assert not left.servo_torque.any() and not right.servo_torque.any()


@pytest.mark.parametrize("left_enable_cycles", [2, 12], ids=["other-bus-finished", "other-bus-partial"])
@pytest.mark.parametrize("fail_at", [1, 4])
def test_a_failed_enable_is_undone_on_every_bus_in_steps(left_enable_cycles, fail_at):
    """Bus 'right' fails at enable step ``fail_at`` while bus 'left' has finished enabling or is
    still on its way: every servo of both buses ends with torque off, each bus's own disable
    steps stepped one per cycle (every cycle still reads both buses: nothing blocked the cycle),
    and the robot is FAULT naming bus 'right'."""
    c, act, left, right, cycle, cycles = controller_rig(left_enable_cycles)
    right.fail_at = fail_at
    c.handle({"id": 1, "cmd": "enable", "ns": None, "data": {}})
    mark = len(cycles)
    run_until(cycle, lambda: right.servo_torque.sum() == fail_at)
    assert left.servo_torque.any()
    run_until(cycle, lambda: c.state is OperatingState.FAULT)
    ended = len(cycles) - 1  # the cycle in which the rollback ended (and the fault reaction began)
    run_until(cycle, lambda: not c.is_busy)
    assert not left.servo_torque.any() and not right.servo_torque.any()
    assert not left.is_enabled and not right.is_enabled and not act.is_enabled
    assert c.state is OperatingState.FAULT
    assert c.fault_cause.message.startswith("bimanual_so101: bus 'right': joint ")
    (reply,) = [m for m in c.outbox if m.get("id") == 1]
    assert not reply["ok"] and "bus 'right': joint " in reply["error"]["message"]
    # the rollback: each bus's own disable steps, one per bus per cycle, every cycle reading both
    # buses first (a blocking disable would switch a bus's servos off within one cycle)
    rollback = cycles[mark:ended + 1]
    for bus in (left, right):
        # (+1: the fault reaction's first step, in the rollback's last cycle)
        assert sum(log.count(("off", bus.name)) for log in rollback) in (bus.n, bus.n + 1)
    for k, log in enumerate(rollback):
        assert set(log[:2]) == {("read", "left"), ("read", "right")}
        # the last rollback cycle may also carry the first step of core's fault reaction
        most = 2 if k == len(rollback) - 1 else 1
        assert log.count(("off", "left")) <= most and log.count(("off", "right")) <= most
    # over n cycles (n + 1 with the fault reaction's first step)
    assert sum(1 for log in rollback[:-1] if ("off", "right") in log) >= right.n - 1


def test_the_rollback_is_bounded_by_the_disable_time_limit():
    """A bus whose torque off never confirms does not keep the rollback going: after the buses'
    disable limits the enable fails naming the bus that failed and the one left unconfirmed."""
    log: list = []

    class Stuck(ServoBus):
        TRAITS = {"transition_timeouts_s": {Lifecycle.ENABLE: 1.0, Lifecycle.DISABLE: 0.05}}

        def _disable_steps(self):
            while True:  # never confirms
                yield

    left = Stuck(PROFILE.bus_profile("left"), "left", log)
    right = Stuck(PROFILE.bus_profile("right"), "right", log)
    right.fail_at = 2
    c = CompositeActuator(PROFILE, {"left": left, "right": right})
    c.open()
    with pytest.raises(BackendError) as info:
        run_transition(c, c.begin(Lifecycle.ENABLE, c.new_feedback()))  # its own limit (2.1 s) is not reached
    assert str(info.value).startswith("bimanual_so101: bus 'right': joint 'right_elbow_flex' did not confirm")
    assert str(info.value).endswith("undoing the enable: torque off not confirmed on 'left', 'right' within 0.1 s")



# ---------------------------------------------------------------- a bus served at its own rate
class SlowBus(FakeBus):
    """A bus slower than the robot's cycle (one read + one write take 20 ms: a Robotiq gripper's
    Modbus RTU beside a 200 Hz loop). Its read waits at ``gate`` while it is closed (a wire that
    holds the bus); ``fail_reads`` makes the next reads fail (transient); every read is stamped
    at its own time (``stamp`` + its number); ``log`` records the thread of every I/O and step."""

    TRAITS = {**FakeBus.TRAITS, "min_period_s": 0.02}

    def __init__(self, profile, base, stamp, **kw):
        super().__init__(profile, base, stamp, **kw)
        self.gate = threading.Event()
        self.gate.set()
        self.waiting = threading.Event()  # a read waits at the closed gate
        self.reads = 0
        self.fail_reads = 0
        self.writes: list[np.ndarray] = []
        self.disable_cycles = 1
        self.step_threads: set[int] = set()

    def _read(self, fb):
        if not self.gate.is_set():
            self.waiting.set()
            self.gate.wait()
        self.reads += 1
        super()._read(fb)
        fb.stamp = self.stamp + self.reads
        if self.fail_reads:
            self.fail_reads -= 1
            return Fault("bus_timeout", f"{self.robot}: no reply from joint 'right_gripper' (id 6)",
                         joint="right_gripper")
        return self.fault

    def _write(self, cmd):
        self.writes.append(cmd.position.copy())
        return super()._write(cmd)

    def _enable_steps(self, feedback):
        self.step_threads.add(threading.get_ident())
        yield from super()._enable_steps(feedback)

    def _disable_steps(self):
        for _ in range(self.disable_cycles - 1):
            self.step_threads.add(threading.get_ident())
            yield
        self.step_threads.add(threading.get_ident())
        self.torque = False


def slow_composite():
    left = FakeBus(PROFILE.bus_profile("left"), 0.0, 100.0)
    right = SlowBus(PROFILE.bus_profile("right"), 10.0, 50.0)
    c = CompositeActuator(PROFILE, {"left": left, "right": right})
    c.open()
    return c, left, right


def in_thread(fn, timeout=10.0):
    """``fn()`` on a thread; fails (instead of hanging the suite) when it does not return in time."""
    box = {}
    t = threading.Thread(target=lambda: box.setdefault("out", fn()), daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), "the cycle was held (it did not return)"
    return box["out"]


def test_a_slow_bus_is_served_at_its_own_rate_and_never_holds_the_cycle():
    """A bus whose min_period_s is longer than the robot's cycle (bimanual_so101: 200 Hz) runs its
    own cycles on its own thread: the robot's read never waits for it (here its wire is held) and
    takes its newest completed read, which keeps its own read's stamp; the robot's sample is
    stamped by the bus read in the cycle, and its period is bound by that bus only."""
    c, left, right = slow_composite()
    assert c.own_rate == {"right": 0.02}
    assert c.traits.min_period_s == 0.0  # the slow bus bounds nothing: it is not joined
    assert combine_traits([left.traits, right.traits], [(0, 0)] * 6 + [(1, 0)] * 6, ["l", "r"], "x").min_period_s == 0.02
    assert right.reads == 1  # read once at open: the loop's first cycles have a sample
    right.threads.clear()  # (that read was the start-up path's, on the calling thread)
    right.gate.clear()  # its worker's first read waits at the held wire
    fb = c.new_feedback()
    faults = [in_thread(lambda: c.read(fb))]  # the first cycle starts its thread
    wait_until(right.waiting.is_set, 5, what="the slow bus waiting at its held wire")
    faults += in_thread(lambda: [c.read(fb) for _ in range(50)])
    assert right.reads == 1  # it was stuck in its read all along
    assert faults == [None] * 51 and fb.stamp == 100.0  # stamped by the bus read in the cycle
    assert c.bus_stamps() == {"left": 100.0, "right": 51.0}  # the sample read at open, its own stamp
    right.gate.set()
    wait_until(lambda: c.read(fb) is None and c.bus_stamps()["right"] > 51.0, 5, what="the slow bus's next sample")
    assert np.array_equal(fb.position, np.r_[np.arange(6.0), 10 + np.arange(6.0)])
    k = c.bus_stamps()["right"] - 50.0  # the slow bus's own read's stamp
    assert k == int(k) and 2 <= k <= right.reads and fb.stamp == 100.0
    # DISABLED: a setpoint posted is never written; its reads go on at its own rate
    cmd = c.new_command()
    cmd.mode[:] = CommandMode.POSITION
    assert c.write(cmd) is None
    reads = right.reads
    wait_until(lambda: right.reads >= reads + 3, 5, what="three more reads of the slow bus")
    assert right.writes == []
    assert threading.get_ident() not in right.threads  # its I/O on its own thread only
    c.close()


def test_lifecycle_steps_of_a_slow_bus_run_on_its_own_cycles_and_disable_waits_for_it():
    """ENABLE / DISABLE steps of a slow bus run on its own thread over several of its cycles; the
    robot's DISABLE ends only when the slow bus's did; a setpoint posted while its wire is held
    is not queued: the newest wins (a stop never waits behind stale setpoints)."""
    c, left, right = slow_composite()
    right.enable_cycles = 3
    c.enable(c.new_feedback())
    assert right.torque and right.is_enabled and c.is_enabled and right.steps == 3
    assert right.step_threads and threading.get_ident() not in right.step_threads
    right.waiting.clear()
    right.gate.clear()
    wait_until(right.waiting.is_set, 5, what="the slow bus waiting at its held wire")
    before = len(right.writes)
    cmd = c.new_command()
    cmd.mode[:] = CommandMode.POSITION
    for value in (1.0, 2.0, 3.0):  # three cycles' setpoints while the bus is held
        cmd.position[:] = value
        assert in_thread(lambda: c.write(cmd)) is None
    right.gate.set()
    wait_until(lambda: len(right.writes) > before, 5, what="the slow bus's next write")
    assert np.all(right.writes[before] == 3.0)  # the newest: 1.0 and 2.0 never reached it
    # DISABLE: 4 of the slow bus's steps; the robot's ends only once its torque is off
    right.disable_cycles = 4
    runner = CycleRunner(c, 0.005)
    t = c.begin(Lifecycle.DISABLE)
    cycles = 0
    while not runner.step_transition(t)[0]:
        cycles += 1
        assert cycles < 2000, "DISABLE did not end"
    assert not right.torque and not left.torque and not right.is_enabled
    assert cycles >= 3  # it took the slow bus's cycles (each several of the robot's)
    c.close()


def test_a_slow_bus_failing_faults_the_robot_naming_bus_and_joint(monkeypatch):
    """Transient failures of the slow bus are counted at its own rate (safety.bus_errors_max of
    its reads in a row, not of the robot's cycles); the robot FAULTs in the cycle that sees the
    FAULT, naming bus and joint, and every bus is switched off. A bus that stops publishing
    altogether (a stuck worker) is a FAULT too."""
    import crtk_bridge.backends.composite as composite_module

    left = FakeBus(PROFILE.bus_profile("left"), 0.0, 100.0)
    right = SlowBus(PROFILE.bus_profile("right"), 10.0, 50.0)
    act = CompositeActuator(PROFILE, {"left": left, "right": right})
    act.open()
    clock = Clock()
    c = Controller(PROFILE, act, clock, effective_period_s(PROFILE, act))
    runner = CycleRunner(act, c.dt, clock=clock, sleep=clock.sleep)

    def until(cond, what, timeout=10.0):
        deadline = time.monotonic() + timeout
        while not cond():
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            runner.cycle(c)
            time.sleep(0.001)

    until(lambda: right.reads > 0, "the slow bus's first sample")
    c.handle({"id": 1, "cmd": "enable", "ns": None, "data": {}})
    until(lambda: c.state is OperatingState.ENABLED, "ENABLED")
    right.fail_reads = PROFILE.safety.bus_errors_max - 1  # fewer than the limit in a row: no FAULT
    start = right.reads
    until(lambda: right.reads >= start + PROFILE.safety.bus_errors_max + 2, "the slow bus's reads")
    assert c.state is OperatingState.ENABLED
    right.fail_reads = 1000
    until(lambda: c.state is OperatingState.FAULT, "FAULT")
    assert c.fault_cause.joint == "right_gripper" and not c.fault_cause.transient
    assert c.fault_cause.message == ("bimanual_so101: bus 'right': no reply from joint 'right_gripper' (id 6) "
                                     f"({PROFILE.safety.bus_errors_max} failed reads in a row)")
    until(lambda: not c.is_busy, "the fault's DISABLE")
    assert not right.torque and not left.torque
    act.close()
    # a worker that publishes nothing any more (its wire holds it for ever)
    monkeypatch.setattr(composite_module, "OWN_RATE_STALE_S", 0.2)
    monkeypatch.setattr(composite_module, "OWN_RATE_STALE_PERIODS", 1)
    c, left, right = slow_composite()
    fb = c.new_feedback()
    wait_until(lambda: c.read(fb) is None, 5, what="a first sample")
    right.gate.clear()
    f = wait_until(lambda: c.read(fb), 5, what="the stuck bus's fault")
    assert not f.transient and f.message.startswith("bimanual_so101: bus 'right': no sample for 0.2 s"), f.message
    right.gate.set()
    c.close()


def test_a_bus_that_resumed_first_holds_until_the_robot_resumed():
    """A device that stops itself on pause (a UR arm) and resumes in one step, beside a bus whose
    resume takes several cycles (a gripper at its own rate): until the robot's RESUME ends, core's
    command is still where its braking ramp ended; the device is not written meanwhile (it would
    rush there), then follows from where it stopped."""

    class SlowResume(FakeBus):
        def _resume_steps(self):
            for _ in range(3):
                yield

    class Counting(Device):  # (a Device is written every cycle: cyclic_write)
        def _write(self, cmd):
            self.modes.append(cmd.mode.copy())
            return super()._write(cmd)

    left = SlowResume(PROFILE.bus_profile("left"), 0.0, 1.0)
    right = Counting(PROFILE.bus_profile("right"), 10.0, 1.0)
    right.modes = []
    act = CompositeActuator(PROFILE, {"left": left, "right": right})
    act.open()
    clock = Clock()
    ctl = Controller(PROFILE, act, clock, effective_period_s(PROFILE, act))
    runner = CycleRunner(act, ctl.dt, clock=clock, sleep=clock.sleep)
    runner.cycle(ctl)
    ctl.handle({"id": 1, "cmd": "enable"})
    run_until(lambda: runner.cycle(ctl), lambda: ctl.state is OperatingState.ENABLED)
    ctl.handle({"id": 2, "cmd": "pause"})
    run_until(lambda: runner.cycle(ctl), lambda: ctl.state is OperatingState.PAUSED)
    right.base = 10.05  # the device stopped elsewhere than core's hold
    runner.cycle(ctl)
    ctl.handle({"id": 3, "cmd": "resume"})
    runner.cycle(ctl)  # both buses' first resume step: the device's is its last
    writes = len(right.modes)
    cycles = 0
    while ctl.state is not OperatingState.ENABLED:
        runner.cycle(ctl)
        cycles += 1
        assert cycles < 20
    # while the other bus resumed: written (every cycle, its bus needs it) with no setpoint
    assert cycles >= 2 and len(right.modes) > writes + 1
    assert all((m == CommandMode.NONE).all() for m in right.modes[writes:-1])
    # the cycle the robot's RESUME ended in: core took the device's measured pose, written at once
    assert (right.modes[-1] == CommandMode.POSITION).all()
    np.testing.assert_allclose(right.written, 10.05 + np.arange(6.0))  # from where it stopped
    act.close()


def test_a_disable_right_after_an_enable_of_a_slow_bus_never_meets_a_stale_enable_step():
    """The loop abandons a slow bus's ENABLE for a DISABLE while the bus's worker is inside its
    read (held here at its wire): the worker asks which transition to step only after the read,
    and the part's DISABLE begins on the worker's thread, after the abandoned ENABLE was closed
    there. So the ENABLE is never stepped again: it does not end (is_enabled stays False) and no
    setpoint is written once the DISABLE began."""
    log: list = []

    class Racy(SlowBus):
        def begin(self, kind, feedback=None):
            log.append(("begin", kind, threading.get_ident()))
            return super().begin(kind, feedback)

        def _enable_steps(self, feedback):
            yield from super()._enable_steps(feedback)  # torque on ...
            log.append(("torque on",))
            self.waiting.clear()
            self.gate.clear()  # ... and the next read holds the wire (the enable's fresh read)

        def _write(self, cmd):
            log.append(("write",))
            return super()._write(cmd)

    left = FakeBus(PROFILE.bus_profile("left"), 0.0, 100.0)
    right = Racy(PROFILE.bus_profile("right"), 10.0, 50.0)
    c = CompositeActuator(PROFILE, {"left": left, "right": right})
    c.open()
    try:
        fb = c.new_feedback()
        enable = c.begin(Lifecycle.ENABLE, fb)
        assert enable.step() is False  # handed to the slow bus's worker
        wait_until(right.waiting.is_set, 5, what="the slow bus's fresh read after torque on, held")
        enable.abort()  # the loop abandons it (a client's disable) ...
        disable = c.begin(Lifecycle.DISABLE)
        assert disable.step() is False  # ... and hands the DISABLE over, the worker still in its read
        right.gate.set()
        deadline = time.monotonic() + 10
        while not disable.step():
            assert time.monotonic() < deadline, "DISABLE did not end"
            c.read(fb)
            time.sleep(0.001)
        (begin_disable,) = [k for k, e in enumerate(log) if e[:2] == ("begin", Lifecycle.DISABLE)]
        assert ("write",) not in log[begin_disable:], log  # nothing written once the DISABLE began
        assert not right.is_enabled and not right.torque and not c.is_enabled
        # every begin() of the bus on its worker's thread, never the loop's
        assert threading.get_ident() not in {e[2] for e in log if e[0] == "begin"}
        # the bus at its own rate goes on disabled: still nothing written
        reads = right.reads
        wait_until(lambda: right.reads >= reads + 3, 5, what="three more reads of the slow bus")
        assert ("write",) not in log[begin_disable:] and not right.is_enabled
    finally:
        right.gate.set()
        c.close()


def test_close_leaves_a_slow_bus_stuck_in_a_call_to_its_worker_and_says_torque_off_is_unconfirmed(monkeypatch):
    """close() waits a bounded time for a slow bus's worker; one still inside a read (its wire
    held) keeps the bus: close() neither runs the part's own torque off nor releases its link on
    a second thread, and says torque off is not confirmed on that bus; the worker closes the bus
    itself once its read returns."""
    import crtk_bridge.backends.composite as composite_module

    monkeypatch.setattr(composite_module, "OWN_RATE_STOP_S", 0.2)
    quick = {"transition_timeouts_s": {Lifecycle.ENABLE: 1.0, Lifecycle.DISABLE: 0.05}}

    class Quick(FakeBus):
        TRAITS = quick

    class Held(SlowBus):
        TRAITS = {**quick, "min_period_s": 0.02}

        def _read(self, fb):
            self.entered.add(threading.get_ident())
            return super()._read(fb)

        def _close_hook(self):
            self.closed_by.append(threading.get_ident())

    left = Quick(PROFILE.bus_profile("left"), 0.0, 100.0)
    right = Held(PROFILE.bus_profile("right"), 10.0, 50.0)
    right.entered, right.closed_by = set(), []
    c = CompositeActuator(PROFILE, {"left": left, "right": right})
    c.open()
    fb = c.new_feedback()
    c.read(fb)  # starts the worker
    right.entered.clear()  # (the read at open was the start-up path's, on this thread)
    right.gate.clear()
    wait_until(right.waiting.is_set, 5, what="the slow bus's worker held in its read")
    (worker,) = right.entered
    closer = threading.Thread(target=c.close, daemon=True)
    closer.start()
    try:
        wait_until(lambda: not closer.is_alive() or len(right.entered) > 1, 10, what="close() returning")
        assert right.entered == {worker}, "a second thread entered the bus its worker was still in"
        assert right.closed_by == []  # its link is not released under the worker
        status, cause = c.take_status()
        assert status is DeviceStatus.FAULT and cause.code == "torque_off_unconfirmed" and not cause.transient
        assert cause.message.startswith("bimanual_so101: close: torque off not confirmed on bus 'right': its "
                                        "worker was still inside a call on the bus after 0.2 s"), cause.message
    finally:
        right.gate.set()
    closer.join(5)
    wait_until(lambda: right.closed_by, 5, what="the worker closing its bus once its read returned")
    assert right.closed_by == [worker] and right.entered == {worker} and not right.torque


def test_no_setpoint_reaches_a_slow_bus_once_the_robot_asked_for_its_disable():
    """The loop hands a DISABLE over while the slow bus's worker is about to write (past the
    point where it asked for a transition): that write carries no setpoint (every joint NONE),
    not the newest one posted: a stop is at once, not one bus cycle later."""

    class AtWrite(SlowBus):
        armed = False

        @property
        def is_enabled(self):  # asked by the worker just before its write: held there when armed
            if self.armed and threading.current_thread().name.startswith("crtk-bus-"):
                self.armed = False
                self.at_write.set()
                self.go.wait(10)
            return self._enabled

        def _write(self, cmd):
            self.modes.append(cmd.mode.copy())
            return super()._write(cmd)

    left = FakeBus(PROFILE.bus_profile("left"), 0.0, 100.0)
    right = AtWrite(PROFILE.bus_profile("right"), 10.0, 50.0)
    right.at_write, right.go, right.modes = threading.Event(), threading.Event(), []
    c = CompositeActuator(PROFILE, {"left": left, "right": right})
    c.open()
    try:
        c.enable(c.new_feedback())
        cmd = c.new_command()
        cmd.mode[:] = CommandMode.POSITION
        cmd.position[:] = 1.0
        assert c.write(cmd) is None
        wait_until(lambda: any(np.all(p == 1.0) for p in right.writes), 5, what="the setpoint written")
        right.armed = True
        wait_until(right.at_write.is_set, 5, what="the worker about to write")
        cmd.position[:] = 2.0
        assert c.write(cmd) is None  # the newest setpoint ...
        disable = c.begin(Lifecycle.DISABLE)
        assert disable.step() is False  # ... then the robot's DISABLE, handed over
        before = len(right.modes)
        right.go.set()
        wait_until(lambda: len(right.modes) > before, 5, what="the worker's write")
        assert (right.modes[before] == CommandMode.NONE).all()  # no setpoint once the stop was asked
        assert not any(np.all(p == 2.0) for p in right.writes)
        fb = c.new_feedback()
        deadline = time.monotonic() + 10
        while not disable.step():
            assert time.monotonic() < deadline, "DISABLE did not end"
            c.read(fb)
            time.sleep(0.001)
        assert not right.is_enabled and not right.torque
    finally:
        right.go.set()
        c.close()

"""The composite actuator (several buses in one robot) on fake buses: joints gathered and scattered
by index, one stamp, faults and statuses naming the bus, lifecycle transitions stepped on every bus
together, enable all-or-none, disable on every bus, and each bus's I/O on its own persistent thread."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from crtk_bridge.backends import create_backend
from crtk_bridge.backends.composite import CompositeActuator
from crtk_bridge.core.actuator import (
    Actuator,
    Capabilities,
    CommandMode,
    DeviceStatus,
    Fault,
    FaultReaction,
    Lifecycle,
)
from crtk_bridge.errors import BackendError, ProfileError
from crtk_bridge.profile import load_profile

PROFILE = load_profile("profiles/bimanual_so101.yaml")


class FakeBus(Actuator):
    """A bus whose enable takes ``enable_cycles`` steps; records which thread did its I/O."""

    capabilities = Capabilities(position=True)
    transition_timeouts_s = {Lifecycle.ENABLE: 1.0, Lifecycle.DISABLE: 1.0}

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
    assert run_steps(t) == 6  # the slowest bus's 5 steps (+ the step that sees it end)
    assert left.steps == 5 and right.steps == 2 and left.torque and right.torque
    assert c.is_enabled and left.is_enabled and right.is_enabled
    assert c.transition_timeout_s(Lifecycle.ENABLE) == 2.0  # the buses' limits add up
    c.close()


def test_enable_is_all_or_none_and_names_the_bus():
    c, left, right = composite(enable_cycles=3)
    right.enable_cycles = 1
    t = c.begin(Lifecycle.ENABLE, c.new_feedback())
    assert not t.step() and not t.step()  # right done after its one step, left still going
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


def test_declarations_combine():
    c, left, right = composite()
    assert not c.cyclic_write and not c.paces_cycle and c.fault_reaction is FaultReaction.TORQUE_OFF

    class Paced(FakeBus):
        paces_cycle = True
        cyclic_write = True
        fault_reaction = FaultReaction.NONE

    a = Paced(PROFILE.bus_profile("left"), 0.0, 0.0)
    b = FakeBus(PROFILE.bus_profile("right"), 0.0, 0.0)
    c = CompositeActuator(PROFILE, {"left": a, "right": b})
    assert c.paces_cycle and c.cyclic_write and c.fault_reaction is FaultReaction.TORQUE_OFF
    with pytest.raises(ProfileError, match="both pace the control loop"):
        CompositeActuator(PROFILE, {"left": a, "right": Paced(PROFILE.bus_profile("right"), 0.0, 0.0)})


def test_native_cartesian_rows_go_to_and_come_from_their_bus():
    """A natively cartesian bus (a UR arm) beside a joint-only one (a servo gripper): the robot's
    cartesian rows are that bus's, its measured pose gathered, its setpoints scattered."""

    class Native(FakeBus):
        capabilities = Capabilities(position=True, native_cartesian=True)

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

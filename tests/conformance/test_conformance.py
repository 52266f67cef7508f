"""The actuator contract, checked on every backend with a simulator (see conftest.py)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from crtk_bridge.core.actuator import Clock, CommandMode, DeviceStatus, Fault
from crtk_bridge.core.state import OperatingState

from ..conftest import _counts_per_rad, wait_until
from .conftest import ROWS, simulated_backends


def test_every_simulated_backend_has_a_row():
    assert simulated_backends(), "no registered backend declares a simulator"
    assert set(simulated_backends()) <= set(ROWS)


def test_lifecycle_is_idempotent(rig):
    b, sim = rig.backend, rig.sim
    b.open()  # again: nothing happens
    b.configure()
    b.enable(rig.fb)
    b.enable(rig.fb)  # enabling an enabled backend holds where it is again
    assert b.is_enabled and all(rig.row.torque(sim, i) for i in rig.ids)
    b.disable()
    b.disable()
    assert not b.is_enabled and not any(rig.row.torque(sim, i) for i in rig.ids)
    b.close()
    b.close()
    assert isinstance(b.read(rig.fb), Fault)  # a closed bus faults; it does not raise


def test_read_and_write_never_raise(rig):
    b, sim = rig.backend, rig.sim
    cmd = b.new_command()
    assert rig.read() is None
    b.enable(rig.fb)
    for mode in CommandMode:
        cmd.mode[:] = int(mode)
        cmd.position[:] = rig.fb.position
        for bad in (np.inf, -np.inf, 1e300):
            cmd.position[0] = bad
            cmd.velocity[:] = bad
            cmd.effort[:] = bad
            result = b.write(cmd)
            assert result is None or isinstance(result, Fault)
    cmd.mode[:] = 200  # no such mode
    assert b.write(cmd) is None or isinstance(b.write(cmd), Fault)
    sim.set_unplugged(True)
    wait_until(lambda: isinstance(rig.read(), Fault), 2, interval=0, what="a Fault from the read")
    cmd.mode[:] = int(CommandMode.POSITION)
    cmd.position[:] = rig.fb.position
    result = b.write(cmd)
    assert result is None or isinstance(result, Fault)  # a write has no reply to miss
    sim.set_unplugged(False)
    b.close()
    assert isinstance(b.read(rig.fb), Fault) and (b.write(cmd) is None or isinstance(b.write(cmd), Fault))


def test_nan_never_reaches_the_bus(rig):
    b, sim, row = rig.backend, rig.sim, rig.row
    b.enable(rig.fb)
    goals = [row.goal(sim, i) for i in rig.ids]
    cmd = b.new_command()
    cmd.mode[:] = int(CommandMode.POSITION)
    cmd.position[:] = rig.measured()
    cmd.position[0] = np.nan
    if b.n > 1:  # a one-joint robot (a gripper) has no other joint to send
        cmd.position[1] += 0.05
    fault = b.write(cmd)
    assert fault is not None and fault.code == "invalid_command" and not fault.transient
    assert fault.joint == b.joint_names[0]
    rig.measured()  # answered: the simulator has taken everything sent before
    assert row.goal(sim, rig.ids[0]) == goals[0]  # the NaN joint kept its goal
    if b.n > 1:
        assert row.goal(sim, rig.ids[1]) != goals[1]  # the others were sent
    # an all-NaN command in any mode changes no goal and no mode (a backend may re-send the
    # goals it holds, never a value made of the NaN)
    held = [row.goal(sim, i) for i in rig.ids]
    for mode in (CommandMode.POSITION, CommandMode.VELOCITY, CommandMode.EFFORT):
        cmd.mode[:] = int(mode)
        cmd.position[:] = cmd.velocity[:] = cmd.effort[:] = np.nan
        fault = b.write(cmd)
        rig.measured()
        assert fault is None or fault.code == "invalid_command"  # None: the mode is not offered
        assert [row.goal(sim, i) for i in rig.ids] == held, mode
        assert all(row.torque(sim, i) for i in rig.ids)
    assert np.all(np.isfinite(rig.measured()))


def test_nothing_goes_on_the_bus_while_disabled(rig):
    b, sim, row = rig.backend, rig.sim, rig.row
    if b.traits.cyclic_write:
        pytest.skip("this backend writes every cycle in every state by design (cyclic_write)")
    goals = [row.goal(sim, i) for i in rig.ids]
    cmd = b.new_command()
    cmd.position[:] = rig.measured() + 0.2
    rx = sim.rx_bytes
    for mode in (CommandMode.POSITION, CommandMode.VELOCITY, CommandMode.EFFORT, CommandMode.FREE):
        cmd.mode[:] = int(mode)
        assert b.write(cmd) is None
    assert sim.rx_bytes == rx  # not one byte
    assert [row.goal(sim, i) for i in rig.ids] == goals and not any(row.torque(sim, i) for i in rig.ids)
    # and the loop, DISABLED with motion requests arriving: only its reads go out
    c = rig.make_controller()
    c.handle({"id": 1, "cmd": "servo_jp", "ns": rig.profile.namespaces[0].name,
              "data": {"position": list(cmd.position[:len(rig.profile.namespaces[0].joints)])}})
    assert c.outbox[-1]["ok"] is False
    rig.cycle(20)
    assert [row.goal(sim, i) for i in rig.ids] == goals and not any(row.torque(sim, i) for i in rig.ids)


def test_enable_holds_the_measured_position(rig):
    b, sim, row = rig.backend, rig.sim, rig.row
    if row.braked_when_disabled:
        pytest.skip("a DISABLED (powered off) arm is held by its brakes: nothing displaces it before enable; "
                    "test_backend_ur.py::test_enable_from_power_off_keeps_the_loop_cycling checks enable holds "
                    "where it is")
    for k, sid in enumerate(rig.ids):  # somewhere other than where the goals were left
        row.set_present(sim, sid, row.present(sim, sid) + 150 + 40 * k)
    before = rig.measured()
    c = rig.make_controller()
    rig.enable(1)
    assert rig.replies(1)[0]["ok"] and c.state is OperatingState.ENABLED
    assert all(row.torque(sim, i) for i in rig.ids)
    for i, sid in enumerate(rig.ids):
        assert abs(row.goal(sim, sid) - row.present(sim, sid)) <= 1, b.joint_names[i]
    rig.cycle(int(0.3 / c.dt))  # held for a while by the loop's own writes
    np.testing.assert_allclose(rig.measured(), before, atol=0.01)
    np.testing.assert_allclose(c.command.position, before, atol=0.01)


def test_a_silent_device_faults_naming_the_joint(rig):
    b, sim, row = rig.backend, rig.sim, rig.row
    if row.one_device:
        pytest.skip("every joint is one device on one link: no joint falls silent alone; test_backend_ur.py::"
                    "test_link_loss_faults_in_the_cycle_that_sees_it_then_reconnects")
    c = rig.enabled_controller()
    k = min(2, b.n - 1)
    row.silence(sim, rig.ids[k])
    deadline = time.monotonic() + 2.0  # its silence is seen within the backend's reply time limit
    fault = rig.read()
    while fault is None and time.monotonic() < deadline:
        fault = rig.read()
    assert fault is not None and fault.joint == b.joint_names[k] and b.joint_names[k] in fault.message
    wait_until(lambda: (rig.cycle(), c.state is OperatingState.FAULT)[1], 2, interval=0, what="FAULT")
    err = rig.events("error")[-1]
    assert err["joint"] == b.joint_names[k] and f"{b.joint_names[k]!r}" in err["message"]


def test_device_status_maps_onto_the_crtk_state(rig):
    b, sim, row = rig.backend, rig.sim, rig.row
    c = rig.enabled_controller()
    k = min(3, b.n - 1)
    row.inject_error(sim, rig.ids[k])
    wait_until(lambda: (rig.cycle(), c.state is OperatingState.FAULT)[1], 2, interval=0, what="FAULT")
    assert b.device_status is DeviceStatus.FAULT
    err = rig.events("error")[-1]
    assert err["code"] == row.error_code
    if row.error_names_joint:
        assert err["joint"] == b.joint_names[k]
    # the backend's fault reaction: torque off (a transition: a CiA 402 drive takes it at a
    # SYNC, a UR powers off over a few cycles)
    wait_until(lambda: (rig.cycle(), not any(row.torque(sim, i) for i in rig.ids))[1], 2, interval=0,
               what="torque off")
    row.clear_errors(sim)
    if row.error_latched:  # only the device's reset (enable) clears it
        rig.cycle(5)
        assert b.device_status is DeviceStatus.FAULT
        rig.enable(2)
        assert rig.replies(2)[0]["ok"], rig.replies(2)
    wait_until(lambda: (rig.cycle(), any(e["code"] == "fault_cleared" for e in rig.events("status")))[1],
               2, interval=0, what="fault_cleared")
    assert b.device_status is DeviceStatus.OK
    if not row.error_latched:
        assert c.state is OperatingState.FAULT  # cleared, but never enabled by itself
        rig.enable(2)
    assert c.state is OperatingState.ENABLED


def test_a_slow_enable_keeps_the_loop_cycling(rig):
    b, sim, row = rig.backend, rig.sim, rig.row
    c = rig.make_controller()
    sim.set_torque_delay(1.0)
    rig.request(1, "enable")
    stamps, t0 = [], time.monotonic()
    while not rig.replies(1) and time.monotonic() - t0 < 5:
        rig.cycle()
        stamps.append(rig.fb.stamp)
        if not rig.replies(1):
            assert c.state is OperatingState.DISABLED and c.is_busy
    took = time.monotonic() - t0
    (reply,) = rig.replies(1)
    assert reply["ok"] and c.state is OperatingState.ENABLED and not c.is_busy and took >= 0.95
    # the cycles kept reading: the stamps advanced all along. An enable blocking the cycle would
    # freeze them for the whole 1 s torque delay (one or two cycles, one gap of 1 s). How many
    # cycles fit in the second, and how many saw a fresh sample, is the host's: a starved host
    # (CI beside other jobs) runs a fraction of them, a device-clocked bus repeats a stamp
    gaps = np.diff(stamps)
    assert np.all(gaps >= 0) and np.count_nonzero(gaps > 0) >= 10 and gaps.max() < 0.4, gaps.max()
    rig.cycle(20)
    assert len(rig.replies(1)) == 1


def test_the_backend_clamps_no_profile_limit(rig):
    """Core owns the profile's limits (docs/architecture.md, Limits): a position a little beyond
    a joint's limit (where core holds a joint enabled outside its limits, never snapping it onto
    the limit) reaches the device as given; a backend clamps only to the device's own range."""
    b, sim, row = rig.backend, rig.sim, rig.row
    if not row.room_beyond_limits:
        pytest.skip("the profile's limits are the device's own range ends (a gripper's stroke)")
    b.enable(rig.fb)
    here = rig.measured()
    j = int(np.argmin(np.array([jt.limits.position_max for jt in rig.profile.joints]) - here))  # closest to its max
    limit = rig.profile.joints[j].limits.position_max
    cmd = b.new_command()
    cmd.mode[:] = int(CommandMode.POSITION)
    goals = []
    for p in (limit, limit + 0.02):
        cmd.position[:] = here
        cmd.position[j] = p
        assert b.write(cmd) is None
        rig.measured()  # the simulator has taken the write
        goals.append(row.goal(sim, rig.ids[j]))
    units = abs(_counts_per_rad(rig.profile.joints[j], row))
    assert abs(goals[1] - goals[0]) >= 0.5 * 0.02 * units, (limit, goals)


def _owners(b) -> dict[int, tuple]:
    """Robot joint -> (the backend of its bus, its index there); a one-bus robot is its own bus."""
    parts = getattr(b, "parts", [b])
    return {b.joint_names.index(name): (p, k) for p in parts for k, name in enumerate(p.joint_names)}


def test_the_robot_declares_exactly_what_its_buses_do(rig):
    """issue 19 item 7: a robot on several buses reports exactly what each bus declares, and core
    acts on it: per joint its bus's capabilities (what it follows and measures) and pause
    behaviour; per namespace the commands its own bus's joints allow; the speed slider, goal
    checks and native homing of the bus that has them (a robot with a bus that needs homing starts
    not homed). A one-bus robot: its backend's own."""
    b, profile = rig.backend, rig.profile
    owners = _owners(b)
    parts = list({id(p): p for p, _ in owners.values()}.values())
    t = b.traits
    for i, (p, k) in owners.items():
        assert t.joints[i] == p.traits.joints[k], b.joint_names[i]
        assert t.stops_itself_on_pause[i] == p.traits.stops_itself_on_pause[k], b.joint_names[i]
    for name in ("goal_check", "native_homing", "speed_scaling", "cyclic_write"):
        assert getattr(t, name) == any(getattr(p.traits, name) for p in parts), name
    assert (t.clock is Clock.DEVICE) == any(p.traits.clock is Clock.DEVICE for p in parts)
    c = rig.make_controller()
    for ns in profile.namespaces:
        idx = [profile.joint_index(j) for j in ns.joints]
        p = owners[idx[0]][0]
        assert c.ns_caps[ns.name] == p.traits.capabilities_of([owners[i][1] for i in idx]), ns.name
    assert c.is_homed == (not any(p.traits.capabilities.needs_homing for p in parts))
    scaled = [p for p in parts if p.traits.speed_scaling]
    if scaled:  # the bus's slider, in operating_state once it reported one
        wait_until(lambda: (rig.cycle(), scaled[0].speed_fraction == scaled[0].speed_fraction)[1], 2, interval=0,
                   what="the speed slider reported")
        rig.cycle()
        assert c.operating_state()["target_speed_fraction"] == pytest.approx(scaled[0].speed_fraction)
    else:
        rig.cycle(3)
        assert "target_speed_fraction" not in c.operating_state()
    rig.enable(1)
    measured = rig.measured()
    for ns in profile.namespaces:  # goal checks: each namespace's own bus asks its device
        idx = [profile.joint_index(j) for j in ns.joints]
        steps = b.goal_check_steps(ns.name, "move_jp", measured[idx]) if t.goal_check else None
        assert (steps is not None) == owners[idx[0]][0].traits.goal_check, ns.name
        if steps is not None:
            steps.close()


def test_a_robot_that_homes_natively_starts_not_homed_and_homes_on_its_devices(rig):
    """issue 19 item 7: a bus that homes natively (a CiA 402 drive with ``homing``) makes the robot
    start not homed, and ``home`` runs the devices' own homing: the homing joints then read their
    home where they are (method 37 takes the current position as zero), every other joint keeps
    its place. Core's move-home (to the profile's home pose, 0 rad) would move every joint."""
    b, sim, row = rig.backend, rig.sim, rig.row
    if not b.traits.native_homing:
        pytest.skip("no bus of this robot homes natively")
    owners = _owners(b)
    homing = [i for i, (p, k) in owners.items() if p.traits.joints[k].needs_homing]
    for k, sid in enumerate(rig.ids):  # away from the home pose (0 rad)
        row.set_present(sim, sid, row.present(sim, sid) + 300 + 40 * k)
    c = rig.enabled_controller()
    assert not c.is_homed
    raw = [row.present(sim, sid) for sid in rig.ids]
    before = rig.measured()
    assert np.all(np.abs(before[homing]) > 0.001)
    rig.request(2, "home")
    assert c.is_busy and not c.is_homed
    deadline = time.monotonic() + 10
    while not rig.replies(2):
        assert time.monotonic() < deadline, "no reply to home"
        rig.cycle()
    assert rig.replies(2)[0]["ok"], rig.replies(2)
    assert c.is_homed and c.state is OperatingState.ENABLED
    rig.cycle(10)
    after = rig.measured()
    np.testing.assert_allclose(after[homing], 0.0, atol=0.01)  # the homing joints: zero where they are
    # joints well away from home (0 rad), where core's move-home would have taken them
    others = [i for i in range(b.n) if i not in homing and abs(before[i]) > 0.05]
    assert others
    for i in others:
        assert abs(row.present(sim, rig.ids[i]) - raw[i]) <= 2, b.joint_names[i]  # nothing moved
    np.testing.assert_allclose(after[others], before[others], atol=0.01)

"""Stepped everything on the serial buses (issue 19, item 4): no cycle carries more than a
bounded number of acknowledged transactions.

Every packet the backend sends goes through its SDK packet handler's ``txPacket``; the tests wrap
it and file each packet under the cycle it went out in (a cycle starts with its sync read). An
acknowledged transaction is a request to one servo (read, write, ping, reboot: it waits for that
servo's status); sync writes and broadcast writes are not; the sync read is the cycle's own.
Transactions are counted, never timed.
"""

from __future__ import annotations

import contextlib
import copy

import yaml

from crtk_bridge.core.actuator import Lifecycle
from crtk_bridge.profile import parse_profile

from .conftest import wait_until

with open("profiles/so101.yaml") as f:
    SO101 = yaml.safe_load(f)
with open("profiles/koch.yaml") as f:
    KOCH = yaml.safe_load(f)

BROADCAST = 0xFE


class BusLog:
    """The packets a backend sends, per cycle: (instruction, id, first parameter bytes)."""

    def __init__(self, backend, vendor: str):
        self.cycles: list[list[tuple[int, int, bytes]]] = [[]]
        ph = backend._ph
        real = ph.txPacket
        # Feetech: FF FF ID LEN INST params; Dynamixel 2.0: FF FF FD 00 ID LEN_L LEN_H INST params
        at = (2, 4, 5) if vendor == "feetech" else (4, 7, 8)

        def tx(port, packet):
            self.cycles[-1].append((packet[at[1]], packet[at[0]], bytes(packet[at[2]:at[2] + 8])))
            return real(port, packet)

        ph.txPacket = tx

    def new_cycle(self) -> None:
        self.cycles.append([])

    @staticmethod
    def acknowledged(cycle) -> list[tuple[int, int, bytes]]:
        """The cycle's requests to one servo (each waits for its status packet)."""
        return [p for p in cycle if p[1] != BROADCAST]


def run(backend, transition, log: BusLog, cmd=None, limit: int = 500) -> int:
    """The cycle (read, one transition step, write) until ``transition`` ends; returns cycles."""
    fb = backend.new_feedback()
    cmd = cmd or backend.new_command()
    for k in range(limit):
        log.new_cycle()
        backend.read(fb)
        done = transition.step()
        backend.write(cmd)
        if done:
            return k + 1
    raise AssertionError(f"{transition} did not end in {limit} cycles")


def feetech(sim_port: str):
    from crtk_bridge.backends.feetech.backend import FeetechBackend

    data = copy.deepcopy(SO101)
    data["backend"].update(port=sim_port, timeout_ms=100)
    return FeetechBackend(parse_profile(data, "so101.yaml"), source="so101.yaml")


def test_so101_disable_is_one_sync_write_then_one_servo_per_cycle():
    """DISABLE of a 6-servo SO-101: the first cycle switches every servo off with ONE sync write
    of Torque_Enable = 0 (no acknowledgement), then each cycle confirms one servo with one
    acknowledged write; no cycle carries more than that beside its sync read."""
    from crtk_bridge.backends.feetech import tables
    from crtk_bridge.sim.feetech import FeetechSimulator

    sim = FeetechSimulator.from_profile(parse_profile(SO101), link=None, control=None, emulate_baud=False)
    sim.start()
    try:
        b = feetech(sim.port)
        with b:
            b.configure()
            b.enable(b.new_feedback())
            assert all(sim.servo(sid).read("Torque_Enable") == 1 for sid in range(1, 7))
            log = BusLog(b, "feetech")
            cycles = run(b, b.begin(Lifecycle.DISABLE), log)
            steps = log.cycles[1:]
            torque = tables.STS_CONTROL_TABLE["Torque_Enable"].address
            # the first step's sync write reaches all six servos at once
            first = [p for p in steps[0] if p[0] == tables.INST_SYNC_WRITE]
            assert len(first) == 1 and first[0][2][0] == torque, steps[0]
            for cycle in steps:
                acked = BusLog.acknowledged(cycle)
                assert len(acked) <= 1, cycle  # one servo's confirmation per cycle, at most
                assert all(p[0] == tables.INST_WRITE and p[2][0] == torque for p in acked), cycle
                assert sum(p[0] == tables.INST_SYNC_READ for p in cycle) <= b._attempts  # the cycle's own
            confirmed = [p[1] for c in steps for p in BusLog.acknowledged(c)]
            assert confirmed == [1, 2, 3, 4, 5, 6] and cycles == 6
            assert all(sim.servo(sid).read("Torque_Enable") == 0 for sid in range(1, 7))
            assert not b.is_enabled
    finally:
        sim.stop()


@contextlib.contextmanager
def koch_enabled():
    """A Koch's simulator and its backend, opened, configured and enabled; stopped after."""
    from crtk_bridge.backends.dynamixel.backend import DynamixelBackend
    from crtk_bridge.sim.dynamixel import DynamixelSimulator

    sim = DynamixelSimulator.from_profile(parse_profile(KOCH))
    sim.start()
    try:
        data = copy.deepcopy(KOCH)
        data["backend"].update(port=sim.port, timeout_ms=100)
        b = DynamixelBackend(parse_profile(data, "koch.yaml"), source="koch.yaml")
        with b:
            b.configure()
            b.enable(b.new_feedback())
            yield sim, b
    finally:
        sim.stop()


def koch_in_velocity_mode(sim, b, speed: float):
    """Switch every joint of an enabled Koch to velocity mode (its MODE_SWITCH transition) at
    ``speed``; returns once every servo has taken a non-zero velocity goal. Returns the command."""
    from crtk_bridge.core.actuator import CommandMode, Transition

    cmd = b.new_command()
    cmd.mode[:] = CommandMode.VELOCITY
    cmd.velocity[:] = speed
    run(b, Transition(b.robot, Lifecycle.MODE_SWITCH, b.mode_switch_steps(cmd.mode), 2.0),
        BusLog(b, "dynamixel"), cmd)
    wait_until(lambda: all(sim.servo(sid).read("Goal_Velocity") != 0 for sid in range(1, 7)), 2.0,
               what="velocity goals applied (a sync write has no reply)")
    return cmd


def test_koch_disable_is_one_sync_write_then_one_servo_per_cycle():
    from crtk_bridge.backends.dynamixel import tables as T

    with koch_enabled() as (sim, b):
        log = BusLog(b, "dynamixel")
        assert run(b, b.begin(Lifecycle.DISABLE), log) == 6
        steps = log.cycles[1:]
        assert [p[0] for p in steps[0] if p[1] == BROADCAST][-1] == T.INST_SYNC_WRITE
        for cycle in steps:
            assert len(BusLog.acknowledged(cycle)) <= 1, cycle
        assert all(sim.servo(sid).read("Torque_Enable") == 0 for sid in range(1, 7))


def test_koch_mode_switch_is_one_joint_per_cycle_and_holds_until_done():
    """Position -> velocity mode on the six joints of a Koch: the MODE_SWITCH transition (the
    backend's mode_switch_steps) switches one joint per cycle -- its own acknowledged
    transactions, to that servo only: torque off, Operating_Mode, a zero goal, torque on -- and
    no velocity goal goes out before every joint is switched; then the cycle's write sends them."""
    from crtk_bridge.backends.dynamixel import tables as T
    from crtk_bridge.core.actuator import CommandMode, Transition

    with koch_enabled() as (sim, b):
        cmd = b.new_command()
        cmd.mode[:] = CommandMode.VELOCITY
        cmd.velocity[:] = 0.2
        steps = b.mode_switch_steps(cmd.mode)  # prepare: no bus
        assert steps is not None
        log = BusLog(b, "dynamixel")
        t = Transition(b.robot, Lifecycle.MODE_SWITCH, steps, 2.0)
        assert run(b, t, log, cmd) == 6
        goal_velocity = (104).to_bytes(2, "little")
        cycles = log.cycles[1:]
        for k, cycle in enumerate(cycles):
            acked = BusLog.acknowledged(cycle)
            assert {p[1] for p in acked} == {k + 1}, cycle  # one servo's work per cycle
            assert len(acked) <= 5, cycle  # its 4 writes and nothing else (no position read)
            assert sum(p[0] in (T.INST_SYNC_READ, T.INST_FAST_SYNC_READ) for p in cycle) <= b._attempts
            if k < len(cycles) - 1:  # the switched joints hold (a zero goal at most) until the last one's step
                for p in cycle:
                    if p[0] == T.INST_SYNC_WRITE and p[2][:2] == goal_velocity:
                        body = p[2][4:]
                        assert not any(any(body[j + 1:j + 5]) for j in range(0, len(body), 5)), cycle  # every value zero
        assert all(sim.servo(sid).read("Operating_Mode") == 1 for sid in range(1, 7))
        assert all(sim.servo(sid).read("Torque_Enable") == 1 for sid in range(1, 7))
        assert b.mode_switch_steps(cmd.mode) is None  # done: the device follows these modes
        # the last cycle's write (after the step that ended it) sends the velocity goals
        assert any(p[0] == T.INST_SYNC_WRITE and p[2][:2] == goal_velocity for p in cycles[-1])


def test_koch_switch_back_to_position_stops_every_velocity_joint_first():
    """Velocity -> position mode (a hold): the switch's first cycle sends ONE sync write of zero
    velocity goals to every joint it will switch (none keeps moving while it waits its turn),
    then switches one joint per cycle, each to a fresh hold position."""
    from crtk_bridge.backends.dynamixel import tables as T
    from crtk_bridge.core.actuator import CommandMode, Transition

    with koch_enabled() as (sim, b):
        cmd = koch_in_velocity_mode(sim, b, 0.3)
        cmd.mode[:] = CommandMode.POSITION
        log = BusLog(b, "dynamixel")
        assert run(b, Transition(b.robot, Lifecycle.MODE_SWITCH, b.mode_switch_steps(cmd.mode), 2.0),
                   log, b.new_command()) == 6
        first = log.cycles[1]
        stop = [p for p in first if p[0] == T.INST_SYNC_WRITE]
        assert stop and stop[0][2][:2] == (104).to_bytes(2, "little"), first  # Goal_Velocity, all six
        assert first.index(stop[0]) < first.index(BusLog.acknowledged(first)[0])  # before any switch
        for k, cycle in enumerate(log.cycles[1:]):
            acked = BusLog.acknowledged(cycle)
            assert {p[1] for p in acked} == {k + 1} and len(acked) <= 5, cycle  # incl. the position read
        assert all(sim.servo(sid).read("Operating_Mode") in (4, 5) for sid in range(1, 7))


def test_koch_velocity_joint_waiting_for_its_mode_switch_gets_a_zero_goal_every_cycle():
    """A stop turns a velocity-mode joint's command into a position hold, but core starts the mode
    switch only when no other transition runs (a composite's PAUSE, a native HOME, a goal check may
    last seconds). Until then every write sends that joint a zero Goal_Velocity: it never keeps
    turning at its last speed (found by the session's review: it did, for the whole transition)."""
    from crtk_bridge.core.actuator import CommandMode

    with koch_enabled() as (sim, b):
        koch_in_velocity_mode(sim, b, 0.3)
        hold = b.new_command()
        hold.mode[:] = CommandMode.POSITION  # core's hold; no MODE_SWITCH run (another transition is)
        fb = b.new_feedback()
        for _ in range(3):
            assert b.read(fb) is None
            assert b.write(hold) is None
        wait_until(lambda: all(sim.servo(sid).read("Goal_Velocity") == 0 for sid in range(1, 7)), 2.0,
                   what="a zero velocity goal on every joint still in velocity mode")
        assert all(sim.servo(sid).read("Operating_Mode") == 1 for sid in range(1, 7))  # not switched yet

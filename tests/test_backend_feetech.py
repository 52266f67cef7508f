"""FeetechBackend against the STS bus simulator (real SDK packets on a pty), and its port fixes.

Every wait is a poll with a deadline; nothing sleeps and hopes.
"""

from __future__ import annotations

import copy
import math
import os
import threading
import time
import tty

import numpy as np
import pytest
import yaml
from scservo_sdk import COMM_RX_TIMEOUT, COMM_SUCCESS, PacketHandler, PortHandler

from crtk_bridge.backends import create_backend
from crtk_bridge.backends.feetech import tables
from crtk_bridge.backends.feetech.backend import FeetechBackend
from crtk_bridge.backends.feetech.port import FastPortHandler
from crtk_bridge.core.actuator import CommandMode
from crtk_bridge.errors import BackendError, ProfileError
from crtk_bridge.profile import parse_profile

from .conftest import wait_until

with open("profiles/so101.yaml") as f:
    SO101 = yaml.safe_load(f)
TICK = 2 * math.pi / 4096


def profile_data(**backend) -> dict:
    data = copy.deepcopy(SO101)
    data["backend"].update(backend)
    return data


# ---------------------------------------------------------------- simulator helpers

def set_present(sim, sid: int, ticks: int) -> None:
    """Place a torque-off servo at ``ticks`` (as if moved by hand)."""
    sim.servo(sid).write("Present_Position", ticks)


def sim_reg(sim, sid: int, name: str) -> int:
    return sim.servo(sid).read(name)


def wait_goals(sim, goals: dict[int, int]) -> None:
    """A sync write has no reply: wait (with a deadline) until the sim has applied it."""
    wait_until(lambda: all(sim_reg(sim, sid, "Goal_Position") == g for sid, g in goals.items()),
               2.0, what=f"sim goals {goals}, got "
               f"{ {sid: sim_reg(sim, sid, 'Goal_Position') for sid in goals} }")


@pytest.fixture
def sim():
    from crtk_bridge.sim.feetech import FeetechSimulator

    s = FeetechSimulator.from_profile(parse_profile(SO101), link=None, control=None,
                                      emulate_baud=False)
    s.start()
    yield s
    s.stop()


def make_backend(sim, data=None, **backend) -> FeetechBackend:
    """The backend on the in-process simulator. Its packet margin (``timeout_ms``) is 100 ms
    unless a test gives one: the simulator is a thread of this process, which a loaded host may
    not run within the profile's 10 ms (only a read that gets no reply waits it out)."""
    data = data or profile_data()
    backend.setdefault("timeout_ms", 100)
    data["backend"].update(port=sim.port, **backend)
    return FeetechBackend(parse_profile(data, "so101.yaml"), source="so101.yaml")


@pytest.fixture
def backend(sim):
    b = make_backend(sim)
    b.open()
    b.configure()
    yield b
    b.close()


def read_ok(b, fb):
    fault = b.read(fb)
    assert fault is None, fault
    return fb


# ---------------------------------------------------------------- profile validation (no bus)

def test_bad_backend_key_names_it():
    with pytest.raises(ProfileError, match=r"so101\.yaml: backend\.baud_rate: unknown key for the feetech "
                                           r"backend; valid keys, nearest first: baudrate, "):
        FeetechBackend(parse_profile(profile_data(baud_rate=1)), source="so101.yaml")


def test_bad_backend_value_names_key():
    with pytest.raises(ProfileError, match=r"backend\.read_retries"):
        FeetechBackend(parse_profile(profile_data(read_retries=-1)))
    with pytest.raises(ProfileError, match=r"backend\.baudrate: 123 is not supported"):
        FeetechBackend(parse_profile(profile_data(baudrate=123)))


def test_missing_port_names_key():
    data = profile_data()
    del data["backend"]["port"]
    with pytest.raises(ProfileError, match=r"backend\.port: required"):
        FeetechBackend(parse_profile(data))


def test_joint_needs_id_and_known_model():
    data = profile_data()
    del data["joints"][2]["id"]
    data["joints"][5]["model"] = "xl430"
    with pytest.raises(ProfileError) as exc:
        FeetechBackend(parse_profile(data))
    assert "joints[2] (elbow_flex).id: required" in str(exc.value)
    assert "joints[5] (gripper).model: unknown model 'xl430'" in str(exc.value)


def test_registry_builds_it_and_capabilities():
    b = create_backend(parse_profile(profile_data()))
    assert isinstance(b, FeetechBackend)
    c = b._traits_hook().capabilities  # what open() declares: from the profile alone, no bus needed
    assert (c.position, c.velocity, c.effort) == (True, False, False)
    assert c.measures_velocity and c.measures_effort and not c.needs_homing and c.can_free
    data = profile_data()
    del data["joints"][0]["effort_per_amp"]
    assert not FeetechBackend(parse_profile(data))._traits_hook().capabilities.measures_effort


def test_open_missing_port_raises_backend_error():
    b = FeetechBackend(parse_profile(profile_data(port="/nonexistent/ttyACM9")))
    with pytest.raises(BackendError, match=r"so101: cannot open port /nonexistent/ttyACM9"):
        b.open()


# ---------------------------------------------------------------- against the simulator

def test_read_positions_match_sim_ticks_with_calibration(sim):
    data = profile_data()
    data["joints"][1]["calibration"]["direction"] = -1
    b = make_backend(sim, data)
    with b:
        b.configure()
        set_present(sim, 1, 2048 + 512)
        set_present(sim, 2, 2048 + 512)  # direction -1
        set_present(sim, 6, 3000)
        fb = b.new_feedback()
        before = time.time()
        read_ok(b, fb)
        assert fb.position[0] == pytest.approx(512 * TICK)
        assert fb.position[1] == pytest.approx(-512 * TICK)
        assert fb.position[5] == pytest.approx((3000 - 2048) * TICK)
        assert fb.position[2] == pytest.approx(0.0)
        assert before <= fb.stamp <= time.time()
        assert np.all(fb.velocity == 0)


def test_enable_holds_position_then_torque_on(sim, backend):
    targets = {1: 1500, 2: 2600, 3: 2048, 4: 1000, 5: 3900, 6: 2500}
    for sid, t in targets.items():
        set_present(sim, sid, t)
        sim.servo(sid).write("Goal_Position", 0)  # a stale goal the arm must not jump to
    fb = backend.new_feedback()  # deliberately stale (all zero): enable must read fresh
    backend.enable(fb)
    assert backend.is_enabled
    for sid, t in targets.items():
        assert sim_reg(sim, sid, "Torque_Enable") == 1
        assert sim_reg(sim, sid, "Goal_Position") == t
    # torque is on and the goal is where it stood: nothing moves over a few read cycles
    for _ in range(20):
        read_ok(backend, fb)
        for sid, t in targets.items():
            assert abs(sim_reg(sim, sid, "Present_Position") - t) <= 1


def test_write_position_sets_goal_and_converges(sim, backend):
    fb = backend.new_feedback()
    backend.enable(fb)
    cmd = backend.new_command()
    cmd.mode[:] = CommandMode.POSITION
    cmd.position[:] = [0.3, -0.2, 0.5, -0.4, 1.0, 0.6]
    cmd.mode[4] = CommandMode.NONE  # wrist_roll: keeps the goal set at enable
    assert backend.write(cmd) is None
    expect = [round(2048 + p / TICK) for p in cmd.position]
    expect[4] = 2048
    wait_goals(sim, dict(zip(range(1, 7), expect)))

    def converged():
        read_ok(backend, fb)
        backend.write(cmd)
        err = np.abs(fb.position - np.where(cmd.mode == CommandMode.POSITION, cmd.position, 0.0))
        return np.all(err < 3 * TICK)

    wait_until(converged, 10.0, what="positions to converge to the command")


def test_out_of_range_commands_clamp_to_calibration_range(sim, backend):
    backend.enable(backend.new_feedback())
    cmd = backend.new_command()
    cmd.mode[:] = CommandMode.POSITION
    cmd.position[:] = 10.0  # rad: far beyond every range
    cmd.position[5] = -10.0
    assert backend.write(cmd) is None
    ranges = {j["id"]: j["calibration"]["range"] for j in SO101["joints"]}
    wait_goals(sim, {sid: (lo if sid == 6 else hi) for sid, (lo, hi) in ranges.items()})


def test_writes_nothing_while_disabled(sim, backend):
    cmd = backend.new_command()
    cmd.mode[:] = CommandMode.POSITION
    cmd.position[:] = 0.5
    assert backend.write(cmd) is None
    assert all(sim_reg(sim, sid, "Torque_Enable") == 0 for sid in range(1, 7))
    assert all(sim_reg(sim, sid, "Goal_Position") != round(2048 + 0.5 / TICK)
               for sid in range(1, 7))


def test_nan_command_is_not_sent(sim, backend):
    backend.enable(backend.new_feedback())
    cmd = backend.new_command()
    cmd.mode[:] = CommandMode.POSITION
    cmd.position[:] = 0.1
    cmd.position[2] = float("nan")
    fault = backend.write(cmd)
    assert fault is not None and fault.code == "invalid_command" and fault.joint == "elbow_flex"
    wait_goals(sim, {1: round(2048 + 0.1 / TICK), 3: 2048})


def test_disable_turns_torque_off_everywhere(sim, backend):
    backend.enable(backend.new_feedback())
    assert all(sim_reg(sim, sid, "Torque_Enable") == 1 for sid in range(1, 7))
    backend.disable()
    assert not backend.is_enabled
    assert all(sim_reg(sim, sid, "Torque_Enable") == 0 for sid in range(1, 7))


def test_configure_writes_registers_with_torque_off(sim):
    b = make_backend(sim, p_coefficient=20, return_delay=3)
    with b:
        for sid in range(1, 7):
            sim.servo(sid).write("Torque_Enable", 1)
        b.configure()
        for sid in range(1, 7):
            assert sim_reg(sim, sid, "Torque_Enable") == 0
            assert sim_reg(sim, sid, "P_Coefficient") == 20
            assert sim_reg(sim, sid, "D_Coefficient") == 32
            assert sim_reg(sim, sid, "Return_Delay_Time") == 3
            assert sim_reg(sim, sid, "Acceleration") == 254
            assert sim_reg(sim, sid, "Operating_Mode") == 0


def test_missing_servo_fails_open_naming_joint(sim):
    data = profile_data()
    data["joints"].append({**copy.deepcopy(data["joints"][3]), "name": "extra_joint", "id": 7})
    data["namespaces"][0]["joints"].append("extra_joint")
    b = make_backend(sim, data, timeout_ms=5, read_retries=0)
    with pytest.raises(BackendError) as exc:
        b.open()
    msg = str(exc.value)
    assert msg.startswith("so101: joint 'extra_joint' (id 7) did not answer ping on ")
    assert "There is no status packet!" in msg
    assert "shoulder_pan" not in msg  # only the silent one is named
    b.close()  # idempotent after a failed open


def test_read_returns_bus_fault_when_sim_stops(sim, backend):
    fb = read_ok(backend, backend.new_feedback())
    good = fb.position.copy()
    sim.stop()
    t0 = time.monotonic()
    fault = backend.read(fb)
    assert time.monotonic() - t0 < 1.0
    # the simulator's pty is gone (EIO on the port): the port itself is lost, not a servo
    assert fault is not None and fault.code == "port_lost", fault
    assert not fault.transient
    assert fault.message.startswith(f"so101: serial port {backend.port_name} is gone")
    assert np.array_equal(fb.position, good)  # a failed read leaves the feedback untouched
    assert backend.write(backend.new_command()) is None  # nothing to send: no exception either


def test_status_error_bit_is_a_servo_fault(sim, backend):
    fb = backend.new_feedback()
    read_ok(backend, fb)
    sim.servo(6).registers[tables.STS_CONTROL_TABLE["Status"].address] = tables.ERR_OVERLOAD
    fault = backend.read(fb)
    assert fault is not None
    assert fault.code == "servo_error" and fault.joint == "gripper"
    assert fault.register == "Status" and fault.value == 0x20 and not fault.transient
    assert fault.message == "so101: joint 'gripper' (id 6) reports overload (Status=0x20)"


def test_effort_estimate_follows_current_with_load_sign(sim, backend):
    fb = backend.new_feedback()
    read_ok(backend, fb)
    assert np.all(fb.effort == 0)  # torque off: the sim draws no current
    backend.enable(fb)
    cmd = backend.new_command()
    cmd.mode[:] = CommandMode.POSITION
    cmd.position[0], cmd.position[1] = 1.0, -1.0  # pushing + on joint 0, - on joint 1
    assert backend.write(cmd) is None
    max_nm = 300 * tables.CURRENT_UNIT_A * 0.95  # sim's stall current
    wait_until(lambda: read_ok(backend, fb).effort[0] > 0.1 and fb.effort[1] < -0.1, 2.0,
               what="effort to follow the pushing direction")
    assert fb.effort[0] <= max_nm and fb.effort[1] >= -max_nm


def test_silent_servo_mid_run_is_a_transient_fault_naming_it(sim):
    b = make_backend(sim, timeout_ms=5, read_retries=1)
    with b:
        fb = read_ok(b, b.new_feedback())
        good = fb.position.copy()
        set_present(sim, 1, 2500)  # would change position[0] if stale/partial data leaked
        sim.set_fault(3, "silent")
        t0 = time.monotonic()
        fault = b.read(fb)
        elapsed = time.monotonic() - t0
        assert fault is not None and fault.code == "bus_timeout" and fault.transient
        assert fault.joint == "elbow_flex"
        assert "joint 'elbow_flex' (id 3)" in fault.message and "2 attempts" in fault.message
        assert "There is no status packet!" in fault.message
        assert np.array_equal(fb.position, good)  # nothing of the failed read is used
        assert elapsed < 0.5  # 2 attempts x (wire time + 5 ms), generous for a noisy host
        sim.clear_faults()
        read_ok(b, fb)  # recovers on the next cycle, and the stale late bytes are gone
        assert fb.position[0] == pytest.approx((2500 - 2048) * TICK)


def test_a_run_of_failed_reads_names_the_joint_its_deepest_read_reached(sim):
    """The FAULT ending a run of failed reads (safety.bus_errors_max) names one joint: the silent
    one, even when a read of the run failed earlier on the bus -- a reply made late by a loaded
    host; here the whole bus unplugged for one read -- since every servo from the first missing
    on went unanswered in that read too. A good read ends the run."""
    b = make_backend(sim, timeout_ms=5, read_retries=0)
    with b:
        fb = read_ok(b, b.new_feedback())
        sim.set_fault(3, "silent")
        wait_until(lambda: getattr(b.read(fb), "joint", None) == "elbow_flex", 2, what="a read naming elbow_flex")
        sim.set_unplugged(True)  # no servo answers this read: the first one asked is missing
        fault = b.read(fb)
        assert fault.code == "bus_timeout" and fault.joint == "elbow_flex", fault
        assert "joint 'elbow_flex' (id 3)" in fault.message
        sim.set_unplugged(False)
        assert b.read(fb).joint == "elbow_flex"
        sim.clear_faults()
        wait_until(lambda: b.read(fb) is None, 2, what="a good read")
        sim.set_unplugged(True)  # a new run
        assert b.read(fb).joint == "shoulder_pan"


def test_corrupt_reply_is_bus_corrupt(sim, backend):
    sim.set_fault(4, "corrupt")
    fault = backend.read(backend.new_feedback())
    assert fault is not None and fault.code == "bus_corrupt" and fault.transient
    assert fault.joint == "wrist_flex"


def test_enable_refused_when_a_servo_reports_an_error(sim, backend):
    sim.set_fault(6, "error_bits", tables.ERR_OVERLOAD)
    with pytest.raises(BackendError, match=r"so101: joint 'gripper' \(id 6\) reports overload"):
        backend.enable(backend.new_feedback())
    assert not backend.is_enabled
    assert all(sim_reg(sim, sid, "Torque_Enable") == 0 for sid in range(1, 7))


def test_disable_tries_every_servo_and_names_the_silent_one(sim):
    b = make_backend(sim, timeout_ms=5, read_retries=0)
    with b:
        b.configure()
        b.enable(b.new_feedback())
        sim.set_fault(2, "silent")
        with pytest.raises(BackendError) as exc:
            b.disable()
        assert "joint 'shoulder_lift' (id 2)" in str(exc.value)
        assert "Torque_Enable" in str(exc.value)
        assert "shoulder_pan" not in str(exc.value)
        # every other servo was still switched off (the silent one did receive it too)
        assert all(sim_reg(sim, sid, "Torque_Enable") == 0 for sid in (1, 3, 4, 5, 6))


def test_read_write_cycle_is_one_transaction_each(sim, backend):
    """Sanity of the hot path: many cycles, no faults, no exceptions."""
    backend.enable(backend.new_feedback())
    fb, cmd = backend.new_feedback(), backend.new_command()
    cmd.mode[:] = CommandMode.POSITION
    for k in range(200):
        read_ok(backend, fb)
        cmd.position[:] = 0.001 * k
        assert backend.write(cmd) is None


# ---------------------------------------------------------------- the port fixes (raw pty)

@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    yield master, path
    os.close(master)
    os.close(slave)


def status_packet(sid: int, data: bytes = b"", err: int = 0) -> bytes:
    body = bytes([sid, len(data) + 2, err]) + data
    return b"\xff\xff" + body + bytes([~sum(body) & 0xFF])


def answer_one_read(master: int, value: int) -> threading.Thread:
    """Reply to the next READ instruction on the pty with a 2-byte ``value``."""

    def run():
        buf = b""
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            try:
                buf += os.read(master, 64)
            except BlockingIOError:
                continue
            i = buf.find(b"\xff\xff")
            if i >= 0 and len(buf) >= i + 8 and buf[i + 4] == tables.INST_READ:
                os.write(master, status_packet(buf[i + 2], value.to_bytes(2, "little")))
                return

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


@pytest.mark.parametrize("handler, fooled", [(PortHandler, True), (FastPortHandler, False)])
def test_stale_input_bytes_do_not_answer_the_next_request(pty_pair, handler, fooled):
    master, path = pty_pair
    port = handler(path)
    assert port.openPort()
    try:
        ph = PacketHandler(0)
        # a late reply of a previous transaction (same id) plus line noise, already queued
        os.write(master, b"\x13\x37" + status_packet(1, (1111).to_bytes(2, "little")))
        wait_until(lambda: port.getBytesAvailable() > 0, 2.0, what="stale bytes to arrive")
        t = answer_one_read(master, 2222)
        value, result, _ = ph.read2ByteTxRx(port, 1, 56)
        t.join()
        assert result == COMM_SUCCESS
        # the plain SDK takes the stale packet as the answer: the gap this subclass fixes
        assert value == (1111 if fooled else 2222)
    finally:
        port.closePort()


def test_silent_bus_times_out_quickly_without_spinning(pty_pair):
    _, path = pty_pair
    port = FastPortHandler(path, margin_ms=30.0)
    assert port.openPort()
    try:
        ph = PacketHandler(0)
        wall0, cpu0 = time.monotonic(), time.thread_time()
        _, result, _ = ph.ping(port, 1)
        wall, cpu = time.monotonic() - wall0, time.thread_time() - cpu0
        assert result == COMM_RX_TIMEOUT
        assert wall >= 0.029  # it did wait for the deadline...
        assert wall < 1.0  # ...a bounded one
        assert cpu < 0.5 * wall  # ...asleep in select, not busy-polling like the SDK
    finally:
        port.closePort()


def test_packet_timeout_is_wire_time_plus_margin():
    port = FastPortHandler("/dev/null", margin_ms=7.0)
    port.tx_time_per_byte = 0.01  # ms per byte at 1 Mbps
    port.setPacketTimeout(126)
    assert port.packet_timeout == pytest.approx(1.26 + 7.0)


def test_a_short_reply_that_trips_the_sdk_is_a_retried_corrupt_reply(backend):
    """scservo's ping indexes the model number of the reply it got: a short (stale, truncated)
    one raises IndexError inside the SDK. That is a corrupt reply, retried, never an escape."""
    real, calls = backend._ph.ping, []

    def short_once(port, sid):
        calls.append(sid)
        if len(calls) == 1:
            raise IndexError("list index out of range")
        return real(port, sid)

    backend._ph.ping = short_once
    model, result, _ = backend._txrx(backend._ph.ping, 1)
    assert result == 0 and model == 777 and calls == [1, 1]

    def always_short(port, sid):
        raise IndexError("list index out of range")

    backend._ph.ping = always_short
    assert backend._txrx(backend._ph.ping, 1)[1] == backend.RX_CORRUPT
    with pytest.raises(BackendError, match=r"did not answer ping"):
        backend._check_servos()

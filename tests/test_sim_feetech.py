"""The STS3215 bus simulator, driven through its pty by the REAL scservo_sdk (and raw bytes).

Motion is checked two ways: over the bus with a deadline (the real clock), and exactly with a fake
physics clock (``sim.clock``), so no test depends on how long a sleep happened to last.
The SDK waits patiently for a reply that must come, and where silence is the answer the test waits
until the simulator has handled what was sent (tests/sdk_patience.py): a loaded host may hold the
simulator's thread back longer than the SDK's packet timeout.
"""

from __future__ import annotations

import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import serial
import scservo_sdk as sdk

from crtk_bridge.backends.feetech import tables as T
from crtk_bridge.profile import load_profile
from crtk_bridge.sim import SimulatorError
from crtk_bridge.sim.control import control_request
from crtk_bridge.sim.feetech import VELOCITY_MAX_TPS, FeetechSimulator

from .conftest import wait_until
from .sdk_patience import REPLY_PATIENCE_MS, caught_up, patient_port, silence_expected

PatientPort = patient_port(sdk.PortHandler)

ROOT = Path(__file__).resolve().parent.parent
SO101 = ROOT / "profiles" / "so101.yaml"
IDS = [1, 2, 3, 4, 5, 6]
BLOCK = (T.PRESENT_BLOCK_START, T.PRESENT_BLOCK_LEN)  # 56, 15


def checksum(body: bytes) -> int:
    return ~sum(body) & 0xFF


def packet(sid: int, inst: int, params: bytes = b"") -> bytes:
    body = bytes((sid, len(params) + 2, inst)) + params
    return b"\xff\xff" + body + bytes((checksum(body),))


class RawWire:
    """Raw bytes to the bus (a sole client): ``read`` waits up to REPLY_PATIENCE_MS for what must
    come; ``quiet`` says whether nothing came once the simulator handled everything sent."""

    def __init__(self, sim):
        self.sim = sim
        self.ser = serial.Serial(sim.port, 1_000_000, timeout=REPLY_PATIENCE_MS / 1000)
        self.sent = 0

    def write(self, data: bytes) -> None:
        self.ser.write(data)
        self.ser.flush()
        self.sent += len(data)

    def read(self, n: int) -> bytes:
        return self.ser.read(n)

    def quiet(self) -> bool:
        caught_up(self.sim, self.sent)
        return self.ser.in_waiting == 0

    def close(self) -> None:
        self.ser.close()


class FakeClock:
    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def tmp():
    d = tempfile.mkdtemp(prefix="sim-")  # Unix socket paths must stay < 108 bytes
    yield Path(d)
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def sim(tmp):
    s = FeetechSimulator(IDS, control=tmp / "ctl", initial_positions={i: 1000 + 100 * i for i in IDS})
    with s:
        yield s


@pytest.fixture
def bus(sim):
    port = PatientPort(sim.port)
    assert port.openPort()
    yield port, sdk.PacketHandler(0)
    port.closePort()


def sync_read(port, ph, ids, start=BLOCK[0], length=BLOCK[1]):
    group = sdk.GroupSyncRead(port, ph, start, length)
    for i in ids:
        assert group.addParam(i)
    return group, group.txRxPacket()


def sync_write_goals(port, ph, goals: dict[int, int]):
    group = sdk.GroupSyncWrite(port, ph, 42, 2)
    for sid, ticks in goals.items():
        raw = T.encode_sign_magnitude(ticks, 15)
        assert group.addParam(sid, [raw & 0xFF, raw >> 8])
    assert group.txPacket() == sdk.COMM_SUCCESS


def present(port, ph, sid):
    raw, res, _ = ph.read2ByteTxRx(port, sid, 56)
    assert res == sdk.COMM_SUCCESS
    return T.decode_sign_magnitude(raw, 15)


# ------------------------------------------------------------------ protocol

def test_ping_returns_model_and_missing_id_times_out(sim, bus):
    port, ph = bus
    for sid in IDS:
        assert ph.ping(port, sid) == (777, sdk.COMM_SUCCESS, 0)
    with silence_expected(sim, port):
        model, res, _ = ph.ping(port, 42)
    assert res == sdk.COMM_RX_TIMEOUT and model == 0


def test_defaults_and_register_read_write(sim, bus):
    port, ph = bus
    assert ph.read1ByteTxRx(port, 3, 0)[0] == 3 and ph.read1ByteTxRx(port, 3, 1)[0] == 10  # firmware
    assert ph.read1ByteTxRx(port, 3, 5)[0] == 3  # ID
    assert ph.read2ByteTxRx(port, 3, 11)[0] == 4095 and ph.read2ByteTxRx(port, 3, 9)[0] == 0
    assert ph.read2ByteTxRx(port, 3, 48)[0] == 1000 and ph.read1ByteTxRx(port, 3, 55)[0] == 1
    assert ph.read1ByteTxRx(port, 3, 62)[0] == 74 and ph.read1ByteTxRx(port, 3, 63)[0] == 30
    assert ph.read2ByteTxRx(port, 3, 42)[0] == 1300 == present(port, ph, 3)  # goal = present

    assert ph.write1ByteTxRx(port, 2, 40, 1) == (sdk.COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 2, 40)[:2] == (1, sdk.COMM_SUCCESS)
    assert sim.servo(2).read("Torque_Enable") == 1
    assert ph.write1ByteTxRx(port, 2, 21, 16) == (sdk.COMM_SUCCESS, 0)  # EEPROM, Lock=1: kept anyway
    assert sim.servo(2).read("P_Coefficient") == 16
    # read-only registers ignore bus writes (the write is still acknowledged)
    assert ph.write2ByteTxRx(port, 2, 56, 7) == (sdk.COMM_SUCCESS, 0)
    assert ph.write2ByteTxRx(port, 2, 3, 5) == (sdk.COMM_SUCCESS, 0)
    assert present(port, ph, 2) == 1200 and ph.read2ByteTxRx(port, 2, 3)[0] == 777
    # negative goals are sign-magnitude on the wire and decoded by the sim
    assert ph.write1ByteTxRx(port, 4, 40, 0)[0] == sdk.COMM_SUCCESS
    assert ph.write2ByteTxRx(port, 4, 42, T.encode_sign_magnitude(-5, 15))[0] == sdk.COMM_SUCCESS
    assert sim.servo(4).read("Goal_Position") == -5


def test_sync_read_present_block_of_six_servos(sim, bus):
    port, ph = bus
    sim.servo(5).write("Present_Position", 3210)
    group, res = sync_read(port, ph, IDS)
    assert res == sdk.COMM_SUCCESS
    expected = {i: 1000 + 100 * i for i in IDS} | {5: 3210}
    for sid in IDS:
        assert group.getData(sid, 56, 2) == expected[sid]
        assert group.getData(sid, 62, 1) == 74 and group.getData(sid, 63, 1) == 30
        assert group.getData(sid, 66, 1) == 0  # not moving
        assert bytes(group.data_dict[sid]) == bytes(sim.servo(sid).registers[56:71])
    # replies come in request order (the SDK drops packets of ids it is not waiting for)
    group, res = sync_read(port, ph, [6, 3, 1])
    assert res == sdk.COMM_SUCCESS and [group.getData(i, 56, 2) for i in (6, 3, 1)] == [1600, 1300, 1100]


def test_sync_read_with_missing_id_fails_with_rx_timeout(sim, bus):
    port, ph = bus
    with silence_expected(sim, port):
        _, res = sync_read(port, ph, [1, 2, 9, 3])
    assert res == sdk.COMM_RX_TIMEOUT
    # the bus is usable right after
    _, res = sync_read(port, ph, IDS)
    assert res == sdk.COMM_SUCCESS


def test_sync_write_goal_with_torque_on_converges(sim, bus):
    port, ph = bus
    for sid in (1, 2):
        assert ph.write1ByteTxRx(port, sid, 40, 1)[0] == sdk.COMM_SUCCESS
    sync_write_goals(port, ph, {1: 4000, 2: 800})  # 0.85 s of travel for servo 1
    seen_moving = []

    def arrived():
        group, res = sync_read(port, ph, [1, 2])
        assert res == sdk.COMM_SUCCESS
        seen_moving.append((group.getData(1, 66, 1), T.decode_sign_magnitude(group.getData(1, 58, 2), 15),
                            group.getData(1, 69, 2)))
        return group.getData(1, 56, 2) == 4000 and group.getData(2, 56, 2) == 800

    wait_until(arrived, 5.0, what="servos 1 and 2 at their goals")
    assert any(m == 1 and v > 0 and cur > 0 for m, v, cur in seen_moving), seen_moving
    assert max(v for _, v, _ in seen_moving) <= VELOCITY_MAX_TPS
    wait_until(lambda: sim.servo(1).read("Moving") == 0, 2.0, what="servo 1 settled")
    assert sim.servo(1).read("Present_Velocity") == 0


def test_physics_with_fake_clock(sim, bus):
    port, ph = bus
    clock = FakeClock()
    sim.clock = clock
    s = sim.servo(1)  # at 1100
    # torque off: a goal changes nothing, however long we wait
    s.write("Goal_Position", 2100)
    clock.t += 10.0
    assert present(port, ph, 1) == 1100
    assert ph.read2ByteTxRx(port, 1, 58)[0] == 0 and ph.read1ByteTxRx(port, 1, 66)[0] == 0
    # torque on: speed-capped phase, then first-order tail
    assert ph.write1ByteTxRx(port, 1, 40, 1)[0] == sdk.COMM_SUCCESS
    clock.t += 0.1
    assert present(port, ph, 1) == 1100 + round(VELOCITY_MAX_TPS * 0.1)
    assert s.read("Present_Velocity") == round(VELOCITY_MAX_TPS) and s.read("Moving") == 1
    assert s.read("Present_Load") > 0 and s.read("Present_Current") > 0
    clock.t += 1.0
    assert present(port, ph, 1) == 2100 and s.read("Moving") == 0
    # Goal_Velocity caps the speed; negative direction reports a negative velocity
    s.write("Goal_Velocity", 500)
    s.write("Goal_Position", 1100)
    clock.t += 0.1
    assert s.read("Present_Position") == 2050 and s.read("Present_Velocity") == -500
    assert s.read("Present_Load") < 0
    # goals are clamped into the position limits
    s.write("Goal_Velocity", 0)
    assert ph.write2ByteTxRx(port, 1, 11, 3000)[0] == sdk.COMM_SUCCESS
    s.write("Goal_Position", 4000)
    clock.t += 2.0
    assert s.read("Present_Position") == 3000
    # Present = Actual - Homing_Offset (sign bit 11)
    assert ph.write2ByteTxRx(port, 1, 31, T.encode_sign_magnitude(-100, 11))[0] == sdk.COMM_SUCCESS
    assert present(port, ph, 1) == 3100


def test_reg_write_applies_only_on_action(sim, bus):
    port, ph = bus
    assert ph.regWriteTxRx(port, 3, 42, 2, [0x34, 0x08]) == (sdk.COMM_SUCCESS, 0)
    assert sim.servo(3).read("Goal_Position") == 1300
    assert ph.action(port, 3) == sdk.COMM_SUCCESS  # by id: acknowledged
    assert sim.servo(3).read("Goal_Position") == 0x834
    # broadcast ACTION applies every pending REG_WRITE, no reply
    for sid in (4, 5):
        assert ph.regWriteTxRx(port, sid, 40, 1, [1])[0] == sdk.COMM_SUCCESS
    assert sim.servo(4).read("Torque_Enable") == 0
    assert ph.action(port, sdk.BROADCAST_ID) == sdk.COMM_SUCCESS
    wait_until(lambda: sim.servo(4).read("Torque_Enable") == sim.servo(5).read("Torque_Enable") == 1, 2.0,
               what="broadcast ACTION applied")
    assert sim.servo(6).read("Torque_Enable") == 0


def test_broadcast_write_and_status_level_zero(sim, bus):
    port, ph = bus
    assert ph.write1ByteTxRx(port, sdk.BROADCAST_ID, 8, 0)[0] == sdk.COMM_SUCCESS  # no reply awaited
    wait_until(lambda: all(sim.servo(i).read("Response_Status_Level") == 0 for i in IDS), 2.0, what="broadcast write")
    # level 0: a write is applied but not acknowledged; reads and pings still answer
    with silence_expected(sim, port):
        assert ph.write1ByteTxRx(port, 1, 40, 1)[0] == sdk.COMM_RX_TIMEOUT
    assert sim.servo(1).read("Torque_Enable") == 1
    assert ph.read1ByteTxRx(port, 1, 40)[:2] == (1, sdk.COMM_SUCCESS)
    assert ph.ping(port, 1)[1] == sdk.COMM_SUCCESS


def test_bad_checksum_ignored_and_garbage_resynced(sim):
    wire = RawWire(sim)
    try:
        good = packet(1, T.INST_WRITE, bytes((40, 1)))
        bad = good[:-1] + bytes((good[-1] ^ 0x5A,))
        wire.write(bad)
        assert wire.quiet()  # silent, like a real servo
        assert sim.servo(1).read("Torque_Enable") == 0
        wire.write(b"\x00\x13\xff\x42" + good)  # garbage, then a valid packet
        reply = wire.read(6)
        assert reply == b"\xff\xff\x01\x02\x00" + bytes((checksum(b"\x01\x02\x00"),))
        assert sim.servo(1).read("Torque_Enable") == 1
        # broadcast: no status reply to READ or WRITE; every servo answers a broadcast PING
        wire.write(packet(T.BROADCAST_ID, T.INST_READ, bytes((5, 1)))
                   + packet(T.BROADCAST_ID, T.INST_WRITE, bytes((41, 9))))
        assert wire.quiet()
        assert all(sim.servo(i).read("Acceleration") == 9 for i in IDS)
        wire.write(packet(T.BROADCAST_ID, T.INST_PING))
        assert [r[2] for r in [wire.read(6) for _ in IDS]] == IDS
        # a packet split across two reads of the simulator still parses: the first part is
        # handled alone before the rest is sent. A loaded host may hold the rest back longer
        # than the servo's inter-byte timeout (FRAME_TIMEOUT_S), which rightly forgets the first
        # part then: tried again, so only a parser that never joins the parts fails. The reply is
        # waited for (read's patience), not looked for with quiet(): a pty hands the simulator's
        # write to this side a moment later, so quiet() can miss a reply on its way, which the
        # next try's quiet() then found (CI, load ~2)
        ping = packet(2, T.INST_PING)
        for _ in range(5):
            wire.write(ping[:3])
            assert wire.quiet()
            wire.write(ping[3:])
            reply = wire.read(6)  # nothing within the patience: the first part was forgotten
            if reply:
                break
        assert reply[:3] == b"\xff\xff\x02"
        # two requests in one write: two replies, in order
        wire.write(packet(3, T.INST_PING) + packet(4, T.INST_READ, bytes((5, 1))))
        assert wire.read(13) == (b"\xff\xff\x03\x02\x00" + bytes((checksum(b"\x03\x02\x00"),))
                                 + b"\xff\xff\x04\x03\x00\x04" + bytes((checksum(b"\x04\x03\x00\x04"),)))
    finally:
        wire.close()


def test_half_packet_is_forgotten_after_a_silence(sim):
    from crtk_bridge.sim.feetech import FRAME_TIMEOUT_S

    wire = RawWire(sim)
    try:
        wire.write(b"\xff\xff\x01\x09\x03\x2a")  # a WRITE cut short (claims 13 bytes)
        assert wire.quiet()  # the simulator holds the half packet (and heard it now)
        time.sleep(3 * FRAME_TIMEOUT_S)  # a guaranteed minimum silence, not a wait for a result
        wire.write(packet(2, T.INST_PING))
        assert wire.read(6)[:3] == b"\xff\xff\x02"
    finally:
        wire.close()


def test_client_can_close_and_reopen_the_port(sim):
    for _ in range(3):
        port = PatientPort(sim.port)
        assert port.openPort()
        assert sdk.PacketHandler(0).ping(port, 1)[1] == sdk.COMM_SUCCESS
        port.closePort()
    assert sim.running


def test_emulated_baud_delays_replies_by_wire_time():
    with FeetechSimulator(IDS, baudrate=115_200, emulate_baud=True) as sim:
        port = PatientPort(sim.port)
        assert port.openPort() and port.setBaudRate(115_200)  # the servos' rate
        ph = sdk.PacketHandler(0)
        wire_s = (8 + len(IDS) + len(IDS) * (6 + BLOCK[1])) * 10 / 115_200  # ~11.7 ms
        t0 = time.perf_counter()
        _, res = sync_read(port, ph, IDS)
        elapsed = time.perf_counter() - t0
        port.closePort()
    assert res == sdk.COMM_SUCCESS
    assert elapsed >= wire_s, (elapsed, wire_s)


def test_from_profile(tmp):
    profile = load_profile(SO101)
    with FeetechSimulator.from_profile(profile, link=tmp / "tty") as sim:
        assert sim.port == str(tmp / "tty") and os.readlink(tmp / "tty") == sim.pty_path
        assert sim.ids == [j.backend["id"] for j in profile.joints] and sim.baudrate == 1_000_000
        for j in profile.joints:
            assert sim.servo(j.backend["id"]).read("Present_Position") == j.backend["calibration"]["offset"]
            assert sim.servo(j.backend["id"]).read("Model_Number") == 777
    assert not (tmp / "tty").exists()


def test_link_replaces_stale_symlink_and_refuses_regular_file(tmp):
    link = tmp / "tty"
    link.symlink_to("/dev/does-not-exist")
    with FeetechSimulator([1], link=link) as sim:
        assert os.readlink(link) == sim.pty_path
    regular = tmp / "file"
    regular.write_text("keep me")
    with pytest.raises(SimulatorError, match="not a symlink"):
        FeetechSimulator([1], link=regular).start()
    assert regular.read_text() == "keep me"


# ------------------------------------------------------------------ control socket and faults

def test_control_dump_read_write(sim, bus):
    port, ph = bus
    ctl = str(sim.control_path)
    dump = control_request(ctl, {"cmd": "dump"})
    assert dump["ok"] and sorted(dump["servos"], key=int) == [str(i) for i in IDS]
    s1 = dump["servos"]["1"]
    assert s1["torque_enable"] == 0 and s1["goal_position"] == s1["present_position"] == 1100
    assert s1["present_velocity"] == 0 and s1["status"] == 0 and s1["model_number"] == 777
    assert s1["present_position_exact"] == 1100.0  # the horn's position, before the rounding to ticks
    assert 0 < dump["clock"] <= time.monotonic()  # as of then
    assert control_request(ctl, {"cmd": "read", "id": 1, "register": "Torque_Enable"}) == {"ok": True, "value": 0}
    assert control_request(ctl, {"cmd": "write", "id": 1, "register": "Present_Position", "value": -12})["ok"]
    assert present(port, ph, 1) == -12  # moved "by hand", seen on the bus
    assert control_request(ctl, {"cmd": "dump"})["servos"]["1"]["present_position_exact"] == -12.0
    assert control_request(ctl, {"cmd": "write", "id": 1, "register": "goal_position", "value": 1500})["ok"]
    assert ph.read2ByteTxRx(port, 1, 42)[0] == 1500
    err = control_request(ctl, {"cmd": "read", "id": 9, "register": "Torque_Enable"})
    assert not err["ok"] and "9" in err["error"]
    err = control_request(ctl, {"cmd": "read", "id": 1, "register": "Nope"})
    assert not err["ok"] and "Nope" in err["error"]
    err = control_request(ctl, {"cmd": "write", "id": 1, "register": "Lock", "value": 300})
    assert not err["ok"] and "Lock" in err["error"]
    assert not control_request(ctl, {"cmd": "fly"})["ok"]


def test_faults_silent_corrupt_error_bits_unplug(sim, bus):
    port, ph = bus
    ctl = str(sim.control_path)
    assert control_request(ctl, {"cmd": "fault", "id": 3, "kind": "silent"})["ok"]
    with silence_expected(sim, port):
        assert sync_read(port, ph, IDS)[1] == sdk.COMM_RX_TIMEOUT
        assert ph.write1ByteTxRx(port, 3, 40, 1)[0] == sdk.COMM_RX_TIMEOUT
    assert sim.servo(3).read("Torque_Enable") == 1  # it still listens
    assert control_request(ctl, {"cmd": "clear_faults"})["ok"]
    assert sync_read(port, ph, IDS)[1] == sdk.COMM_SUCCESS

    assert control_request(ctl, {"cmd": "fault", "id": 2, "kind": "corrupt"})["ok"]
    assert ph.ping(port, 2)[1] == sdk.COMM_RX_CORRUPT
    assert control_request(ctl, {"cmd": "fault", "id": 4, "kind": "error_bits", "bits": T.ERR_OVERLOAD})["ok"]
    value, res, error = ph.read1ByteTxRx(port, 4, 65)
    assert res == sdk.COMM_SUCCESS and error == T.ERR_OVERLOAD == value
    assert control_request(ctl, {"cmd": "dump"})["faults"] == {"2": ["corrupt"], "4": ["error_bits"]}
    assert not control_request(ctl, {"cmd": "fault", "id": 4, "kind": "melt"})["ok"]
    assert control_request(ctl, {"cmd": "clear_faults"})["ok"]
    assert ph.ping(port, 2)[1] == sdk.COMM_SUCCESS and ph.read1ByteTxRx(port, 4, 65)[2] == 0

    assert control_request(ctl, {"cmd": "unplug", "on": True})["ok"]
    with silence_expected(sim, port):
        assert ph.ping(port, 1)[1] == sdk.COMM_RX_TIMEOUT
        assert ph.write1ByteTxRx(port, 1, 40, 1)[0] == sdk.COMM_RX_TIMEOUT
    assert control_request(ctl, {"cmd": "unplug", "on": False})["ok"]
    assert ph.ping(port, 1)[1] == sdk.COMM_SUCCESS
    assert sim.servo(1).read("Torque_Enable") == 0  # nothing reached it while unplugged


def test_freeze_fault_stops_the_joint(sim, bus):
    port, ph = bus
    clock = FakeClock()
    sim.clock = clock
    sim.set_fault(1, "freeze")
    assert ph.write1ByteTxRx(port, 1, 40, 1)[0] == sdk.COMM_SUCCESS
    sim.servo(1).write("Goal_Position", 2000)
    clock.t += 1.0
    assert present(port, ph, 1) == 1100 and sim.servo(1).read("Present_Load") > 0
    sim.clear_faults(1)
    clock.t += 1.0
    assert present(port, ph, 1) == 2000


# ------------------------------------------------------------------ CLI

def test_cli_serves_until_sigterm(tmp):
    link, ctl = tmp / "tty", tmp / "ctl"
    proc = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", "feetech", "--profile", str(SO101),
                             "--link", str(link), "--control", str(ctl)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 20.0)
        assert ready, "crtk-sim printed nothing within 20 s"
        line = proc.stdout.readline()  # printed once the link and the socket exist
        assert f"port={link}" in line and f"control={ctl}" in line, (line, proc.stderr.read())
        assert link.is_symlink() and ctl.exists()
        port = PatientPort(str(link))
        assert port.openPort()
        assert sdk.PacketHandler(0).ping(port, 6) == (777, sdk.COMM_SUCCESS, 0)
        port.closePort()
        assert control_request(str(ctl), {"cmd": "read", "id": 6, "register": "ID"}) == {"ok": True, "value": 6}
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not os.path.lexists(link) and not ctl.exists()


def test_cli_errors(tmp):
    regular = tmp / "tty"
    regular.write_text("")
    res = subprocess.run([sys.executable, "-m", "crtk_bridge.sim.cli", "feetech", "--profile", str(SO101),
                          "--link", str(regular)], capture_output=True, text=True, timeout=30)
    assert res.returncode == 1 and "not a symlink" in res.stderr and res.stderr.count("\n") == 1
    res = subprocess.run([sys.executable, "-m", "crtk_bridge.sim.cli", "feetech", "--profile", str(tmp / "nope.yaml"),
                          "--link", str(tmp / "x")], capture_output=True, text=True, timeout=30)
    assert res.returncode == 2 and "nope.yaml" in res.stderr

"""The simulated CiA 402 drive (crtk_bridge/sim/canopen402.py), driven by canopen's own
``BaseNode402`` and ``RemoteNode`` (independent clients, unmodified) over python-can's in-process
``virtual`` bus: boot, heartbeat, PDO configuration over SDO, the 402 state machine through the
client's ``state`` setter, CSP / CSV / CST, quick stop, homing, following error, EMCY and fault
reset, injected faults, and hostile frames. The same tests run on socketcan ``vcan0`` when the
kernel has it (the simulator joins it), skipped with the reason otherwise."""

from __future__ import annotations

import math
import os
import time

import can
import canopen
import msgspec
import pytest
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from crtk_bridge.profile import Joint, JointLimits, load_profile
from crtk_bridge.sim import SimulatorError, simulator_class
from crtk_bridge.sim.canopen402 import (
    EMCY_FOLLOWING_ERROR,
    EMCY_PDO_LENGTH,
    CanopenSimulator,
    error_register,
    make_object_dictionary,
)

from .conftest import SO101, wait_until

SYNC_S = 0.01


def _vcan0() -> str | None:
    """Why vcan0 cannot be used here, or None when it can."""
    if not os.path.exists("/sys/class/net/vcan0"):
        return "no socketcan vcan0 on this machine (modprobe vcan; ip link add vcan0 type vcan)"
    try:
        can.Bus(interface="socketcan", channel="vcan0").shutdown()
    except Exception as exc:  # noqa: BLE001 - any reason is a skip reason
        return f"socketcan vcan0 cannot be opened: {exc}"
    return None


@pytest.fixture(scope="module", params=["virtual", "socketcan"])
def bus(request):
    """The simulator (drives 1 and 2) and a master Network on the same bus."""
    if request.param == "socketcan":
        reason = _vcan0()
        if reason:
            pytest.skip(reason)
        sim = CanopenSimulator([1, 2], interface="socketcan", channel="vcan0")
    else:
        sim = CanopenSimulator([1, 2], interface="virtual")
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.02  # disconnect() waits up to one cycle
    net.connect(interface=sim.interface, channel=sim.port)
    sim.start()
    yield sim, net
    net.sync.stop()
    sim.stop()
    net.disconnect()


def _reset(sim, node) -> None:
    """NMT reset node (the drive boots again: defaults, SWITCH ON DISABLED), then a confirmed SDO
    round trip: the drive handles frames in order, so the reset is done."""
    sim.clear_faults()
    node.nmt.send_command(0x81)
    wait_until(lambda: node.sdo[0x1000].raw == 0x00020192, 2, what="the drive back after reset")


def _csp_mapping(node) -> None:
    """The typical CSP + SYNC mapping (reference canopen-ur.md part A section 1)."""
    node.tpdo.read()
    node.rpdo.read()
    for pdo, variables, trans in (
        (node.rpdo[1], (0x6040, 0x607A), 1),
        (node.rpdo[2], (0x6060,), 255),
        (node.tpdo[1], (0x6041, 0x6064), 1),
        (node.tpdo[2], (0x6061, 0x606C, 0x6077), 1),
    ):
        pdo.clear()
        for index in variables:
            pdo.add_variable(index)
        pdo.trans_type = trans
        pdo.enabled = True
    node.rpdo.save()
    node.tpdo.save()


@pytest.fixture
def drive(bus):
    """Node 1 as canopen's BaseNode402 sees it, reset, mapped for CSP, OPERATIONAL, with SYNC
    and its SYNC-type RPDO1 sent every 10 ms (the library sends neither by itself)."""
    sim, net = bus
    node = canopen.BaseNode402(1, make_object_dictionary(1))
    # the library's limits on waiting for the drive (0.2..0.8 s) are real-time budgets; here the
    # drive is a thread of this process, which a loaded host may not run for that long: more
    # patience (each wait ends as soon as the drive has answered)
    node.TIMEOUT_CHECK_TPDO = node.TIMEOUT_SWITCH_STATE_SINGLE = node.TIMEOUT_SWITCH_OP_MODE = 2.0
    node.TIMEOUT_SWITCH_STATE_FINAL = node.TIMEOUT_RESET_FAULT = 4.0
    net.add_node(node)
    _reset(sim, node)
    _csp_mapping(node)
    node.nmt.state = "OPERATIONAL"
    net.sync.start(SYNC_S)
    node.setup_402_state_machine(read_pdos=False)
    wait_until(lambda: node.tpdo[1].wait_for_reception(0.2), 2, what="TPDO1")
    node.rpdo[1][0x607A].raw = node.tpdo_values[0x6064]  # hold where it is
    node.rpdo[1].start(SYNC_S)
    yield node
    node.rpdo[1].stop()
    net.sync.stop()
    sim.clear_faults()
    del net[1]


def _emcy(node, code: int):
    """The EMCY ``code`` the client has received (now or within 1 s). Polls the client's log:
    ``emcy.wait`` misses one that arrived before it was called."""
    return wait_until(lambda: next((e for e in node.emcy.log if e.code == code), None), 1,
                      what=f"EMCY 0x{code:04X}")


def _move(node, counts: int) -> None:
    node.rpdo[1][0x607A].raw = counts
    node.rpdo[1].update()


def test_base_node_402_enables_follows_csp_and_recovers_from_a_fault(bus, drive):
    sim, _ = bus
    node = drive
    assert node.state == "SWITCH ON DISABLED"
    node.state = "OPERATION ENABLED"  # the client's own walk: shutdown, switch on, enable
    assert sim.drive(1).state.name == "OPERATION_ENABLED" and sim.drive(1).enabled
    node.op_mode = "CYCLIC SYNCHRONOUS POSITION"  # RPDO2, confirmed by the client through TPDO2
    assert node.op_mode == "CYCLIC SYNCHRONOUS POSITION" and sim.drive(1).mode == 8
    start = node.tpdo_values[0x6064]
    _move(node, start + 5000)
    wait_until(lambda: node.tpdo_values[0x6064] == start + 5000, 2, what="CSP position reached")
    assert node.statusword & 0x1000  # CSP: the drive follows the command value
    assert sim.drive(2).snapshot()["position"] == 0  # the other drive did not move

    sim.set_fault(1, "emcy", 0x2310)  # over-current
    emcy = _emcy(node, 0x2310)
    assert emcy.register & 0x03 == 0x03  # generic + current bits
    wait_until(lambda: node.state == "FAULT", 1, what="FAULT")
    assert node.sdo[0x603F].raw == 0x2310
    # the reset the reference recommends: CW 0, then SWITCH ON DISABLED (0x80: a rising edge)
    node.controlword = 0
    node.check_statusword()
    node.state = "SWITCH ON DISABLED"
    assert node.sdo[0x603F].raw == 0 and node.sdo[0x1001].raw == 0
    wait_until(lambda: any(e.code == 0 for e in node.emcy.log), 1, what="EMCY error reset")
    _move(node, node.tpdo_values[0x6064])
    node.state = "OPERATION ENABLED"
    _move(node, start)
    wait_until(lambda: node.tpdo_values[0x6064] == start, 2, what="CSP after the fault reset")


def test_a_fault_reset_needs_a_rising_edge(bus, drive):
    sim, _ = bus
    node = drive
    node.state = "OPERATION ENABLED"
    node.rpdo[1].stop()  # from here the controlword goes over SDO only
    sim.set_fault(1, "emcy", 0x5000)
    wait_until(lambda: node.state == "FAULT", 1, what="FAULT")
    node.sdo[0x6040].raw = 0x80  # rising edge: fault reset
    assert sim.drive(1).state.name == "SWITCH_ON_DISABLED"
    sim.set_fault(1, "emcy", 0x5000)
    wait_until(lambda: sim.drive(1).state.name == "FAULT", 1, what="FAULT again")
    node.sdo[0x6040].raw = 0x80  # bit 7 already high: no edge, no reset
    assert sim.drive(1).state.name == "FAULT"
    node.sdo[0x6040].raw = 0x00
    node.sdo[0x6040].raw = 0x80
    assert sim.drive(1).state.name == "SWITCH_ON_DISABLED"


def test_following_error_faults_with_emcy_8611(bus, drive):
    sim, _ = bus
    node = drive
    node.state = "OPERATION ENABLED"
    node.op_mode = "CYCLIC SYNCHRONOUS POSITION"
    node.sdo[0x6065].raw = 2000  # following error window, counts
    sim.set_fault(1, "jam")  # the shaft is blocked
    _move(node, node.tpdo_values[0x6064] + 10_000)
    assert _emcy(node, EMCY_FOLLOWING_ERROR).register == 0x21  # generic + device profile (not communication)
    wait_until(lambda: node.state == "FAULT", 1, what="FAULT")
    assert node.statusword & 0x2000  # CSP bit 13: following error
    assert node.sdo[0x603F].raw == EMCY_FOLLOWING_ERROR


# CiA 301 error register bits: 0 generic, 1 current, 2 voltage, 3 temperature, 4 communication,
# 5 device profile specific, 7 manufacturer specific; by the EMCY code's class / group
@pytest.mark.parametrize("code,register", [
    (0x1000, 0x01), (0x2310, 0x03), (0x2220, 0x03), (0x3210, 0x05), (0x4310, 0x09), (0x5000, 0x01),
    (0x6320, 0x01), (0x7121, 0x01), (0x8110, 0x11), (0x8130, 0x11), (0x8210, 0x11), (0x8400, 0x21),
    (0x8611, 0x21), (0x8612, 0x21), (0x9000, 0x01), (0xFF00, 0x81), (0x0000, 0x00),
])
def test_the_error_register_bit_of_each_emcy_code_follows_its_class(code, register):
    assert error_register(code) == register


def test_a_warning_emcy_agrees_with_0x1001_and_its_end_clears_the_masters_active_list(bus, drive):
    """canopen's EmcyConsumer as an independent master: the warning is in its active list with
    the error register 0x1001 reads, and leaves it with the EMCY 0x0000 sent when it ends."""
    sim, _ = bus
    node = drive
    node.state = "OPERATION ENABLED"
    sim.set_fault(1, "warning", 0x4310)  # drive temperature: a warning, the drive runs on
    emcy = _emcy(node, 0x4310)
    assert emcy.register == 0x09  # generic + temperature
    assert [e.code for e in node.emcy.active] == [0x4310]
    assert node.sdo[0x1001].raw == emcy.register
    assert node.sdo[0x6041].raw & 0x80 and node.state == "OPERATION ENABLED"  # statusword bit 7
    sim.clear_faults(1)  # the drive cooled down
    reset = _emcy(node, 0x0000)
    assert reset.register == 0 and node.emcy.active == []
    assert node.sdo[0x1001].raw == 0 and not node.sdo[0x6041].raw & 0x80

    # a fault on top of a warning: 0x1001 carries both; the fault reset acknowledges both
    node.emcy.log.clear()
    sim.set_fault(1, "warning", 0x3220)
    sim.set_fault(1, "emcy", 0x2310)
    assert _emcy(node, 0x2310).register == 0x07  # generic + current + voltage
    wait_until(lambda: node.state == "FAULT", 1, what="FAULT")
    assert node.sdo[0x1001].raw == 0x07
    node.controlword = 0
    node.check_statusword()
    node.state = "SWITCH ON DISABLED"  # fault reset
    assert _emcy(node, 0x0000).register == 0 and node.emcy.active == []
    assert node.sdo[0x1001].raw == 0


def test_no_emcy_in_nmt_stopped_and_stopped_entered_while_enabled_gets_the_0x6007_reaction(bus, drive):
    """CiA 301: EMCY only in PRE-OPERATIONAL and OPERATIONAL. CiA 402 0x6007: "NMT stopped
    entered" gets the reaction a lost master heartbeat gets (here 1, fault; then 3, quick stop)."""
    sim, _ = bus
    node = drive
    for option, state in ((1, "FAULT"), (3, "QUICK_STOP_ACTIVE")):
        node.sdo[0x6007].raw = option
        node.state = "OPERATION ENABLED"
        node.op_mode = "CYCLIC SYNCHRONOUS VELOCITY"
        node.sdo[0x60FF].raw = 20_000  # counts/s
        wait_until(lambda: abs(node.tpdo_values[0x606C] - 20_000) < 200, 2, what="CSV speed")
        node.emcy.log.clear()
        node.nmt.state = "STOPPED"  # by this master or another one
        wait_until(lambda: sim.drive(1).snapshot()["velocity"] == 0, 2, what="the drive stopped")
        snap = sim.drive(1).snapshot()
        assert snap["nmt"] == "STOPPED" and snap["state"] == state, snap
        p = snap["position"]
        sim.set_fault(1, "warning", 0x4210)  # an error while STOPPED: kept, not sent
        wait_until(lambda: sim.drive(1).snapshot()["position"] == p, 1, what="no motion")
        node.nmt.state = "PRE-OPERATIONAL"
        if option == 1:  # the fault (0x8100) stays until a fault reset; nothing was sent in STOPPED
            assert node.sdo[0x1001].raw == 0x19  # generic, communication (0x8100), temperature (0x4210)
            assert node.sdo[0x603F].raw == 0x8100 and not node.emcy.log, node.emcy.log
        else:  # the 0x8100 warning ends as the master takes the node back: its EMCY 0x0000, the
            # temperature warning still in 0x1001 (the only EMCY: none was sent in STOPPED)
            _emcy(node, 0x0000)
            assert [(e.code, e.register) for e in node.emcy.log] == [(0x0000, 0x09)]
            assert node.sdo[0x1001].raw == 0x09
        sim.clear_faults(1)  # the warning ends: EMCY 0x0000, PRE-OPERATIONAL may send it
        _emcy(node, 0x0000)
        node.nmt.state = "OPERATIONAL"
        node.sdo[0x60FF].raw = 0
        node.controlword = 0
        node.check_statusword()
        node.state = "SWITCH ON DISABLED"
        node.rpdo[1][0x607A].raw = sim.drive(1).snapshot()["position"]
        node.rpdo[1].update()


def test_csv_cst_and_quick_stop(bus, drive):
    sim, _ = bus
    node = drive
    node.state = "OPERATION ENABLED"
    node.op_mode = "CYCLIC SYNCHRONOUS VELOCITY"
    node.sdo[0x60FF].raw = 20_000  # counts/s
    wait_until(lambda: abs(node.tpdo_values[0x606C] - 20_000) < 200, 2, what="CSV speed")
    p0 = node.tpdo_values[0x6064]
    wait_until(lambda: node.tpdo_values[0x6064] > p0 + 1000, 2, what="CSV motion")
    node.state = "QUICK STOP ACTIVE"
    wait_until(lambda: node.tpdo_values[0x606C] == 0, 1, what="stopped on the quick-stop ramp")
    p1 = node.tpdo_values[0x6064]
    node.check_statusword()
    node.check_statusword()
    assert node.state == "QUICK STOP ACTIVE" and node.tpdo_values[0x6064] == p1  # stays, holds
    node.state = "OPERATION ENABLED"  # transition 16: resume
    node.sdo[0x60FF].raw = 0
    node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
    node.sdo[0x6071].raw = -100  # per mille
    wait_until(lambda: node.tpdo_values[0x606C] < -15_000, 2, what="CST speed")
    assert node.tpdo_values[0x6077] == -100
    node.sdo[0x6071].raw = 0


def test_homing_on_the_current_position_and_on_a_limit_switch(bus, drive):
    sim, _ = bus
    node = drive
    node.sdo[0x6098].raw = 37  # current position
    node.sdo[0x607C].raw = 1234  # home offset
    assert node.homing(timeout=2)
    wait_until(lambda: node.tpdo_values[0x6064] == 1234, 1, what="position = home offset")
    assert node.statusword & 0x3400 == 0x1400 and sim.drive(1).homed
    node.sdo[0x6098].raw = 17  # negative limit switch: a search that takes time
    node.sdo[0x607C].raw = 0
    node.controlword = 0x0F  # bit 4 low again: homing() starts on its rising edge
    node.check_statusword()
    t0 = time.monotonic()
    assert node.homing(timeout=3)
    assert time.monotonic() - t0 > 0.1  # 20000 counts at 100000 counts/s
    wait_until(lambda: node.tpdo_values[0x6064] == 0, 1, what="homed at the switch")
    node.sdo[0x6098].raw = 1  # a method this drive does not have: homing error
    node.controlword = 0x0F
    node.check_statusword()
    assert not node.homing(timeout=1)
    assert node.statusword & 0x3400 == 0x2400 and not sim.drive(1).homed


def test_pdos_follow_the_nmt_state_and_the_mapping(bus, drive):
    sim, net = bus
    node = drive
    tpdos = []
    node.tpdo[1].add_callback(tpdos.append)
    node.state = "SWITCHED ON"
    node.nmt.state = "PRE-OPERATIONAL"
    count, n = sim.drive(1).sync_count, len(tpdos)
    node.rpdo[1]["Controlword"].raw = 0x0F  # no RPDO applied either
    wait_until(lambda: sim.drive(1).sync_count > count + 10, 2, what="SYNCs")
    assert len(tpdos) - n <= 1  # no TPDO outside OPERATIONAL (one may have been in flight)
    assert sim.drive(1).state.name == "SWITCHED_ON"
    # remap in PRE-OPERATIONAL: TPDO1 every 2nd SYNC; takes effect on start
    node.tpdo[1].trans_type = 2
    node.tpdo[1].save()
    node.nmt.state = "OPERATIONAL"
    node.tpdo[1].wait_for_reception(1)
    count, n = sim.drive(1).sync_count, len(tpdos)
    wait_until(lambda: sim.drive(1).sync_count >= count + 20, 2, what="20 SYNCs")
    syncs, sent = sim.drive(1).sync_count - count, len(tpdos) - n
    assert abs(2 * sent - syncs) <= 4, (syncs, sent)  # one TPDO every second SYNC (+-2 in flight)
    wait_until(lambda: sim.drive(1).state.name == "OPERATION_ENABLED", 1, what="the RPDO applied")


def test_sdo_aborts_and_hostile_frames(bus, drive):
    sim, net = bus
    node = drive
    cases = [
        (lambda: node.sdo.upload(0x2000, 0), 0x06020000),  # no such object
        (lambda: node.sdo.upload(0x6099, 7), 0x06090011),  # no such sub-index
        (lambda: node.sdo.download(0x6041, 0, b"\x00\x00"), 0x06010002),  # read only
        (lambda: node.sdo.download(0x6040, 0, b"\x00"), 0x06070010),  # wrong length
        (lambda: node.sdo.download(0x6060, 0, b"\x03"), 0x06090030),  # PV: not supported
        (lambda: node.sdo.download(0x1A00, 1, (0x60640020).to_bytes(4, "little")), 0x06010000),  # valid PDO
        (lambda: node.sdo.download(0x1801, 1, (0x80000700).to_bytes(4, "little")), None),  # disable
        (lambda: node.sdo.download(0x1A01, 1, (0x10000020).to_bytes(4, "little")), 0x06040041),  # not mappable
        (lambda: node.sdo.download(0x1A01, 1, (0x60640010).to_bytes(4, "little")), 0x06040041),  # wrong size
    ]
    for k, (call, code) in enumerate(cases):
        if code is None:
            call()
            continue
        with pytest.raises(SdoAbortedError) as err:
            call()
        assert err.value.code == code, hex(code)
    node.state = "SWITCHED ON"
    raw = can.Bus(interface=sim.interface, channel=sim.port)
    try:
        before = sim.drive(1).snapshot()
        for arbitration_id, data, extended in [
            (0x000, b"\x81", False),  # NMT of one byte: not an NMT frame
            (0x601, b"\x40", False),  # SDO request of one byte
            (0x080, bytes(8), False),  # SYNC with 8 bytes
            (0x7E5, bytes(8), False),  # LSS / unknown COB-IDs
            (0x1FFFF601, bytes(8), True),  # an extended id that ends like ours
            (0x201, b"\x0f", False),  # RPDO1 one byte short of its mapping
        ]:
            raw.send(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=extended))
        _emcy(node, EMCY_PDO_LENGTH)
        after = sim.drive(1).snapshot()
        assert after["nmt"] == "OPERATIONAL" and after["state"] == before["state"] == "SWITCHED_ON"
        assert node.sdo[0x1018][4].raw == 1  # still answering
    finally:
        raw.shutdown()


def test_heartbeat_silence_and_bus_off(bus, drive):
    """Each injected fault silences what it should. Counted over a window: at most one frame
    already in flight may still arrive (a loaded host delays it), against about 20 in the same
    window when the node is healthy."""
    sim, _ = bus
    node = drive
    beats, tpdos = [], []
    node.nmt.add_heartbeat_callback(beats.append)
    node.tpdo[1].add_callback(tpdos.append)
    node.sdo[0x1017].raw = 10  # ms
    wait_until(lambda: len(beats) >= 3, 1, what="heartbeats")
    assert beats[-1] == 5  # OPERATIONAL

    def window(tpdos_at_least: int = 0) -> tuple[int, int]:
        b, t = len(beats), len(tpdos)
        time.sleep(0.2)  # the observation window; stretched until that many TPDOs came (load)
        wait_until(lambda: len(tpdos) - t >= tpdos_at_least, 3, what=f"{tpdos_at_least} TPDOs")
        return len(beats) - b, len(tpdos) - t

    sim.set_fault(1, "heartbeat_stop")
    new_beats, new_tpdos = window(tpdos_at_least=5)
    assert new_beats <= 1 and new_tpdos >= 5  # the heartbeat stopped, the rest works
    sim.clear_faults(1)
    n = len(beats)
    wait_until(lambda: len(beats) > n + 2, 1, what="heartbeats again")

    for inject in (lambda: sim.set_fault(1, "silent"), lambda: sim.set_bus_off(True)):
        inject()
        new_beats, new_tpdos = window()
        assert new_beats <= 1 and new_tpdos <= 1
        sim.clear_faults()
        n, t = len(beats), len(tpdos)
        wait_until(lambda: len(beats) > n and len(tpdos) > t, 1, what="heartbeats and TPDOs again")


def test_a_drive_whose_master_falls_silent_stops(bus, drive):
    """Heartbeat consumer (0x1016) on the master's heartbeat; 0x6007 picks the reaction."""
    sim, net = bus
    node = drive
    node.sdo[0x1016][1].raw = (0x7F << 16) | 40  # watch node 127 (the master here), 40 ms
    for option, state in ((3, "QUICK STOP ACTIVE"), (1, "FAULT")):
        node.sdo[0x6007].raw = option
        node.rpdo[1].start(SYNC_S)
        node.state = "OPERATION ENABLED"
        beat = net.send_periodic(0x77F, [5], 0.01)  # the master's heartbeat
        try:
            time.sleep(0.1)
            assert node.state == "OPERATION ENABLED"  # watched and alive
        finally:
            beat.stop()  # the master dies: no heartbeat, no RPDO
            node.rpdo[1].stop()
        emcy = _emcy(node, 0x8130)
        assert emcy.data[:1] == b"\x7f"  # names the node it lost
        wait_until(lambda: node.check_statusword() and node.state == state, 1, what=state)
        node.emcy.log.clear()

    node.sdo[0x1016][1].raw = 0


def test_a_lost_master_heard_again_ends_the_heartbeat_warning_with_emcy_0000(bus, drive):
    """0x6007 = 3 (quick stop): the lost heartbeat is a warning (EMCY 0x8130, 0x1001 generic +
    communication); when the master's heartbeat comes back the error ends: EMCY 0x0000 and the
    master's active list (canopen's EmcyConsumer) empties."""
    sim, net = bus
    node = drive
    node.sdo[0x1016][1].raw = (0x7F << 16) | 40
    node.sdo[0x6007].raw = 3
    node.state = "OPERATION ENABLED"
    beat = net.send_periodic(0x77F, [5], 0.01)
    try:
        wait_until(lambda: 0x7F in sim.drive(1)._heartbeats, 1, what="the master's heartbeat watched")
        beat.stop()  # the master dies: no heartbeat, no RPDO (whose controlword would resume)
        node.rpdo[1].stop()
        emcy = _emcy(node, 0x8130)
        assert emcy.register == 0x11 and [e.code for e in node.emcy.active] == [0x8130]
        wait_until(lambda: node.check_statusword() and node.state == "QUICK STOP ACTIVE", 1, what="quick stop")
        assert node.sdo[0x1001].raw == 0x11
        node.emcy.log.clear()
        beat = net.send_periodic(0x77F, [5], 0.01)  # the master is back
        assert _emcy(node, 0x0000).register == 0 and node.emcy.active == []
        assert node.sdo[0x1001].raw == 0
    finally:
        node.sdo[0x1016][1].raw = 0
        beat.stop()
        node.sdo[0x6007].raw = 1


def test_boot_up_message_and_a_second_drive_on_the_bus(bus):
    sim, net = bus
    node2 = canopen.RemoteNode(2, make_object_dictionary(2))
    net.add_node(node2)
    try:
        boots = []
        node2.nmt.add_heartbeat_callback(boots.append)
        node2.nmt.send_command(0x81)  # reset node: boot-up message, PRE-OPERATIONAL
        wait_until(lambda: boots == [0], 1, what="the boot-up message")
        assert node2.sdo[0x1018][4].raw == 2 and node2.sdo[0x6502].raw == 0x3A0  # HM, CSP, CSV, CST
        assert node2.sdo[0x1000].raw == 0x00020192  # a CiA 402 servo drive
        node2.sdo[0x1017].raw = 10
        assert node2.nmt.wait_for_heartbeat(1) == "PRE-OPERATIONAL"
        node2.nmt.state = "STOPPED"  # CiA 301: no SDO in STOPPED, heartbeats go on
        assert node2.nmt.wait_for_heartbeat(1) == "STOPPED"
        node2.sdo.RESPONSE_TIMEOUT, node2.sdo.MAX_RETRIES = 0.05, 1  # one try (0 retries forever)
        with pytest.raises(SdoCommunicationError):
            node2.sdo[0x1000].raw
        node2.nmt.state = "PRE-OPERATIONAL"
        assert node2.sdo[0x1000].raw == 0x00020192
    finally:
        node2.sdo[0x1017].raw = 0
        del net[2]


def test_the_simulator_is_registered_and_reads_the_profile():
    limits = JointLimits(position_min=-3, position_max=3, velocity_max=2, acceleration_max=10, jerk_max=100)
    joints = [Joint(name=f"j{i}", limits=limits, backend={"node_id": i + 3, "counts_per_revolution": 4096})
              for i in range(2)]
    profile = msgspec.structs.replace(load_profile(SO101), joints=joints,
                                      backend={"type": "canopen402", "bitrate": 500_000})
    assert simulator_class("canopen") is CanopenSimulator
    sim = CanopenSimulator.from_profile(profile)
    assert sim.ids == [3, 4] and sim.bitrate == 500_000 and sim.interface == "slcan"
    assert sim.drive(3).options.max_velocity == pytest.approx(1.5 * 2 * 4096 / (2 * math.pi))
    bad = msgspec.structs.replace(profile, joints=[Joint(name="j", limits=limits, backend={"node_id": 200})])
    with pytest.raises(SimulatorError, match=r"joints\[0\] \(j\)\.node_id"):
        CanopenSimulator.from_profile(bad)


def test_a_drive_answers_to_the_serial_simulators_register_names():
    """What the conformance suite's rows call on every simulator (sim.servo(id).read / write)."""
    sim = CanopenSimulator([5], interface="virtual")  # not started: state only
    drive = sim.servo(5)
    drive.write("Present_Position", 1500)  # by hand
    drive.write("Goal_Position", 1400)
    assert drive.read("Present_Position") == 1500 and drive.read("Goal_Position") == 1400
    assert drive.read("Torque_Enable") == 0 and drive.read("statusword") & 0x4F == 0x00
    with pytest.raises(SimulatorError, match="Statusword.*read-only"):
        drive.write("Statusword", 0)
    with pytest.raises(SimulatorError, match="unknown register 'Baud_Rate'"):
        drive.read("Baud_Rate")

"""The Robotiq 2F backend (crtk_bridge/backends/robotiq) on its simulator (crtk_bridge/sim/robotiq.py),
driven cycle by cycle as production does (core/cycle.py's CycleRunner around the controller)."""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from crtk_bridge.backends.robotiq import tables as T
from crtk_bridge.backends.robotiq.backend import RobotiqBackend
from crtk_bridge.core.actuator import effective_period_s
from crtk_bridge.core.control import Controller
from crtk_bridge.core.cycle import CycleRunner
from crtk_bridge.core.state import OperatingState
from crtk_bridge.errors import BackendError, ProfileError
from crtk_bridge.profile import load_profile, parse_profile
from crtk_bridge.sim.robotiq import CLOSED_COUNT, OPEN_COUNT, RobotiqSimulator

from .conftest import ROOT, wait_until

PROFILE = ROOT / "profiles" / "robotiq_2f85.yaml"
ACTIVATION_S = 0.3
COUNT_M = 0.085 / (CLOSED_COUNT - OPEN_COUNT)  # m of opening per count once calibrated


class Rig:
    """A 2F-85 simulator (not activated: as after power-up), the backend on it, a controller."""

    def __init__(self, tcp: bool = False, activated: bool = False, **profile_changes):
        profile = load_profile(PROFILE)
        if profile_changes:
            profile = msgspec.structs.replace(profile, **profile_changes)
        self.tmp = tempfile.mkdtemp(prefix="robotiq-")
        link = None if tcp else Path(self.tmp) / "tty"  # a stable name, as /dev/serial/by-id: replugs keep it
        self.sim = RobotiqSimulator.from_profile(profile, link=link, host="127.0.0.1" if tcp else None, tcp_port=0,
                                                 activation_s=ACTIVATION_S, activated=activated)
        self.sim.start()
        self.profile = RobotiqBackend.sim_profile(profile, self.sim.port)
        self.backend = RobotiqBackend(self.profile)
        self.backend.open()
        period = effective_period_s(self.profile, self.backend)
        self.runner = CycleRunner(self.backend, period)
        self.c = Controller(self.profile, self.backend, time.time, period)
        self.rid = 0
        self.cycle()

    def cycle(self, n: int = 1) -> None:
        for _ in range(n):
            self.runner.cycle(self.c)

    def request(self, cmd: str, **kw) -> int:
        self.rid += 1
        self.c.handle({"id": self.rid, "cmd": cmd, **kw})
        return self.rid

    def reply(self, rid: int, timeout: float = 5.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            got = [m for m in self.c.outbox if m.get("id") == rid]
            if got:
                return got[0]
            assert time.monotonic() < deadline, f"no reply to request {rid}"
            self.cycle()

    def until(self, what: str, predicate, timeout: float = 5.0) -> None:
        wait_until(lambda: (self.cycle(), predicate())[1], timeout, interval=0, what=what)

    def events(self, kind: str) -> list[dict]:
        return [m["data"] for m in self.c.outbox if m.get("event") == kind]

    def enable(self) -> None:
        reply = self.reply(self.request("enable"))
        assert reply["ok"], reply
        assert self.c.state is OperatingState.ENABLED

    def move(self, opening: float) -> None:
        reply = self.reply(self.request("move_jp", ns="gripper", data={"position": [opening]}))
        assert reply["ok"], reply
        self.until("the move's end", lambda: not self.c.is_busy)

    @property
    def measured(self) -> float:
        return float(self.runner.feedback.position[0])

    def close(self) -> None:
        self.backend.close()
        self.sim.stop()
        shutil.rmtree(self.tmp, ignore_errors=True)


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_activation_runs_stepped_while_the_loop_keeps_cycling(rig):
    """enable = reset + rACT 1, then waiting on gSTA across cycles: the loop reads every cycle
    meanwhile (its stamps advance), the robot stays DISABLED and busy until the gripper says
    activation completed; the opening is calibrated from the gripper's own stroke-end readings."""
    assert rig.sim.gripper.dump()["gSTA"] == T.GSTA_RESET
    rid = rig.request("enable")
    stamps, t0 = [], time.monotonic()
    while not [m for m in rig.c.outbox if m.get("id") == rid]:
        assert time.monotonic() - t0 < 5, "no reply to enable"
        rig.cycle()
        stamps.append(rig.runner.feedback.stamp)
        if not [m for m in rig.c.outbox if m.get("id") == rid]:
            assert rig.c.state is OperatingState.DISABLED and rig.c.is_busy
            assert rig.sim.gripper.dump()["gSTA"] in (T.GSTA_RESET, T.GSTA_ACTIVATING, T.GSTA_ACTIVE)
    took = time.monotonic() - t0
    assert rig.reply(rid)["ok"] and rig.c.state is OperatingState.ENABLED and took >= ACTIVATION_S
    gaps = np.diff(stamps)
    # the cycles kept reading: the stamps advanced all along (a blocking activation would freeze
    # them); a loaded host may miss a read or stall a little
    assert len(stamps) >= 5 and np.all(gaps >= 0) and np.mean(gaps > 0) > 0.8
    dump = rig.sim.gripper.dump()
    assert dump["gSTA"] == T.GSTA_ACTIVE and dump["rGTO"] == 1 and dump["gGTO"] == 1
    cal = rig.backend.info().details["calibration"]
    assert cal == {"open": OPEN_COUNT, "closed": CLOSED_COUNT}  # the gripper's own readings
    rig.cycle(3)
    assert rig.measured == pytest.approx(0.085, abs=1e-6)  # activation ends fully open, held there


def test_enable_of_an_activated_gripper_does_not_activate_it_again():
    """A held object must not fall: an activated gripper without a fault only gets rGTO 1 with
    its position request where the fingers are (activation would run the whole stroke)."""
    r = Rig(activated=True)
    try:
        r.sim.gripper.write("Present_Position", 120)  # the fingers are somewhere in the middle
        with r.sim.gripper.lock:
            r.sim.gripper._last_heard -= 1.5  # nothing asked it for a second (a daemon restarting): minor 0x09
        r.cycle(2)
        assert any(e["code"] == "device_warning" and e["value"] == 0x09 for e in r.events("warning"))
        r.enable()
        dump = r.sim.gripper.dump()
        assert dump["gSTA"] == T.GSTA_ACTIVE and dump["rPR"] == 120 and dump["gPO"] == 120
        reply = r.reply(r.request("disable"))
        assert reply["ok"] and r.sim.gripper.dump()["gGTO"] == 0 and r.sim.gripper.dump()["rACT"] == 1
    finally:
        r.close()


def test_move_jp_to_a_position(rig):
    rig.enable()
    rig.move(0.03)
    rig.cycle(3)
    assert rig.measured == pytest.approx(0.03, abs=COUNT_M)
    dump = rig.sim.gripper.dump()
    assert dump["gOBJ"] == T.GOBJ_AT_REQUEST and dump["rPR"] == round(CLOSED_COUNT - 0.03 / COUNT_M)
    assert rig.c.state is OperatingState.ENABLED


def test_move_jp_onto_an_object_reports_the_grasp_and_no_fault(rig):
    """Closing on an object at 40 mm: the fingers stop there (gOBJ 2), a device_status event and
    operating_state's device_notices say so, the measured effort follows the force setting, and
    the robot stays ENABLED (no tracking error, no FAULT)."""
    rig.enable()
    rig.sim.set_object(0.04)
    rid = rig.request("move_jp", ns="gripper", data={"position": [0.0]})
    assert rig.reply(rid)["ok"]
    rig.until("the grasp event", lambda: any(e["code"] == "device_status" and e.get("value") == T.GOBJ_CONTACT_CLOSING
                                             for e in rig.events("status")))
    grasp = next(e for e in rig.events("status") if e["code"] == "device_status" and e["value"] == 2)
    assert grasp["register"] == "gOBJ" and grasp["joint"] == "finger" and "object while closing" in grasp["message"]
    rig.until("the move's end", lambda: not rig.c.is_busy)
    rig.cycle(int(0.2 / rig.c.dt))  # holding on the object for a while
    assert rig.measured == pytest.approx(0.04, abs=COUNT_M)  # stopped at the object, not at 0
    assert rig.sim.gripper.dump()["gOBJ"] == T.GOBJ_CONTACT_CLOSING
    assert rig.c.state is OperatingState.ENABLED and not rig.events("error")
    notices = rig.c.operating_state()["device_notices"]
    assert notices["finger"]["register"] == "gOBJ" and notices["finger"]["value"] == T.GOBJ_CONTACT_CLOSING
    # effort estimate: the grip current x effort_per_amp, closing (negative); 60 N set in the profile
    assert rig.runner.feedback.effort[0] == pytest.approx(-60.0, abs=5.0)
    rig.sim.set_object(None)  # the object taken away: the fingers close on, gOBJ 3
    rig.until("the fingers at the request", lambda: rig.sim.gripper.dump()["gOBJ"] == T.GOBJ_AT_REQUEST)
    rig.until("the no-object event", lambda: rig.c.operating_state()["device_notices"]["finger"]["value"] == 3)


@pytest.mark.parametrize("kind, code, meaning", [("overcurrent", 0x0E, "overcurrent triggered"),
                                                  ("under_voltage", 0x0A, "under minimum operating voltage")])
def test_a_gripper_fault_faults_naming_it_and_enable_recovers(rig, kind, code, meaning):
    rig.enable()
    rig.sim.set_fault(None, kind)
    rig.until("FAULT", lambda: rig.c.state is OperatingState.FAULT)
    err = rig.events("error")[-1]
    assert err["code"] == "gripper_fault" and err["register"] == "gFLT" and err["value"] == code
    assert f"gFLT 0x{code:02X}: {meaning}" in err["message"] and "'finger'" in err["message"]
    rig.until("rGTO off (the fault's disable)", lambda: rig.sim.gripper.dump()["gGTO"] == 0)
    rig.enable()  # reset (rACT 0 clears it) + activation
    assert rig.sim.gripper.dump()["gFLT"] == 0 and any(e["code"] == "fault_cleared" for e in rig.events("status"))
    rig.move(0.05)
    assert rig.measured == pytest.approx(0.05, abs=COUNT_M)


def test_a_minor_fault_is_a_warning_not_a_fault(rig):
    rig.enable()
    with rig.sim.gripper.lock:
        rig.sim.gripper.fault = 0x08  # overheating: a minor fault, the gripper works on
    rig.until("the warning", lambda: any(e["code"] == "device_warning" for e in rig.events("warning")))
    warning = next(e for e in rig.events("warning") if e["code"] == "device_warning")
    assert warning["register"] == "gFLT" and warning["value"] == 0x08 and "temperature" in warning["message"]
    rig.cycle(5)
    assert rig.c.state is OperatingState.ENABLED


def test_loss_of_the_link_faults_naming_the_port_then_enable_recovers(rig):
    rig.enable()
    port = rig.profile.backend["port"]
    rig.sim.set_unplugged(True)
    rig.until("FAULT", lambda: rig.c.state is OperatingState.FAULT)
    err = rig.events("error")[-1]
    assert err["code"] == "port_lost" and port in err["message"], err
    refused = rig.reply(rig.request("enable"))  # nothing to activate while the port is gone
    assert not refused["ok"] and port in refused["error"]["message"]
    rig.sim.set_unplugged(False)
    rig.until("the port back", lambda: any(e["code"] == "fault_cleared" and port in e["message"]
                                           for e in rig.events("status")))
    rig.enable()
    rig.move(0.06)
    assert rig.measured == pytest.approx(0.06, abs=COUNT_M)


def test_a_silent_gripper_faults_naming_the_port_after_a_few_misses(rig):
    """No reply is a transient fault (a loaded host may miss one): FAULT after
    safety.bus_errors_max in a row, naming the gripper and the port."""
    rig.enable()
    rig.sim.set_fault(None, "no_communication")
    fault = rig.backend.read(rig.runner.feedback)
    assert fault is not None and fault.transient and fault.code == "bus_timeout"
    rig.until("FAULT", lambda: rig.c.state is OperatingState.FAULT)
    err = rig.events("error")[-1]
    assert err["code"] == "bus_timeout" and rig.profile.backend["port"] in err["message"]
    assert "'finger'" in err["message"] and err["joint"] == "finger"
    rig.sim.clear_faults()
    rig.enable()


def test_effort_commands_are_refused_naming_the_joint(rig):
    """The force setting is a grip-force limit while moving to a position, not an effort held
    in free space: servo_jf is not offered and refused with one line."""
    rig.enable()
    assert "servo_jf" not in rig.c.supported_commands("gripper")
    reply = rig.reply(rig.request("servo_jf", ns="gripper", data={"effort": [-10.0]}))
    assert not reply["ok"] and "no effort control on joint 'finger'" in reply["error"]["message"], reply
    assert rig.c.state is OperatingState.ENABLED


def test_the_tool_flange_socket_carries_the_same_gripper():
    """backend.port socket://HOST:PORT: raw RTU over TCP (a UR tool flange's port 54321)."""
    r = Rig(tcp=True)
    try:
        assert r.profile.backend["port"].startswith("socket://127.0.0.1:")
        r.enable()
        r.move(0.02)
        assert r.measured == pytest.approx(0.02, abs=COUNT_M)
        r.sim.set_unplugged(True)  # the tool cable: the connection dropped
        r.until("FAULT", lambda: r.c.state is OperatingState.FAULT)
        assert r.events("error")[-1]["code"] == "port_lost" and r.profile.backend["port"] in r.events("error")[-1]["message"]
    finally:
        r.close()


def test_one_cycle_is_one_read_and_at_most_one_write(rig):
    """The bus's budget: a status read every cycle; a request only when it changed."""
    rig.enable()
    rig.cycle(3)
    before = rig.sim.gripper.dump()["requests"]
    rig.cycle(20)  # holding: nothing new to ask
    assert rig.sim.gripper.dump()["requests"] - before == 20
    rid = rig.request("servo_jp", ns="gripper", data={"position": [rig.measured - 0.002]})
    assert rig.reply(rid)["ok"]
    before = rig.sim.gripper.dump()["requests"]
    rig.cycle(10)
    assert 10 < rig.sim.gripper.dump()["requests"] - before <= 20


def test_profile_errors_name_the_key():
    base = load_profile(PROFILE)

    def with_joint(**keys):
        data = msgspec.to_builtins(base)
        data["joints"][0]["backend"] = {**data["joints"][0]["backend"], **keys}
        return RobotiqBackend(parse_profile(data), source="p.yaml")

    with pytest.raises(ProfileError, match=r"joints\[0\] \(finger\)\.model: '2f99' is not a Robotiq 2F model"):
        with_joint(model="2f99")
    with pytest.raises(ProfileError, match=r"joints\[0\] \(finger\)\.force: 500 N is outside the 2f85's 20..235 N"):
        with_joint(force=500.0)
    with pytest.raises(ProfileError, match=r"joints\[0\] \(finger\)\.unit: 'rad', but a Robotiq 2F's joint is its "
                                           r"finger opening in metres: set unit: m"):
        data = msgspec.to_builtins(base)
        data["joints"][0]["unit"] = "rad"
        RobotiqBackend(parse_profile(data), source="p.yaml")
    with pytest.raises(ProfileError, match=r"backend\.port: required"):
        data = msgspec.to_builtins(base)
        del data["backend"]["port"]
        RobotiqBackend(parse_profile(data), source="p.yaml")


def test_open_names_the_port_and_the_register_when_nothing_answers(tmp_path):
    sim = RobotiqSimulator(link=tmp_path / "tty")
    sim.start()
    sim.set_fault(None, "no_communication")
    try:
        b = RobotiqBackend(RobotiqBackend.sim_profile(load_profile(PROFILE), str(tmp_path / "tty")))
        with pytest.raises(BackendError, match=r"slave 9\) on .*tty at 115200 baud: no answer to the status read "
                                               r"\(function 4, register 0x07D0\)"):
            b.open()
    finally:
        sim.stop()


def test_disable_during_activation_stops_the_fingers(rig):
    """rGTO 0 does not stop an activation: a disable while the gripper activates resets it (rACT
    0) and replies DISABLED only once gACT is 0 and the fingers stand still; the abandoned
    activation is run anew by the next enable."""
    rig.sim.set_activation_s(3.0)
    rid = rig.request("enable")
    rig.until("the activation under way", lambda: rig.sim.gripper.dump()["gSTA"] == T.GSTA_ACTIVATING)
    rig.cycle(2)  # the backend read it too (gACT 1, gSTA 1)
    reply = rig.reply(rig.request("disable"))
    assert reply["ok"] and rig.c.state is OperatingState.DISABLED, reply
    assert not rig.reply(rid)["ok"]  # the enable was aborted
    before = rig.sim.gripper.dump()
    assert before["gACT"] == 0 and before["rACT"] == 0
    end = time.monotonic() + 1.0  # a second of cycles (a 3 s activation would run on meanwhile)
    while time.monotonic() < end:
        rig.cycle()
    after = rig.sim.gripper.dump()
    assert after["gPO"] == before["gPO"] and after["gACT"] == 0 and after["gSTA"] == T.GSTA_RESET
    rig.sim.set_activation_s(ACTIVATION_S)
    rig.enable()  # activates from the start, calibrated
    assert rig.backend.info().details["calibration"] == {"open": OPEN_COUNT, "closed": CLOSED_COUNT}


@pytest.mark.parametrize("cause", ["robot_fault", "link_drop"])
def test_enable_after_a_fault_not_of_the_gripper_does_not_reactivate_it(cause):
    """A FAULT of the robot's own (a tracking error elsewhere, an invalid command) or a drop of
    the link that came back leaves an activated gripper as it is: the enable that leaves FAULT
    is only the go, the fingers stay where they are (an activation runs the whole stroke and
    drops a held object)."""
    from crtk_bridge.core.actuator import Fault

    r = Rig(activated=True)
    try:
        r.sim.gripper.write("Present_Position", 120)
        r.cycle(2)
        r.enable()
        if cause == "robot_fault":
            r.c.enter_fault(Fault("tracking_error", "arm: joint 'shoulder': tracking error", transient=False))
        else:
            r.sim.set_unplugged(True)
        r.until("FAULT", lambda: r.c.state is OperatingState.FAULT)
        if cause == "link_drop":
            r.sim.set_unplugged(False)
            r.until("the port back", lambda: any(e["code"] == "fault_cleared" for e in r.events("status")))
        else:
            r.until("rGTO off (the fault's disable)", lambda: r.sim.gripper.dump()["gGTO"] == 0)
        r.enable()
        r.cycle(5)
        dump = r.sim.gripper.dump()
        assert dump["gPO"] == 120 and dump["rPR"] == 120 and dump["gSTA"] == T.GSTA_ACTIVE and dump["gGTO"] == 1, dump
    finally:
        r.close()


def test_a_gripper_fallen_into_reset_beside_a_minor_fault_faults_and_is_not_reactivated(rig):
    """While ENABLED with a minor gFLT showing (0x08, overheating), a gripper that left its
    activated state (gACT 0, gSTA 0) is a FAULT naming gSTA; the next position request is not
    written (rACT|rGTO to a gripper in reset is an activation: the whole stroke)."""
    rig.enable()
    rig.move(0.05)
    with rig.sim.gripper.lock:
        rig.sim.gripper.fault = 0x08
        rig.sim.gripper.gact, rig.sim.gripper.gsta = False, T.GSTA_RESET
    rig.cycle(3)
    rig.request("move_jp", ns="gripper", data={"position": [0.02]})
    for _ in range(10):
        rig.cycle()
        dump = rig.sim.gripper.dump()
        assert dump["gACT"] == 0 and dump["gSTA"] == T.GSTA_RESET, dump  # no activation started
    assert rig.c.state is OperatingState.FAULT
    err = [e for e in rig.events("error") if e["code"] == "gripper_fault"]
    assert len(err) == 1 and err[0]["register"] == "gSTA" and err[0]["value"] == T.GSTA_RESET, err
    assert "no longer activated (gSTA 0" in err[0]["message"], err


def test_a_gripper_found_activated_uses_the_nominal_ends_and_says_so():
    """Found activated (a daemon restart): no activation to calibrate from, none in the profile:
    the opening uses the nominal stroke ends (the simulator's), said in a warning naming the
    joint and the profile key; closed reads 0 m (on the 0-255 scale it read 0.0083 m)."""
    r = Rig(activated=True)
    try:
        r.sim.gripper.write("Present_Position", CLOSED_COUNT)  # the fingers closed
        r.cycle(2)
        r.enable()
        r.cycle(2)
        assert r.measured == pytest.approx(0.0, abs=1e-9)
        assert r.backend.count(0.0) == CLOSED_COUNT and r.backend.count(0.085) == OPEN_COUNT
        (warning,) = [e for e in r.events("warning") if "found activated" in e["message"]]
        assert warning["joint"] == "finger" and "joints[0].calibration {open: N, closed: M}" in warning["message"]
    finally:
        r.close()


def test_a_blocked_activation_stroke_fails_the_enable_naming_it_and_a_changed_scale_is_reported(rig):
    """An activation whose fingers ran far less than a 2F's stroke (something blocked them)
    fails the enable naming the span instead of calibrating a wrong scale; the next enable
    activates anew, and a re-activation whose ends moved says so."""
    with rig.sim.gripper.lock:
        rig.sim.gripper.closed_count = 100  # the fingers stop at 100: a span of 87 counts
    reply = rig.reply(rig.request("enable"))
    assert not reply["ok"] and rig.c.state is OperatingState.FAULT
    assert "the fingers ran only 87 counts (gPO 13..100)" in reply["error"]["message"], reply
    assert "joints[0].calibration" in reply["error"]["message"]
    with rig.sim.gripper.lock:
        rig.sim.gripper.closed_count = 225  # cleared: another gripper's end
    rig.enable()  # activates anew (the blocked one is not trusted)
    assert rig.backend.info().details["calibration"] == {"open": OPEN_COUNT, "closed": 225}
    rig.sim.set_fault(None, "overcurrent")  # a major fault: the enable re-activates
    rig.until("FAULT", lambda: rig.c.state is OperatingState.FAULT)
    with rig.sim.gripper.lock:
        rig.sim.gripper.closed_count = CLOSED_COUNT
    rig.enable()
    (changed,) = [e for e in rig.events("warning") if "calibration changed" in e["message"]]
    assert f"closed 225 -> {CLOSED_COUNT}" in changed["message"] and changed["joint"] == "finger"


def test_enable_on_a_held_object_keeps_squeezing_it(rig):
    """Disabled with the fingers on an object, the enable sends the request that held it (the
    closing one), not the fingers' position (request == position: the grip force drops, gOBJ
    3); core's hold there writes nothing over it."""
    rig.enable()
    rig.sim.set_object(0.04)
    rig.move(0.0)
    rig.until("the grasp", lambda: rig.sim.gripper.dump()["gOBJ"] == T.GOBJ_CONTACT_CLOSING)
    assert rig.reply(rig.request("disable"))["ok"]
    rig.enable()
    rig.cycle(10)
    dump = rig.sim.gripper.dump()
    assert dump["gOBJ"] == T.GOBJ_CONTACT_CLOSING and dump["rPR"] == CLOSED_COUNT and dump["gGTO"] == 1, dump
    rig.move(0.06)  # a command elsewhere goes out
    assert rig.measured == pytest.approx(0.06, abs=COUNT_M)

"""Setting up servos on a new arm, against the wire-level simulators.

First the simulators' EEPROM (what `crtk-bridge setup-servos` and `check --scan --all-bauds` meet on
a real bus): writes that persist for the simulator's life under each vendor's lock rule (Feetech:
Lock = 0; Dynamixel: torque off), a Baud_Rate write after which the servo answers only at the new
rate, factory-fresh servos added, detached and attached through the control socket, and the
`crtk-sim` options that build day-one buses.

Then `crtk-bridge setup-servos`, the real command in its own process: six factory-fresh STS3215
connected one at a time through the simulator's control socket (as a user swaps cables) ending in
a bus the daemon enables on; a Dynamixel servo moved from its factory 57600 baud; several servos at
once and a servo of another model refused; --json parsed line by line."""

from __future__ import annotations

import json
import subprocess
import sys

import dynamixel_sdk as dxl
import pytest
import scservo_sdk as scs
import yaml

from crtk_bridge.backends.feetech.port import FastPortHandler
from crtk_bridge.client import connect
from crtk_bridge.sim.control import control_request
from crtk_bridge.sim.dynamixel import DynamixelSimulator
from crtk_bridge.sim.feetech import FeetechSimulator

from .conftest import KOCH, ROOT, SO101, DaemonProcess, profile_data, so101_data


def sdk_port(module, path: str, baud: int):
    # Feetech: the backend's port, which discards stale input (the status of an unacknowledged
    # write) before each request; the pip SDK's does not
    port = FastPortHandler(path) if module is scs else module.PortHandler(path)
    assert port.openPort() and port.setBaudRate(baud)
    return port


def write_unacknowledged(ph, port, sid: int, address: int, value: int) -> None:
    """A one-byte write whose status may come back under a new id or rate: sent without
    waiting for it, then that status read off the wire (so no later request takes it as its own)."""
    assert ph.write1ByteTxOnly(port, sid, address, value) == 0
    port.setPacketTimeout(12)
    ph.rxPacket(port, False) if isinstance(ph, dxl.Protocol2PacketHandler) else ph.rxPacket(port)
    port.is_using = False


def sts_ping(port, sid: int) -> bool:
    return scs.PacketHandler(0).ping(port, sid)[1] == scs.COMM_SUCCESS


# ---------------------------------------------------------------- simulators: EEPROM
def test_feetech_eeprom_persists_only_while_unlocked_and_baud_moves_the_servo():
    with FeetechSimulator(servo_ids=[1]) as sim:
        port = sdk_port(scs, sim.port, 1_000_000)
        ph = scs.PacketHandler(0)
        try:
            # Lock = 1 (power-on default): the new id takes effect, but a power cycle forgets it
            write_unacknowledged(ph, port, 1, 5, 7)
            assert sts_ping(port, 7) and not sts_ping(port, 1)
            sim.power_cycle()
            assert sim.ids == [1] and sts_ping(port, 1)
            # Lock = 0: id and Return_Delay_Time persist
            assert ph.write1ByteTxRx(port, 1, 55, 0)[0] == scs.COMM_SUCCESS
            write_unacknowledged(ph, port, 1, 5, 7)
            assert ph.write1ByteTxRx(port, 7, 7, 0)[0] == scs.COMM_SUCCESS
            # the new baud rate: deaf at 1 Mbps from now on, answering at 115200 only
            write_unacknowledged(ph, port, 7, 6, 4)
            assert not sts_ping(port, 7)
            assert port.setBaudRate(115_200) and sts_ping(port, 7)
            sim.power_cycle()
            assert sim.ids == [7] and sts_ping(port, 7)
            assert sim.servo(7).read("Lock") == 1 and sim.servo(7).read("Baud_Rate") == 4
            assert port.setBaudRate(1_000_000) and not sts_ping(port, 7)
        finally:
            port.closePort()


def test_dynamixel_eeprom_needs_torque_off_and_persists_across_a_power_cycle():
    with DynamixelSimulator({3: "xl430-w250"}) as sim:
        port = sdk_port(dxl, sim.port, 1_000_000)
        ph = dxl.PacketHandler(2.0)
        try:
            assert ph.write1ByteTxRx(port, 3, 64, 1)[0] == dxl.COMM_SUCCESS  # torque on
            result, error = ph.write4ByteTxRx(port, 3, 20, 300)  # Homing_Offset: EEPROM
            assert result == dxl.COMM_SUCCESS and error == 7  # access error: not written
            assert sim.servo(3).read("Homing_Offset") == 0
            assert ph.write1ByteTxRx(port, 3, 64, 0)[0] == dxl.COMM_SUCCESS
            assert ph.write4ByteTxRx(port, 3, 20, 300) == (dxl.COMM_SUCCESS, 0)
            write_unacknowledged(ph, port, 3, 8, 1)  # Baud_Rate 1: 57600
            assert ph.ping(port, 3)[1] != dxl.COMM_SUCCESS
            assert port.setBaudRate(57_600) and ph.ping(port, 3)[1] == dxl.COMM_SUCCESS
            sim.power_cycle()
            assert sim.servo(3).read("Homing_Offset") == 300 and sim.servo(3).read("Baud_Rate") == 1
            assert sim.servo(3).read("Torque_Enable") == 0
        finally:
            port.closePort()


def test_factory_servos_through_the_control_socket(short_tmp):
    ctl = short_tmp / "sim.ctl"
    with DynamixelSimulator({5: "xm430-w350"}, control=ctl):
        reply = control_request(ctl, {"cmd": "add_servo"})
        assert reply["ok"] and reply["serial"] == 2
        dump = control_request(ctl, {"cmd": "dump"})
        fresh = dump["servos"]["1"]
        assert (fresh["model"], fresh["baud_rate"], fresh["return_delay_time"], fresh["serial"]) == \
            ("xl430-w250", 1, 250, 2)  # id 1, 57600 baud, 500 us: as shipped
        taken = control_request(ctl, {"cmd": "add_servo", "model": "xl330-m288"})
        assert not taken["ok"] and "id 1 is taken on the bus" in taken["error"]
        assert control_request(ctl, {"cmd": "write", "id": 1, "register": "ID", "value": 9})["ok"]
        assert control_request(ctl, {"cmd": "detach", "serial": 2})["ok"]
        dump = control_request(ctl, {"cmd": "dump"})
        assert list(dump["servos"]) == ["5"] and dump["detached"]["2"]["id"] == 9  # keeps its EEPROM
        assert control_request(ctl, {"cmd": "attach", "serial": 2})["ok"]
        assert sorted(control_request(ctl, {"cmd": "dump"})["servos"]) == ["5", "9"]
        bad = control_request(ctl, {"cmd": "add_servo", "model": "ax-12"})
        assert not bad["ok"] and "unknown model 'ax-12'" in bad["error"]


def crtk_sim(short_tmp, *options) -> tuple[subprocess.Popen, str]:
    ctl = short_tmp / "sim.ctl"
    proc = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", "feetech", "--profile", str(SO101),
                             "--control", str(ctl), *options], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    assert "bus ready" in line, line
    return proc, str(ctl)


@pytest.mark.parametrize("options, expect", [
    (["--empty", "--factory-servo"], {"1": (0, 777, 250)}),
    (["--servo-baud", "115200", "--model", "3=sts3250"],
     {str(i): (4, 2825, 250) if i == 3 else (4, 777, 0) for i in range(1, 7)}),
], ids=["one-unconfigured-servo", "baud-mismatch-and-other-model"])
def test_crtk_sim_day_one_buses(short_tmp, options, expect):
    proc, ctl = crtk_sim(short_tmp, *options)
    try:
        servos = control_request(ctl, {"cmd": "dump"})["servos"]
        assert {sid: (s["baud_rate"], s["model_number"], s["return_delay_time"]) for sid, s in servos.items()} \
            == expect
    finally:
        proc.terminate()
        assert proc.wait(10) == 0


# ---------------------------------------------------------------- crtk-bridge setup-servos
def write_profile(tmp, data: dict, port: str) -> str:
    data["backend"]["port"] = port
    path = tmp / "arm.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def setup_servos(profile: str, *options, stdin=subprocess.DEVNULL) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "crtk_bridge.cli", "setup-servos", "--profile", profile,
                             *options], cwd=ROOT, stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def test_six_factory_fresh_servos_one_at_a_time_then_the_daemon_enables(short_tmp):
    ctl = short_tmp / "sim.ctl"
    with FeetechSimulator(servo_ids=[], control=ctl) as sim:
        profile = write_profile(short_tmp, so101_data(), sim.port)
        proc = setup_servos(profile, "--yes", "--json", "--timeout", "20")
        events, serials = [], []
        try:
            for line in proc.stdout:
                event = json.loads(line)
                events.append(event)
                # the user swaps cables (the last one out, a new one in) only once the command
                # says it still sees the servo it set up last: it must wait for the swap
                first = event["event"] == "connect" and not serials
                if first or (event["event"] == "waiting" and event["reason"] == "previous"):
                    if serials:
                        assert control_request(ctl, {"cmd": "detach", "serial": serials[-1]})["ok"]
                    reply = control_request(ctl, {"cmd": "add_servo", "position": 2048})
                    serials.append(reply["serial"])
            assert proc.wait(30) == 0, proc.stderr.read()
        finally:
            proc.kill()
            proc.wait()
        summary = events[-1]
        assert summary["event"] == "summary" and summary["ok"] and summary["exit_code"] == 0
        order = ["gripper", "wrist_roll", "wrist_flex", "elbow_flex", "shoulder_lift", "shoulder_pan"]
        assert [e["joint"] for e in events if e["event"] == "connect"] == order  # id 1 last
        configured = [e for e in events if e["event"] == "configured"]
        assert [(e["joint"], e["from_id"], e["id"], e["baudrate"]) for e in configured] == \
            [(name, 1, 6 - k, 1_000_000) for k, name in enumerate(order)]
        assert configured[0]["written"] == ["ID", "Return_Delay_Time"]
        assert configured[-1]["written"] == ["Return_Delay_Time"]  # id 1 already: only the delay
        waits = [e for e in events if e["event"] == "waiting" and e["reason"] == "previous"]
        assert [e["joint"] for e in waits] == order[1:] and waits[0]["message"] == (
            "only the servo of joint 'gripper' (id 6) answers: disconnect it and connect the servo of joint "
            "'wrist_roll'")
        assert summary["joints"] == [{k: e[k] for k in e if k != "event"} for e in configured]

        # all six on the bus again, after a power cycle: the EEPROM kept what was written
        control_request(ctl, {"cmd": "detach", "serial": serials[-1]})
        for serial in serials:
            assert control_request(ctl, {"cmd": "attach", "serial": serial})["ok"]
        sim.power_cycle()
        servos = control_request(ctl, {"cmd": "dump"})["servos"]
        assert {sid: (s["baud_rate"], s["return_delay_time"], s["lock"]) for sid, s in servos.items()} == \
            {str(i): (0, 0, 1) for i in range(1, 7)}
        d = DaemonProcess(["--profile", profile, "--no-realtime"], short_tmp / "arm.sock", short_tmp / "arm.log")
        try:
            robot = connect(socket=str(d.socket_path))
            try:
                assert robot.device("so101").enable(5.0)
            finally:
                robot.close()
        finally:
            d.stop()


def test_dynamixel_servo_moves_from_its_factory_rate_and_id(short_tmp):
    with DynamixelSimulator({}) as sim:
        sim.add_servo(model="xl330-m288")  # id 1 at 57600 baud, as shipped
        profile = write_profile(short_tmp, profile_data(KOCH), sim.port)
        proc = setup_servos(profile, "--yes", "--joint", "gripper", "--timeout", "10")
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
        assert "[1/1] gripper: connect ONLY its servo (xl330-m288); it gets id 6 at 1000000 baud" in out
        assert "  found xl330-m288 at id 1, 57600 baud" in out
        assert ("  set up: id 1 -> 6, 57600 -> 1000000 baud (wrote ID, Return_Delay_Time, Baud_Rate); "
                "verified") in out
        sim.power_cycle()
        servo = sim.servo(6)
        assert (servo.read("Baud_Rate"), servo.read("Return_Delay_Time")) == (3, 0)


def test_several_servos_at_once_are_refused_and_nothing_is_written(short_tmp):
    with FeetechSimulator(servo_ids=[]) as sim:
        sim.add_servo()
        sim.add_servo(servo_id=9)
        profile = write_profile(short_tmp, so101_data(), sim.port)
        proc = setup_servos(profile, "--yes", "--json", "--timeout", "1")
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 4, err
        events = [json.loads(line) for line in out.splitlines()]
        assert [e["event"] for e in events if e["event"] != "waiting"] == ["connect", "summary"]
        several = "2 servos answer at 1000000 baud (ids 1, 9): connect ONLY the servo of joint 'gripper'"
        assert {"event": "waiting", "joint": "gripper", "reason": "several", "message": several} in events
        assert events[-1]["error"].startswith("so101: joint 'gripper': no single new servo within 1 s: ")
        assert sim.ids == [1, 9] and sim.servo(1).read("Return_Delay_Time") == 250


def test_a_servo_of_another_model_is_refused_at_the_prompt(short_tmp):
    with FeetechSimulator(servo_ids=[]) as sim:
        sim.add_servo(model="sts3250")
        profile = write_profile(short_tmp, so101_data(), sim.port)
        proc = setup_servos(profile, "--joint", "elbow_flex", stdin=subprocess.PIPE)
        out, err = proc.communicate("\n", timeout=60)  # Enter at the prompt
        assert proc.returncode == 3, err
        assert "Connect ONLY the servo of joint 'elbow_flex' (sts3215) to the bus, power it, then press Enter." in out
        assert err.strip() == (
            "crtk-bridge: so101: joint 'elbow_flex': the servo found (id 1 at 1000000 baud) is model number 2825 "
            "(sts3250), the profile says sts3215 (777): connect the servo the profile names, or correct "
            "joints[2] (elbow_flex).model; nothing was written")
        assert sim.ids == [1] and sim.servo(1).read("Return_Delay_Time") == 250


def test_a_several_bus_profile_needs_bus_and_an_unknown_joint_is_refused(short_tmp):
    bimanual = str(ROOT / "profiles" / "bimanual_so101.yaml")
    proc = setup_servos(bimanual, "--yes")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "--bus must name one of the profile's buses (left, right)" in err
    proc = setup_servos(str(SO101), "--joint", "elbow", "--yes")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "--joint elbow: not a joint of this bus (shoulder_pan, " in err


def test_a_backend_that_cannot_set_up_servos_is_named_with_those_that_can():
    # setting up ids is an optional capability (backends/optional.py), not a private method looked up
    proc = setup_servos(str(ROOT / "profiles" / "canopen_2axis.yaml"), "--yes", "--json")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err
    summary = json.loads(out.splitlines()[-1])
    assert summary == {"event": "summary", "ok": False, "exit_code": 1, "error": (
        "canopen_2axis: backend: backend 'canopen402' (Canopen402Backend) cannot set up its devices' ids "
        "and baud rate (crtk-bridge setup-servos); backends that can: dynamixel, feetech")}

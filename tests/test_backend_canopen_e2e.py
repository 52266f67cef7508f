"""End to end on CANopen: ``crtk-bridge --profile profiles/canopen_2axis.yaml --sim`` as a real
subprocess (the simulated drives behind the simulated SLCAN USB-CAN adapter, in their own
process), driven through the client; the drives inspected and faulted over the simulator's control
socket. One daemon serves the module (tests leave it DISABLED with no fault injected)."""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from crtk_bridge.client import connect
from crtk_bridge.sim.control import control_request

from .conftest import ROOT, DaemonProcess, RawSession, wait_until

# --sim reaches the simulated drives in their own process through the simulated USB-CAN adapter
pytest.importorskip("crtk_bridge.sim.slcan", reason="the simulated SLCAN adapter (sim/slcan.py) is not there")

PROFILE = ROOT / "profiles" / "canopen_2axis.yaml"
NS = "pantilt"
TOL = 0.01  # rad


@pytest.fixture(scope="module")
def daemon():
    tmp = Path(tempfile.mkdtemp(prefix="crtk-can-"))
    d = DaemonProcess(["--profile", str(PROFILE), "--sim"], tmp / "can.sock", tmp / "daemon.log")
    yield d
    d.stop()


@pytest.fixture
def rig(daemon):
    robot = connect(socket=str(daemon.socket_path))
    arm = robot.device(NS)
    sim = daemon.sim_control_path()
    try:
        yield arm, sim
    finally:
        control_request(sim, {"cmd": "clear_faults"})
        control_request(sim, {"cmd": "enable_delay", "seconds": 0})
        try:
            arm.disable(5.0)
        finally:
            robot.close()


def drives(sim) -> dict:
    return control_request(sim, {"cmd": "dump"})["drives"]


def test_enable_walks_the_402_states_while_the_loop_keeps_publishing(rig, daemon):
    arm, sim = rig
    watcher = connect(socket=str(daemon.socket_path))  # another session watches meanwhile
    view = watcher.device(NS)
    assert arm.operating_state() == "DISABLED"
    assert {d["state"] for d in drives(sim).values()} == {"SWITCH_ON_DISABLED"}
    control_request(sim, {"cmd": "enable_delay", "seconds": 0.4})  # a brake releasing
    result = {}
    worker = threading.Thread(target=lambda: result.setdefault("ok", arm.enable(5.0)))
    worker.start()
    states, stamps, busy = set(), [], []
    try:
        while worker.is_alive():
            full = view.operating_state_full()
            stamps.append(view.measured_js()[3])
            states |= {d["state"] for d in drives(sim).values()}
            if full["state"] != "ENABLED":
                assert full["state"] == "DISABLED"  # until the walk ends
                busy.append(full["is_busy"])
    finally:
        worker.join()
        watcher.close()
    assert any(busy)
    assert result["ok"] and arm.is_enabled()
    assert "SWITCHED_ON" in states  # held there by the enable delay while the loop went on
    assert {d["state"] for d in drives(sim).values()} == {"OPERATION_ENABLED"}
    assert len(stamps) > 5 and np.all(np.diff(stamps) >= 0) and stamps[-1] - stamps[0] > 0.3


def test_move_jp_is_tracked_in_csp(rig):
    arm, sim = rig
    assert arm.enable(5.0)
    goal = [0.4, -0.3]
    assert arm.move_jp(goal).wait(timeout=10.0)
    wait_until(lambda: np.allclose(arm.measured_jp()[0], goal, atol=TOL), 3, what="at the goal")
    d = drives(sim)
    assert d["1"]["mode"] == 8 and d["2"]["mode"] == 8
    # counts = offset + direction * goal * counts_per_revolution * gear_ratio / (2 pi)
    assert d["1"]["target_position"] == round(0.4 * 16384 * 10 / (2 * np.pi))
    assert d["2"]["target_position"] == round(-1 * -0.3 * 16384 * 10 / (2 * np.pi))


def test_servo_jv_runs_csv_and_servo_jf_runs_cst(rig):
    arm, sim = rig
    assert arm.enable(5.0)
    assert arm.supports("servo_jv") and arm.supports("servo_jf")
    arm.servo_jv([0.4, -0.2])
    wait_until(lambda: np.allclose(arm.measured_jv()[0], [0.4, -0.2], atol=0.05), 3, what="velocity followed")
    assert {d["mode"] for d in drives(sim).values()} == {9}
    arm.servo_jf([0.5, -0.25])
    wait_until(lambda: {d["mode"] for d in drives(sim).values()} == {10}, 3, what="CST")
    d = drives(sim)
    assert d["1"]["target_torque"] == 100 and d["2"]["target_torque"] == 50  # per mille of 5 N*m (tilt: direction -1)
    wait_until(lambda: np.allclose(arm.measured_jf()[0], [0.5, -0.25], atol=0.05), 3, what="effort measured")
    arm.servo_jv([0.0, 0.0])


def _error(raw: RawSession, code: str) -> dict:
    def found():
        with raw.lock:
            return [e["data"] for e in raw.events if e.get("event") == "error" and e["data"].get("code") == code]
    return wait_until(found, 3, what=f"an error event {code}")[-1]


def test_emcy_faults_naming_the_code_and_enable_recovers(rig, daemon):
    arm, sim = rig
    raw = RawSession(str(daemon.socket_path))
    try:
        assert arm.enable(5.0)
        control_request(sim, {"cmd": "fault", "node": 2, "kind": "emcy", "code": 0x8611})
        err = _error(raw, "drive_fault")
        assert err["joint"] == "tilt" and err["value"] == 0x8611
        assert "node 2" in err["message"] and "EMCY 0x8611 following error" in err["message"]
        wait_until(lambda: arm.is_fault(), 3, what="FAULT")
        assert drives(sim)["2"]["state"] == "FAULT"
        wait_until(lambda: not arm.is_busy(), 3, what="the fault's torque off")
        assert arm.enable(5.0) and arm.is_enabled()  # fault reset (bit 7 rising edge), then the walk
        assert {d["state"] for d in drives(sim).values()} == {"OPERATION_ENABLED"}
    finally:
        raw.close()


def test_heartbeat_loss_faults_naming_the_node(rig, daemon):
    arm, sim = rig
    raw = RawSession(str(daemon.socket_path))
    try:
        assert arm.enable(5.0)
        control_request(sim, {"cmd": "fault", "node": 1, "kind": "heartbeat_stop"})
        err = _error(raw, "heartbeat_lost")
        assert err["joint"] == "pan" and "node 1" in err["message"]
        wait_until(lambda: arm.is_fault(), 3, what="FAULT")
        control_request(sim, {"cmd": "clear_faults"})  # the heartbeat comes back
        wait_until(lambda: not arm.is_busy(), 3, what="the fault's torque off")
        assert arm.enable(5.0) and arm.is_enabled()
    finally:
        raw.close()


def test_pause_is_a_quick_stop_and_resume_leaves_it(rig):
    arm, sim = rig
    assert arm.enable(5.0)
    arm.servo_jv([0.5, 0.5])
    wait_until(lambda: abs(arm.measured_jv()[0][0]) > 0.3, 3, what="moving")
    assert arm.pause(5.0) and arm.is_paused()
    d = drives(sim)
    assert {x["state"] for x in d.values()} == {"QUICK_STOP_ACTIVE"} and {x["controlword"] for x in d.values()} == {2}
    wait_until(lambda: np.all(np.abs(arm.measured_jv()[0]) < 0.01), 3, what="stopped")
    assert arm.resume(5.0) and arm.is_enabled()
    for x in drives(sim).values():  # left QUICK STOP ACTIVE holding where it stopped: no jump
        assert x["state"] == "OPERATION_ENABLED" and x["mode"] == 8
        assert abs(x["target_position"] - x["position"]) < 0.01 * 16384 * 10 / (2 * np.pi)


def test_adapter_bus_off_faults_and_enable_recovers_once_it_passes_again(rig, daemon):
    arm, sim = rig
    raw = RawSession(str(daemon.socket_path))
    try:
        assert arm.enable(5.0)
        control_request(sim, {"cmd": "bus_off", "on": True})  # the simulated adapter passes nothing
        err = _error(raw, "tpdo_missing")
        assert err["joint"] in ("pan", "tilt") and "node" in err["message"]
        wait_until(lambda: arm.is_fault(), 3, what="FAULT")
        assert arm.measured_js()[3] == 0.0  # no valid sample while the bus is off
        # the drives hear no master heartbeat either: each stops itself (0x1016 consumer, EMCY
        # 0x8130) within 300 ms; enable must then reset their FAULT too
        wait_until(lambda: {d["state"] for d in drives(sim).values()} == {"FAULT"}, 3,
                   what="the drives' own heartbeat-loss FAULT")
        control_request(sim, {"cmd": "bus_off", "on": False})
        wait_until(lambda: arm.measured_js()[3] > 0 and not arm.is_busy(), 5,
                   what="valid samples again, the fault's torque off settled")
        assert arm.enable(5.0) and arm.is_enabled()
    finally:
        raw.close()


def test_drives_stop_by_themselves_when_the_control_process_is_killed(short_tmp):
    """kill -9 of the control process while ENABLED: nothing disables the drives, yet they leave
    OPERATION ENABLED within their heartbeat consumer time (0x1016, written by the backend), with
    EMCY 0x8130. The simulator runs here, not under the daemon, so it outlives it."""
    import os
    import signal

    import yaml

    from crtk_bridge.profile import load_profile
    from crtk_bridge.sim.canopen402 import CanopenSimulator

    from .conftest import profile_data
    from .test_e2e_processes import _control_pid

    sim = CanopenSimulator.from_profile(load_profile(PROFILE), link=short_tmp / "can")
    sim.start()
    try:
        data = profile_data(PROFILE)
        data["backend"].update(interface="slcan", channel=sim.port, options={"sleep_after_open": 0},
                               tpdo_timeout_ms=50)
        profile = short_tmp / "p.yaml"
        profile.write_text(yaml.safe_dump(data))
        daemon = DaemonProcess(["--profile", str(profile)], short_tmp / "d.sock", short_tmp / "d.log")
        try:
            robot = connect(socket=str(daemon.socket_path))
            try:
                assert robot.device(NS).enable(5.0)
                assert {d.state.name for d in sim.drives.values()} == {"OPERATION_ENABLED"}
                os.kill(_control_pid(daemon.proc.pid), signal.SIGKILL)
                killed = time.monotonic()
                wait_until(lambda: all(d.state.name != "OPERATION_ENABLED" for d in sim.drives.values()),
                           0.3 + 2.0, interval=0.005, what="the drives leaving OPERATION ENABLED")
                took = time.monotonic() - killed
            finally:
                robot.close()
            # heartbeat lost (consumer time 300 ms: 3 x master_heartbeat_ms); 0.27-0.28 s measured
            assert all(d.error_code == 0x8130 for d in sim.drives.values()), took
        finally:
            daemon.stop()
    finally:
        sim.stop()

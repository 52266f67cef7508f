"""The UR backend (backends/ur) on the simulated UR controller (sim/ur.py), through ur_rtde
unmodified: the controller (core/control/) driven cycle by cycle as core/loop.py does, paced by
the controller's RTDE packets (``wait_cycle``), checked on what the simulated controller reports.

One simulator and one backend serve the whole module; each test starts from a fresh controller,
the arm DISABLED and powered off with no stop active. ur_rtde runs in the backend's worker process
(backends/ur/worker.py), never in this one: an abort there ends the worker, not the session.
"""

from __future__ import annotations

import os
import signal
import time

import msgspec
import numpy as np
import pytest

from crtk_bridge.backends.ur.backend import UrBackend
from crtk_bridge.backends.ur.channel import CTL_RUNNING
from crtk_bridge.core.actuator import Lifecycle
from crtk_bridge.core.control import Controller
from crtk_bridge.core.cycle import CycleRunner, run_transition
from crtk_bridge.core.state import OperatingState
from crtk_bridge.errors import ProfileError
from crtk_bridge.profile import load_profile
from crtk_bridge.sim import simulator_class

from .conftest import ROOT, wait_until

UR5E = ROOT / "profiles" / "ur5e.yaml"
NS = "ur5e"
#: a comfortable pose away from the stretched-out singularity at all zeros (rad)
READY = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
#: the daemon's own limit of wrist_3 widened past the controller's (+-2 pi), so that only the
#: controller's safety limits can refuse a goal there
WRIST_3_DAEMON_LIMIT = 6.9


class URRig:
    """The simulated controller, the backend on it, and a controller stepped like the loop."""

    def __init__(self):
        profile = load_profile(UR5E)
        # quick power-on / brake release, and a protective stop unlockable after 0.3 s (UR: 5 s)
        self.sim = simulator_class("ur").from_profile(profile, power_on_s=0.1, brake_release_s=0.1,
                                                      unlock_delay_s=0.3)
        self.sim.start()
        joints = list(profile.joints)
        lim = msgspec.structs.replace(joints[5].limits, position_min=-WRIST_3_DAEMON_LIMIT,
                                      position_max=WRIST_3_DAEMON_LIMIT)
        joints[5] = msgspec.structs.replace(joints[5], limits=lim)
        self.profile = UrBackend.sim_profile(msgspec.structs.replace(profile, joints=joints), self.sim.port)
        self.backend = UrBackend(self.profile)
        self.backend.open()
        self.backend.configure()
        self.runner = CycleRunner(self.backend, self.backend.dt)  # paced by the controller's packages
        self.fb = self.runner.feedback
        self.c: Controller | None = None
        self.rid = 0
        self.cycles = 0

    # ---- the loop, as core/loop.py runs it (core/cycle.py) ----
    def cycle(self, n: int = 1) -> None:
        for _ in range(n):
            self.runner.cycle(self.c)
            self.cycles += 1

    def until(self, predicate, timeout: float = 5.0, what: str = "condition"):
        deadline = time.monotonic() + timeout
        while True:
            value = predicate()
            if value:
                return value
            assert time.monotonic() < deadline, f"timed out after {timeout} s waiting for {what}"
            self.cycle()

    def send(self, cmd: str, ns: str | None = None, **data) -> int:
        self.rid += 1
        self.c.handle({"id": self.rid, "cmd": cmd, "ns": ns, "data": data})
        return self.rid

    def reply(self, rid: int, timeout: float = 5.0) -> dict:
        found = self.until(lambda: [m for m in self.c.outbox if m.get("id") == rid], timeout, f"reply {rid}")
        return found[0]

    def do(self, cmd: str, ns: str | None = None, timeout: float = 5.0, **data) -> dict:
        return self.reply(self.send(cmd, ns, **data), timeout)

    def events(self, kind: str) -> list[dict]:
        return [m["data"] for m in self.c.outbox if m.get("event") == kind]

    def states(self) -> list[dict]:
        return [m["data"] for m in self.c.outbox if m.get("event") == "operating_state"]

    # ---- set-up ----
    def fresh(self) -> Controller:
        """A new controller; the arm DISABLED, powered off, no stop, no lost link."""
        b = self.backend
        st = self.sim.state()
        if st["safety_mode"] == "SAFEGUARD_STOP":
            self.sim.release("safeguard")
        deadline = time.monotonic() + 5
        while not b._refresh():  # a link lost by the previous test comes back by itself
            b._maybe_reconnect()
            assert time.monotonic() < deadline, "the RTDE link did not come back"
            time.sleep(0.05)
        if b.safety_mode != 1:
            run_transition(b, b.begin(Lifecycle.FAULT_RESET))
        b.disable()
        self.c = Controller(self.profile, b, time.time, b.dt)
        self.cycle()
        return self.c

    def enabled(self, pose: np.ndarray | None = None) -> Controller:
        c = self.fresh()
        assert self.do("enable", timeout=10)["ok"]
        if pose is not None:
            self.move_to(pose)
        return c

    def move_to(self, goal: np.ndarray) -> None:
        r = self.do("move_jp", NS, position=list(goal))
        assert r["ok"], r
        self.until(lambda: not self.c.is_busy, 10, "move_jp done")

    def sim_q(self) -> np.ndarray:
        return np.array(self.sim.state()["q"])

    def close(self) -> None:
        try:
            self.backend.close()
        finally:
            self.sim.stop()


@pytest.fixture(scope="module")
def ur():
    rig = URRig()
    yield rig
    rig.close()


def test_enable_from_power_off_keeps_the_loop_cycling(ur):
    c = ur.fresh()
    assert ur.sim.state()["robot_mode"] == "POWER_OFF" and c.state is OperatingState.DISABLED
    q0 = ur.sim_q()
    rid = ur.send("enable")
    stamps, t0 = [], time.monotonic()
    while not [m for m in c.outbox if m.get("id") == rid]:
        assert c.state is OperatingState.DISABLED and c.is_busy  # the state stays until it ends
        ur.cycle()
        stamps.append(ur.fb.stamp)
        assert time.monotonic() - t0 < 10, "enable did not end"
    took = time.monotonic() - t0
    assert ur.reply(rid)["ok"] and c.state is OperatingState.ENABLED and not c.is_busy, ur.reply(rid)
    st = ur.sim.state()
    assert st["robot_mode"] == "RUNNING" and st["runtime_state"] == "PLAYING" and st["program"]
    # power on + brake release took >= 0.2 s on the simulator, and the cycle went on reading:
    # the measured stamps advanced all along (a blocking enable would freeze them)
    assert took >= 0.2 and len(stamps) > 0.25 * took / ur.backend.dt
    gaps = np.diff(stamps)
    assert np.all(gaps >= 0) and gaps.max() < 0.1, gaps.max()
    np.testing.assert_allclose(ur.sim_q(), q0, atol=1e-3)  # enabled where it was: no motion
    np.testing.assert_allclose(c.command.position, q0, atol=1e-3)


def test_servo_jp_and_move_jp_track(ur):
    c = ur.enabled()
    q0 = ur.fb.position.copy()
    # servo_jp: a ramp on two joints, one command per cycle (0.2 rad over 0.4 s)
    steps = int(0.4 / ur.backend.dt)
    for k in range(1, steps + 1):
        target = q0 + np.array([0.2, -0.2, 0, 0, 0, 0]) * k / steps
        ur.send("servo_jp", NS, position=list(target))
        ur.cycle()
    assert not [m for m in c.outbox if m.get("ok") is False]
    ur.until(lambda: np.allclose(ur.sim_q(), target, atol=2e-3), 2, "the arm at the servo_jp target")
    # move_jp: the daemon's jerk-limited trajectory, streamed with servoJ, ends on the goal
    goal = READY.copy()
    r = ur.do("move_jp", NS, position=list(goal))
    assert r["ok"] and c.is_busy
    ur.until(lambda: not c.is_busy, 10, "move_jp done")
    ur.until(lambda: np.allclose(ur.sim_q(), goal, atol=2e-3), 2, "the arm at the move_jp goal")
    np.testing.assert_allclose(ur.fb.position, ur.sim_q(), atol=5e-3)  # measured_js is the arm's


def test_servo_cp_and_move_cp_track(ur):
    c = ur.enabled(READY)
    cart = ur.fb.cartesian
    p0, q0 = cart.position[0].copy(), cart.orientation[0].copy()
    tcp = np.array(ur.sim.state()["tcp_pose"])
    np.testing.assert_allclose(p0, tcp[:3], atol=1e-4)  # measured_cp is actual_TCP_pose
    # servo_cp: 4 cm up over 0.4 s, one pose per cycle
    steps = int(0.4 / ur.backend.dt)
    for k in range(1, steps + 1):
        p = p0 + np.array([0.0, 0.0, 0.04]) * k / steps
        r = ur.send("servo_cp", NS, position=list(p), orientation=list(q0))
        ur.cycle()
    assert not [m for m in c.outbox if m.get("ok") is False], [m for m in c.outbox if m.get("ok") is False]
    ur.until(lambda: np.allclose(ur.sim.state()["tcp_pose"][:3], p, atol=1e-3), 2, "the TCP at the servo_cp pose")
    # move_cp: the backend's straight-line trajectory, is_busy until the TCP is there
    goal = p + np.array([0.05, -0.03, -0.04])
    r = ur.do("move_cp", NS, position=list(goal), orientation=list(q0))
    assert r["ok"], r
    assert c.is_busy
    ur.until(lambda: not c.is_busy, 10, "move_cp done")
    tcp = np.array(ur.sim.state()["tcp_pose"])
    assert np.linalg.norm(tcp[:3] - goal) < 2e-3 and np.linalg.norm(tcp[3:] - ur.sim.state()["tcp_pose"][3:]) < 1e-6
    assert c.state is OperatingState.ENABLED


def test_goals_outside_the_controllers_safety_limits_are_refused(ur):
    c = ur.enabled(READY)
    q = ur.fb.position.copy()
    q[5] = 6.5  # inside the daemon's limit (6.9), outside the controller's (2 pi)
    r = ur.do("move_jp", NS, position=list(q))
    assert not r["ok"] and r["error"]["code"] == "out_of_limits", r
    assert "'wrist_3_joint'" in r["error"]["message"] and "safety limits" in r["error"]["message"]
    p = ur.fb.cartesian.position[0]
    r = ur.do("move_cp", NS, position=[2.0, 0.0, 0.3], orientation=list(ur.fb.cartesian.orientation[0]))
    assert not r["ok"] and r["error"]["code"] == "out_of_limits", r
    assert "pose [2.0000" in r["error"]["message"]
    assert not c.is_busy and c.state is OperatingState.ENABLED
    np.testing.assert_allclose(ur.fb.cartesian.position[0], p, atol=1e-3)  # nothing moved
    # a goal inside both limits goes
    assert ur.do("move_jp", NS, position=list(READY + 0.05))["ok"]
    ur.until(lambda: not c.is_busy, 10, "move_jp done")


def test_protective_stop_faults_naming_the_cause_then_enable_recovers(ur):
    c = ur.enabled(READY)
    ur.sim.inject_stop("protective", cause="a test collision")
    ur.until(lambda: c.state is OperatingState.FAULT, 2, "FAULT")
    err = ur.events("error")[-1]
    assert err["code"] == "protective_stop" and "protective stop" in err["message"], err
    ur.until(lambda: not c.is_busy, 5, "the fault reaction's end")
    assert ur.sim.state()["robot_mode"] == "POWER_OFF"  # the fault reaction: stopped, powered off
    r = ur.do("enable", timeout=15)
    assert r["ok"], r
    st = ur.sim.state()
    assert c.state is OperatingState.ENABLED and st["safety_mode"] == "NORMAL" and st["runtime_state"] == "PLAYING"
    assert ur.do("move_jp", NS, position=list(READY + 0.1))["ok"]  # and it moves again
    ur.until(lambda: not c.is_busy, 10, "move_jp done")
    ur.until(lambda: np.allclose(ur.sim_q(), READY + 0.1, atol=2e-3), 2, "the arm at the goal")


def test_enable_after_disable_from_a_protective_stop_unlocks_it(ur):
    c = ur.enabled(READY)
    ur.sim.inject_stop("protective", cause="a test collision")
    ur.until(lambda: c.state is OperatingState.FAULT, 2, "FAULT")
    ur.until(lambda: not c.is_busy, 5, "the fault reaction's end")
    assert ur.do("disable", timeout=10)["ok"] and c.state is OperatingState.DISABLED  # FAULT -> DISABLED
    assert ur.sim.state()["safety_mode"] == "PROTECTIVE_STOP"  # the stop outlives the FAULT...
    r = ur.do("enable", timeout=15)  # ...and enable from DISABLED unlocks it, as from FAULT
    assert r["ok"], r
    st = ur.sim.state()
    assert c.state is OperatingState.ENABLED and st["safety_mode"] == "NORMAL" and st["runtime_state"] == "PLAYING"
    assert ur.do("move_jp", NS, position=list(READY + 0.1))["ok"]
    ur.until(lambda: not c.is_busy, 10, "move_jp done")
    ur.until(lambda: np.allclose(ur.sim_q(), READY + 0.1, atol=2e-3), 2, "the arm at the goal")


def test_safeguard_stop_pauses_and_resume_starts_from_the_measured_pose(ur):
    c = ur.enabled(READY)
    goal = READY + np.array([0.6, 0, 0, 0, 0, 0])
    assert ur.do("move_jp", NS, position=list(goal))["ok"]
    ur.until(lambda: abs(ur.fb.position[0] - READY[0]) > 0.15, 5, "the move under way")
    ur.sim.inject_stop("safeguard")
    ur.until(lambda: c.state is OperatingState.PAUSED, 2, "PAUSED")
    assert ur.events("warning")[-1]["code"] == "device_paused"
    r = ur.do("move_jp", NS, position=list(goal))
    assert not r["ok"] and r["error"]["code"] == "invalid_state"
    stopped = ur.sim_q()
    ur.sim.release("safeguard")
    ur.cycle(int(0.2 / ur.backend.dt))  # released, not resumed: the arm stays where it stopped
    np.testing.assert_allclose(ur.sim_q(), stopped, atol=2e-3)
    assert ur.do("resume")["ok"] and c.state is OperatingState.ENABLED
    np.testing.assert_allclose(c.namespaces[NS].setpoint_p, ur.fb.position, atol=1e-9)  # re-seeded
    ur.cycle(int(0.2 / ur.backend.dt))
    np.testing.assert_allclose(ur.sim_q(), stopped, atol=2e-3)  # no rush to where it was going


def test_link_loss_faults_in_the_cycle_that_sees_it_then_reconnects(ur):
    c = ur.enabled(READY)
    ur.sim.link_loss(0.5, ports=("rtde",))
    seen = None
    for _ in range(int(2.0 / ur.backend.dt)):
        ur.cycle()
        if not ur.backend._link:
            seen = ur.cycles
            break
    assert seen is not None, "the backend never saw the link go down"
    assert c.state is OperatingState.FAULT  # in that same cycle
    assert ur.events("error")[-1]["code"] == "link_lost", ur.events("error")[-1]
    ur.until(lambda: any(e["code"] == "fault_cleared" for e in ur.events("status")), 5, "the link back")
    assert c.state is OperatingState.FAULT  # never enabled by itself
    # the fault reaction (stop, power off) could not be confirmed without the link: it is, now
    ur.until(lambda: not c.is_busy and ur.sim.state()["robot_mode"] == "POWER_OFF", 5, "the arm powered off")
    ur.until(lambda: not c.is_busy and not c.torque_unconfirmed, 5, "the fault reaction confirmed")
    r = ur.do("enable", timeout=15)
    assert r["ok"], r
    assert ur.do("move_jp", NS, position=list(READY - 0.1))["ok"]
    ur.until(lambda: not c.is_busy, 10, "move_jp done")
    ur.until(lambda: np.allclose(ur.sim_q(), READY - 0.1, atol=2e-3), 2, "the arm at the goal")


def test_free_is_teach_mode(ur):
    c = ur.enabled(READY)
    assert ur.do("free", NS)["ok"]
    ur.until(lambda: ur.sim.state()["teach_mode"], 2, "teach mode")
    pushed = READY + np.array([0.2, 0.1, 0, 0, 0, 0])
    ur.sim.control({"cmd": "hand", "q": list(pushed), "speed": 1.0})
    ur.until(lambda: np.allclose(ur.fb.position, pushed, atol=2e-3), 3, "measured_js following the hand")
    assert ur.do("hold", NS)["ok"]
    ur.until(lambda: not ur.sim.state()["teach_mode"], 2, "teach mode ended")
    ur.cycle(int(0.2 / ur.backend.dt))
    np.testing.assert_allclose(ur.sim_q(), pushed, atol=2e-3)  # holds where the hand left it


def test_speed_slider_and_tcp_wrench_are_reported(ur):
    c = ur.fresh()
    ur.sim.set_speed_slider(0.4)
    ur.until(lambda: any(s.get("target_speed_fraction") == pytest.approx(0.4) for s in ur.states()), 2,
             "an operating_state carrying the slider")
    assert c.operating_state()["target_speed_fraction"] == pytest.approx(0.4)
    ur.sim.set_speed_slider(1.0)
    ur.sim.control({"cmd": "wrench", "force": [1.0, -2.0, 3.0, 0.1, 0.2, -0.3]})
    ur.until(lambda: np.allclose(ur.fb.cartesian.wrench[0], [1.0, -2.0, 3.0, 0.1, 0.2, -0.3]), 2, "the wrench")
    ur.sim.control({"cmd": "wrench", "force": [0.0] * 6})


def test_a_stalled_loop_stops_the_arm(ur):
    """The control script's RTDE watchdog (backend.watchdog_hz: 10 Hz, 2 Hz under --sim): a control
    process that stops cycling (dead, stalled) must not leave a speedJ running; the script stops,
    the arm with it, and the next cycle reports it (script_stopped -> FAULT)."""
    c = ur.enabled(READY)
    watchdog_s = 1.0 / ur.backend.config.watchdog_hz
    ur.cycle(int(1.5 * watchdog_s / ur.backend.dt))  # held by the cycle past the watchdog's period: it is fed
    assert ur.sim.state()["runtime_state"] == "PLAYING"
    ur.send("servo_jv", NS, velocity=[0.3, 0, 0, 0, 0, 0])
    ur.until(lambda: abs(ur.sim.state()["qd"][0]) > 0.2, 2, "the arm turning under speedJ")
    t0 = time.monotonic()  # the loop stops cycling here
    while ur.sim.state()["runtime_state"] == "PLAYING":
        assert time.monotonic() - t0 < watchdog_s + 0.5, "the script ran on without the daemon's inputs"
        time.sleep(0.01)
    st = ur.sim.state()
    assert st["qd"] == [0.0] * 6 and "watchdog" in st["last_error"]
    # the simulator's control socket told us first; the RTDE packet that says so reaches the
    # backend a cycle or two later on a loaded host
    ur.until(lambda: c.state is OperatingState.FAULT, 1, "FAULT once the stopped script is seen over RTDE")
    assert ur.events("error")[-1]["code"] == "script_stopped"


def test_the_simulated_controller_gets_link_and_watchdog_limits_that_a_loaded_host_does_not_trip():
    profile = load_profile(UR5E)
    wired = UrBackend.sim_profile(profile, "127.0.0.9")
    assert wired.backend["host"] == "127.0.0.9"
    cfg = UrBackend(wired).config  # valid profile keys
    assert (cfg.link_timeout_s, cfg.watchdog_hz) == (0.5, 2.0)  # the defaults 0.1 s and 10 Hz, under --sim
    own = msgspec.structs.replace(profile, backend={**profile.backend, "link_timeout_s": 0.2, "watchdog_hz": 10.0})
    cfg = UrBackend(UrBackend.sim_profile(own, "127.0.0.9")).config
    assert (cfg.link_timeout_s, cfg.watchdog_hz) == (0.2, 10.0)  # a profile's own values kept


def test_the_scripts_watchdog_cannot_be_switched_off():
    """backend.watchdog_hz: 0 would leave a dead control process's last speedJ running: refused
    naming the key (CANopen refuses master_heartbeat_ms: 0 alike)."""
    profile = load_profile(UR5E)
    off = msgspec.structs.replace(profile, backend={**profile.backend, "watchdog_hz": 0})
    with pytest.raises(ProfileError, match=r"backend\.watchdog_hz: 0 would switch the control script's RTDE watchdog off"):
        UrBackend(off)
    assert UrBackend(msgspec.structs.replace(profile, backend={**profile.backend, "watchdog_hz": 2})).config.watchdog_hz == 2


def test_a_speedj_running_into_a_goal_check_is_stopped_by_the_scripts_watchdog(ur):
    """During a GOAL_CHECK the cycle sends nothing on the control interface (the check's blocking
    call owns it, and no watchdog kick goes out meanwhile): a speedJ issued before it runs on
    until the check ends. If the controller does not answer the check, what stops the arm is the
    script's RTDE watchdog (1 / backend.watchdog_hz after the check's own input package: 0.1 s,
    0.5 s under --sim), not the check's 2 s time limit."""
    c = ur.enabled(READY)
    watchdog_s = 1.0 / ur.backend.config.watchdog_hz
    ur.send("servo_jv", NS, velocity=[0.3, 0, 0, 0, 0, 0])
    ur.until(lambda: abs(ur.sim.state()["qd"][0]) > 0.2, 2, "the arm turning under speedJ")
    ur.sim.control({"cmd": "stall_script", "on": True})  # the program stops taking commands
    try:
        rid = ur.send("move_jp", NS, position=list(READY))  # its goal check waits for the program
        t0 = time.monotonic()
        ur.until(lambda: ur.sim.state()["qd"] == [0.0] * 6, 1.0, "the arm stopped")
        stopped_after = time.monotonic() - t0
        st = ur.sim.state()
        assert "watchdog" in st["last_error"] and st["runtime_state"] != "PLAYING", st
        # the watchdog's period + the stop, well before the check's limit
        assert stopped_after < watchdog_s + 0.4 < ur.backend.traits.timeout_s(Lifecycle.GOAL_CHECK), stopped_after
        r = ur.reply(rid, 5)
        # refused: aborted by the FAULT of the stopped script, or ur_rtde's call failing first
        assert not r["ok"] and r["error"]["code"] in ("aborted", "out_of_limits"), r
        print(f"speedJ stopped {stopped_after * 1e3:.0f} ms after the goal check began")
        ur.until(lambda: c.state is OperatingState.FAULT, 2, "FAULT")  # the script stopped
    finally:
        ur.sim.control({"cmd": "stall_script", "on": False})


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGABRT], ids=["SIGKILL", "SIGABRT"])
def test_a_worker_that_dies_mid_servo_faults_naming_the_signal_then_enable_recovers(ur, sig):
    """ur_rtde's heap corruption at a link loss aborts the process it runs in: that is the worker,
    never the control process. Its death is a FAULT naming robot and signal in the cycle that
    sees it; the arm stops (nothing feeds the script's watchdog, and the fault reaction powers it
    off through the new worker that comes by itself, whichever is first); ``enable`` recovers
    with that worker, and the arm moves again."""
    c = ur.enabled(READY)
    b = ur.backend
    ur.send("servo_jv", NS, velocity=[0.3, 0, 0, 0, 0, 0])
    ur.until(lambda: abs(ur.sim.state()["qd"][0]) > 0.2, 2, "the arm turning under speedJ")
    old = b.worker_pid
    os.kill(old, sig)
    killed = time.monotonic()
    ur.until(lambda: not b._link, 2, "the backend to see the worker gone")
    assert c.state is OperatingState.FAULT  # in that same cycle
    err = ur.events("error")[-1]
    assert err["code"] == "worker_died", err
    assert f"ur5e: ur_rtde worker died ({sig.name})" in err["message"], err
    watchdog_s = 1.0 / b.config.watchdog_hz
    ur.until(lambda: ur.sim.state()["qd"] == [0.0] * 6, watchdog_s + 1.5, "the arm stopped")
    assert time.monotonic() - killed < watchdog_s + 1.5
    assert not _alive(old)
    # a new worker by itself; once its link is up the fault reaction (power off) is confirmed
    ur.until(lambda: b.worker_pid not in (None, old) and not c.is_busy and not c.torque_unconfirmed, 10,
             "a new worker and the fault reaction confirmed")
    assert ur.sim.state()["robot_mode"] == "POWER_OFF"
    r = ur.do("enable", timeout=15)
    assert r["ok"], r
    assert ur.do("move_jp", NS, position=list(READY + 0.1))["ok"]
    ur.until(lambda: not c.is_busy, 10, "move_jp done")
    ur.until(lambda: np.allclose(ur.sim_q(), READY + 0.1, atol=2e-3), 2, "the arm at the goal")


def test_link_losses_end_workers_not_the_process_and_leak_no_file(ur, monkeypatch):
    """Each link loss ends the worker (its ur_rtde interfaces with it: none is reconnected in
    place, none abandoned) and a fresh one connects once the controller is back: over many
    losses, this process's open files do not grow and every old worker is gone. The backend is
    cycled alone (no controller, so no fault reaction powers the arm off): every few losses the
    new worker builds a control interface too, uploading its script."""
    ur.enabled(READY)
    b = ur.backend
    monkeypatch.setattr(b.config, "reconnect_interval_s", 0.05)  # (0.5 s by default) a quicker run

    def spin(predicate, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        while not predicate():
            assert time.monotonic() < deadline, f"timed out after {timeout} s waiting for {what}"
            ur.runner.idle()  # a cycle without the controller

    losses = 30
    fds = len(os.listdir("/proc/self/fd"))
    olds = []
    for k in range(losses):
        old = b.worker_pid
        olds.append(old)
        ur.sim.link_loss(0.05, ports=("rtde",))
        spin(lambda: b.worker_pid not in (None, old) and b._link, 5, f"worker {k + 2}")
        if k % 5 == 0:
            steps = b._job("start_script", "control script upload")
            spin(lambda: next(steps, True) is True, 5, "the control script uploaded")
            spin(lambda: b._flags & CTL_RUNNING, 2, "the control interface up")
    wait_until(lambda: not any(_alive(p) for p in olds), 5, what="every old worker gone")
    assert len(set(olds)) == losses
    assert len(os.listdir("/proc/self/fd")) <= fds, os.listdir("/proc/self/fd")


def test_a_stalled_worker_never_blocks_the_cycle(ur):
    """A worker that stops (SIGSTOP: it takes no command, forwards no package): the cycle goes on
    (its commands are never waited for) and the robot FAULTs (link_lost once no package came for
    link_timeout_s, or worker_stalled once the channel is full, whichever first); the stalled
    worker is then ended and a fresh one connects."""
    c = ur.enabled(READY)
    b = ur.backend
    old = b.worker_pid
    q = ur.fb.position.copy()
    os.kill(old, signal.SIGSTOP)
    try:
        longest = 0.0
        deadline = time.monotonic() + 5
        while c.state is not OperatingState.FAULT:
            assert time.monotonic() < deadline, "no FAULT with the worker stopped"
            q[5] += 1e-4
            ur.send("servo_jp", NS, position=list(q))
            t0 = time.monotonic()
            ur.cycle()
            longest = max(longest, time.monotonic() - t0)
        assert longest < 1.0, longest  # a blocking send would wait for as long as the worker is stopped
        assert ur.events("error")[-1]["code"] in ("worker_stalled", "link_lost"), ur.events("error")[-1]
        print("stalled worker:", ur.events("error")[-1]["message"], f"longest cycle {longest * 1e3:.1f} ms")
        ur.until(lambda: b.worker_pid not in (None, old) and b._link, 10, "a fresh worker")
        assert not _alive(old)
    finally:
        try:
            os.kill(old, signal.SIGCONT)
        except ProcessLookupError:
            pass


def test_a_full_channel_drops_the_command_and_faults_never_blocks():
    """Drop-and-fault: a worker that takes no commands (here a channel nobody reads) fills the
    socket; the next command is refused at once (never waited for) and the cycle's write is a
    FAULT naming the robot and the dropped command; the worker is ended, as on a lost link."""
    import socket

    from crtk_bridge.backends.ur.channel import SERVOJ, WorkerHandle

    b = UrBackend(UrBackend.sim_profile(load_profile(UR5E), "127.0.0.1"))
    h = WorkerHandle("127.0.0.1", 500.0)
    h.sock, nobody = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    h.sock.setblocking(False)
    try:
        b._w = h
        sent = 0
        # a moving target (an unchanged one goes out only every keep-alive period)
        while b._out(SERVOJ, [sent * 1e-6] * 6) is None:  # each returns at once; a blocking send would hang here
            sent += 1
            assert sent < 100000
        fault = b._out(SERVOJ, [sent * 1e-6] * 6)
        assert fault is not None and fault.code == "worker_stalled" and not fault.transient, fault
        assert fault.message.startswith("ur5e: the ur_rtde worker takes no commands") and "servoJ dropped" in fault.message
        assert b._w is None and h in b._dispose  # that worker is ended (reaped on the restart's thread)
        assert sent > 100  # the whole buffer first: ~0.5 s of commands at 500 Hz
    finally:
        b._w = None
        h.sock.close()
        nobody.close()


class _NoPlan:
    """A ruckig whose every plan fails (RuckigError), as ruckig 0.19 does on a few bit-exact inputs."""

    calls = 0

    def update(self, inp, out):
        self.calls += 1
        from ruckig import RuckigError
        raise RuckigError("[ruckig] error in step 1")

    def reset(self):
        pass


def test_a_move_cp_no_plan_reaches_stays_on_its_path_start_and_never_jumps_to_the_goal():
    from crtk_bridge.backends.ur.backend import _CartesianMove

    cfg = UrBackend(load_profile(UR5E)).config
    mv = _CartesianMove(0.002, cfg)
    p0, r0 = np.array([0.3, -0.2, 0.4]), np.eye(3)
    mv.start(1, p0, r0, np.array([0.5, 0.1, 0.2]), np.array([0.0, 0.0, 0.0, 1.0]), now=0.0)
    mv.otg = _NoPlan()
    for k in range(3):
        p, r = mv.step(0.002 * k)
        np.testing.assert_allclose(p, p0)  # the path's start, not its goal
        np.testing.assert_allclose(r, r0, atol=1e-12)
    assert mv.failed and mv.finished and mv.otg.calls == 5  # the plan and its four nudged retries, once


@pytest.mark.parametrize("peer", ["closes at once", "nothing listens"])
def test_an_unreachable_controller_is_said_with_what_to_check(peer):
    """Something at the address that closes the connection (ur_rtde: ``read: End of file``), or
    nothing listening: one line naming the host and what to check, not only the socket's words."""
    import socket
    import threading

    from crtk_bridge.errors import BackendError
    from crtk_bridge.sim.loopback import free_loopback_host

    host = free_loopback_host((30004, 29999))
    server = None
    if peer == "closes at once":
        server = socket.socket()
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind((host, 30004))
        server.listen(4)

        def serve():
            while True:
                try:
                    conn, _ = server.accept()
                except OSError:
                    return
                conn.settimeout(2.0)
                try:
                    conn.recv(4096)  # the client's request read: the close is a clean EOF
                except OSError:
                    pass
                conn.close()

        threading.Thread(target=serve, daemon=True).start()
    profile = load_profile(UR5E)
    profile = msgspec.structs.replace(profile, backend={**profile.backend, "host": host})
    backend = UrBackend(profile, source=str(UR5E))
    try:
        with pytest.raises(BackendError) as err:
            backend.open()
    finally:
        backend.close()
        if server is not None:
            server.close()
    message = str(err.value)
    assert f"the UR controller at {host} did not answer RTDE (port 30004)" in message, message
    assert "backend.host" in message and "remote control" in message and "\n" not in message


def test_a_cartesian_row_refused_by_the_finiteness_gate_sends_nothing_not_the_old_joint_target():
    """The write gate hands a non-finite cartesian row to the backend in NONE, its joints in NONE
    too: nothing is left to follow, so the UR backend sends nothing new (the script keeps its last
    command: the arm keeps its last goal) and the write faults naming the namespace. It fell
    through to servoJ on its last JOINT target, stale while servoL ran (session 7's review)."""
    from crtk_bridge.backends.ur.channel import CTL_CONNECTED, CTL_UP, SERVOL
    from crtk_bridge.core.actuator import CartesianMode

    b = UrBackend(UrBackend.sim_profile(load_profile(UR5E), "127.0.0.1"))
    b._traits = b._traits_hook()  # what open() declares (no controller here)
    sent: list[int] = []

    class Worker:  # every gate before the command passes; the command itself is recorded
        refused = None

    b._w, b._enabled, b._flags = Worker(), True, CTL_UP | CTL_CONNECTED
    b._movable = lambda: True
    b._out = lambda op, *args: sent.append(op)
    b._target[:] = READY - 0.5  # the last servoJ target, long before the servoL stream
    cmd = b.new_command()
    cmd.cartesian.mode[0] = CartesianMode.POSE
    cmd.cartesian.position[0] = [0.3, -0.2, 0.4]
    assert b.write(cmd) is None and sent == [SERVOL]  # a finite pose is followed
    sent.clear()
    cmd.cartesian.position[0] = [0.3, np.nan, 0.4]
    fault = b.write(cmd)
    assert fault is not None and fault.code == "invalid_command" and "namespace 'ur5e'" in fault.message, fault
    assert sent == []  # nothing new: no servoJ to the stale joint target
    assert cmd.cartesian.mode[0] == CartesianMode.POSE  # the caller's buffer as it was


def test_a_hold_keeps_the_scripts_watchdog_fed_and_a_stopped_cycle_lets_it_stop_the_program(ur):
    """A hold sends its unchanged servoJ only every keep-alive period (the script repeats it by
    itself): over three of the script's watchdog periods the program keeps running, ENABLED; once
    the cycle stops (a control process stalled), the watchdog stops the program within its period."""
    c = ur.enabled(READY)
    b = ur.backend
    sends = []
    real = b._w.send
    b._w.send = lambda data: (sends.append(bytes(data[:1])), real(data))[1]
    period = 1.0 / b.config.watchdog_hz
    end = time.monotonic() + 3 * period
    cycles = 0
    while time.monotonic() < end:
        ur.cycle()
        cycles += 1
    assert ur.sim.state()["runtime_state"] == "PLAYING" and c.state is OperatingState.ENABLED
    assert 0 < len(sends) < cycles / 2, (len(sends), cycles)  # the hold's repeats were not every cycle
    wait_until(lambda: ur.sim.state()["runtime_state"] != "PLAYING", period + 2.0, interval=0.01,
               what=f"the script's watchdog ({period:g} s) stopping the program once the cycle stopped")

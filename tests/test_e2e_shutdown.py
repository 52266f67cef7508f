"""End to end, shutdown (issue 9, defect 7) on each simulated robot: SIGTERM with the arm ENABLED
parks it (a jerk-limited move to the profile's rest pose, then torque off, within
``shutdown.timeout_s``); with the arm DISABLED nothing moves. The simulator runs on its own, so
what the servos did during and after the daemon's shutdown can be read from it."""

from __future__ import annotations

import math
import signal
import threading
import time

import numpy as np
import pytest

from crtk_bridge.client import connect
from crtk_bridge.profile import load_profile
from crtk_bridge.sim.control import control_request

from .conftest import DaemonProcess, only_on, wait_until
from .conftest import standalone_sim as conftest_standalone_sim

# the park's rest pose needs shutdown.action: park; the servos are sampled through the serial
# simulators' dump (ticks)
pytestmark = pytest.mark.requires("servo_bus", "park")

RAD_PER_TICK = 2 * math.pi / 4096  # both robots: joint zero at tick 2048, direction +1


class Recorder:
    """Samples the simulator (torque and position of every servo) until stopped."""

    def __init__(self, control: str):
        self.control = control
        self.samples: list[tuple[float, dict]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            servos = control_request(self.control, {"cmd": "dump"})["servos"]
            self.samples.append((time.monotonic(), servos))
            time.sleep(0.02)  # paces the sampling: a dump loop flat out starves the simulator's bus thread

    def stop(self) -> list[tuple[float, dict]]:
        self._stop.set()
        self._thread.join(5)
        return self.samples


def positions(servos: dict, ids: list[str]) -> np.ndarray:
    return np.array([(servos[i]["present_position"] - 2048) * RAD_PER_TICK for i in ids])


@pytest.fixture
def standalone_sim(short_tmp, sim_robot):
    with conftest_standalone_sim(sim_robot, short_tmp) as (profile, sim):
        yield profile, sim.path


def test_sigterm_while_disabled_moves_nothing(standalone_sim, short_tmp, sim_robot):
    profile, control = standalone_sim
    assert load_profile(profile).shutdown.action == "park"
    daemon = DaemonProcess(["--profile", str(profile)], short_tmp / "d.sock", short_tmp / "d.log")
    try:
        before = control_request(control, {"cmd": "dump"})["servos"]
        rec = Recorder(control)
        wait_until(lambda: len(rec.samples) > 2, 5, what="simulator samples")
        assert daemon.terminate() == 0, daemon.output()
        samples = rec.stop()
        samples.append((time.monotonic(), control_request(control, {"cmd": "dump"})["servos"]))
        for _, servos in samples:
            for sid, s in servos.items():
                assert s["torque_enable"] == 0, (sid, s)
                assert s["goal_position"] == before[sid]["goal_position"], (sid, s)
                assert abs(s["present_position"] - before[sid]["present_position"]) <= 1, (sid, s)
        out = daemon.output()
        assert "shutdown_park" not in out and "shutdown_torque_off" not in out  # nothing to do, nothing said
    finally:
        daemon.stop()


def test_sigterm_while_enabled_parks_then_switches_torque_off(standalone_sim, short_tmp, sim_robot):
    profile, control = standalone_sim
    prof = load_profile(profile)
    sd = prof.shutdown
    ids = [str(sim_robot.servo_id[j.name]) for j in prof.joints]
    rest = np.array([sd.rest[j.name] for j in prof.joints])
    daemon = DaemonProcess(["--profile", str(profile)], short_tmp / "d.sock", short_tmp / "d.log")
    try:
        robot = connect(socket=str(daemon.socket_path))
        arm = robot.device(sim_robot.arm)
        assert arm.enable(5.0)
        goal = sim_robot.goals["reach"]
        assert arm.move_jp(goal).wait(timeout=10.0)
        start = positions(control_request(control, {"cmd": "dump"})["servos"], ids)
        assert np.max(np.abs(start - rest)) > 1.0  # far from the rest pose: the park has work to do
        mark = robot.connection.event_count
        rec = Recorder(control)
        wait_until(lambda: len(rec.samples) > 2, 5, what="simulator samples")
        t_term = time.monotonic()
        daemon.proc.send_signal(15)
        # the clients hear it: a status event, and the busy edge of the park move
        ev = robot.wait_for_event("shutdown_park", 5.0, kind="status", since=mark)
        assert ev is not None and "rest pose" in ev.data["message"]
        assert daemon.proc.wait(sd.timeout_s + 10) == 0, daemon.output()
        samples = rec.stop()
        robot.close()
        final = control_request(control, {"cmd": "dump"})["servos"]
        samples.append((time.monotonic(), final))

        # torque went off on every servo, at the rest pose, within the time limit
        assert all(final[i]["torque_enable"] == 0 for i in ids), final
        np.testing.assert_allclose(positions(final, ids), rest, atol=0.03)
        first_off = next(k for k, (_, s) in enumerate(samples) if any(s[i]["torque_enable"] == 0 for i in ids))
        t_off, at_off = samples[first_off]
        assert t_off - t_term < sd.timeout_s + 1.0
        np.testing.assert_allclose(positions(at_off, ids), rest, atol=0.03)  # torque off only once there
        # the arm travelled the way there with torque on (not dropped, not snapped)
        travel = [positions(s, ids) for _, s in samples[:first_off]]
        assert len(travel) > 5
        mid = [p for p in travel if 0.2 < np.max(np.abs(p - rest)) < np.max(np.abs(start - rest)) - 0.2]
        assert mid, "no sample on the way to the rest pose"
        out = daemon.output()
        assert "parking at the rest pose" in out and "parked at the rest pose" in out, out
        assert "shutdown_park_timeout" not in out
    finally:
        daemon.stop()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["TERM+TERM", "INT+INT"])
@only_on("so101-feetech")
def test_a_second_signal_by_pid_switches_torque_off_without_finishing_the_park(standalone_sim, short_tmp,
                                                                                sim_robot, sig):
    """``kill -TERM`` (or ``-INT``) twice to the daemon's pid, as systemd or a script sends it (not
    a terminal's Ctrl-C to the whole group): the second cuts the park short, torque off at once."""
    profile, control = standalone_sim
    prof = load_profile(profile)
    ids = [str(sim_robot.servo_id[j.name]) for j in prof.joints]
    rest = np.array([prof.shutdown.rest[j.name] for j in prof.joints])
    daemon = DaemonProcess(["--profile", str(profile)], short_tmp / "d.sock", short_tmp / "d.log")
    try:
        robot = connect(socket=str(daemon.socket_path))
        arm = robot.device(sim_robot.arm)
        assert arm.enable(5.0)
        far = sim_robot.vec(shoulder_lift=1.4, elbow_flex=-1.4)  # ~3 rad from the rest pose
        assert arm.move_jp(far).wait(timeout=10.0)
        start = positions(control_request(control, {"cmd": "dump"})["servos"], ids)
        rec = Recorder(control)
        wait_until(lambda: len(rec.samples) > 2, 5, what="simulator samples")
        daemon.proc.send_signal(sig)
        # the park is under way: the arm has left where it was, torque on
        wait_until(lambda: any(np.max(np.abs(positions(s, ids) - start)) > 0.1 for _, s in rec.samples[-3:]),
                   10, what="the park to move the arm")
        daemon.proc.send_signal(sig)
        assert daemon.proc.wait(15) == 0, daemon.output()
        samples = rec.stop()
        robot.close()
        final = control_request(control, {"cmd": "dump"})["servos"]
        samples.append((time.monotonic(), final))
        assert all(final[i]["torque_enable"] == 0 for i in ids), final
        first_off = next(s for _, s in samples if any(s[i]["torque_enable"] == 0 for i in ids))
        assert np.max(np.abs(positions(first_off, ids) - rest)) > 0.5  # torque off well before the rest pose
        out = daemon.output()
        assert "park cut short by a second signal" in out, out
        assert "parked at the rest pose" not in out, out
    finally:
        daemon.stop()

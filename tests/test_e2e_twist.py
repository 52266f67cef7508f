"""servo_cv / interpolate_cv end to end: crtk-ctl streams a twist to the daemon on --sim and the
simulated arm's tip, measured with measured_cp, moves as far as the twist says (issue 8 item 7),
on every robot with a URDF: the SO-101 (the twist mapped to joint velocities every cycle), the
UR5e (``native_cartesian``: speedL on its controller)."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np
import pytest

from crtk_bridge.client import connect
from crtk_bridge.client.cli import main as ctl_main

from .cartesian_targets import targets, wait_still
from .conftest import wait_until

# one daemon per robot for both commands (reuse_daemon): each test enables and moves to its start
# pose itself, and leaves the arm ENABLED (asserted), which SharedDaemons puts back DISABLED
pytestmark = [pytest.mark.requires("kinematics"), pytest.mark.reuse_daemon]

SETTLED = 0.0005  # m: the simulated servos' tracking lag has died out


def measured_tip(c, ns):
    return np.array(c.request("measured_cp", ns)["position"])


def settled_tip(c, ns, native: bool):
    """The tip once the arm has caught up with a held setpoint."""
    def close():
        sp = c.request("setpoint_cp", ns)
        return sp["stamp"] > 0 and np.linalg.norm(measured_tip(c, ns) - sp["position"]) < SETTLED

    if native:
        # a native backend integrates the twist itself: no position setpoint of the daemon's while
        # it runs or after it ends (the joints hold where the controller stopped them)
        return wait_still(lambda: measured_tip(c, ns),
                          lambda: np.linalg.norm(c.request("measured_cv", ns)["linear"]), 10)
    wait_until(close, 10, what="the tip settled on its setpoint")
    return measured_tip(c, ns)


def controller_clock(daemon):
    """The simulated controller's own clock (s) where it keeps one (a UR controller: one tick per
    RTDE period; on a stalled host it loses ticks, and the arm then moves less in wall time, as
    a real controller would not), else None: the daemon's control loop integrates the twist in
    wall time, and the stream's second is the twist's."""
    sim = daemon.robot.sim(daemon.sim_control_path())
    if "ticks" not in (sim.state() if hasattr(sim, "state") else {}):
        return None

    def now() -> float:
        st = sim.state()
        return st["ticks"] / st["rate_hz"]
    return now


class SpeedSampler:
    """The tip's measured speed along ``axis`` (m/s, measured_cv: the joint velocities the
    controller reports, through the Jacobian), sampled on a session of its own while a stream runs."""

    def __init__(self, sock: str, ns: str, axis: int):
        self.robot = connect(socket=sock)
        self.ns, self.axis = ns, axis
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        c = self.robot.connection
        while not self._stop.is_set():
            self.samples.append(float(c.request("measured_cv", self.ns)["linear"][self.axis]))
            self._stop.wait(0.005)

    def __enter__(self) -> SpeedSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(5)
        self.robot.close()


@pytest.mark.parametrize("cmd,axis", [("servo_cv", 1), ("interpolate_cv", 2)])
def test_crtk_ctl_twist_stream_moves_the_tip_as_far_as_the_twist_says(sim_daemon, capsys, cmd, axis):
    r = sim_daemon.robot
    ns, native = r.arm, "native_cartesian" in r.capabilities
    sock = str(sim_daemon.socket_path)
    robot = connect(socket=sock)
    c = robot.connection
    try:
        assert robot.device(ns).enable(20.0)
        seq = c.request("move_jp", ns, {"position": targets(r).start.tolist()})["busy_seq"]
        wait_until(lambda: c.idle_seq >= seq, 15, what="move_jp to the start pose")
        c.request("release")  # crtk-ctl takes control, as a user's second terminal would
        p0 = settled_tip(c, ns, native)

        linear = ["0", "0", "0"]
        linear[axis] = "0.02"
        # 0.02 m/s for 1 s, streamed at crtk-ctl's 50 Hz; the stream ends with a hold at 1 s
        clock = controller_clock(sim_daemon)
        w0, c0 = time.monotonic(), clock() if clock else 0.0
        with SpeedSampler(sock, ns, axis) if native else contextlib.nullcontext() as speeds:
            assert ctl_main(["--socket", sock, cmd, *linear, "0", "0", "0", "--duration", "1"]) == 0
        # the stream's second, on the clock the arm moves by: its share of wall time (1 where the
        # daemon integrates the twist, or where the simulated controller kept up)
        second = (clock() - c0) / (time.monotonic() - w0) if clock else 1.0
        assert cmd in capsys.readouterr().out
        p1 = settled_tip(c, ns, native)
        d = p1 - p0
        if native:
            # the controller integrates the twist (speedL) on its own clock, from the first sample
            # it gets until the daemon passes crtk-ctl's hold on (later on a loaded host):
            # the speed it ran at is the twist's, and the distance is at least the stream's
            # second's and at most that plus the servo watchdog's (servo_timeout_s) bound
            steady = [v for v in speeds.samples if v > 0.01]
            assert len(steady) >= 10 and np.median(steady) == pytest.approx(0.020, rel=0.05), speeds.samples
            assert 0.020 * second - 0.002 <= d[axis] <= 0.020 * (second + r.servo_timeout_s) + 0.002, \
                f"tip moved {d} m in {second:.3f} s"
        else:
            assert d[axis] == pytest.approx(0.020, abs=0.002), f"tip moved {d} m"
        off_axis = np.delete(d, axis)
        assert np.all(np.abs(off_axis) < 0.002), f"tip left its line: moved {d} m"
        assert c.request("operating_state")["state"] == "ENABLED"
    finally:
        robot.close()

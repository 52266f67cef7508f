"""interpolate_jp of a sparse stream, on the controller driven cycle by cycle (no timing). With
``loop.interpolation: smooth`` the setpoint follows a 30 Hz stream smoothly, without a kink or a
stop at each goal, and still reaches the last goal exactly, without passing it, and holds it
(issue 21); ``linear`` (the default) passes through every goal."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from .test_controller import PROFILE, FakeActuator, make_rig

SMOOTH = msgspec.structs.replace(PROFILE, loop=msgspec.structs.replace(PROFILE.loop, interpolation="smooth"))

STREAM_HZ = 30.0  # LeRobot's rate: 33.3 ms, not a whole number of 5 ms cycles
AMP, FREQ = 0.4, 0.4  # rad, Hz: a hand's motion on shoulder_pan
A_STREAM = AMP * (2 * math.pi * FREQ) ** 2  # the stream's largest acceleration, rad/s^2


def _stream(c, clock, cycle, req, seconds: float, goals: list | None = None):
    """One sine goal every 1/30 s for ``seconds``, then nothing; the setpoint every cycle."""
    t0, sent, out, goal = clock(), 0, [], None
    goals = [] if goals is None else goals
    while clock() - t0 < seconds + 1.0:
        t = clock() - t0
        if t < seconds and t >= sent / STREAM_HZ:
            goal = [AMP * math.sin(2 * math.pi * FREQ * sent / STREAM_HZ), 0, 0, 0, 0]
            assert req("interpolate_jp", "so101", position=goal)["ok"]
            goals.append(goal[0])
            sent += 1
        cycle()
        out.append(c.namespaces["so101"].setpoint_p[0])
    return np.array(out), goal[0]


def test_smooth_interpolate_jp_follows_a_30hz_stream_smoothly_and_ends_on_the_last_goal():
    c, act, clock, cycle, req = make_rig(FakeActuator(SMOOTH), SMOOTH)
    assert req("enable")["ok"]
    dt = c.dt
    p, last = _stream(c, clock, cycle, req, seconds=1.6)  # 0.625 s up to the crest, then down
    v = np.diff(p) / dt
    acc = np.diff(v) / dt
    assert np.all(np.abs(v) <= PROFILE.joints[0].limits.velocity_max + 1e-9)
    moving = slice(int(0.3 / dt), int(1.5 / dt))  # past the stream's first goals, before its end
    # no stop-and-go between goals: while the sine rises (0.3 .. 0.55 s) the setpoint never
    # stands still nor slows to a stop; the bare linear interpolation stopped for a cycle at
    # each goal that came a cycle after the estimated period
    rising = v[int(0.3 / dt):int(0.55 / dt)]
    assert rising.min() > 0.3 * rising.max(), rising.round(3)
    # acceleration and jerk of the setpoint within several times the stream's own: each goal's
    # change of velocity is spread over a command period. Linear interpolation to each goal
    # (a kink at each goal, and a cycle at rest when a goal comes a cycle after the estimated
    # period, as 33.3 ms goals on 5 ms cycles do) reached 41x and 72x here
    assert np.abs(acc[moving]).max() < 8.0 * A_STREAM, np.abs(acc[moving]).max() / A_STREAM
    jerk_per_cycle = np.abs(np.diff(acc[moving]))  # rad/s^2 per cycle
    assert jerk_per_cycle.max() < 10.0 * A_STREAM, jerk_per_cycle.max() / A_STREAM
    # the stream stopped: the last goal is reached exactly, never passed, and held
    end = int(1.6 / dt) + 2
    tail = p[end:]
    assert tail[-1] == last
    side = np.sign(last - p[end])
    assert np.all(side * (last - tail) >= 0)  # approaches from one side, never beyond
    assert np.all(p[-20:] == last)


def test_linear_interpolate_jp_passes_through_every_goal():
    """The default: the setpoint reaches each goal of a 20 Hz stream (10 cycles apart) exactly,
    one estimated period after it came."""
    assert PROFILE.loop.interpolation == "linear"
    c, act, clock, cycle, req = make_rig(FakeActuator(PROFILE))
    assert req("enable")["ok"]
    m = c.namespaces["so101"]
    for k in range(1, 15):
        goal = 0.02 * k
        assert req("interpolate_jp", "so101", position=[goal, 0, 0, 0, 0])["ok"]
        cycle(10)
        if k > 3:  # the period estimate (first assumed 50 Hz) has converged to 10 cycles
            assert m.setpoint_p[0] == pytest.approx(goal, abs=1e-12)

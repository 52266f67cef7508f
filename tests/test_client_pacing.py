"""The pacing of timed command streams (client/pacing.py, Device.stream), on a simulated clock:
a stream ends at its duration whatever the rate and however slow the replies, and a relative
stream's samples add up to its whole offset (issue 18, item 1)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crtk_bridge.client.device import pose_share
from crtk_bridge.client.pacing import Pacing


class Clock:
    """A clock that moves only when slept on or when a sample's round trip is charged to it."""

    def __init__(self):
        self.now = 100.0
        self.slept = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        assert s > 0
        self.slept.append(s)
        self.now += s


def run(duration, rate, round_trip):
    """Iterate a Pacing whose every sample takes ``round_trip`` s; the (time, tick) of each."""
    clock = Clock()
    t0 = clock.now
    out = []
    for tick in Pacing(duration, rate, clock=clock, sleep=clock.sleep):
        out.append((clock.now - t0, tick))
        clock.now += round_trip
    return out, clock.now - t0


def test_ticks_at_the_rate_from_now_to_the_duration_when_replies_are_quick():
    ticks, _ = run(1.0, 50, 0.0)
    assert len(ticks) == 51
    assert [t for t, _ in ticks] == pytest.approx([k / 50 for k in range(51)])
    assert [tk.index for _, tk in ticks] == list(range(51))
    assert [tk.final for _, tk in ticks] == [False] * 50 + [True]
    assert all(tk.share == pytest.approx(1 / 51) for _, tk in ticks)
    assert ticks[-1][1].reached == 1.0


@pytest.mark.parametrize("rate, round_trip", [(1000, 0.005), (5000, 0.005), (200, 0.005), (50, 0.3),
                                              (1000, 0.0123), (10, 2.5)])
def test_the_stream_ends_at_its_duration_however_slow_the_replies(rate, round_trip):
    ticks, total = run(1.0, rate, round_trip)
    (t_last, last) = ticks[-1]
    assert last.final and last.index == last.last and last.reached == 1.0
    # the last sample goes out at the duration, or as soon after as the previous reply allows
    assert 1.0 <= t_last < 1.0 + round_trip + 1e-9
    assert total < 1.0 + 2 * round_trip + 1e-9  # the defect: 1001 round trips at 1000 Hz
    # never two samples for one tick, never a tick back in time
    idx = [tk.index for _, tk in ticks]
    assert idx == sorted(set(idx))
    # a late reply skips the ticks already due, it does not send them late in a burst
    assert len(ticks) <= 1 + math.ceil(1.0 / max(round_trip, 1.0 / rate)) + 1
    # the shares of a relative offset add up to all of it, whatever was skipped
    assert sum(tk.share for _, tk in ticks) == pytest.approx(1.0, abs=1e-12)
    assert all(b.before == a.reached for (_, a), (_, b) in zip(ticks, ticks[1:]))


def test_a_sample_is_sent_when_its_tick_is_due_not_before():
    ticks, _ = run(0.1, 100, 0.001)  # replies quicker than the period: sleeps make up the rest
    for t, tk in ticks:
        assert t == pytest.approx(tk.index * 0.01, abs=1e-9)


def test_a_stream_shorter_than_a_period_still_has_its_two_ends():
    ticks, _ = run(0.005, 50, 0.0)
    assert [(round(t, 6), tk.index, tk.final) for t, tk in ticks] == [(0.0, 0, False), (0.005, 1, True)]


@pytest.mark.parametrize("value", [0, -1, float("nan"), float("inf")])
def test_duration_and_rate_must_be_finite_and_positive(value):
    with pytest.raises(ValueError, match="duration must be a finite number > 0"):
        Pacing(value, 50)
    with pytest.raises(ValueError, match="rate_hz must be a finite number > 0"):
        Pacing(1.0, value)


def test_pose_shares_compose_to_the_whole_relative_pose():
    from crtk_bridge.client.device import matrix_from_quaternion

    angle = 0.3
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    delta = {"position": [0.01, -0.02, 0.03], "orientation": [*(axis * math.sin(angle / 2)), math.cos(angle / 2)]}
    fractions = [0.0, 0.1, 0.15, 0.5, 0.9, 1.0]  # uneven: ticks were skipped
    p, R = np.zeros(3), np.eye(3)
    for before, reached in zip(fractions, fractions[1:]):
        part = pose_share(delta, before, reached)
        p += part["position"]
        R = matrix_from_quaternion(part["orientation"]) @ R  # servo_cr pre-multiplies
    np.testing.assert_allclose(p, delta["position"], atol=1e-15)
    np.testing.assert_allclose(R, matrix_from_quaternion(delta["orientation"]), atol=1e-12)

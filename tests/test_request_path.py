"""The per-request path's fast paths (issue 23: a request's validation in Python floats, not a
dozen numpy calls) decide exactly as the general path: crtk_client.vectors.floats and the
controller's step and limit checks, on the edge cases each fast path must hand over."""

from __future__ import annotations

import numpy as np
import pytest

from crtk_bridge import vectors
from crtk_bridge.core.control.common import Refused
from crtk_bridge.core.control.validation import ValidationMixin


@pytest.mark.parametrize("values", [[1, 2, 3], [True, 0, 1.5], np.array([1, 2, 3], dtype=np.float32),
                                    np.array([1, 2, 3], dtype=np.int16), (0.5, -1, 2**40)])
def test_numbers_of_any_kind_are_read_as_float64(values):
    vec = vectors.floats(values, "arm: servo_jp position", 3)
    assert vec.dtype == np.float64 and vec.tolist() == [float(v) for v in np.asarray(values, dtype=float)]


def test_finite_numbers_whose_sum_overflows_pass_and_non_finite_ones_are_named():
    big = [1e308, 1e308, -1e308]
    assert vectors.floats(big, "arm: servo_jp position", 3).tolist() == big
    for bad, i in (([1.0, float("inf"), float("-inf")], 1), ([0.0, 1.0, float("nan")], 2)):
        with pytest.raises(vectors.InvalidVector, match=f"entry {i} .*non-finite"):
            vectors.floats(bad, "arm: servo_jp position", 3, ["a", "b", "c"])


@pytest.mark.parametrize("values, bad", [([1.0, "1.5", 2.0], 1), ([None, 1.0, 2.0], 0), ([1.0, 2.0, b"3"], 2),
                                         ([1.0, [2.0], 3.0], 1), ([1.0, 2.0, 1j], 2), ([1.0, 2.0, 10**400], 2),
                                         ([1.0, 10**5000, 2.0], 1), ([1.0, 10**400, [2.0]], 2)])
def test_text_none_and_other_non_numbers_are_refused_naming_the_entry(values, bad):
    # (an int too large for a float, even one past Python's digits limit for str(), is named too)
    with pytest.raises(vectors.InvalidVector, match=f"entry {bad}"):
        vectors.floats(values, "arm: servo_jp position", 3)


class _Motion:
    name = "arm"
    joint_names = ["j0", "j1", "j2"]
    pos_min = np.array([-1.0, -1.0, -1.0])
    pos_max = np.array([1.0, 1.0, 1.0])
    last_clip_warning = -1e9


class _Validator(ValidationMixin):
    def __init__(self):
        self.safety = type("S", (), {"servo_step_max": 0.3})()
        self.events = []

    def clock(self):
        return 0.0

    def event(self, *args, **kw):
        self.events.append((args, kw))


def test_a_step_over_the_bound_is_refused_naming_the_worst_joint_and_one_at_it_passes():
    v, m = _Validator(), _Motion()
    base = np.zeros(3)
    v._check_step(m, np.array([0.3, -0.3, 0.1]), base, "servo_jp")  # at the bound: taken
    with pytest.raises(Refused, match="joint 'j2' would jump 0.5"):
        v._check_step(m, np.array([0.31, -0.2, -0.5]), base, "servo_jp")


def test_a_position_inside_the_limits_is_taken_as_is_and_one_outside_clipped_with_a_warning():
    v, m = _Validator(), _Motion()
    p = np.array([1.0, -1.0, 0.0])  # on the limits
    assert v._clip(m, p) is p and v.events == []
    q = np.array([0.0, 1.5, -0.2])
    out = v._clip(m, q)
    assert out.tolist() == [0.0, 1.0, -0.2] and q.tolist() == [0.0, 1.5, -0.2]
    assert len(v.events) == 1 and v.events[0][1]["joint"] == "j1"
    nan = np.array([0.0, np.nan, 0.0])  # never passed as is (the write's finiteness gate faults it)
    assert np.isnan(v._clip(m, nan)[1])

"""servo_cv / interpolate_cv mapped every cycle in the controller (core/twist.py), driven cycle by
cycle with the fake position-controlled actuator of test_controller and a fake clock."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crtk_bridge.core.kinematics import Kinematics
from crtk_bridge.core.motion import Mode

from .test_controller import PROFILE, FakeActuator, make_rig, rig  # noqa: F401  (the fixture)

ARM = "so101"
NS = PROFILE.namespace(ARM)
START = np.array([0.1, 0.2, 0.3, 0.0, 0.0])  # well away from singularities and limits


@pytest.fixture
def kin():
    k = Kinematics(NS.kinematics.urdf, NS.kinematics.base_frame, NS.kinematics.tip_frame, list(NS.joints))
    return k


def enabled_at(rig, q):  # noqa: F811
    c, act, clock, cycle, req = rig
    act.pos[c.namespaces[ARM].idx] = q  # the arm rests there when enabled
    cycle()
    assert req("enable")["ok"]
    assert req("servo_jp", ARM, position=list(q))["ok"]
    cycle(2)
    return c.namespaces[ARM]


def tip(kin, m):
    return kin.fk(m.setpoint_p)[0]


def test_servo_cv_follows_the_twist_over_time(rig, kin):  # noqa: F811
    """The regression: a twist mapped once at request time drifts off course as the arm moves;
    mapped every cycle, 0.02 m/s along y for 1 s moves the tip 20 mm along y."""
    c, act, clock, cycle, req = rig
    m = enabled_at(rig, START)
    p0 = tip(kin, m)
    steps = int(round(1.0 / c.dt))
    period = int(round(0.02 / c.dt))  # a 50 Hz stream, as crtk-ctl sends
    for k in range(steps):
        if k % period == 0:
            assert req("servo_cv", ARM, linear=[0, 0.02, 0], angular=[0, 0, 0])["ok"]
        cycle()
    d = tip(kin, m) - p0
    assert d[1] == pytest.approx(0.02, abs=0.0005)  # the tip follows the twist (acceleration ramp only)
    assert abs(d[0]) < 2e-4 and abs(d[2]) < 2e-4  # and stays on its line
    assert m.mode is Mode.SERVO_V
    # the same joint velocity held for 1 s (the old front-process mapping) leaves the line
    q = START + 1.0 * kin.joint_velocity(START, np.array([0, 0.02, 0, 0, 0, 0]))
    off_line = kin.fk(q)[0] - p0
    assert np.hypot(off_line[0], off_line[2]) > 5 * max(abs(d[0]), abs(d[2]), 1e-5)


def test_servo_cv_setpoint_twist_and_watchdog(rig, kin):  # noqa: F811
    c, act, clock, cycle, req = rig
    m = enabled_at(rig, START)
    assert req("servo_cv", ARM, linear=[0.0, 0.0, 0.03], angular=[0, 0, 0])["ok"]
    cycle(20)
    v = kin.twist(m.setpoint_p, m.setpoint_v)
    assert v[:3] == pytest.approx([0, 0, 0.03], abs=1e-4)  # setpoint_cv: the twist (mapped one step back)
    assert m.setpoint_fields() == (True, True, False)  # integrated position + velocity (setpoint_cp valid)
    c.outbox.clear()
    held = None
    for _ in range(int(PROFILE.safety.servo_timeout_s / c.dt) + 3):
        cycle()
        if m.mode is Mode.HOLD and held is None:
            held = m.setpoint_p.copy()
    assert [e["data"]["code"] for e in c.outbox if e.get("event") == "warning"] == ["servo_timeout"]
    assert held is not None and np.array_equal(m.setpoint_p, held) and not m.setpoint_v.any()
    assert not c.twist_motions[ARM].active


def test_body_frame_twist(rig, kin):  # noqa: F811
    c, act, clock, cycle, req = rig
    m = enabled_at(rig, START)
    R0 = kin.fk_matrix(m.setpoint_p)[:3, :3]
    p0 = tip(kin, m)
    for k in range(40):
        if k % 4 == 0:
            assert req("servo_cv", ARM, linear=[0.0, 0.0, 0.02], angular=[0, 0, 0], frame="body")["ok"]
        cycle()
    d = tip(kin, m) - p0
    along = R0[:, 2]  # the tip's own z axis, in base axes
    assert d @ along == pytest.approx(0.02 * 40 * c.dt, rel=0.05)
    assert np.linalg.norm(d - (d @ along) * along) < 1e-4


def test_velocity_limit_scales_the_whole_vector_keeping_direction(rig, kin):  # noqa: F811
    c, act, clock, cycle, req = rig
    m = enabled_at(rig, START)
    p0 = tip(kin, m)
    direction = np.array([0.0, 1.0, 1.0]) / np.sqrt(2)
    for k in range(100):
        if k % 4 == 0:
            assert req("servo_cv", ARM, linear=list(5.0 * direction), angular=[0, 0, 0])["ok"]  # far too fast
        cycle()
        assert np.all(np.abs(m.setpoint_v) <= m.vel_max + 1e-9)
    assert np.isclose(np.abs(m.setpoint_v) / m.vel_max, 1.0).any()  # one joint at its limit
    assert np.linalg.norm(tip(kin, m) - p0) > 0.05
    v = kin.twist(m.setpoint_p, m.setpoint_v)[:3]
    assert np.linalg.norm(v) < 5.0 * 0.5  # slower than asked...
    assert np.linalg.norm(np.cross(v / np.linalg.norm(v), direction)) < 0.03  # ...in the asked direction


def test_acceleration_limit_on_servo_cv(rig):  # noqa: F811
    c, act, clock, cycle, req = rig
    m = enabled_at(rig, START)
    assert req("servo_cv", ARM, linear=[0, 0.3, 0], angular=[0, 0, 0])["ok"]
    prev = m.setpoint_v.copy()
    for _ in range(10):
        cycle()
        assert np.all(np.abs(m.setpoint_v - prev) <= m.acc_max * c.dt + 1e-12)
        prev = m.setpoint_v.copy()
    assert np.any(m.setpoint_v != 0.0)


def test_joint_at_limit_is_frozen_and_never_passes_it(rig, kin):  # noqa: F811
    """Tangential tip motion needs shoulder_pan; at its limit pan is frozen and the twist
    re-solved with the other joints (only wrist_roll can still move the tip sideways, the tip
    being 8 mm off its axis): pan stays at its limit, no joint passes one."""
    c, act, clock, cycle, req = rig
    start = np.array([1.8, 0.2, 0.3, 0.0, 0.0])  # 0.12 rad below pan's upper limit
    m = enabled_at(rig, start)
    sideways = kin.jacobian(start)[:3, 0]
    sideways = list(0.05 * sideways / np.linalg.norm(sideways))
    at_limit = None
    for k in range(400):  # 2 s: pan reaches its limit after about 0.5 s
        if k % 4 == 0:
            assert req("servo_cv", ARM, linear=sideways, angular=[0, 0, 0])["ok"]
        cycle()
        assert np.all(m.setpoint_p <= m.pos_max) and np.all(m.setpoint_p >= m.pos_min)
        if at_limit is None and m.setpoint_p[0] == m.pos_max[0]:
            at_limit = k
        if at_limit is not None and k > at_limit:
            assert m.setpoint_p[0] == m.pos_max[0] and m.setpoint_v[0] == 0.0  # frozen there
    assert at_limit is not None and at_limit < 200, "shoulder_pan never reached its limit"
    assert c.twist_motions[ARM].active  # still streaming: the command is bounded, not refused


def test_interpolate_cv_follows_and_ramps(rig, kin):  # noqa: F811
    c, act, clock, cycle, req = rig
    m = enabled_at(rig, START)
    p0 = tip(kin, m)
    prev = m.setpoint_v.copy()
    for k in range(200):
        if k % 4 == 0:
            assert req("interpolate_cv", ARM, linear=[0, 0, 0.02], angular=[0, 0, 0])["ok"]
        cycle()
        assert np.all(np.abs(m.setpoint_v - prev) <= m.acc_max * c.dt + 1e-12)
        prev = m.setpoint_v.copy()
    assert m.mode is Mode.INTERP_V
    d = tip(kin, m) - p0
    assert d[2] == pytest.approx(0.02 * 200 * c.dt, abs=5e-4)
    assert abs(d[0]) < 2e-4 and abs(d[1]) < 2e-4
    assert m.goal_fields() == (False, True, False)
    assert kin.twist(m.setpoint_p, m.goal_v)[:3] == pytest.approx([0, 0, 0.02], abs=1e-4)  # goal_cv


def test_a_joint_command_ends_the_twist_stream(rig):  # noqa: F811
    c, act, clock, cycle, req = rig
    m = enabled_at(rig, START)
    assert req("servo_cv", ARM, linear=[0, 0.02, 0], angular=[0, 0, 0])["ok"]
    cycle(5)
    assert req("servo_jv", ARM, velocity=[0, 0, 0, 0, 0.1])["ok"]
    cycle(5)
    assert not c.twist_motions[ARM].active
    assert m.setpoint_v == pytest.approx([0, 0, 0, 0, 0.1])  # the joint command, not the twist
    assert req("servo_cv", ARM, linear=[0, 0.02, 0], angular=[0, 0, 0])["ok"]
    cycle(2)
    assert req("hold", ARM)["ok"]
    cycle(2)
    assert not c.twist_motions[ARM].active and not m.setpoint_v.any()


def test_twist_commands_refused_cleanly(rig):  # noqa: F811
    c, act, clock, cycle, req = rig
    r = req("servo_cv", ARM, linear=[0, 0.02, 0], angular=[0, 0, 0])
    assert not r["ok"] and r["error"]["code"] == "invalid_state"  # DISABLED
    assert req("enable")["ok"]
    for data, word in (({"linear": [0, 1], "angular": [0, 0, 0]}, "linear"),
                       ({"linear": [0, 0, float("nan")], "angular": [0, 0, 0]}, "non-finite"),
                       ({"linear": [0, 0, 0], "angular": [0, 0, 0], "frame": "tool"}, "frame")):
        r = req("servo_cv", ARM, **data)
        assert not r["ok"] and r["error"]["code"] == "bad_request" and word in r["error"]["message"]
        assert ARM in r["error"]["message"]
    r = req("interpolate_cv", "so101/gripper", linear=[0, 0, 0], angular=[0, 0, 0])
    assert not r["ok"] and r["error"]["code"] == "unsupported" and "kinematics" in r["error"]["message"]
    assert c.namespaces[ARM].mode is Mode.HOLD  # nothing changed


def test_velocity_integrates_over_elapsed_time_when_a_cycle_is_skipped(rig):  # noqa: F811
    """A loop that skips a cycle after an overrun must not shorten the path (nor jump after a
    stall): the integrated setpoint advances by v times the time really elapsed, at most 50 ms."""
    c, act, clock, cycle, req = rig
    m = enabled_at(rig, START)
    assert req("servo_jv", ARM, velocity=[0.5, 0, 0, 0, 0])["ok"]
    cycle(3)
    p = m.setpoint_p[0]
    # one cycle skipped: the last one overran by a period (the fake clock moves only when the
    # rig's cycle runner sleeps), so the next one starts two periods after it
    clock.t += 2 * c.dt
    cycle()
    assert m.setpoint_p[0] - p == pytest.approx(0.5 * 2 * c.dt)
    p = m.setpoint_p[0]
    clock.t += 1.0  # a 1 s stall (the stream goes on): at most 50 ms' worth
    assert req("servo_jv", ARM, velocity=[0.5, 0, 0, 0, 0])["ok"]
    cycle()
    assert m.setpoint_p[0] - p == pytest.approx(0.5 * 0.05)


_vec3 = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3)
_twist_cmd = st.tuples(st.sampled_from(["servo_cv", "interpolate_cv"]), _vec3, _vec3,
                       st.sampled_from(["spatial", "body"]), st.integers(1, 40))


@settings(max_examples=40, deadline=None)
@given(st.lists(_twist_cmd, min_size=1, max_size=6),
       st.lists(st.floats(-1.5, 1.5), min_size=5, max_size=5))
def test_any_twist_sequence_stays_within_every_limit(commands, start):
    """Whatever twists arrive (up to 1 m/s, 1 rad/s, either frame, any pose, through
    singularities): every cycle the setpoint stays within the position limits, the joint
    velocities within velocity_max, and a servo_cv stream changes them by at most
    acceleration_max * dt (except a joint stopped at its limit); nothing becomes NaN."""
    c, act, clock, cycle, req = rig = make_rig(FakeActuator(PROFILE))
    m = c.namespaces[ARM]
    q0 = np.clip(np.array(start), m.pos_min, m.pos_max)
    enabled_at(rig, q0)
    for cmd, lin, ang, frame, cycles in commands:
        assert req(cmd, ARM, linear=lin, angular=ang, frame=frame)["ok"]
        for _ in range(cycles):
            prev_v = m.setpoint_v.copy()
            cycle()
            assert np.all(np.isfinite(m.setpoint_p)) and np.all(np.isfinite(m.setpoint_v))
            assert np.all(m.setpoint_p >= m.pos_min - 1e-12) and np.all(m.setpoint_p <= m.pos_max + 1e-12)
            assert np.all(np.abs(m.setpoint_v) <= m.vel_max + 1e-9)
            if cmd == "servo_cv" and c.twist_motions[ARM].active:
                # (the integrator stops a joint dead at its position limit: the one exception)
                free = (m.setpoint_p > m.pos_min) & (m.setpoint_p < m.pos_max)
                assert np.all(np.abs(m.setpoint_v - prev_v)[free] <= m.acc_max[free] * c.dt + 1e-9)
    assert c.state.value == "ENABLED"

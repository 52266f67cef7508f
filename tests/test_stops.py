"""Stops brake at each joint's stop deceleration (docs/protocol.md, Safety: stopping distances),
`home` needs a home pose, `hold` of a paused arm is a no-op; driven on the controller directly.

The SO-101 must stop from 3 rad/s within 0.25 rad (DESIGN's target): a hold / pause during a fast
move_jp braked with the move's own acceleration (10 rad/s^2) and jerk (100 rad/s^3), ~0.6-0.9 rad."""

from __future__ import annotations

import math
import re
from pathlib import Path

import msgspec
import numpy as np
import pytest
import yaml

from crtk_bridge.backends import create_backend
from crtk_bridge.core.actuator import effective_period_s
from crtk_bridge.core.motion import Mode
from crtk_bridge.core.state import OperatingState
from crtk_bridge.errors import ProfileError
from crtk_bridge.profile import STOP_DECELERATION_FACTOR, load_profile, parse_profile, stop_deceleration

from .test_controller import PROFILE, FakeActuator, make_rig
from .test_transitions import HookedActuator

SO101_STOP_MAX_RAD = 0.25  # DESIGN: the SO-101 stops from 3 rad/s within 0.25 rad


def rig_for(act, profile=None):
    """(controller, actuator, cycle(n), req(cmd, ns, **data)) for ``act`` on ``profile`` (the
    actuator's own by default): test_controller's rig, one reply per request asserted."""
    c, act, _, cycle, req = make_rig(act, profile or act.profile)
    return c, act, cycle, req


class FeetechBounded(FakeActuator):
    """The fake robot, bounded as the SO-101's STS3215 at Acceleration 254 (38.96 rad/s^2)."""

    def deceleration_limit(self, i):
        return 254 * 100 * 2 * math.pi / 4096


def _at_full_speed(c, cycle, ns="so101", j=0, deadline_cycles=2000):
    """Cycle until joint ``j`` of ``ns`` moves at its velocity_max; return its setpoint velocity."""
    m = c.namespaces[ns]
    for _ in range(deadline_cycles):
        cycle()
        if abs(m.setpoint_v[j]) >= m.vel_max[j] - 1e-9:
            return m.setpoint_v[j]
    raise AssertionError(f"joint {j} never reached velocity_max (last {m.setpoint_v[j]})")


def _travel_until_rest(c, act, cycle, ns="so101", j=0, deadline_cycles=2000):
    """Cycle until ``ns`` is at rest (HOLD); return (travel of joint j, cycles, per-cycle speeds)."""
    m = c.namespaces[ns]
    start = act.pos[j]
    speeds = [abs(m.setpoint_v[j])]
    for k in range(deadline_cycles):
        if m.mode is Mode.HOLD:
            return abs(act.pos[j] - start), k, speeds
        cycle()
        speeds.append(abs(m.setpoint_v[j]))
    raise AssertionError("the stop never came to rest")


@pytest.mark.parametrize("stop", ["hold", "pause"])
def test_so101_stops_from_full_speed_within_its_stopping_distance(stop):
    c, act, cycle, req = rig_for(FeetechBounded(PROFILE))
    act.pos[0] = -1.8
    cycle()
    assert req("enable")["ok"]
    assert req("move_jp", "so101", position=[1.8, 0, 0, 0, 0])["ok"]
    v = _at_full_speed(c, cycle)
    assert v == pytest.approx(3.0)
    assert req(stop, "so101" if stop == "hold" else None)["ok"]
    travel, _, speeds = _travel_until_rest(c, act, cycle)
    d = c.stop_dec[0]
    assert d == pytest.approx(254 * 100 * 2 * math.pi / 4096)  # 4 x 10 rad/s^2, bounded by the servo
    assert travel <= SO101_STOP_MAX_RAD
    assert travel <= v * v / (2 * d) + v * c.dt  # the documented stopping distance
    # braked at the stop deceleration, never harder (the servo could not follow)
    assert max(a - b for a, b in zip(speeds, speeds[1:])) <= d * c.dt + 1e-9
    held = act.pos.copy()
    cycle(20)
    np.testing.assert_array_equal(act.pos, held)  # then holds


def test_a_stop_brings_every_joint_to_rest_together_in_its_direction():
    c, act, cycle, req = rig_for(FakeActuator(PROFILE))
    assert req("enable")["ok"]
    assert req("move_jp", "so101", position=[1.5, -1.0, 0.5, 1.2, 2.0])["ok"]
    cycle(30)
    m = c.namespaces["so101"]
    v0 = m.setpoint_v.copy()
    assert np.all(np.abs(v0) > 0.1)
    assert req("hold", "so101")["ok"]
    assert m.mode is Mode.STOP
    rest_at = {}
    for k in range(500):
        before = act.pos.copy()
        cycle()
        step = act.pos[:5] - before[:5]
        assert np.all(step * np.sign(v0) >= -1e-12)  # no joint turns back
        for j in np.flatnonzero(np.abs(m.setpoint_v) == 0.0):
            rest_at.setdefault(int(j), k)
        if m.mode is Mode.HOLD:
            break
    assert m.mode is Mode.HOLD and len(set(rest_at.values())) == 1  # all at rest in the same cycle


def test_watchdog_brakes_an_integrated_velocity_stream():
    c, act, cycle, req = rig_for(FeetechBounded(PROFILE))
    act.pos[0] = -1.8
    cycle()
    assert req("enable")["ok"]
    assert req("servo_jv", "so101", velocity=[3.0, 0, 0, 0, 0])["ok"]
    m = c.namespaces["so101"]
    c.outbox.clear()
    for _ in range(1000):  # the stream falls silent: the watchdog fires after servo_timeout_s
        cycle()
        if m.mode is not Mode.SERVO_V:
            break
    warn = [e["data"]["message"] for e in c.outbox if e.get("event") == "warning"]
    assert m.mode is Mode.STOP and warn and "braking to rest" in warn[0]
    travel, cycles, speeds = _travel_until_rest(c, act, cycle)
    assert cycles > 1  # braked over several cycles, not a dead stop of the setpoint
    assert travel <= 3.0 ** 2 / (2 * c.stop_dec[0]) + 3.0 * c.dt
    assert max(a - b for a, b in zip(speeds, speeds[1:])) <= c.stop_dec[0] * c.dt + 1e-9


def test_a_move_replanned_from_a_stop_starts_from_the_braking_velocity():
    c, act, cycle, req = rig_for(FakeActuator(PROFILE))
    act.pos[0] = -1.8
    cycle()
    assert req("enable")["ok"]
    assert req("move_jp", "so101", position=[1.8, 0, 0, 0, 0])["ok"]
    _at_full_speed(c, cycle)
    assert req("hold", "so101")["ok"]
    cycle(2)
    m = c.namespaces["so101"]
    v = m.setpoint_v[0]
    assert m.mode is Mode.STOP and 0 < v < 3.0
    before = act.pos[0]
    assert req("move_jp", "so101", position=[1.0, 0, 0, 0, 0])["ok"]
    cycle()
    assert 0 < act.pos[0] - before <= 3.0 * c.dt  # no jump (at most velocity_max), no reversal
    cycle(2000)
    assert act.pos[0] == pytest.approx(1.0, abs=1e-6)


def _so101_with(**limits):
    data = msgspec.to_builtins(PROFILE)
    data["joints"][0]["limits"].update(limits)
    data["joints"] = [{**{k: v for k, v in j.items() if k != "backend"}, **j["backend"]} for j in data["joints"]]
    return parse_profile(data, "<so101>")


def test_stop_deceleration_default_and_profile_value():
    lim = PROFILE.joints[0].limits
    assert lim.stop_deceleration_max is None
    assert stop_deceleration(lim) == STOP_DECELERATION_FACTOR * lim.acceleration_max
    assert stop_deceleration(lim, 30.0) == 30.0  # bounded by what the hardware follows
    p = _so101_with(stop_deceleration_max=20.0)
    assert stop_deceleration(p.joints[0].limits, 30.0) == 20.0
    c, _, _, _ = rig_for(FakeActuator(p), p)
    assert c.stop_dec[0] == 20.0 and c.namespaces["so101"].stop_dec[0] == 20.0


@pytest.mark.parametrize("value", [0.0, -1.0, float("inf")])
def test_stop_deceleration_must_be_positive_and_finite(value):
    with pytest.raises(ProfileError, match=r"joints\[0\] \(shoulder_pan\)\.limits\.stop_deceleration_max: "
                                           r"must be a finite number > 0"):
        _so101_with(stop_deceleration_max=value)


def test_feetech_bounds_the_stop_deceleration_by_its_acceleration_register():
    b = create_backend(PROFILE)
    assert b.deceleration_limit(0) == pytest.approx(254 * 100 * 2 * math.pi / 4096)
    with pytest.raises(ProfileError, match=r"joints\[0\] \(shoulder_pan\)\.limits\.stop_deceleration_max: 60 rad/s\^2 "
                                           r"is above what the servo follows with backend\.acceleration 254"):
        create_backend(_so101_with(stop_deceleration_max=60.0))


# ---------------------------------------------------------------- home

def _without_home(profile):
    data = msgspec.to_builtins(profile)
    data["joints"] = [{**{k: v for k, v in j.items() if k not in ("backend", "home")}, **j["backend"]}
                      for j in data["joints"]]
    return parse_profile(data, "<no home>")


def test_home_without_a_home_pose_is_refused_naming_the_key():
    p = _without_home(PROFILE)
    c, act, cycle, req = rig_for(FakeActuator(p), p)
    act.pos[:] = 0.3
    cycle()
    assert req("enable")["ok"]
    r = req("home")
    assert not r["ok"] and r["error"]["code"] == "unsupported"
    msg = r["error"]["message"]
    assert msg.startswith("so101: home refused") and "`home`" in msg and "'shoulder_pan'" in msg
    assert "\n" not in msg
    cycle(100)
    np.testing.assert_array_equal(act.pos, 0.3)  # nothing moved (no default zeros)
    assert not c.is_busy


def test_native_homing_needs_no_home_pose():
    p = _without_home(PROFILE)
    c, act, cycle, req = rig_for(HookedActuator(p, enable_cycles=1), p)
    c.handle({"id": 98, "cmd": "enable"})
    cycle(3)
    assert c.state is OperatingState.ENABLED
    c.handle({"id": 99, "cmd": "home"})
    cycle(6)
    assert c.is_homed and [m for m in c.outbox if m.get("id") == 99][0]["ok"]


def test_home_outside_the_limits_names_the_limits():
    data = msgspec.to_builtins(PROFILE)
    data["joints"] = [{**{k: v for k, v in j.items() if k != "backend"}, **j["backend"]} for j in data["joints"]]
    data["joints"][5]["home"] = 2.0
    with pytest.raises(ProfileError, match=r"joints\[5\] \(gripper\)\.home: 2\.0 is outside the position limits "
                                           r"\[-0\.174533, 1\.74533\]"):
        parse_profile(data, "<so101>")


def test_limits_excluding_zero_need_no_home():
    """A joint whose limits exclude 0 is valid without a `home` (no default 0.0 to complain about)."""
    data = msgspec.to_builtins(_without_home(PROFILE))
    data["joints"] = [{**{k: v for k, v in j.items() if k != "backend"}, **j["backend"]} for j in data["joints"]]
    data["joints"][5]["limits"].update(position_min=0.2, position_max=1.5)
    data["shutdown"]["rest"]["gripper"] = 0.5
    assert parse_profile(data, "<so101>").joints[5].home is None


# ---------------------------------------------------------------- hold while PAUSED

def test_hold_of_a_paused_arm_is_a_no_op_success():
    c, act, cycle, req = rig_for(FakeActuator(PROFILE))
    assert req("enable")["ok"] and req("pause")["ok"]
    cycle(5)
    assert c.state is OperatingState.PAUSED and not c.in_motion()
    held = act.pos.copy()
    c.outbox.clear()
    r = req("hold", "so101")
    assert r["ok"], r
    assert c.state is OperatingState.PAUSED  # still paused: resume is still what moves it again
    cycle(5)
    np.testing.assert_array_equal(act.pos, held)
    assert not req("move_jp", "so101", position=[0.1, 0, 0, 0, 0])["ok"]  # motion still refused


# ---------------------------------------------------------------- shipped profiles

PROFILES_DIR = Path(__file__).resolve().parent.parent / "profiles"
PROTOCOL_MD = Path(__file__).resolve().parent.parent / "docs" / "protocol.md"
SERIAL_SERVOS = {"feetech", "dynamixel"}  # no brakes: an arm of these falls when torque goes off


def shipped_profiles() -> list[Path]:
    """Every shipped robot profile (not example.yaml, the documentation of every key)."""
    return sorted(p for p in PROFILES_DIR.glob("*.yaml") if p.name != "example.yaml")


def _backend_types(p) -> set[str]:
    sections = [p.backend] if p.backend is not None else list(p.backends.values())
    return {s["type"] for s in sections}


@pytest.mark.parametrize("path", shipped_profiles(), ids=lambda p: p.name)
def test_every_shipped_arm_that_falls_with_torque_off_parks(path):
    """issue 18 item 6: bimanual_so101 dropped both arms on Ctrl-C while so101 parked."""
    p = load_profile(path)
    if _backend_types(p) & SERIAL_SERVOS:
        assert p.shutdown.action == "park", f"{path.name}: serial servos without brakes: needs shutdown: park"
        assert set(p.shutdown.rest) == set(p.joint_names), f"{path.name}: the rest pose names every joint"


@pytest.mark.parametrize("path", shipped_profiles(), ids=lambda p: p.name)
def test_every_shipped_profile_that_homes_has_a_home_pose(path):
    """issue 18 item 3: `home` on the UR5e drove every joint to 0 (the arm stretched out). A
    leader arm (``*_leader.yaml``) is moved by hand and never homed: `home` is refused there."""
    p = load_profile(path)
    native = any("homing" in j.backend for j in p.joints)  # a CiA 402 drive that homes itself
    if not native and not path.stem.endswith("_leader"):
        missing = [j.name for j in p.joints if j.home is None]
        assert not missing, f"{path.name}: no home pose for {missing}"


def test_ur5e_home_is_the_folded_upright_pose():
    p = load_profile(PROFILES_DIR / "ur5e.yaml")
    np.testing.assert_allclose([j.home for j in p.joints], [0, -math.pi / 2, 0, -math.pi / 2, 0, 0], atol=1e-4)


_ROW = re.compile(r"^\| `([^`]+\.yaml)`(?: \(if enabled\))? \| [^|]+ \| ([0-9.]+) \| ([0-9.]+) \| ([0-9.]+) \| ([0-9.]+) \|$")


def _stopping_rows(path: Path) -> set[tuple[str, str, str, str]]:
    """(velocity_max, stop deceleration, distance, time) per distinct joint group, from the
    profile and its backend, formatted as docs/protocol.md writes them."""
    p = load_profile(path)
    b = create_backend(p)
    dt = effective_period_s(p, b)
    out = set()
    for i, j in enumerate(p.joints):
        v, d = j.limits.velocity_max, stop_deceleration(j.limits, b.deceleration_limit(i))
        out.add((f"{v:g}", f"{d:.4g}", f"{v * v / (2 * d) + v * dt:.3f}", f"{v / d + dt:.3f}"))
    return out


def test_protocol_md_stopping_distances_match_the_profiles():
    """docs/protocol.md (Safety, Stopping distances) is computed from the shipped profiles; it
    cannot drift from them. The SO-101 stops from any joint's velocity_max within 0.25 rad."""
    doc: dict[str, set] = {}
    for line in PROTOCOL_MD.read_text().splitlines():
        m = _ROW.match(line)
        if m:
            doc.setdefault(m.group(1), set()).add(m.groups()[1:])
    names = [p.name for p in shipped_profiles()]
    assert sorted(doc) == sorted(names), "one table row (or more) per shipped profile"
    for path in shipped_profiles():
        assert doc[path.name] == _stopping_rows(path), path.name
    for name in ("so101.yaml", "bimanual_so101.yaml"):
        assert all(float(dist) <= SO101_STOP_MAX_RAD for _, _, dist, _ in doc[name])


def test_dynamixel_bounds_the_stop_deceleration_by_its_profile_acceleration():
    koch = PROFILES_DIR / "koch.yaml"
    assert create_backend(load_profile(koch)).deceleration_limit(0) == math.inf  # 0: no on-servo profile
    data = yaml.safe_load(koch.read_text())
    data["backend"]["profile_acceleration"] = 50  # 50 x 214.577 rev/min^2 = 18.7 rad/s^2
    data["joints"][1]["limits"]["stop_deceleration_max"] = 30.0
    p = parse_profile(data, "<koch>")
    with pytest.raises(ProfileError, match=r"joints\[1\] \(shoulder_lift\)\.limits\.stop_deceleration_max: 30 "
                                           r"rad/s\^2 is above what the servo follows with backend\.profile_acceleration 50 "
                                           r"\(18\.73 rad/s\^2\)"):
        create_backend(p)
    del data["joints"][1]["limits"]["stop_deceleration_max"]
    b = create_backend(parse_profile(data, "<koch>"))
    assert b.deceleration_limit(1) == pytest.approx(50 * 214.577 * 2 * math.pi / 3600)


@pytest.mark.parametrize("source", ["profile", "hardware"])
def test_a_stop_never_carries_a_move_past_its_goal(source):
    """A stop deceleration below the move's own acceleration (a profile's stop_deceleration_max,
    or the default bounded by a servo's low acceleration register) braked a hold that came as the
    move neared its goal over a longer distance than the move had left: the arm went ~0.2 rad past
    the goal it was sent to (found in review). Braking ends at the move's goal at the latest."""
    if source == "profile":
        p = _so101_with(stop_deceleration_max=2.0)  # acceleration_max 10
        act = FakeActuator(p)
    else:
        p = PROFILE

        class SlowServo(FakeActuator):  # e.g. a Feetech at backend.acceleration 13: 2 rad/s^2
            def deceleration_limit(self, i):
                return 2.0

        act = SlowServo(p)
    c, act, cycle, req = rig_for(act, p)
    assert c.stop_dec[0] == pytest.approx(2.0)
    assert req("enable")["ok"]
    assert req("move_jp", "so101", position=[1.0, 0, 0, 0, 0])["ok"]
    m = c.namespaces["so101"]
    for _ in range(5000):  # until the move decelerates near its goal, still fast
        cycle()
        if m.setpoint_v[0] > 0.5 and 1.0 - m.setpoint_p[0] < 0.06:
            break
    assert m.mode is Mode.MOVE and m.setpoint_v[0] > 0.5
    assert req("hold", "so101")["ok"]
    _travel_until_rest(c, act, cycle)
    assert m.setpoint_p[0] <= 1.0 + 1e-9 and act.pos[0] <= 1.0 + 1e-9, m.setpoint_p[0]
    # braking that does not reach the goal is untouched: a hold early in the move stops short
    assert req("move_jp", "so101", position=[-1.0, 0, 0, 0, 0])["ok"]
    cycle(30)
    assert m.mode is Mode.MOVE and m.setpoint_v[0] < -0.5
    assert req("hold", "so101")["ok"]
    travel, _, _ = _travel_until_rest(c, act, cycle)
    assert m.setpoint_p[0] > -1.0 and travel > 0.05

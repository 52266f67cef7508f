"""Limits in one place (issue 19, item 5; docs/architecture.md, "Limits").

* crtk_client/vectors.py (crtk_bridge.vectors) is the one reader of vectors, poses and quaternions (client, front,
  core), a leaf module (numpy, stdlib, crtk_bridge.errors);
* ``Actuator.write`` refuses a non-finite setpoint for every backend: the backend's ``_write``
  never sees one (the joint goes out in NONE, keeping its last goal), the write returns a
  non-transient ``invalid_command`` Fault naming robot and joint, and core faults the robot;
* core's motion output bounds every value on every path to the profile's limits, whatever the
  client sent (hostile values included), so backends clamp only to their devices' ranges.
"""

from __future__ import annotations

import importlib
import json
import math
import subprocess
import sys

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crtk_bridge import registry, vectors
from crtk_bridge.core.actuator import Capabilities, CartesianMode, CommandMode
from crtk_bridge.core.state import OperatingState
from crtk_bridge.errors import CommandError
from crtk_bridge.profile import JointLimits

from .test_controller import PROFILE, FakeActuator, make_rig
from .test_native_cartesian import FakeNativeArm

ARM = "so101"
ARM_IDX = np.array([PROFILE.joint_index(j) for j in PROFILE.namespace(ARM).joints])


# ---------------------------------------------------------------- the one reader
def test_vectors_is_a_leaf_module():
    """The client distribution carries it (crtk_client.vectors, also named crtk_bridge.vectors):
    importing it loads no other module of the project than crtk_client.errors (nor crtk_bridge,
    pinocchio, msgspec, yaml)."""
    probe = ("import json, sys; import crtk_client.vectors; "
             "print(json.dumps(sorted(m for m in sys.modules if m.startswith(('crtk_bridge', 'crtk_client', "
             "'pinocchio', 'msgspec', 'yaml', 'ruckig')))))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True)
    assert json.loads(out.stdout) == ["crtk_client", "crtk_client.errors", "crtk_client.vectors"]
    assert vectors is importlib.import_module("crtk_client.vectors")  # the old name is the same module


@pytest.mark.parametrize("values, words", [
    ([0.1, 0.2], ["needs 3 values", "(a, b, c)", "got 2"]),
    ([0.1, float("nan"), 0.3], ["entry 1", "'b'", "non-finite", "nan"]),
    ([0.1, 0.2, float("inf")], ["entry 2", "'c'", "non-finite", "inf"]),
    ([0.1, "0.2", 0.3], ["entry 1", "'b'", "not a number"]),
    ([0.1, None, 0.3], ["entry 1", "'b'", "not a number"]),
    ([[0.1], [0.2], [0.3]], ["entry 0", "not a number"]),
    ("0.1 0.2 0.3", ["expected a list of numbers", "str"]),
    ({"x": 1}, ["expected a list of numbers", "dict"]),
])
def test_a_bad_vector_is_refused_naming_the_entry_and_joint(values, words):
    with pytest.raises(vectors.InvalidVector) as info:
        vectors.floats(values, "arm: servo_jp position", 3, ["a", "b", "c"])
    exc = info.value
    assert isinstance(exc, CommandError) and isinstance(exc, ValueError) and exc.code == "bad_request"
    assert str(exc).startswith("arm: servo_jp position") and "\n" not in str(exc)
    for word in words:
        assert word in str(exc), (word, str(exc))


def test_floats_reads_lists_tuples_and_arrays_as_new_float_arrays():
    src = np.array([[1, 2], [3, 4]])
    for given_ in ([1, 2, 3, 4], (1, 2, 3, 4), src):
        out = vectors.floats(given_, "v", 4)
        assert out.dtype == float and out.tolist() == [1.0, 2.0, 3.0, 4.0]
    out[0] = 9
    assert src[0, 0] == 1  # a copy, never a view of the caller's array
    assert vectors.client_floats(x * 0.5 for x in range(3)) == [0.0, 0.5, 1.0]


def test_quaternions_and_poses():
    q = vectors.unit_quaternion([0, 0, 0, 1.2], "q")
    assert q.tolist() == [0, 0, 0, 1.0]
    for bad in ([0, 0, 0, 0], [0, 0, 0, 2], [0, 0, 0, 0.4]):
        with pytest.raises(vectors.InvalidVector, match="unit quaternion"):
            vectors.unit_quaternion(bad, "arm: move_cp orientation")
    rng = np.random.default_rng(7)
    for _ in range(200):  # every branch of Shepperd's method, both signs of w
        quat = rng.normal(size=4)
        quat /= np.linalg.norm(quat)
        back = vectors.quaternion_from_matrix(vectors.matrix_from_quaternion(quat))
        assert back[3] >= 0 and np.allclose(back, quat if quat[3] >= 0 else -quat, atol=1e-12)
    p, quat = vectors.pose({"position": [1, 2, 3], "orientation": [0, 0, 1, 1]}, "arm: servo_cp")
    assert p.tolist() == [1, 2, 3] and np.allclose(quat, [0, 0, math.sqrt(0.5), math.sqrt(0.5)])
    T = vectors.pose_matrix(p, quat)
    assert [a.tolist() for a in vectors.pose_pq(T)] == [a.tolist() for a in vectors.any_pose(T)]
    with pytest.raises(vectors.InvalidVector, match="arm: servo_cp needs 'orientation'"):
        vectors.pose({"position": [1, 2, 3]}, "arm: servo_cp")
    with pytest.raises(vectors.InvalidVector, match="has no direction"):
        vectors.matrix_from_quaternion([0, 0, 0, 0])


def test_client_front_and_core_refuse_alike():
    """The client's encoder, the front's cartesian reader and core's twist / pose readers are
    the one implementation: the same input, the same refusal."""
    from crtk_bridge.client.device import encode_pose, encode_six
    from crtk_bridge.core.native_cartesian import parse_pose
    from crtk_bridge.core.twist import parse_twist

    bad_twist = {"linear": [0, 0, float("inf")], "angular": [0, 0, 0]}
    with pytest.raises(CommandError) as core:
        parse_twist("arm", "servo_cv", bad_twist)
    with pytest.raises(CommandError) as client:
        encode_six([0, 0, float("inf"), 0, 0, 0], "linear", "angular", "arm: servo_cv")
    assert "non-finite (inf)" in str(core.value) and "non-finite (inf)" in str(client.value)
    bad_pose = {"position": [0, 0, 0], "orientation": [0, 0, 0, 3]}
    for read in (lambda: parse_pose("arm", "servo_cp", bad_pose), lambda: encode_pose(bad_pose, "arm: servo_cp")):
        with pytest.raises(CommandError, match=r"arm: servo_cp orientation must be a unit quaternion .*norm 3"):
            read()


# ---------------------------------------------------------------- the write template
class SpyActuator(FakeActuator):
    """Records what ``_write`` was handed: a backend must never see a non-finite setpoint."""

    capabilities = Capabilities(position=True, velocity=True, effort=True, measures_velocity=True)

    def __init__(self, profile):
        super().__init__(profile)
        self.handed: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def _write(self, cmd):
        self.handed.append((cmd.mode.copy(), cmd.position.copy(), cmd.velocity.copy(), cmd.effort.copy()))
        return super()._write(cmd)


def assert_nothing_non_finite_handed(handed) -> None:
    for mode, p, v, f in handed:
        pos = mode == CommandMode.POSITION
        assert np.isfinite(p[pos]).all() and np.isfinite(v[pos]).all(), (mode, p, v)
        assert np.isfinite(v[mode == CommandMode.VELOCITY]).all(), (mode, v)
        assert np.isfinite(f[mode == CommandMode.EFFORT]).all(), (mode, f)


@pytest.mark.parametrize("mode, field", [(CommandMode.POSITION, "position"), (CommandMode.POSITION, "velocity"),
                                         (CommandMode.VELOCITY, "velocity"), (CommandMode.EFFORT, "effort")])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_write_refuses_a_non_finite_setpoint_for_the_backend(mode, field, bad):
    act = SpyActuator(PROFILE)
    cmd = act.new_command()
    cmd.mode[:] = int(mode)
    cmd.position[:] = 0.1
    getattr(cmd, field)[2] = bad
    getattr(cmd, field)[4] = bad
    fault = act.write(cmd)
    name = PROFILE.joints[2].name
    assert fault is not None and fault.code == "invalid_command" and not fault.transient and fault.joint == name
    assert fault.message.startswith(f"{PROFILE.name}: joint {name!r}: {field} setpoint") and "not finite" in fault.message
    (handed,) = act.handed
    assert_nothing_non_finite_handed([handed])
    assert handed[0].tolist() == [int(mode)] * 2 + [int(CommandMode.NONE), int(mode), int(CommandMode.NONE), int(mode)]
    assert cmd.mode.tolist() == [int(mode)] * act.n  # the caller's buffer as it was
    # a finite command (one huge enough that a sum overflows) goes out whole, no Fault
    getattr(cmd, field)[:] = 1e308
    assert act.write(cmd) is None and act.handed[-1][0].tolist() == [int(mode)] * act.n
    # a non-finite value in a field the joint's mode does not follow is not the backend's concern
    cmd.mode[:] = int(CommandMode.NONE)
    getattr(cmd, field)[:] = bad
    assert act.write(cmd) is None


@pytest.mark.parametrize("kind", ["pose", "twist"])
def test_write_refuses_a_non_finite_cartesian_setpoint(kind):
    act = FakeNativeArm(PROFILE)
    cmd = act.new_command()
    cart = cmd.cartesian
    cart.mode[0] = CartesianMode.POSE if kind == "pose" else CartesianMode.TWIST
    (cart.orientation if kind == "pose" else cart.angular)[0, 1] = np.nan
    fault = act.write(cmd)
    assert fault is not None and fault.code == "invalid_command" and not fault.transient
    assert fault.message == (f"{PROFILE.name}: namespace {ARM!r}: cartesian {kind} setpoint is not finite; "
                             "not sent (the arm keeps its last goal)")
    assert act.writes[-1][0] is CartesianMode.NONE  # the backend got no cartesian setpoint
    assert cart.mode[0] == (CartesianMode.POSE if kind == "pose" else CartesianMode.TWIST)


@pytest.mark.parametrize("name", ["composite", *registry.names()])
def test_every_backend_writes_through_the_gate(name):
    """No backend (nor the composite) replaces ``Actuator.write``: the finiteness gate runs for
    each; tests/conformance::test_nan_never_reaches_the_bus shows it on every simulator's wire."""
    from crtk_bridge.backends.composite import CompositeActuator
    from crtk_bridge.core.actuator import Actuator

    cls = CompositeActuator if name == "composite" else registry.backend_class(name)
    assert cls.write is Actuator.write


def test_a_buggy_core_path_never_reaches_the_backend_and_faults_the_robot(monkeypatch):
    """A NaN produced inside core (here: the motion layer's output, patched) is refused by the
    write template: the backend never writes it, the robot goes to FAULT naming the joint."""
    from crtk_bridge.core import motion

    act = SpyActuator(PROFILE)
    c, act, clock, cycle, req = make_rig(act)
    assert req("enable")["ok"]
    cycle(3)
    fill = motion.NamespaceMotion.fill

    def buggy_fill(self, cmd, block):
        fill(self, cmd, block)
        if self.name == ARM:
            cmd.position[self.idx[1]] = np.nan

    monkeypatch.setattr(motion.NamespaceMotion, "fill", buggy_fill)
    cycle(3)
    assert c.state is OperatingState.FAULT
    name = PROFILE.joints[int(ARM_IDX[1])].name
    (err,) = [m["data"] for m in c.outbox if m.get("event") == "error"]
    assert err["code"] == "invalid_command" and err["joint"] == name and PROFILE.name in err["message"]
    assert_nothing_non_finite_handed(act.handed)


# ---------------------------------------------------------------- hostile input on every path
HOSTILE = (st.sampled_from([np.nan, np.inf, -np.inf, 1e308, -1e308, 1e-320])
           | st.floats(-1e6, 1e6) | st.floats(-3.0, 3.0))
JOINT_COMMANDS = ["servo_jp", "servo_jp_ff", "servo_jr", "servo_jv", "servo_jf", "interpolate_jp",
                  "interpolate_jr", "interpolate_jv", "interpolate_jf", "move_jp", "move_jr"]
_step = st.one_of(
    st.tuples(st.sampled_from(JOINT_COMMANDS), st.lists(HOSTILE, min_size=len(ARM_IDX), max_size=len(ARM_IDX)),
              st.integers(0, 30)),
    st.tuples(st.sampled_from(["servo_cv", "interpolate_cv"]), st.lists(HOSTILE, min_size=6, max_size=6),
              st.integers(0, 30)),
    st.tuples(st.sampled_from(["home", "hold"]), st.just([]), st.integers(0, 200)),
)


def _limited_profile():
    """The test profile with effort_max on every joint (effort commands are bounded too)."""
    joints = [msgspec.structs.replace(j, limits=msgspec.structs.replace(j.limits, effort_max=2.0))
              for j in PROFILE.joints]
    return msgspec.structs.replace(PROFILE, joints=joints)


LIMITED = _limited_profile()
assert isinstance(LIMITED.joints[0].limits, JointLimits)
POS_MIN = np.array([j.limits.position_min for j in LIMITED.joints])
POS_MAX = np.array([j.limits.position_max for j in LIMITED.joints])
V_MAX = np.array([j.limits.velocity_max for j in LIMITED.joints])
EPS = 1e-9


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(steps=st.lists(_step, min_size=1, max_size=8))
def test_hostile_values_on_every_path_reach_the_motors_bounded_and_finite(steps):
    """servo / interpolate / move (joint), twists, home, hold, with NaN, inf, 1e308 and plain
    values: every refused command changes nothing, every accepted one reaches the backend within
    the profile's limits (position, velocity_max, effort_max), finite, and the robot never
    faults for it."""
    act = SpyActuator(LIMITED)
    c, act, clock, cycle, req = make_rig(act, LIMITED)
    assert req("enable")["ok"]
    cycle(2)
    for cmd, values, cycles in steps:
        values = list(values)
        if cmd in ("servo_cv", "interpolate_cv"):
            data = {"linear": values[:3], "angular": values[3:]}
        elif cmd == "servo_jp_ff":
            m = c.namespaces[ARM]
            cmd, data = "servo_jp", {"position": list(m.setpoint_p + 0.01), "velocity": values}
        elif cmd in JOINT_COMMANDS:
            data = {{"v": "velocity", "f": "effort"}.get(cmd[-1], "position"): values}
        else:
            data = {}
        reply = req(cmd, None if cmd == "home" else ARM, **data)
        if not all(math.isfinite(v) for v in values):
            assert not reply["ok"], reply  # bad_request (or refused for the state: homing)
        cycle(cycles)
        assert c.state is OperatingState.ENABLED, [m for m in c.outbox if m.get("event") == "error"]
    assert_nothing_non_finite_handed(act.handed)
    for mode, p, v, f in act.handed:
        pos = mode == CommandMode.POSITION
        assert np.all((p[pos] >= POS_MIN[pos] - EPS) & (p[pos] <= POS_MAX[pos] + EPS)), p
        assert np.all(np.abs(v) <= V_MAX + EPS), v
        assert np.all(np.abs(f) <= 2.0 + EPS), f


_cart_step = st.tuples(
    st.sampled_from(["servo_cp", "interpolate_cp", "move_cp", "servo_cv", "interpolate_cv", "hold"]),
    st.lists(HOSTILE | st.floats(-0.005, 0.005), min_size=7, max_size=7),
    st.integers(0, 25),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(steps=st.lists(_cart_step, min_size=1, max_size=8))
def test_hostile_values_on_the_native_cartesian_path_reach_the_backend_bounded_and_finite(steps):
    """A backend with its own cartesian control (a UR) gets poses and twists: with NaN, inf, 1e308
    and plain values, every row it is handed is finite, a stream's pose never steps farther than
    safety.cartesian_step_max (and cartesian_rotation_step_max) from the last, and a twist never
    exceeds safety.cartesian_velocity_max / cartesian_angular_velocity_max."""
    sf = PROFILE.safety
    c, act, clock, cycle, req = make_rig(FakeNativeArm(PROFILE))
    assert req("enable")["ok"]
    cycle(2)
    for cmd, values, cycles in steps:
        if cmd.endswith("_cp"):
            data = {"position": list(act.tcp_p + np.array(values[:3])),
                    "orientation": list(act.tcp_q + np.array(values[3:]))}
        elif cmd.endswith("_cv"):
            data = {"linear": values[:3], "angular": values[3:6]}
        else:
            data = {}
        reply = req(cmd, ARM, **data)
        if not all(math.isfinite(v) for v in values[:6 if cmd.endswith("_cv") else 7]) and cmd != "hold":
            assert not reply["ok"] and reply["error"]["code"] == "bad_request", reply
        cycle(cycles)
        assert c.state is OperatingState.ENABLED, [m for m in c.outbox if m.get("event") == "error"]
    last = None
    for mode, joint_modes, row in act.writes:
        assert all(np.isfinite(row[k]).all() for k in ("position", "orientation", "linear", "angular")), row
        if mode is CartesianMode.POSE:
            if last is not None:
                assert np.linalg.norm(row["position"] - last[0]) <= sf.cartesian_step_max + EPS
                assert vectors.rotation_angle(row["orientation"], last[1]) <= sf.cartesian_rotation_step_max + 1e-6
            last = (row["position"], row["orientation"])
        elif mode is CartesianMode.TWIST:
            assert np.linalg.norm(row["linear"]) <= sf.cartesian_velocity_max + EPS
            assert np.linalg.norm(row["angular"]) <= sf.cartesian_angular_velocity_max + EPS
        if mode is not CartesianMode.POSE:
            last = None  # a new stream steps from the measured pose

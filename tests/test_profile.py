"""Profile loading: the shipped profiles load; every error names the file, the key path and why."""

from __future__ import annotations

import copy
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import msgspec
import pytest
import yaml

from crtk_bridge import profile as profile_mod
from crtk_bridge import registry
from crtk_bridge.backends import BACKENDS, backend_class, create_backend
from crtk_bridge.errors import ProfileError
from crtk_bridge.profile import Profile, backend_config, load_profile

PROFILES = Path(__file__).resolve().parent.parent / "profiles"
SO101 = PROFILES / "so101.yaml"
EXAMPLE = PROFILES / "example.yaml"


# ---------------------------------------------------------------- shipped profiles


def test_so101_loads():
    p = load_profile(SO101)
    assert p.name == "so101"
    assert p.backend_type == "feetech"
    assert p.joint_names == ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex",
                             "wrist_roll", "gripper"]
    assert [ns.name for ns in p.namespaces] == ["so101", "so101/gripper"]
    assert p.namespace("so101/gripper").joints == ["gripper"]
    assert p.joints[0].backend["calibration"]["range"] == [700, 3400]  # the backend's key, as written


def test_example_loads():
    p = load_profile(EXAMPLE)
    assert p.backend_type == "feetech"
    assert p.backend["port"]
    assert len(p.namespaces) == 2
    # every joint in exactly one namespace (the loader checks it; the example must show it)
    assert sorted(j for ns in p.namespaces for j in ns.joints) == sorted(p.joint_names)


def _struct_keys(t: Any, seen: set[str]) -> None:
    """Every field name of a msgspec Struct type, recursively (through lists and optionals)."""
    info = msgspec.inspect.type_info(t)
    _collect(info, seen)


def _collect(info: Any, seen: set[str]) -> None:
    if isinstance(info, msgspec.inspect.StructType):
        for f in info.fields:
            seen.add(f.name)
            _collect(f.type, seen)
    elif isinstance(info, (msgspec.inspect.ListType, msgspec.inspect.TupleType,
                           msgspec.inspect.VarTupleType)):
        for sub in getattr(info, "item_types", None) or [getattr(info, "item_type", None)]:
            if sub is not None:
                _collect(sub, seen)
    elif isinstance(info, msgspec.inspect.UnionType):
        for sub in info.types:
            _collect(sub, seen)


def _yaml_keys(node: Any, out: set[str]) -> None:
    if isinstance(node, dict):
        for k, v in node.items():
            out.add(k)
            _yaml_keys(v, out)
    elif isinstance(node, list):
        for v in node:
            _yaml_keys(v, out)


def _documented_structs() -> list[Any]:
    """Core's profile schema and the schemas the example's backend owns (its joints' keys)."""
    from crtk_bridge.backends.servo_keys import ServoJoint

    return [Profile, ServoJoint]


#: keys that cannot coexist with the example's own (a one-bus robot), or whose section turns a
#: transport on (transport.zenoh): documented as commented YAML
ALTERNATIVE_KEYS = {"backends", "transport", "zenoh", "mode", "connect", "listen", "connect_timeout_s", "lease_ms",
                    "ros_domain_id", "publish_rate_hz", "tls", "access_control", "root_ca_certificate",
                    "listen_certificate", "listen_private_key", "connect_certificate", "connect_private_key",
                    "enable_mtls", "verify_name_on_connect"}


def test_example_documents_every_model_key():
    model_keys: set[str] = set()
    for t in _documented_structs():
        _struct_keys(t, model_keys)
    example_keys: set[str] = set()
    text = EXAMPLE.read_text()
    _yaml_keys(yaml.safe_load(text), example_keys)
    example_keys |= {k for k in ALTERNATIVE_KEYS if re.search(rf"^#\s+{k}:", text, re.M)}
    assert model_keys - example_keys == set(), "keys of profile.py missing from example.yaml"


def test_example_keys_all_commented():
    # Each key of the model appears in a line preceded by a comment somewhere in the file.
    text = EXAMPLE.read_text()
    model_keys: set[str] = set()
    for t in _documented_structs():
        _struct_keys(t, model_keys)
    lines = text.splitlines()
    for key in model_keys:
        pattern = rf"^#\s+{key}:" if key in ALTERNATIVE_KEYS else rf"^\s*(- )?{key}:"
        rows = [i for i, line in enumerate(lines) if re.match(pattern, line)]
        assert rows, key
        assert any(lines[i - 1].lstrip().startswith("#") or "- #" in lines[i - 1] for i in rows), key


def test_example_backend_section_matches_feetech_config():
    try:
        from crtk_bridge.backends.feetech.backend import Config
    except ImportError as exc:  # the vendor SDK or the backend module is not installed
        pytest.skip(f"feetech backend not importable: {exc}")
    p = load_profile(EXAMPLE)
    cfg = backend_config(p, Config, source=str(EXAMPLE))
    assert cfg.baudrate == 1_000_000
    documented = set(p.backend) - {"type"}
    fields = {f.name for f in msgspec.structs.fields(Config)}
    assert fields - documented == set(), "feetech Config keys missing from example.yaml"


# ---------------------------------------------------------------- error messages


@pytest.fixture
def base() -> dict:
    from .conftest import so101_data

    return so101_data()


def load_bad(tmp_path: Path, data: Any, name: str = "bad.yaml") -> str:
    """Write ``data`` as YAML, load it and validate its backend section and backend-owned joint
    keys (as ``crtk-bridge check`` does), return the ProfileError message (which must name the file)."""
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ProfileError) as info:
        create_backend(load_profile(path), source=str(path))
    message = str(info.value)
    assert str(path) in message, message
    return message


def test_unknown_top_level_key(tmp_path, base):
    base["colour"] = "red"
    msg = load_bad(tmp_path, base)
    assert msg.endswith("bad.yaml: colour: unknown key; valid keys, nearest first: loop, recording, calibration_file, "
                        "transport, description, "
                        "server, joints, backend, backends, shutdown, namespaces, name, safety")


def test_unknown_nested_key(tmp_path, base):
    base["joints"][2]["limits"]["bogus"] = 1.0
    msg = load_bad(tmp_path, base)
    assert "joints[2] (elbow_flex).limits.bogus: unknown key; valid keys, nearest first: " in msg
    valid = msg.rsplit(": ", 1)[1].split(", ")
    assert sorted(valid) == sorted(["position_min", "position_max", "velocity_max", "acceleration_max",
                                    "jerk_max", "effort_max", "stop_deceleration_max"])


def test_unknown_key_in_section(tmp_path, base):
    base["safety"]["servo_timeout"] = 1.0  # the real key is servo_timeout_s
    msg = load_bad(tmp_path, base)
    assert "safety.servo_timeout: unknown key; valid keys, nearest first: servo_timeout_s, " in msg


@pytest.mark.parametrize("where, typo, nearest", [
    (("joints", 2, "calibration"), "ofset", "offset"),
    (("namespaces", 0, "kinematics"), "tip", "tip_frame"),
    (("loop",), "rate", "rate_hz"),
])
def test_unknown_key_lists_the_intended_key_first(tmp_path, base, where, typo, nearest):
    node = base
    for k in where:
        node = node[k]
    node[typo] = 1
    msg = load_bad(tmp_path, base)
    assert f".{typo}: unknown key; valid keys, nearest first: {nearest}," in msg, msg


def test_wrong_type(tmp_path, base):
    base["joints"][0]["limits"]["position_min"] = "minus one"
    msg = load_bad(tmp_path, base)
    assert "joints[0] (shoulder_pan).limits.position_min" in msg
    assert "Expected `float`, got `str`" in msg


def test_wrong_type_of_section(tmp_path, base):
    base["loop"] = [200]
    msg = load_bad(tmp_path, base)
    assert "loop" in msg and "Expected `object`, got `array`" in msg


def test_missing_required_top_level_key(tmp_path, base):
    del base["joints"]
    msg = load_bad(tmp_path, base)
    assert msg.endswith("bad.yaml: Object missing required field `joints`")


def test_missing_required_nested_key(tmp_path, base):
    del base["joints"][1]["limits"]["velocity_max"]
    msg = load_bad(tmp_path, base)
    assert "joints[1] (shoulder_lift).limits: Object missing required field `velocity_max`" in msg


def test_missing_backend_type(tmp_path, base):
    del base["backend"]["type"]
    msg = load_bad(tmp_path, base)
    assert "backend.type: required" in msg


def test_duplicate_joint_name(tmp_path, base):
    base["joints"][3]["name"] = "shoulder_pan"
    msg = load_bad(tmp_path, base)
    assert "joints[3] (shoulder_pan).name: duplicate joint name (also joints[0])" in msg


def test_duplicate_bus_id(tmp_path, base):
    base["joints"][4]["id"] = 2
    msg = load_bad(tmp_path, base)
    assert "joints[4] (wrist_roll).id: bus id 2 is also used by joint 'shoulder_lift'" in msg


def test_namespace_names_unknown_joint(tmp_path, base):
    base["namespaces"][1]["joints"] = ["gripper", "claw"]
    msg = load_bad(tmp_path, base)
    assert "namespaces[1] (so101/gripper).joints: unknown joint 'claw'" in msg
    assert "known: shoulder_pan" in msg


def test_joint_in_no_namespace(tmp_path, base):
    base["namespaces"] = [base["namespaces"][0]]
    msg = load_bad(tmp_path, base)
    assert "namespaces: joint 'gripper' belongs to no namespace" in msg


def test_joint_in_two_namespaces(tmp_path, base):
    base["namespaces"][1]["joints"] = ["gripper", "wrist_roll"]
    msg = load_bad(tmp_path, base)
    assert "joint 'wrist_roll' is already in namespace 'so101'" in msg


def test_home_outside_limits(tmp_path, base):
    base["joints"][5]["home"] = 2.0  # gripper limits are [-0.17, 1.75]
    msg = load_bad(tmp_path, base)
    assert "joints[5] (gripper).home: 2.0 is outside the position limits" in msg


@pytest.mark.parametrize("lo, hi", [(1.0, 1.0), (1.0, -1.0)])
def test_position_min_not_below_max(tmp_path, base, lo, hi):
    base["joints"][0]["limits"].update(position_min=lo, position_max=hi)
    base["joints"][0]["home"] = lo
    msg = load_bad(tmp_path, base)
    assert "joints[0] (shoulder_pan).limits: position_min must be < position_max" in msg


@pytest.mark.parametrize("direction", [0, 2, -2])
def test_direction_not_plus_minus_one(tmp_path, base, direction):
    base["joints"][2]["calibration"]["direction"] = direction
    msg = load_bad(tmp_path, base)
    assert "joints[2] (elbow_flex).calibration.direction: must be 1 or -1" in msg


def test_direction_float_is_a_type_error(tmp_path, base):
    base["joints"][2]["calibration"]["direction"] = -1.5
    msg = load_bad(tmp_path, base)
    assert "joints[2] (elbow_flex).calibration.direction: Expected `int`" in msg


def test_non_positive_velocity_limit(tmp_path, base):
    base["joints"][0]["limits"]["velocity_max"] = 0
    msg = load_bad(tmp_path, base)
    assert "joints[0] (shoulder_pan).limits.velocity_max: must be a finite number > 0" in msg


def test_all_problems_reported_at_once(tmp_path, base):
    base["joints"][0]["calibration"]["direction"] = 0
    base["joints"][1]["id"] = 1
    msg = load_bad(tmp_path, base)
    assert "calibration.direction" in msg and "bus id 1" in msg


def yaml_error(tmp_path: Path, text: str) -> tuple[Path, str]:
    path = tmp_path / "broken.yaml"
    path.write_text(text)
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    return path, str(info.value)


def test_not_yaml(tmp_path):
    path, msg = yaml_error(tmp_path, "name: so101\njoints: [unclosed\n  - {name: a\n")
    # the file, then the line and column (1-based), one line; never PyYAML's "<unicode string>"
    assert msg == (f"{path}: line 3, column 5: not valid YAML: expected ',' or ']', but got '{{' "
                   "(while parsing a flow sequence at line 2)")


def test_yaml_error_names_file_and_line(tmp_path):
    path, msg = yaml_error(tmp_path, "name: so101\nbackend:\n  type: feetech\n   port: /dev/ttyACM0\n")
    assert msg.startswith(f"{path}: line 4, column ") and "not valid YAML" in msg
    assert "<unicode string>" not in msg and "\n" not in msg


def test_yaml_that_is_not_a_mapping(tmp_path):
    path = tmp_path / "list.yaml"
    path.write_text("- a\n- b\n")
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    msg = str(info.value)
    assert str(path) in msg and "expected a mapping at the top level, got list" in msg


def test_empty_file(tmp_path):
    path = tmp_path / "empty.yaml"
    path.write_text("")
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    assert str(path) in str(info.value) and "got NoneType" in str(info.value)


def test_binary_file(tmp_path):
    path = tmp_path / "firmware.bin"
    path.write_bytes(b"\x00\xff\xfe\x80 not text")
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    assert str(path) in str(info.value)


def test_missing_file(tmp_path):
    path = tmp_path / "nope.yaml"
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    msg = str(info.value)
    assert str(path) in msg and "cannot read profile" in msg and "No such file" in msg


def test_directory_instead_of_file(tmp_path):
    with pytest.raises(ProfileError) as info:
        load_profile(tmp_path)
    assert "cannot read profile" in str(info.value)


def test_parse_profile_names_its_source(base):
    base["joints"][0]["limits"]["bogus"] = 1
    with pytest.raises(ProfileError) as info:
        profile_mod.parse_profile(copy.deepcopy(base), "robot.yaml")
    assert str(info.value).startswith("robot.yaml: joints[0] (shoulder_pan).limits.bogus: unknown key; ")


def test_unknown_joint_key_is_the_backends_to_refuse(tmp_path, base):
    base["joints"][0]["bogus"] = 1
    p = profile_mod.parse_profile(copy.deepcopy(base), "robot.yaml")  # core: not its key
    assert p.joints[0].backend["bogus"] == 1
    msg = load_bad(tmp_path, base)  # the feetech backend: not its key either
    assert "joints[0] (shoulder_pan).bogus: unknown key for a feetech backend joint; valid keys, nearest " \
           "first: " in msg
    valid = msg.split("nearest first: ", 1)[1].split(", ")
    assert sorted(valid) == sorted(["home", "limits", "name", "unit", "id", "model", "calibration", "effort_per_amp"])


def test_unknown_joint_key_lists_the_intended_key_first(tmp_path, base):
    base["joints"][1]["modle"] = base["joints"][1].pop("model")
    msg = load_bad(tmp_path, base)
    assert "joints[1] (shoulder_lift).modle: unknown key for a feetech backend joint; valid keys, nearest " \
           "first: model, " in msg


def test_backend_keys_may_be_nested_under_the_joint(base):
    j = base["joints"][0]
    j["backend"] = {k: j.pop(k) for k in ("id", "model", "calibration")}
    p = profile_mod.parse_profile(copy.deepcopy(base), "robot.yaml")
    assert p.joints[0].backend["id"] == 1 and p.joints[0].backend["effort_per_amp"] == 0.95
    assert create_backend(p).joint_keys[0].calibration.range == (700, 3400)
    base["joints"][0]["id"] = 1  # both flat and nested: ambiguous
    with pytest.raises(ProfileError, match=r"^robot\.yaml: joints\[0\] \(shoulder_pan\)\.id: given both"):
        profile_mod.parse_profile(base, "robot.yaml")


def test_a_joint_backend_section_that_is_not_a_mapping_names_file_and_joint(base):
    base["joints"][2]["backend"] = 5
    with pytest.raises(ProfileError, match=r"^robot\.yaml: joints\[2\] \(elbow_flex\)\.backend: expected a "
                                           r"mapping of backend keys, got int$"):
        profile_mod.parse_profile(base, "robot.yaml")


def test_joint_keys_are_validated_by_the_joints_backend(base):
    """The same joint keys are a feetech servo's and a dynamixel servo's, checked against each
    backend's own models: core's schema does not know them."""
    p = profile_mod.parse_profile(copy.deepcopy(base), "robot.yaml")
    with pytest.raises(ProfileError, match=r"joints\[0\] \(shoulder_pan\)\.model: unknown model 'sts3215' "
                       r"for the dynamixel backend"):
        create_backend(msgspec.structs.replace(p, backend={**p.backend, "type": "dynamixel"}), source="robot.yaml")


def test_unknown_backend_type(tmp_path, base):
    base["backend"]["type"] = "kuka"
    path = tmp_path / "kuka.yaml"
    path.write_text(yaml.safe_dump(base))
    p = load_profile(path)  # the common schema accepts any backend name ...
    with pytest.raises(ProfileError) as info:  # ... the registry refuses it
        backend_class(p.backend_type)
    msg = str(info.value)
    assert "backend.type: unknown backend 'kuka'" in msg
    assert "valid backends: " + ", ".join(registry.names()) in msg
    assert set(registry.names()) >= set(BACKENDS)
    assert "feetech" in msg


def test_backend_config_error_names_key(base):
    class Config(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
        port: str
        baudrate: int = 1_000_000

    base["backend"]["baudrate"] = "fast"
    p = profile_mod.parse_profile(base, "so101.yaml")
    with pytest.raises(ProfileError) as info:
        backend_config(p, Config, source="so101.yaml")
    assert str(info.value) == "so101.yaml: backend.baudrate: Expected `int`, got `str`"


@pytest.mark.parametrize("key, value, where", [
    ("servo_timeout_s", 0.0, "(0, 10]"), ("servo_timeout_s", -1.0, "(0, 10]"),
    ("servo_timeout_s", 1e9, "(0, 10]"), ("servo_timeout_s", float("nan"), "(0, 10]"),
    ("servo_step_max", 0.0, "(0, 3.14159]"), ("servo_step_max", float("inf"), "(0, 3.14159]"),
    ("tracking_error_max", -0.1, "(0, 6.28319]"), ("tracking_error_max", 100.0, "(0, 6.28319]"),
    ("cartesian_step_max", 0.0, "(0, 1]"), ("cartesian_rotation_step_max", 4.0, "(0, 3.14159]"),
    ("cartesian_velocity_max", float("inf"), "(0, 5]"), ("cartesian_angular_velocity_max", -1.0, "(0, 6.28319]"),
    ("bus_errors_max", 0, "[1, 100]"), ("bus_errors_max", 10**6, "[1, 100]"),
])
def test_safety_thresholds_are_finite_positive_and_bounded(tmp_path, base, key, value, where):
    """A safety threshold of 0, below 0, NaN, inf or beyond what still guards anything (a 1e9 s
    servo watchdog, a million failed bus cycles before FAULT) is refused, naming the key."""
    base["loop"]["rate_hz"] = 100.0  # bus_errors_max: at most 1 s of failed cycles
    base["safety"][key] = value
    msg = load_bad(tmp_path, base)
    assert f"safety.{key}: {value} is not in {where}" in msg


def test_safety_thresholds_at_their_bounds_load(tmp_path, base):
    base["loop"]["rate_hz"] = 100.0
    base["safety"].update(servo_timeout_s=10.0, bus_errors_max=100, tracking_error_max=0.01)
    path = tmp_path / "edge.yaml"
    path.write_text(yaml.safe_dump(base))
    sf = load_profile(path).safety
    assert (sf.servo_timeout_s, sf.bus_errors_max, sf.tracking_error_max) == (10.0, 100, 0.01)


# ---------------------------------------------------------------- issue 18 item 14: words
def test_a_key_of_fixed_values_lists_them(tmp_path, base):
    base["shutdown"]["action"] = "parc"
    msg = load_bad(tmp_path, base)
    assert msg.endswith("shutdown.action: 'parc' is not a valid value; valid: park, torque_off"), msg


@pytest.mark.parametrize("rate", [0, -5.0, float("nan"), 20000])
def test_a_wrong_loop_rate_is_one_error_not_a_cascade(tmp_path, base, rate):
    """bus_errors_max's bound follows from loop.rate_hz: a wrong rate is said once, not again as a
    bus_errors_max 'not in [1, 1]' the user never got wrong."""
    base["loop"]["rate_hz"] = rate
    msg = load_bad(tmp_path, base)
    assert "loop.rate_hz:" in msg and "(0, 10000]" in msg
    assert "bus_errors_max" not in msg, msg


def test_a_profile_path_not_found_never_stands_for_the_shipped_one_on_hardware(tmp_path, monkeypatch):
    # from a folder without profiles/: --sim (and check) take the shipped profile README names,
    # the daemon on hardware and setup-servos refuse, so a user's own profile typed from the wrong
    # folder never drives the arm with the shipped port and calibration (found by the review)
    from crtk_bridge.profile import resolve_profile_arg, shipped_profiles_dir

    monkeypatch.chdir(tmp_path)
    shipped = shipped_profiles_dir() / "so101.yaml"
    assert resolve_profile_arg("profiles/so101.yaml") == shipped
    assert resolve_profile_arg("so101", hardware=True) == shipped  # named outright: asked for
    with pytest.raises(ProfileError) as exc:
        resolve_profile_arg("profiles/so101.yaml", hardware=True)
    assert "init-profile so101 my_arm.yaml" in str(exc.value) and "--profile so101" in str(exc.value)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    for argv in (["--profile", "profiles/so101.yaml"], ["setup-servos", "--profile", "profiles/so101.yaml", "--yes"]):
        done = subprocess.run([sys.executable, "-P", "-m", "crtk_bridge.cli", *argv], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 1, (argv, done.stderr)
        assert done.stderr.strip().splitlines() == [f"crtk-bridge: {exc.value}"]

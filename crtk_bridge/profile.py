"""Robot profiles: YAML -> typed, validated model.

A profile describes one robot: its backend and bus, its joints (with their limits), how joints
group into CRTK namespaces, the loop rate and the safety thresholds.
``profiles/example.yaml`` documents every key.

Validation is strict: an unknown key, a wrong type or an inconsistent value is a
:class:`~crtk_bridge.errors.ProfileError` whose message names the file, the key path and what
was expected. The ``backend`` section is validated in two steps: the common keys here, the
backend's own keys by the backend's ``Config`` struct (see ``backends/``), so a backend's options
live beside its code. Joints likewise: the generic keys (name, limits, home) are core's; every
other key of a joint (a servo's id, model and tick calibration, a drive's node id...) belongs to
the joint's backend, which validates it (:func:`joint_keys`).
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import msgspec
import yaml

from .errors import ProfileError

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*(/[A-Za-z_][A-Za-z0-9_\-]*)*$")


class _Strict(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    pass


class JointLimits(_Strict, kw_only=True):
    """Joint limits in SI units (rad, rad/s, rad/s^2, rad/s^3, N*m)."""

    position_min: float
    position_max: float
    velocity_max: float
    acceleration_max: float
    jerk_max: float
    effort_max: float | None = None


class Joint(_Strict, kw_only=True):
    """A joint as core sees it. ``backend`` holds the joint's backend-owned keys, written in the
    profile either beside the generic keys (as every shipped profile does) or nested under the
    joint's ``backend:`` key; the backend validates them (``joint_keys``)."""

    name: str
    limits: JointLimits
    home: float = 0.0  # rad: the position `home` moves to
    backend: dict[str, Any] = {}


#: the joint keys core owns; a joint's other keys go to its backend
CORE_JOINT_KEYS = frozenset(Joint.__struct_fields__) - {"backend"}


class KinematicsConfig(_Strict, kw_only=True):
    """Cartesian space of a namespace (pinocchio, see core/kinematics.py)."""

    urdf: str  # path to the URDF, relative to the profile file
    base_frame: str  # reference frame of every pose (a link fixed to the URDF root)
    tip_frame: str  # the moving frame (tool tip)
    ik_tolerance_position: float = 1e-3  # m: IK goals not reached this close are refused
    ik_tolerance_orientation: float = 0.01  # rad


class Namespace(_Strict, kw_only=True):
    name: str  # CRTK namespace, e.g. "so101" or "so101/gripper"
    joints: list[str]
    kinematics: KinematicsConfig | None = None  # cartesian commands and queries; None = joint only


class Loop(_Strict, kw_only=True):
    rate_hz: float = 100.0
    realtime_priority: int = 80  # SCHED_FIFO priority asked for (1-99)
    cpu: int | None = None  # pin the control process to this CPU


class Safety(_Strict, kw_only=True):
    servo_timeout_s: float = 0.5  # servo stream watchdog
    servo_step_max: float = 0.35  # rad: largest servo_jp step from the last setpoint
    tracking_error_max: float = 0.6  # rad: measured vs setpoint before FAULT
    bus_errors_max: int = 5  # consecutive failed cycles before FAULT


class Server(_Strict, kw_only=True):
    socket: str | None = None  # default: $XDG_RUNTIME_DIR/crtk-bridge/<name>.sock


class Profile(_Strict, kw_only=True):
    name: str
    description: str = ""
    backend: dict[str, Any]
    loop: Loop = Loop()
    safety: Safety = Safety()
    server: Server = Server()
    joints: list[Joint]
    namespaces: list[Namespace]

    # --- derived helpers (no state of their own) ---
    @property
    def backend_type(self) -> str:
        return str(self.backend["type"])

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    def joint_index(self, name: str) -> int:
        return self.joint_names.index(name)

    def namespace(self, name: str) -> Namespace:
        for ns in self.namespaces:
            if ns.name == name:
                return ns
        raise KeyError(name)


def _msgspec_error_path(exc: msgspec.ValidationError) -> tuple[str, str]:
    """(key path, message) of a msgspec error: "... - at `$.joints[0].limits`" -> "joints[0].limits"."""
    msg = str(exc)
    m = re.search(r" - at `\$\.?(.*)`$", msg)
    if m:
        return m.group(1), msg[: m.start()]
    return "", msg


def _format_msgspec_error(exc: msgspec.ValidationError) -> str:
    path, msg = _msgspec_error_path(exc)
    return f"{path or '(top level)'}: {msg}" if path or msg != str(exc) else msg


def _check(profile: Profile) -> list[str]:
    """Cross-field checks msgspec cannot express. Returns problems as 'key: message'."""
    problems = []
    if not _NAME_RE.match(profile.name) or "/" in profile.name:
        problems.append(f"name: {profile.name!r} is not a valid robot name (letters, digits, _ -)")
    if "type" not in profile.backend or not isinstance(profile.backend["type"], str):
        problems.append("backend.type: required, a backend name such as 'feetech'")
    if not (0 < profile.loop.rate_hz <= 10000):
        problems.append(f"loop.rate_hz: {profile.loop.rate_hz} is not in (0, 10000]")
    seen: dict[str, int] = {}
    for i, j in enumerate(profile.joints):
        key = f"joints[{i}] ({j.name})"
        if j.name in seen:
            problems.append(f"{key}.name: duplicate joint name (also joints[{seen[j.name]}])")
        seen[j.name] = i
        lim = j.limits
        if not lim.position_min < lim.position_max:
            problems.append(f"{key}.limits: position_min must be < position_max")
        for field in ("velocity_max", "acceleration_max", "jerk_max"):
            v = getattr(lim, field)
            if not (v > 0 and math.isfinite(v)):
                problems.append(f"{key}.limits.{field}: must be a finite number > 0, got {v}")
        if not lim.position_min <= j.home <= lim.position_max:
            problems.append(f"{key}.home: {j.home} is outside the position limits")
    used: dict[str, str] = {}
    ns_names = set()
    if not profile.namespaces:
        problems.append("namespaces: at least one namespace is required")
    for i, ns in enumerate(profile.namespaces):
        key = f"namespaces[{i}] ({ns.name})"
        if not _NAME_RE.match(ns.name):
            problems.append(f"{key}.name: not a valid CRTK namespace")
        if ns.name in ns_names:
            problems.append(f"{key}.name: duplicate namespace")
        ns_names.add(ns.name)
        if not ns.joints:
            problems.append(f"{key}.joints: a namespace needs at least one joint")
        for jn in ns.joints:
            if jn not in seen:
                problems.append(f"{key}.joints: unknown joint {jn!r} (known: {', '.join(seen)})")
            elif jn in used:
                problems.append(f"{key}.joints: joint {jn!r} is already in namespace {used[jn]!r}")
            else:
                used[jn] = ns.name
    for jn in seen:
        if jn not in used:
            problems.append(f"namespaces: joint {jn!r} belongs to no namespace")
    return problems


def _split_joint_keys(data: dict) -> dict:
    """Move each joint's non-core keys into its ``backend`` mapping (a copy; ``data`` is kept)."""
    joints = data.get("joints")
    if not isinstance(joints, list):
        return data  # msgspec reports the type error with its key path
    out = []
    for i, j in enumerate(joints):
        if not isinstance(j, dict):
            out.append(j)
            continue
        nested = j.get("backend", {})
        if not isinstance(nested, dict):
            raise ProfileError(f"joints[{i}].backend: expected a mapping of backend keys, "
                               f"got {type(nested).__name__}")
        flat = {k: v for k, v in j.items() if k not in CORE_JOINT_KEYS and k != "backend"}
        both = sorted(set(flat) & set(nested))
        if both:
            raise ProfileError(f"joints[{i}].{both[0]}: given both beside the joint's keys and under "
                               f"its backend: section")
        out.append({**{k: v for k, v in j.items() if k in CORE_JOINT_KEYS}, "backend": {**flat, **nested}})
    return {**data, "joints": out}


def parse_profile(data: Any, source: str = "<profile>") -> Profile:
    """Validate already-parsed YAML data. Raises ProfileError naming ``source`` and the key."""
    if not isinstance(data, dict):
        raise ProfileError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    try:
        profile = msgspec.convert(_split_joint_keys(data), Profile)
    except msgspec.ValidationError as exc:
        raise ProfileError(f"{source}: {_format_msgspec_error(exc)}") from exc
    problems = _check(profile)
    if problems:
        raise ProfileError(f"{source}: " + "; ".join(problems))
    return profile


def load_profile(path: str | Path) -> Profile:
    """Read and validate a profile file. Blocks on file I/O. Raises ProfileError."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ProfileError(f"{path}: cannot read profile: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ProfileError(f"{path}: not a text (UTF-8) file: {exc.reason} at byte {exc.start}") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ProfileError(f"{path}: not valid YAML: {exc}") from exc
    profile = parse_profile(data, str(path))
    # URDF paths are relative to the profile file: resolve them now, so the daemon can chdir
    namespaces = []
    for i, ns in enumerate(profile.namespaces):
        k = ns.kinematics
        if k is not None:
            urdf = (path.parent / k.urdf).resolve()
            if not urdf.is_file():
                raise ProfileError(f"{path}: namespaces[{i}] ({ns.name}).kinematics.urdf: no file {urdf}")
            ns = msgspec.structs.replace(ns, kinematics=msgspec.structs.replace(k, urdf=str(urdf)))
        namespaces.append(ns)
    return msgspec.structs.replace(profile, namespaces=namespaces)


def backend_config(profile: Profile, config_type: type, source: str = "<profile>") -> Any:
    """Convert the profile's ``backend`` section into a backend's own ``Config`` struct."""
    data = {k: v for k, v in profile.backend.items() if k != "type"}
    try:
        return msgspec.convert(data, config_type)
    except msgspec.ValidationError as exc:
        raise ProfileError(f"{source}: backend.{_format_msgspec_error(exc)}") from exc


def joint_keys(profile: Profile, joint_type: type, owner: str, source: str = "<profile>") -> list[Any]:
    """Convert every joint's backend-owned keys into the backend's ``joint_type`` struct.

    ``owner`` names the backend in messages. Raises one ProfileError listing every joint's problem,
    each with its key path as written in the profile (``joints[2] (elbow_flex).calibration``)."""
    valid = [f for f in joint_type.__struct_fields__]
    out, problems = [], []
    for i, j in enumerate(profile.joints):
        key = f"joints[{i}] ({j.name})"
        unknown = sorted(set(j.backend) - set(valid))
        for k in unknown:
            problems.append(f"{key}.{k}: unknown joint key (core keys: {', '.join(sorted(CORE_JOINT_KEYS))}; "
                            f"{owner} keys: {', '.join(valid) or 'none'})")
        if unknown:
            continue
        try:
            out.append(msgspec.convert(j.backend, joint_type))
        except msgspec.ValidationError as exc:
            path, msg = _msgspec_error_path(exc)
            problems.append(f"{key}{'.' + path if path else ''}: {msg}")
    if problems:
        raise ProfileError(f"{source}: " + "; ".join(problems))
    return out

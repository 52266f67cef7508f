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

import difflib
import math
import re
from pathlib import Path
from typing import Any, Literal

import msgspec
import yaml

from .errors import ProfileError
# the Zenoh lease's bounds: a module of their own, which crtk-ctl imports without this one
from .zenoh_lease import (  # noqa: F401 - re-exported
    ZENOH_KEEP_ALIVE_PER_LEASE, ZENOH_LEASE_MS_DEFAULT, ZENOH_LEASE_MS_MAX, ZENOH_LEASE_MS_MIN, zenoh_lease_problem)

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
    #: rad/s^2: what a stop (hold, pause, a stream's watchdog, client loss, the shutdown's first
    #: stop) brakes at, jerk-unlimited; None: :func:`stop_deceleration`'s default
    stop_deceleration_max: float | None = None


#: the default stop deceleration, in multiples of ``acceleration_max`` (bounded by the hardware)
STOP_DECELERATION_FACTOR = 4.0


def stop_deceleration(limits: JointLimits, hardware_max: float = math.inf) -> float:
    """rad/s^2 a stop brakes this joint at: ``limits.stop_deceleration_max`` when the profile gives
    it, else ``STOP_DECELERATION_FACTOR * acceleration_max`` bounded by ``hardware_max`` (what the
    backend says the joint can do, :meth:`~crtk_bridge.core.actuator.Actuator.deceleration_limit`).
    A trajectory's acceleration is chosen for smooth motion; a stop needs the shortest distance
    the hardware allows (docs/protocol.md, Safety: stopping distances)."""
    if limits.stop_deceleration_max is not None:
        return limits.stop_deceleration_max
    return min(STOP_DECELERATION_FACTOR * limits.acceleration_max, hardware_max)


class Joint(_Strict, kw_only=True):
    """A joint as core sees it. ``backend`` holds the joint's backend-owned keys, written in the
    profile either beside the generic keys (as every shipped profile does) or nested under the
    joint's ``backend:`` key; the backend validates them (``joint_keys``)."""

    name: str
    #: what the joint's numbers are in: ``rad`` (revolute: positions rad, velocities rad/s, efforts
    #: N*m) or ``m`` (prismatic: m, m/s, N). Reported per joint by ``list`` (``units``) so clients
    #: label them; a backend whose joint is one kind refuses the other (a gripper's opening is m)
    unit: Literal["rad", "m"] = "rad"
    limits: JointLimits
    #: rad (m): the position `home` moves to. No default: a joint's zero is not always a safe pose (a
    #: UR's zero is the arm stretched out), so `home` is refused while a joint has none
    home: float | None = None
    backend: dict[str, Any] = {}


#: the joint keys core owns; a joint's other keys go to its backend
CORE_JOINT_KEYS = frozenset(Joint.__struct_fields__) - {"backend"}


def joint_bus_id(joint: Joint) -> int | None:
    """The joint's address on its bus as its backend keys give it: a servo's ``id``, a CiA 402
    drive's ``node_id``; None for a backend without one (a UR arm). Not validated here."""
    for key in ("id", "node_id"):
        value = joint.backend.get(key)
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    return None


class KinematicsConfig(_Strict, kw_only=True):
    """Cartesian space of a namespace (pinocchio, see core/kinematics.py)."""

    urdf: str  # path to the URDF, relative to the profile file (else to the shipped profiles)
    base_frame: str  # reference frame of every pose (a link fixed to the URDF root)
    tip_frame: str  # the moving frame (tool tip)
    ik_tolerance_position: float = 1e-3  # m: IK goals not reached this close are refused
    ik_tolerance_orientation: float = 0.01  # rad


class Namespace(_Strict, kw_only=True):
    name: str  # CRTK namespace, e.g. "so101" or "so101/gripper"
    joints: list[str]
    kinematics: KinematicsConfig | None = None  # cartesian commands and queries; None = joint only
    backend: str | None = None  # the bus (a name in ``backends``) its joints live on; several buses only


class Loop(_Strict, kw_only=True):
    rate_hz: float = 100.0
    realtime_priority: int = 80  # SCHED_FIFO priority asked for (1-99)
    cpu: int | None = None  # pin the control process to this CPU
    # interpolate_jp: "linear" to each goal over the command period, or "smooth": that averaged
    # over the command period (velocity-continuous, half a period more latency), or "predict":
    # smooth toward each goal extrapolated by one step (no added latency; core/motion.py)
    interpolation: Literal["linear", "smooth", "predict"] = "linear"


class Safety(_Strict, kw_only=True):
    servo_timeout_s: float = 0.5  # servo stream watchdog
    servo_step_max: float = 0.35  # rad: largest servo_jp step from the last setpoint
    # native cartesian backends (core/native_cartesian.py): servo_cp / interpolate_cp steps, twists
    cartesian_step_max: float = 0.05  # m: largest tip translation from the last pose
    cartesian_rotation_step_max: float = 0.35  # rad: largest tip rotation from the last pose
    cartesian_velocity_max: float = 0.25  # m/s: largest linear speed of a servo_cv / interpolate_cv twist
    cartesian_angular_velocity_max: float = 1.0  # rad/s: largest angular speed of a twist
    tracking_error_max: float = 0.6  # rad: measured vs setpoint before FAULT
    bus_errors_max: int = 5  # consecutive failed cycles before FAULT


SHUTDOWN_TIMEOUT_MAX_S = 10.0  # the systemd unit's TimeoutStopSec leaves room for this plus clean-up


class Shutdown(_Strict, kw_only=True):
    """What the daemon does with a robot that is ENABLED (or PAUSED) when it stops (SIGTERM,
    SIGINT, loss of the front process): ``torque_off`` at once (an arm without brakes drops), or
    ``park``: a jerk-limited move of every torqued joint to ``rest`` within ``timeout_s``, then
    torque off (at once if the move faults or runs out of time)."""

    action: Literal["torque_off", "park"] = "torque_off"
    timeout_s: float = 4.0  # s: the park's time limit
    rest: dict[str, float] = {}  # joint name -> rad: the rest pose (required for park); others stay put


#: longest black box window (s): the front keeps this many seconds of every cycle in memory
BLACKBOX_MAX_S = 600.0
#: bounds of recording.rotate_s (s): one bag per second at most, one a day at least
ROTATE_MIN_S, ROTATE_MAX_S = 1.0, 86400.0


class Recording(_Strict, kw_only=True):
    """Recording and the black box (docs/recording.md)."""

    blackbox_s: float = 30.0  # s of every cycle kept in memory, written on FAULT; 0: no black box
    blackbox_dir: str | None = None  # default: $XDG_STATE_HOME (~/.local/state)/crtk-bridge/blackbox
    dir: str | None = None  # record every cycle from start-up into this folder (also: crtk-bridge --record)
    rotate_s: float = 300.0  # ...a new bag every rotate_s seconds of cycles


class Server(_Strict, kw_only=True):
    socket: str | None = None  # default: $XDG_RUNTIME_DIR/crtk-bridge/<name>.sock


class ZenohTls(_Strict, kw_only=True):
    """Zenoh's ``transport/link/tls`` keys: PEM files (paths relative to the profile file)."""

    root_ca_certificate: str | None = None  # CA that signed the peers' certificates
    listen_certificate: str | None = None  # this daemon's certificate, for tls/ listen endpoints
    listen_private_key: str | None = None
    connect_certificate: str | None = None  # mutual TLS: this daemon's certificate when connecting
    connect_private_key: str | None = None
    enable_mtls: bool = False  # require a certificate from whoever connects (mutual TLS)
    verify_name_on_connect: bool = True  # the router's certificate must name the host connected to


class ZenohTransport(_Strict, kw_only=True):
    """The Zenoh transport (transport/zenoh_session.py; docs/zenoh.md). Present = on."""

    mode: Literal["peer", "client"] = "peer"
    connect: list[str] = []  # routers or peers to join, e.g. tcp/127.0.0.1:7447
    # loopback only unless tls + access_control; default: one loopback port the system picks
    listen: list[str] = msgspec.field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    connect_timeout_s: float = 5.0  # how long start-up waits for each connect endpoint
    # this session's link lease (ms): peers drop it after this much silence; keep-alives every lease/4
    lease_ms: int = ZENOH_LEASE_MS_DEFAULT
    ros_domain_id: int = 0  # ROS_DOMAIN_ID of the ROS 2 graph (the first key segment)
    publish_rate_hz: float | None = None  # ROS topics' rate; default: the loop rate
    tls: ZenohTls | None = None
    access_control: dict[str, Any] | None = None  # Zenoh's access_control section, verbatim


class Transport(_Strict, kw_only=True):
    zenoh: ZenohTransport | None = None  # off unless present (or --zenoh-connect / --zenoh-listen)


class Profile(_Strict, kw_only=True):
    name: str
    description: str = ""
    backend: dict[str, Any] | None = None  # one bus: its backend section
    backends: dict[str, dict[str, Any]] | None = None  # several buses, by name (one loop serves all)
    loop: Loop = Loop()
    safety: Safety = Safety()
    server: Server = Server()
    transport: Transport = Transport()
    shutdown: Shutdown = Shutdown()
    recording: Recording = Recording()
    joints: list[Joint]
    namespaces: list[Namespace]
    # a YAML file (relative to the profile) of joint name -> calibration keys, replacing those
    # joints' `calibration`; `crtk-ctl calibrate` writes it (docs/calibration.md)
    calibration_file: str | None = None

    # --- derived helpers (no state of their own) ---
    @property
    def backend_type(self) -> str:
        """The backend's name; with several buses, their distinct names joined by '+'."""
        if self.backends is None:
            return str(self.backend["type"])
        return "+".join(dict.fromkeys(str(b["type"]) for b in self.backends.values()))

    @property
    def bus_names(self) -> list[str]:
        """The buses' names (``backends`` keys); empty for a one-bus profile."""
        return list(self.backends or ())

    def namespace_bus(self, ns: Namespace) -> str:
        """The bus a namespace's joints live on (several buses only)."""
        if ns.backend is not None:
            return ns.backend
        return next(iter(self.backends))  # validated: only one bus then

    def bus_profile(self, bus: str) -> Profile:
        """A one-bus profile of bus ``bus``: its backend section, its namespaces and their joints
        (in the robot's joint order). The robot's name, loop and safety are kept, so its backend's
        messages name the robot."""
        spaces = [ns for ns in self.namespaces if self.namespace_bus(ns) == bus]
        names = {j for ns in spaces for j in ns.joints}
        return msgspec.structs.replace(
            self, backend=self.backends[bus], backends=None,
            joints=[j for j in self.joints if j.name in names],
            namespaces=[msgspec.structs.replace(ns, backend=None) for ns in spaces])

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


_PATH_TOKEN = re.compile(r"\.?([^.\[\]]+)|\[(\d+)\]")


def _named_path(path: str, data: Any) -> str:
    """``joints[0].limits`` -> ``joints[0] (shoulder_pan).limits``: list items that have a ``name``
    in ``data`` are named, so a message points at the joint or namespace, not only an index."""
    out = []
    node = data
    for m in _PATH_TOKEN.finditer(path):
        key, index = m.group(1), m.group(2)
        if index is None:
            out.append(("." if out else "") + key)
            node = node.get(key) if isinstance(node, dict) else None
            continue
        out.append(f"[{index}]")
        node = node[int(index)] if isinstance(node, list) and int(index) < len(node) else None
        if isinstance(node, dict) and isinstance(node.get("name"), str):
            out.append(f" ({node['name']})")
    return "".join(out)


def _struct_keys_at(root: type, path: str) -> list[str] | None:
    """The keys the struct at ``path`` (a msgspec error path below ``root``) accepts, or None."""
    info = _type_at(root, path)
    if isinstance(info, msgspec.inspect.StructType):
        return [f.encode_name for f in info.fields]
    return None


def _literal_values_at(root: type, path: str) -> list[str] | None:
    """The values a key of a fixed set of values (a ``Literal``) at ``path`` accepts, or None."""
    info = _type_at(root, path)
    if isinstance(info, msgspec.inspect.LiteralType):
        return [str(v) for v in info.values]
    return None


def _type_at(root: type, path: str) -> Any:
    """msgspec's type info of the value at ``path`` (a msgspec error path below ``root``), an
    optional one unwrapped, or None."""
    info: Any = msgspec.inspect.type_info(root)
    for m in _PATH_TOKEN.finditer(path):
        while isinstance(info, msgspec.inspect.UnionType):  # optional sections: X | None
            inner = [t for t in info.types if not isinstance(t, msgspec.inspect.NoneType)]
            if len(inner) != 1:
                return None
            info = inner[0]
        if m.group(2) is not None:
            info = getattr(info, "item_type", None)
        elif isinstance(info, msgspec.inspect.StructType):
            info = next((f.type for f in info.fields if f.encode_name == m.group(1)), None)
        else:
            return None
    while isinstance(info, msgspec.inspect.UnionType):
        inner = [t for t in info.types if not isinstance(t, msgspec.inspect.NoneType)]
        info = inner[0] if len(inner) == 1 else None
    return info


def unknown_key_message(key: str, valid: list[str], owner: str = "") -> str:
    """'unknown key[ for OWNER]; valid keys, nearest first: a, b, c' (nearest by difflib's
    similarity ratio, so a typo's intended key comes first)."""
    ranked = sorted(valid, key=lambda k: -difflib.SequenceMatcher(None, key, k).ratio())
    return f"unknown key{' for ' + owner if owner else ''}; valid keys, nearest first: {', '.join(ranked)}"


def _format_msgspec_error(exc: msgspec.ValidationError, data: Any = None, root: type | None = None) -> str:
    """msgspec's "... - at `$.joints[0].limits`" as "joints[0] (shoulder_pan).limits: ...": the
    profile's key path with list items named; an unknown key lists the valid ones, nearest first."""
    path, text = _msgspec_error_path(exc)
    unknown = re.fullmatch(r"Object contains unknown field `(.*)`", text)
    if unknown and root is not None:
        valid = _struct_keys_at(root, path)
        if valid is not None:
            key = unknown.group(1)
            named = _named_path(path, data)
            return f"{named + '.' if named else ''}{key}: {unknown_key_message(key, valid)}"
    wrong = re.fullmatch(r"Invalid enum value (.*)", text)
    if wrong and root is not None:
        valid = _literal_values_at(root, path)
        if valid is not None:  # say what the key takes (shutdown.action: torque_off or park)
            text = f"{wrong.group(1)} is not a valid value; valid: {', '.join(valid)}"
    if not path and text == str(exc):
        return text
    return f"{_named_path(path, data) or '(top level)'}: {text}"


def _check(profile: Profile) -> list[str]:
    """Cross-field checks msgspec cannot express. Returns problems as 'key: message'."""
    problems = []
    if not _NAME_RE.match(profile.name) or "/" in profile.name:
        problems.append(f"name: {profile.name!r} is not a valid robot name (letters, digits, _ -)")
    if (profile.backend is None) == (profile.backends is None):
        problems.append("backend: required: `backend` for a robot on one bus, or `backends` (by name) "
                        "for several, not both")
    buses = {"backend": profile.backend} if profile.backend is not None else {
        f"backends.{name}": section for name, section in (profile.backends or {}).items()}
    if profile.backends is not None and not profile.backends:
        problems.append("backends: name at least one bus")
    for key, section in buses.items():
        if key != "backend" and (not _NAME_RE.match(key[9:]) or "/" in key[9:]):
            problems.append(f"{key}: {key[9:]!r} is not a valid bus name (letters, digits, _ -)")
        if "type" not in section or not isinstance(section["type"], str):
            problems.append(f"{key}.type: required, a backend name such as 'feetech'")
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
        for field in ("velocity_max", "acceleration_max", "jerk_max", "stop_deceleration_max"):
            v = getattr(lim, field)
            if v is not None and not (v > 0 and math.isfinite(v)):
                problems.append(f"{key}.limits.{field}: must be a finite number > 0, got {v}")
        if j.home is not None and not lim.position_min <= j.home <= lim.position_max:
            problems.append(f"{key}.home: {j.home} is outside the position limits "
                            f"[{lim.position_min}, {lim.position_max}]")
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
    problems += _check_buses(profile)
    problems += _check_safety(profile)
    problems += _check_shutdown(profile)
    if not 0.0 <= profile.recording.blackbox_s <= BLACKBOX_MAX_S:
        problems.append(f"recording.blackbox_s: {profile.recording.blackbox_s} is not in [0, {BLACKBOX_MAX_S:g}] "
                        "(seconds of every cycle kept for the black box; 0: none)")
    if not ROTATE_MIN_S <= profile.recording.rotate_s <= ROTATE_MAX_S:
        problems.append(f"recording.rotate_s: {profile.recording.rotate_s} is not in [{ROTATE_MIN_S:g}, "
                        f"{ROTATE_MAX_S:g}] (seconds of cycles per bag of the start-up recording)")
    problems += _check_zenoh(profile.transport.zenoh)
    return problems


#: safety.servo_timeout_s at most: a stream silent longer than this is no stream a watchdog guards
SERVO_TIMEOUT_MAX_S = 10.0
#: safety.bus_errors_max at most this many seconds of failed bus cycles (at loop.rate_hz)
BUS_ERRORS_MAX_S = 1.0


def _check_safety(profile: Profile) -> list[str]:
    """Every safety threshold a finite positive number, within what still guards something."""
    sf, problems = profile.safety, []

    def bounded(key: str, value: float, high: float, unit: str) -> None:
        if not (math.isfinite(value) and 0 < value <= high):
            problems.append(f"safety.{key}: {value} is not in (0, {high:g}] {unit}")

    bounded("servo_timeout_s", sf.servo_timeout_s, SERVO_TIMEOUT_MAX_S, "s (the servo stream watchdog)")
    bounded("servo_step_max", sf.servo_step_max, math.pi, "rad")
    bounded("tracking_error_max", sf.tracking_error_max, 2 * math.pi, "rad")
    bounded("cartesian_step_max", sf.cartesian_step_max, 1.0, "m")
    bounded("cartesian_rotation_step_max", sf.cartesian_rotation_step_max, math.pi, "rad")
    bounded("cartesian_velocity_max", sf.cartesian_velocity_max, 5.0, "m/s")
    bounded("cartesian_angular_velocity_max", sf.cartesian_angular_velocity_max, 2 * math.pi, "rad/s")
    if not 0 < profile.loop.rate_hz <= 10000:
        return problems  # loop.rate_hz is said to be wrong; the bound below follows from it
    most = max(1, int(BUS_ERRORS_MAX_S * profile.loop.rate_hz))
    if not 1 <= sf.bus_errors_max <= most:
        problems.append(f"safety.bus_errors_max: {sf.bus_errors_max} is not in [1, {most}] (at most "
                        f"{BUS_ERRORS_MAX_S:g} s of failed bus cycles at loop.rate_hz {profile.loop.rate_hz:g})")
    return problems


def _check_buses(profile: Profile) -> list[str]:
    """Each namespace's joints live on one bus: a namespace names its bus when there are several."""
    problems = []
    names = profile.bus_names
    used = set()
    for i, ns in enumerate(profile.namespaces):
        key = f"namespaces[{i}] ({ns.name}).backend"
        if ns.backend is None:
            if len(names) > 1:
                problems.append(f"{key}: required with several buses, one of {', '.join(names)}")
        elif profile.backends is None:
            problems.append(f"{key}: only with `backends` (several buses); this profile has one `backend`")
        elif ns.backend not in profile.backends:
            problems.append(f"{key}: unknown bus {ns.backend!r} (backends: {', '.join(names)})")
        used.add(ns.backend if ns.backend is not None else (names[0] if len(names) == 1 else None))
    for name in names:
        if name not in used:
            problems.append(f"backends.{name}: no namespace lives on this bus")
    return problems


def _check_zenoh(z: ZenohTransport | None) -> list[str]:
    """Numbers of transport.zenoh; its endpoints are checked where the session opens
    (transport/zenoh_session.py: loopback unless TLS and access control)."""
    if z is None:
        return []
    problems = []
    if z.ros_domain_id < 0:
        problems.append(f"transport.zenoh.ros_domain_id: must be >= 0, got {z.ros_domain_id}")
    for key in ("connect_timeout_s", "publish_rate_hz"):
        v = getattr(z, key)
        if v is not None and not (v > 0 and math.isfinite(v)):
            problems.append(f"transport.zenoh.{key}: must be a finite number > 0, got {v}")
    lease = zenoh_lease_problem(z.lease_ms)
    if lease:
        problems.append(f"transport.zenoh.lease_ms: {lease}")
    return problems


def _check_shutdown(profile: Profile) -> list[str]:
    sd = profile.shutdown
    problems = []
    if not (0 < sd.timeout_s <= SHUTDOWN_TIMEOUT_MAX_S):
        problems.append(f"shutdown.timeout_s: {sd.timeout_s} is not in (0, {SHUTDOWN_TIMEOUT_MAX_S:g}]")
    by_name = {j.name: j for j in profile.joints}
    for name, value in sd.rest.items():
        j = by_name.get(name)
        if j is None:
            problems.append(f"shutdown.rest.{name}: unknown joint (known: {', '.join(by_name)})")
        elif not j.limits.position_min <= value <= j.limits.position_max:
            problems.append(f"shutdown.rest.{name}: {value} is outside the position limits "
                            f"[{j.limits.position_min}, {j.limits.position_max}]")
    if sd.action == "park" and not sd.rest:
        problems.append("shutdown.rest: park needs a rest pose (joint name: rad)")
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
            raise ProfileError(f"{_named_path(f'joints[{i}]', data)}.backend: expected a mapping of "
                               f"backend keys, got {type(nested).__name__}")
        flat = {k: v for k, v in j.items() if k not in CORE_JOINT_KEYS and k != "backend"}
        both = sorted(set(flat) & set(nested))
        if both:
            raise ProfileError(f"{_named_path(f'joints[{i}]', data)}.{both[0]}: given both beside the "
                               f"joint's keys and under its backend: section")
        out.append({**{k: v for k, v in j.items() if k in CORE_JOINT_KEYS}, "backend": {**flat, **nested}})
    return {**data, "joints": out}


def parse_profile(data: Any, source: str = "<profile>") -> Profile:
    """Validate already-parsed YAML data. Raises ProfileError naming ``source`` and the key."""
    if not isinstance(data, dict):
        raise ProfileError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    try:
        profile = msgspec.convert(_split_joint_keys(data), Profile)
    except ProfileError as exc:  # from _split_joint_keys: the key, but not yet the file
        raise ProfileError(f"{source}: {exc}") from exc
    except msgspec.ValidationError as exc:
        raise ProfileError(f"{source}: {_format_msgspec_error(exc, data, Profile)}") from exc
    problems = _check(profile)
    if problems:
        raise ProfileError(f"{source}: " + "; ".join(problems))
    return profile


def _yaml_error_text(exc: yaml.MarkedYAMLError) -> str:
    """'line 3, column 5: not valid YAML: expected ...' (1-based, as editors count): one line with
    the place, instead of PyYAML's several lines naming "<unicode string>"."""
    mark = exc.problem_mark or exc.context_mark
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
    text = f"{where}not valid YAML: {exc.problem or exc.context or 'syntax error'}"
    if exc.problem and exc.context:
        started = f" at line {exc.context_mark.line + 1}" if exc.context_mark else ""
        text += f" ({exc.context}{started})"
    return text


def _load_yaml(path: Path, text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        raise ProfileError(f"{path}: {_yaml_error_text(exc)}") from exc
    except yaml.YAMLError as exc:
        raise ProfileError(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from exc


def shipped_profiles_dir() -> Path:
    """The folder of the shipped profiles and their URDFs: ``crtk_bridge/profiles`` in an installed
    package (setup.py installs the repository's ``profiles/`` there), else the checkout's
    ``profiles/`` beside the package (a source tree, an editable install)."""
    here = Path(__file__).resolve().parent
    installed = here / "profiles"
    for folder in (installed, here.parent / "profiles"):
        if (folder / "example.yaml").is_file():
            return folder
    return installed


def shipped_profile_names() -> list[str]:
    """The names ``--profile NAME`` and ``init-profile NAME`` accept: each shipped profile's file stem."""
    return sorted(p.stem for p in shipped_profiles_dir().glob("*.yaml"))


def resolve_profile_arg(arg: str | Path, hardware: bool = False) -> Path:
    """The profile file a ``--profile`` argument means: the file itself when it exists; else a
    shipped profile, named bare (``so101``) or as README writes it from the clone's root
    (``profiles/so101.yaml``), so those commands work from any folder once the package is
    installed; else the path as given (loading it then says the file is missing).

    ``hardware``: the caller drives real hardware (the daemon without ``--sim``, ``setup-servos``).
    There a path that is not found never stands for the shipped profile: a user who typed their
    own profile's path from the wrong folder would otherwise drive the arm with the shipped port
    and calibration. Raises :class:`ProfileError` naming both ways out; a bare name still asks
    for the shipped profile outright."""
    path = Path(arg).expanduser()
    if path.exists():
        return path
    text = str(arg)
    if "/" not in text and not text.endswith((".yaml", ".yml")):
        name = f"{text}.yaml"
    elif len(path.parts) == 2 and path.parts[0] == "profiles":
        name = path.name
        if hardware and (shipped_profiles_dir() / name).is_file():
            raise ProfileError(
                f"--profile {text}: no such file in {Path.cwd()}; on hardware give your own profile's "
                f"path (`crtk-bridge init-profile {path.stem} my_arm.yaml` writes one) or name the shipped "
                f"profile outright (`--profile {path.stem}`); with --sim the shipped one is used")
    else:
        return path
    shipped = shipped_profiles_dir() / name
    return shipped if shipped.is_file() else path


def profile_relative_file(profile_path: str | Path, name: str) -> tuple[Path, Path | None]:
    """A file a profile names (a URDF), relative to the profile file first and to the shipped
    profiles second (a copied shipped profile keeps its URDF). Returns (the path relative to the
    profile, the existing file or None)."""
    own = (Path(profile_path).parent / name).resolve()
    if own.is_file():
        return own, own
    if not Path(name).is_absolute():
        shipped = (shipped_profiles_dir() / name).resolve()
        if shipped.is_file():
            return own, shipped
    return own, None


def calibration_file_path(profile_path: str | Path, name: str) -> Path:
    """Where a profile's ``calibration_file`` is: relative to the profile file."""
    return (Path(profile_path).parent / name).resolve()


def _with_calibration_file(data: dict, path: Path) -> dict:
    """``data`` with the joints' ``calibration`` replaced by the calibration file's (a copy). A
    file not written yet (no calibration so far) changes nothing. Raises ProfileError naming the
    file and the key."""
    name = data["calibration_file"]
    if not isinstance(name, str):
        raise ProfileError(f"{path}: calibration_file: expected a file name, got {type(name).__name__}")
    cal_path = calibration_file_path(path, name)
    try:
        text = cal_path.read_text()
    except FileNotFoundError:
        return data
    except (OSError, UnicodeDecodeError) as exc:
        raise ProfileError(f"{path}: calibration_file: cannot read {cal_path}: {exc}") from exc
    cal = _load_yaml(cal_path, text)
    if cal is None:
        return data
    if not isinstance(cal, dict) or not all(isinstance(v, dict) for v in cal.values()):
        raise ProfileError(f"{cal_path}: expected a mapping of joint name -> calibration keys "
                           f"(offset, direction, range...)")
    joints = data.get("joints")
    names = [j.get("name") for j in joints if isinstance(j, dict)] if isinstance(joints, list) else []
    unknown = sorted(set(map(str, cal)) - set(names))
    if unknown:
        raise ProfileError(f"{cal_path}: {unknown[0]}: no joint of that name in {path} (joints: {', '.join(map(str, names))})")
    out = []
    for j in joints:
        if isinstance(j, dict) and j.get("name") in cal:
            nested = j.get("backend")
            if isinstance(nested, dict) and "calibration" in nested:
                j = {**j, "backend": {**nested, "calibration": cal[j["name"]]}}
            else:
                j = {**j, "calibration": cal[j["name"]]}
        out.append(j)
    return {**data, "joints": out}


def load_profile(path: str | Path) -> Profile:
    """Read and validate a profile file. Blocks on file I/O. Raises ProfileError."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ProfileError(f"{path}: cannot read profile: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ProfileError(f"{path}: not a text (UTF-8) file: {exc.reason} at byte {exc.start}") from exc
    data = _load_yaml(path, text)
    if isinstance(data, dict) and data.get("calibration_file") is not None:
        data = _with_calibration_file(data, path)
    profile = parse_profile(data, str(path))
    # URDF paths are relative to the profile file (else to the shipped profiles): resolve them now,
    # so the daemon can chdir
    namespaces = []
    for i, ns in enumerate(profile.namespaces):
        k = ns.kinematics
        if k is not None:
            own, urdf = profile_relative_file(path, k.urdf)
            if urdf is None:
                raise ProfileError(f"{path}: namespaces[{i}] ({ns.name}).kinematics.urdf: no file {own}, nor "
                                   f"{k.urdf} among the shipped profiles' files ({shipped_profiles_dir()}): "
                                   f"give the URDF's path, relative to the profile file")
            ns = msgspec.structs.replace(ns, kinematics=msgspec.structs.replace(k, urdf=str(urdf)))
        namespaces.append(ns)
    profile = msgspec.structs.replace(profile, namespaces=namespaces)
    tls = profile.transport.zenoh.tls if profile.transport.zenoh is not None else None
    if tls is not None:  # PEM paths are relative to the profile file, as URDFs are
        files = {f: str((path.parent / getattr(tls, f)).resolve()) for f in tls.__struct_fields__
                 if isinstance(getattr(tls, f), str)}
        zenoh = msgspec.structs.replace(profile.transport.zenoh, tls=msgspec.structs.replace(tls, **files))
        profile = msgspec.structs.replace(profile, transport=Transport(zenoh=zenoh))
    return profile


def backend_config(profile: Profile, config_type: type, source: str = "<profile>", *, owner: str = "",
                   required: dict[str, str] | None = None) -> Any:
    """Convert the profile's ``backend`` section into a backend's own ``Config`` struct.

    msgspec reports unknown and missing fields "at $" (no key name), so an unknown key (listing
    ``owner``'s valid ones, nearest first) and each key of ``required`` (key -> what to give) are
    named here first. Raises ProfileError."""
    given = set(profile.backend) - {"type"}
    fields = config_type.__struct_fields__
    for key in sorted(given - set(fields)):
        raise ProfileError(f"{source}: backend.{key}: {unknown_key_message(key, ['type', *fields], owner)}")
    for key, what in (required or {}).items():
        if key not in given:
            raise ProfileError(f"{source}: backend.{key}: required, {what}")
    data = {k: v for k, v in profile.backend.items() if k != "type"}
    try:
        return msgspec.convert(data, config_type)
    except msgspec.ValidationError as exc:
        raise ProfileError(f"{source}: backend.{_format_msgspec_error(exc, data, config_type)}") from exc


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
            problems.append(f"{key}.{k}: "
                            f"{unknown_key_message(k, [*sorted(CORE_JOINT_KEYS), *valid], f'a {owner} joint')}")
        if unknown:
            continue
        try:
            out.append(msgspec.convert(j.backend, joint_type))
        except msgspec.ValidationError as exc:
            path, text = _msgspec_error_path(exc)
            problems.append(f"{key}.{_format_msgspec_error(exc, j.backend, joint_type)}" if path
                            else f"{key}: {text}")
    if problems:
        raise ProfileError(f"{source}: " + "; ".join(problems))
    return out

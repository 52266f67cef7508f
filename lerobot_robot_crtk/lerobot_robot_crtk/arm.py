"""A crtk-bridge daemon's joints as LeRobot sees a robot: flat ``<joint>.pos`` dictionaries in
LeRobot's units, without LeRobot (so it is tested without torch). :mod:`.crtk` wraps it in
LeRobot's ``Robot`` and ``Teleoperator``.

Units (``units``): ``lerobot`` gives exactly the numbers LeRobot's own SO / Koch classes compute
from the same servo ticks and calibration, from the per-joint affine maps the daemon's ``list``
carries (docs/protocol.md, "LeRobot units"): a joint of a namespace named ``.../gripper`` in
``range_0_100``, the others in ``degrees`` (``use_degrees``, LeRobot's SO default since 0.4.4) or
``range_m100_100``. ``si`` gives the daemon's own values (rad, m) for any robot.

The daemon does the motion: an action becomes an ``interpolate_jp`` goal (``command``:
``interpolate``, the default: 30 Hz actions become smooth motion at the loop rate) or a
``servo_jp`` setpoint (``servo``, for callers at the loop rate). Before sending, each joint's
target is clipped as LeRobot's ``max_relative_target`` does (to the measured position +- the cap,
in the action's units), to the joint's position limits (where the daemon would clip it), and to
``servo_step_max`` from the previous goal (a far first action approaches over several actions
instead of being refused): :meth:`DaemonArm.send` returns what was sent, in the action's units.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from crtk_client import connect
from crtk_client.errors import CommandError, CrtkBridgeError

log = logging.getLogger(__name__)

#: release("hold") waits for the last action's interpolation to end: at least SETTLE_S, and
#: SETTLE_PERIODS of the slowest of the last actions' intervals (a stream's interpolation ends
#: within a few of its periods: ``predict`` returns to the last goal after about 4, more for bursty
#: actions; a 2 Hz policy needs longer than 1 s), at most SETTLE_MAX_S
SETTLE_S = 1.0
SETTLE_PERIODS = 6
SETTLE_MAX_S = 10.0
SETTLE_POLL_S = 0.005
#: the action intervals the settle time is measured on
SETTLE_INTERVALS = 4

UNITS = ("lerobot", "si")
COMMANDS = ("interpolate", "servo")
ON_DISCONNECT = ("hold", "disable")
#: the interval each LeRobot RANGE mode clamps to (LeRobot clamps the ticks to the range first)
CLAMP = {"degrees": None, "range_m100_100": (-100.0, 100.0), "range_0_100": (0.0, 100.0)}
#: a step just inside servo_step_max, so float rounding never makes the daemon refuse it
STEP_MARGIN = 0.98


class CrtkFaultError(CrtkBridgeError, ConnectionError):
    """The robot is in FAULT (at connect, or it faulted mid-episode): the daemon stopped it. The
    message is one line with the daemon's reason."""


class ConfigError(CrtkBridgeError, ValueError):
    """A plugin setting LeRobot passed is invalid (the message names the field)."""


@dataclass
class Joint:
    """One joint of the exposed namespaces: its key, namespace, index there, and the map from its
    SI value to the action's units (``scale * si + bias``, then clamped to ``clamp``)."""

    name: str
    ns: str
    index: int
    scale: float = 1.0
    bias: float = 0.0
    clamp: tuple[float, float] | None = None
    lo: float = -math.inf  # position limits (SI)
    hi: float = math.inf

    @property
    def key(self) -> str:
        return f"{self.name}.pos"

    def to_units(self, si: float) -> float:
        v = self.scale * si + self.bias
        if self.clamp is not None:
            v = min(self.clamp[1], max(self.clamp[0], v))
        return float(v)

    def to_si(self, value: float) -> float:
        if self.clamp is not None:
            value = min(self.clamp[1], max(self.clamp[0], value))
        return float((value - self.bias) / self.scale)


def check_settings(units: str, command: str | None = None, on_disconnect: str | None = None,
                   max_relative_target: Any = None) -> None:
    """Refuse, in one line naming the field, a value the plugin cannot use (before any connection)."""
    if units not in UNITS:
        raise ConfigError(f"crtk: units must be one of {', '.join(UNITS)}, got {units!r}")
    if command is not None and command not in COMMANDS:
        raise ConfigError(f"crtk: command must be one of {', '.join(COMMANDS)}, got {command!r}")
    if on_disconnect is not None and on_disconnect not in ON_DISCONNECT:
        raise ConfigError(f"crtk: on_disconnect must be one of {', '.join(ON_DISCONNECT)}, got {on_disconnect!r}")
    caps = max_relative_target.values() if isinstance(max_relative_target, Mapping) else \
        [] if max_relative_target is None else [max_relative_target]
    for cap in caps:
        # LeRobot's own check lets nan (no clamp), a negative cap (inverted) and an int (TypeError) through
        if isinstance(cap, bool) or not isinstance(cap, (int, float)) or not math.isfinite(cap) or cap <= 0:
            raise ConfigError(f"crtk: max_relative_target must be a finite number > 0 (or a dict of them by "
                              f"joint), got {cap!r}")


class DaemonArm:
    """The exposed joints of one daemon. :meth:`describe` (one ``list`` round trip, on a short
    connection) makes the joints known before :meth:`open`; :meth:`open` keeps a connection."""

    def __init__(self, socket: str | None = None, robot: str | None = None, zenoh_connect: str | None = None,
                 namespaces: list[str] | None = None, units: str = "lerobot", use_degrees: bool = True,
                 timeout_s: float = 5.0, who: str = "crtk"):
        check_settings(units)
        self.where = dict(socket=socket, robot=robot, zenoh_connect=zenoh_connect)
        self.wanted = list(namespaces or [])
        self.units = units
        self.use_degrees = use_degrees
        self.timeout_s = float(timeout_s)
        self.who = who
        self.joints: list[Joint] | None = None
        self.info: dict | None = None
        self.client: Any = None
        self.devices: dict[str, Any] = {}
        self.goal: dict[str, np.ndarray] = {}  # per namespace: the last goal sent (SI)
        self._sent_at: float | None = None  # monotonic time of the last action sent
        self._intervals: deque[float] = deque(maxlen=SETTLE_INTERVALS)  # between the last actions (s)

    # ---------------------------------------------------------------- description
    def _connect(self) -> Any:
        return connect(timeout=self.timeout_s, **self.where)

    def describe(self) -> list[Joint]:
        """The exposed joints, from the daemon's ``list`` (cached). Raises DaemonConnectionError
        (no daemon there), ConfigError (an unknown namespace; a joint without LeRobot numbers in
        ``lerobot`` units)."""
        if self.joints is None:
            if self.client is not None:
                info = self.client.list()
            else:
                with self._connect() as client:
                    info = client.list()
            self.joints = self._joints(info)
            self.info = info
        return self.joints

    def _joints(self, info: dict) -> list[Joint]:
        robot = info.get("robot", "?")
        by_name = {ns["name"]: ns for ns in info["namespaces"]}
        names = self.wanted or list(by_name)
        unknown = [n for n in names if n not in by_name]
        if unknown:
            raise ConfigError(f"{self.who}: {robot} has no namespace {', '.join(map(repr, unknown))} "
                              f"(namespaces: {', '.join(by_name)})")
        joints, missing = [], []
        for ns_name in names:
            ns = by_name[ns_name]
            gripper = ns_name.rsplit("/", 1)[-1] == "gripper"
            limits = ns.get("position_limits") or [[-math.inf, math.inf]] * len(ns["joints"])
            maps = ns.get("lerobot") or [None] * len(ns["joints"])
            for k, (name, lim, m) in enumerate(zip(ns["joints"], limits, maps)):
                j = Joint(name, ns_name, k, lo=float(lim[0]), hi=float(lim[1]))
                if self.units == "lerobot":
                    mode = "range_0_100" if gripper else "degrees" if self.use_degrees else "range_m100_100"
                    if not m or mode not in m:
                        missing.append(name)
                        continue
                    j.scale, j.bias = (float(x) for x in m[mode])
                    j.clamp = CLAMP[mode]
                joints.append(j)
        if missing:
            raise ConfigError(f"{self.who}: {robot}: joint{'s' if len(missing) > 1 else ''} {', '.join(missing)} "
                              f"{'have' if len(missing) > 1 else 'has'} no LeRobot units (no servo calibration "
                              f"with a range in the daemon's profile): calibrate it, or use units=si")
        keys = [j.key for j in joints]
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise ConfigError(f"{self.who}: {robot}: keys {', '.join(dup)} appear in several namespaces: "
                              f"expose one of them (namespaces=[...])")
        return joints

    @property
    def robot_name(self) -> str:
        return (self.info or {}).get("robot", self.where.get("robot") or "robot")

    def keys(self) -> list[str]:
        return [j.key for j in self.describe()]

    # ---------------------------------------------------------------- connection
    @property
    def is_open(self) -> bool:
        return self.client is not None

    def open(self) -> None:
        """Connect and describe. Raises CrtkFaultError when the robot is in FAULT, with the reason
        the daemon gave (it repeats the error event to a session joining a FAULT)."""
        client = self._connect()
        try:
            self.client = client
            self.joints = None
            self.describe()
            self.devices = {ns: client.device(ns) for ns in dict.fromkeys(j.ns for j in self.joints)}
            self.check_fault("connect")
        except BaseException:
            self.client = None
            client.close()
            raise

    def close(self) -> None:
        client, self.client = self.client, None
        if client is not None:
            client.close()

    def fault_reason(self) -> str:
        """The latest error event's message this connection heard (the reason of the FAULT)."""
        errors = [e for e in self.client.connection.events if e.kind == "error"]
        return errors[-1].data.get("message", "") if errors else "no reason received"

    def check_fault(self, what: str) -> None:
        """Raise CrtkFaultError when the robot is in FAULT."""
        if next(iter(self.devices.values())).is_fault():
            raise CrtkFaultError(f"{self.who}: {self.robot_name} is in FAULT ({self.fault_reason()}); {what} "
                                 f"refused: the robot is stopped; clear the cause, then enable it again")

    def enable(self) -> None:
        """Enable the robot (the user's command: connecting a LeRobot robot asks for it). Raises
        CrtkFaultError naming the reason when it does not reach ENABLED."""
        self.check_fault("enable")
        dev = next(iter(self.devices.values()))
        if not dev.is_enabled():
            try:
                ok = dev.enable(self.timeout_s)
            except CommandError as exc:
                raise CrtkFaultError(f"{self.who}: {self.robot_name}: enable refused: {exc}") from None
            if not ok:
                state = dev.operating_state()
                reason = self.fault_reason() if state == "FAULT" else f"still {state} after {self.timeout_s:g} s"
                raise CrtkFaultError(f"{self.who}: {self.robot_name}: enable failed: {reason}")
        self.goal = {}
        self._sent_at = None
        self._intervals.clear()

    # ---------------------------------------------------------------- reading
    def read_si(self) -> dict[str, np.ndarray]:
        """Measured positions per exposed namespace (SI). Raises CrtkFaultError in FAULT (the
        daemon reports no valid measurement then)."""
        out = {}
        # every namespace's in one round trip (the daemon answers them in order)
        replies = self.client.connection.request_all([("measured_js", ns, None) for ns in self.devices])
        for ns, js in zip(self.devices, replies):
            p = js.get("position") or []
            if not js.get("stamp") or len(p) == 0:
                self.check_fault("reading")
                raise CrtkBridgeError(f"{self.who}: {ns}: the daemon has no measurement yet")
            out[ns] = np.asarray(p, dtype=float)
        return out

    def read(self) -> dict[str, float]:
        """``{<joint>.pos: value}`` in the configured units."""
        si = self.read_si()
        return {j.key: j.to_units(float(si[j.ns][j.index])) for j in self.joints}

    def _setpoint_or(self, present: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Per namespace, the daemon's position setpoint (what its step bound is measured from),
        or the measured position where it has none (just enabled, nothing commanded yet)."""
        replies = self.client.connection.request_all([("setpoint_js", ns, None) for ns in self.devices])
        out = {}
        for ns, js in zip(self.devices, replies):
            p = js.get("position") or []
            ok = js.get("stamp") and len(p) == len(present[ns])
            out[ns] = np.asarray(p, dtype=float) if ok else present[ns].copy()
        return out

    # ---------------------------------------------------------------- commanding
    def send(self, action: Mapping[str, Any], command: str = "interpolate",
             max_relative_target: float | Mapping[str, float] | None = None) -> dict[str, float]:
        """Send ``action`` (``<joint>.pos`` keys, values convertible with ``float()``: 0-dim
        tensors from a dataset included; other keys are ignored, as LeRobot's SO follower does)
        and return what was sent, in the same units. A joint absent from ``action`` keeps its
        previous goal. Raises CrtkFaultError when the robot is in
        FAULT, CommandError on another refusal, ConfigError on an unknown key."""
        joints = self.joints
        known = {j.key for j in joints}
        action = {k: v for k, v in action.items() if str(k).endswith(".pos")}  # as LeRobot's SO follower
        unknown = [k for k in action if k not in known]
        if unknown:
            raise ConfigError(f"{self.who}: {self.robot_name}: unknown action key{'s' if len(unknown) > 1 else ''} "
                              f"{', '.join(map(str, unknown))} (keys: {', '.join(sorted(known))})")
        wanted = {k: float(v) for k, v in action.items()}
        present = None
        if max_relative_target is not None or not self.goal:
            present = self.read_si()
        if not self.goal:  # the first goal of this connection: from where the daemon's setpoint is
            self.goal = self._setpoint_or(present)
        target = {ns: g.copy() for ns, g in self.goal.items()}
        step = float((self.info or {}).get("servo_step_max", math.inf)) * STEP_MARGIN
        clamped = {}
        for j in joints:
            if j.key not in wanted:
                continue
            value = wanted[j.key]
            if not math.isfinite(value):
                raise ConfigError(f"{self.who}: {self.robot_name}: action {j.key} is {value}, not a finite number")
            if max_relative_target is not None:
                cap = max_relative_target[j.name] if isinstance(max_relative_target, Mapping) else max_relative_target
                now = j.to_units(float(present[j.ns][j.index]))
                safe = min(now + cap, max(now - cap, value))
                if abs(safe - value) > 1e-4:
                    clamped[j.key] = (value, safe)
                value = safe
            si = min(j.hi, max(j.lo, j.to_si(value)))
            prev = self.goal[j.ns][j.index]
            target[j.ns][j.index] = min(prev + step, max(prev - step, si))
        if clamped:
            log.warning("%s: %s: relative goal clamped by max_relative_target: %s", self.who, self.robot_name,
                        ", ".join(f"{k} {a:.4g} -> {b:.4g}" for k, (a, b) in clamped.items()))
        cmd = "servo_jp" if command == "servo" else "interpolate_jp"
        for ns, dev in self.devices.items():
            if not dev.supports(cmd):
                raise CommandError("unsupported", f"{self.who}: {ns}: {cmd} is not supported by this robot")
        try:  # every namespace's goal in one round trip: never more than about one daemon cycle
            self.client.connection.request_all(
                [(cmd, ns, {"position": [float(x) for x in target[ns]]}) for ns in self.devices])
        except CommandError as exc:
            if exc.code == "invalid_state" or next(iter(self.devices.values())).is_fault():
                self.check_fault("send_action")
            raise
        self.goal = target
        now = time.monotonic()
        if self._sent_at is not None:
            self._intervals.append(now - self._sent_at)
        self._sent_at = now
        return {j.key: j.to_units(float(self.goal[j.ns][j.index])) for j in joints if j.key in wanted}

    def settle_s(self) -> float:
        """How long :meth:`release` waits for the last action's interpolation to end (s)."""
        slowest = max(self._intervals, default=0.0)
        return min(SETTLE_MAX_S, max(SETTLE_S, SETTLE_PERIODS * slowest))

    def _settle(self, devices: list) -> None:
        """Until each device's interpolation reached its goal (the last action sent), at most
        :meth:`settle_s`: ``hold`` stops where the setpoint is, and LeRobot disconnects right
        after its last ``send_action``, so a hold at once left the arm short of the last action
        by up to one interpolation (a replay ended off its recorded path), or with ``predict``
        past it."""
        deadline = time.monotonic() + self.settle_s()
        for dev in devices:
            while time.monotonic() < deadline:
                goal, setpoint = dev.goal_jp()[0], dev.setpoint_jp()[0]
                if len(goal) == 0 or len(goal) != len(setpoint) or np.array_equal(goal, setpoint):
                    break
                time.sleep(SETTLE_POLL_S)

    def release(self, on_disconnect: str = "hold") -> None:
        """End of the session: ``hold`` (every namespace holds its position, the robot stays
        ENABLED, control is released for the next client) or ``disable`` (torque off: an arm
        without brakes falls). Never raises (LeRobot disconnects in ``finally`` blocks, where an
        error would hide the one that ended the episode): a robot in FAULT or DISABLED, or a
        daemon gone, is logged."""
        try:
            if on_disconnect == "disable":
                next(iter(self.devices.values())).disable(self.timeout_s)
            else:
                enabled = [dev for dev in self.devices.values() if dev.is_enabled()]
                self._settle(enabled)
                for dev in enabled:
                    dev.hold()
                self.client.release()
        except (CrtkBridgeError, ConnectionError, TimeoutError) as exc:  # CommandError, the daemon gone
            log.warning("%s: %s: on disconnect: %s", self.who, self.robot_name, exc)

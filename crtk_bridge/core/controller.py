"""The CRTK controller: operating-state machine and joint motion, one step per loop cycle.

It is the logic of the control process without the process: it owns no socket and no clock of
its own, so tests drive it directly with a fake actuator. The loop (``core/loop.py``) feeds it
one measured sample per cycle, the requests that arrived, and sends what it puts in ``outbox``.

Messages (dicts, see docs/protocol.md):
* request: ``{"id", "cmd", "ns", "data"}`` -> exactly one reply appended to ``outbox``:
  ``{"id", "ok": True, "data"}`` or ``{"id", "ok": False, "error": {"code", "message"}}``;
* events appended to ``outbox`` in causal order: ``{"event": "operating_state", "data"}``,
  ``{"event": "warning"|"error"|"status", "data": {"stamp", "ns", "code", "message"}}``.

Motion per namespace lives in ``motion.py``; twists (``servo_cv``, ``interpolate_cv``) are mapped
to joint velocities every cycle by ``twist.py``; the namespaces of a backend with its own
cartesian control get cartesian setpoints from ``native_cartesian.py``. Safety here:
* servo and interpolate positions outside the joint limits are clipped with a rate-limited
  warning; a ``servo_jp`` / ``interpolate_jp`` step larger than ``safety.servo_step_max`` from the
  last setpoint (or goal) is refused; a stream silent for ``safety.servo_timeout_s`` holds;
* move goals outside the joint limits are refused naming joint and limit;
* faults (bus, servo error bits, tracking error beyond ``safety.tracking_error_max``) put the
  robot in FAULT with the cause in an ``error`` event, and torque off (the backend's DISABLE
  transition; a UR stops, powers off and applies its brakes).

Lifecycle transitions (enable, disable, the torque-off of a fault, pause, resume, native home)
run as the backend's :class:`~crtk_bridge.core.actuator.Transition`, one step per cycle after the
cycle's read (:meth:`Controller.step`): the state stays as it was and ``is_busy`` is true until
it ends, its requests get their one reply then, and a transition that outlives the backend's time
limit faults the robot naming it. A stop (``disable``, ``pause``) is never refused: it aborts a
running enable / resume / home (whose requests get an ``aborted`` error). What the device reports
about itself (:class:`~crtk_bridge.core.actuator.DeviceStatus`) goes through ONE table,
``state.DEVICE_STATUS``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..errors import BackendError, CommandError, fmt_number
from ..profile import Profile, stop_deceleration
from .actuator import (
    Actuator,
    Capabilities,
    CommandMode,
    DeviceStatus,
    Fault,
    JointFeedback,
    Lifecycle,
    Steps,
    Transition,
)
from .motion import Mode, NamespaceMotion
from .state import DEVICE_STATUS, OperatingState, StateCommand, transition
from .native_cartesian import NATIVE_COMMANDS, build_native_cartesian, parse_pose
from .twist import TWIST_COMMANDS, build_twist_motions, parse_twist

STATE_COMMANDS = tuple(c.value for c in StateCommand)
#: joint motion commands -> (payload field, capability needed: "position" / "velocity" / "effort" / "free")
MOTION_COMMANDS: dict[str, tuple[str | None, str]] = {
    "servo_jp": ("position", "position"),
    "servo_jr": ("position", "position"),
    "servo_jv": ("velocity", "velocity"),
    "servo_jf": ("effort", "effort"),
    "interpolate_jp": ("position", "position"),
    "interpolate_jr": ("position", "position"),
    "interpolate_jv": ("velocity", "velocity"),
    "interpolate_jf": ("effort", "effort"),
    "move_jp": ("position", "position"),
    "move_jr": ("position", "position"),
    "hold": (None, "position"),
    "free": (None, "free"),
}
_STATUS_TEXT = {
    DeviceStatus.OK: "the device reports it is ok again",
    DeviceStatus.PAUSED: "the device paused itself",
    DeviceStatus.POWERED_OFF: "the device powered itself off",
    DeviceStatus.FAULT: "the device reports a fault",
    DeviceStatus.FAULT_CLEARED: "the device's fault cleared (enable or disable to go on)",
}
_WARN_INTERVAL_S = 1.0  # at most one clipping warning per namespace per second
TRACKING_CYCLES = 3  # consecutive cycles beyond the bound before FAULT (one glitch is not a fault)
ENABLE_FRESH_READ_ATTEMPTS = 3  # reads tried for the pose an enable holds (after torque on)


_DEFERRED = object()  # _dispatch: the reply comes when the transition ends
_NONE = int(CommandMode.NONE)


@dataclass
class _Running:
    """A lifecycle transition in progress and who waits for it."""

    transition: Transition
    deadline: float  # controller clock
    on_done: Callable[[], Any]  # -> reply data; may raise Refused
    on_fail: Callable[[Exception], "Refused"]  # handles the failure; -> the waiting requests' error
    rids: list = field(default_factory=list)  # requests answered when it ends
    stepped: int = -1  # cycle of the last step (one step per cycle)


class Refused(CommandError):
    """A request refused; becomes an error reply with ``code``."""


class Controller:
    """Operating-state machine + motion layer. Not thread-safe; one call at a time.

    ``actuator`` is used on the lifecycle path only (enable / disable, which may block);
    the loop does the real-time read and write.
    """

    def __init__(self, profile: Profile, actuator: Actuator, clock: Callable[[], float],
                 period_s: float | None = None):
        self.profile = profile
        self.actuator = actuator
        #: what the backend declares (immutable, final once open): read here and nowhere else
        self.traits = traits = actuator.traits
        self.caps = traits.capabilities
        self.clock = clock
        self.robot = profile.name
        #: the cycle period (s): actuator.effective_period_s, passed in by the loop
        self.dt = period_s if period_s is not None else 1.0 / profile.loop.rate_hz
        self.safety = profile.safety
        self.state = OperatingState.DISABLED
        self.is_homed = not self.caps.needs_homing
        self.homing = False
        self.busy_seq = 0
        self._busy_reported = False
        self._checked_seq: int | None = None  # the busy_seq a running GOAL_CHECK raised (_move_edge)
        self.state_stamp = clock()
        self.outbox: list[dict] = []
        #: what each namespace's joints can do together: commands are offered and refused per namespace
        self.ns_caps = {ns.name: traits.capabilities_of([profile.joint_index(j) for j in ns.joints])
                        for ns in profile.namespaces}
        #: rad/s^2 each joint's stops brake at (the profile's, or its default bounded by the hardware)
        self.stop_dec = np.array([stop_deceleration(j.limits, actuator.deceleration_limit(i))
                                  for i, j in enumerate(profile.joints)])
        self.namespaces: dict[str, NamespaceMotion] = {
            ns.name: NamespaceMotion(ns.name, [profile.joint_index(j) for j in ns.joints], profile, self.dt,
                                     self.ns_caps[ns.name], self.stop_dec[[profile.joint_index(j) for j in ns.joints]])
            for ns in profile.namespaces
        }
        # servo_cv / interpolate_cv, mapped every cycle (core/twist.py); namespaces with kinematics
        self.twist_motions = build_twist_motions(profile, self.namespaces)
        # namespaces the backend controls in cartesian space itself (core/native_cartesian.py)
        self.native_cartesian = build_native_cartesian(self.namespaces, actuator.cartesian_namespaces(),
                                                       profile.safety)
        self.command = actuator.new_command()
        self.feedback = actuator.new_feedback()  # latest sample, copied in by on_read()
        self._fresh = actuator.new_feedback()  # the read that follows torque on
        self.fault_cause: Fault | None = None
        self._consecutive_bus_errors = 0
        self._tracking_cycles = 0
        self._written = False  # self.command holds what was written last cycle
        self._torque_unconfirmed = False  # a fault's torque off did not reach the bus
        self._last_torque_retry = -math.inf
        self._consecutive_write_errors = 0
        self._running: _Running | None = None  # the lifecycle transition in progress
        self._cycle = 0  # counts on_read calls: one transition step per cycle
        self._rid: Any = None  # id of the request being handled
        self._speed_fraction = float("nan")  # the device's speed slider as last reported (NaN: none)

    # ------------------------------------------------------------------ queries
    @property
    def is_busy(self) -> bool:
        return self.homing or self._running is not None or any(m.busy for m in self.namespaces.values()) \
            or any(nc.busy for nc in self.native_cartesian.values())

    def operating_state(self) -> dict[str, Any]:
        out = {
            "state": self.state.value,
            "is_homed": self.is_homed,
            "is_busy": self.is_busy,
            "busy_seq": self.busy_seq,
            "stamp": self.state_stamp,
        }
        if self._speed_fraction == self._speed_fraction:  # not NaN: the device has a speed slider
            out["target_speed_fraction"] = self._speed_fraction
        return out

    @staticmethod
    def _allows(c: Capabilities, need: str) -> bool:
        return {"position": c.position, "velocity": c.velocity or c.position, "effort": c.effort,
                "free": c.can_free}[need]

    def can(self, need: str, ns: str | None = None) -> bool:
        """Whether namespace ``ns`` (None: every joint of the robot) can follow ``need`` commands."""
        return self._allows(self.ns_caps[ns] if ns is not None else self.caps, need)

    def supported_commands(self, ns: str | None = None) -> list[str]:
        """State commands and the motion commands namespace ``ns``'s capabilities allow (None:
        those some namespace allows).

        Velocity commands exist on position-only hardware too: the loop integrates them into
        position setpoints (crtk-spec 4.2.5). Effort commands need effort control."""
        names = [ns] if ns is not None else list(self.namespaces)
        return list(STATE_COMMANDS) + [cmd for cmd, (_, need) in MOTION_COMMANDS.items()
                                       if any(self.can(need, n) for n in names)]

    def namespace_commands(self) -> dict[str, list[str]]:
        """Every namespace's motion commands (what `list` advertises per namespace)."""
        return {ns: [cmd for cmd, (_, need) in MOTION_COMMANDS.items() if self.can(need, ns)]
                for ns in self.namespaces}

    # ------------------------------------------------------------------ events
    def _push_state(self) -> None:
        self.state_stamp = self.clock()
        self._busy_reported = self.is_busy
        self.outbox.append({"event": "operating_state", "data": self.operating_state()})

    def _event(self, kind: str, code: str, message: str, ns: str | None = None, **cause: Any) -> None:
        data = {"stamp": self.clock(), "ns": ns or self.robot, "code": code, "message": message}
        data.update((k, v) for k, v in cause.items() if v is not None)
        self.outbox.append({"event": kind, "data": data})

    def _set_state(self, state: OperatingState) -> None:
        if state is not self.state:
            self.state = state
            self._event("status", "state_changed", f"{self.robot}: {state.value}")
        self._push_state()

    # ------------------------------------------------------------------ requests
    def handle(self, request: dict) -> None:
        """Handle one request; appends exactly one reply (after any events it caused)."""
        rid = request.get("id")
        self._rid = rid
        try:
            data = self._dispatch(request.get("cmd"), request.get("ns"), request.get("data") or {})
        except Refused as exc:
            self.outbox.append({"id": rid, "ok": False, "error": {"code": exc.code, "message": str(exc)}})
        except Exception as exc:  # a bug must not kill the loop: report it
            self.outbox.append({"id": rid, "ok": False, "error": {"code": "internal", "message": f"{self.robot}: {exc!r}"}})
        else:
            if data is not _DEFERRED:  # else the transition's end replies
                self.outbox.append({"id": rid, "ok": True, "data": data})

    def _dispatch(self, cmd: Any, ns: Any, data: dict) -> Any:
        if cmd in STATE_COMMANDS:
            return self._state_command(StateCommand(cmd))
        if cmd == "_client_lost":
            self._client_lost()
            return None
        if cmd == "calibrate":
            return self._calibrate(data)
        if cmd in NATIVE_COMMANDS and ns in self.native_cartesian:
            return self._native_cartesian_command(cmd, ns, data)
        if cmd in TWIST_COMMANDS:
            return self._twist_command(cmd, ns, data)
        if cmd not in MOTION_COMMANDS:
            raise Refused("unknown_command", f"{self.robot}: unknown command {cmd!r}")
        m = self.namespaces.get(ns)
        if m is None:
            raise Refused("unknown_namespace", f"{self.robot}: unknown namespace {ns!r} (have: {', '.join(self.namespaces)})")
        field, need = MOTION_COMMANDS[cmd]
        if not self.can(need, ns):
            what = {"position": "position control", "velocity": "velocity or position control",
                    "effort": "effort control", "free": "a way to switch torque off"}[need]
            lacking = [self.profile.joints[i].name for i in m.idx
                       if not self._allows(self.traits.joints[int(i)], need)]
            where = (f"joint{'s' if len(lacking) > 1 else ''} {', '.join(map(repr, lacking))}" if lacking
                     else f"the {self.profile.backend_type} backend")
            raise Refused("unsupported", f"{ns}: {cmd} is not supported: no {what} on {where}")
        if cmd == "hold" and self._hold_anyway(ns):
            return None
        self._check_can_move(ns, cmd)
        vec = self._vector(ns, cmd, m, data.get(field), field) if field else None
        now = self.clock()
        leaving_free = m.mode is Mode.FREE and cmd != "free"
        if leaving_free:
            m.reset(self.feedback.position[m.idx])  # start from where the joints are
        try:
            result = self._motion(cmd, m, vec, data, ns, now)
        except Refused:
            if leaving_free:
                m.free()  # a refused command changes nothing: the joints stay free (torque off)
            raise
        self._end_cartesian(ns)  # a joint command takes over from a cartesian one
        return result

    def _calibrate(self, data: dict) -> Any:
        """``calibrate`` (docs/calibration.md): ``begin`` a sweep by hand from the middle pose,
        ``status`` (range seen per joint, rad), ``end`` (the joints' calibration keys), ``cancel``;
        only while DISABLED: the joints move by hand with torque off. ``import`` converts another
        tool's calibration file, in any state (nothing moves, nothing is written here)."""
        action = data.get("action")
        grippers = list(data.get("grippers", ()))
        if action == "import":
            try:
                return {"calibration": self.actuator.calibration_import(data.get("format", "lerobot"),
                                                                       data.get("file", {}), grippers)}
            except BackendError as exc:
                raise Refused("bad_request", str(exc)) from None
        if action == "cancel":
            self.actuator.calibration_cancel()
            return None
        if self.state is not OperatingState.DISABLED or self._running is not None:
            self.actuator.calibration_cancel()  # a sweep under way ends: the joints may move now
            what = self.state.value + (f", {self._running.transition.kind.value} under way" if self._running else "")
            raise Refused("invalid_state", f"{self.robot}: calibrate needs the robot DISABLED (it is {what}): the "
                                           f"joints are moved by hand with torque off; disable it first"
                                           + ("" if action == "begin" else "; the calibration sweep was cancelled"))
        if action == "begin":
            self.actuator.calibration_cancel()

            def failed(exc: Exception) -> Refused:
                return Refused("unsupported", str(exc))

            t = Transition(self.robot, Lifecycle.CALIBRATE, self.actuator.calibration_begin(),
                           self.traits.timeout_s(Lifecycle.CALIBRATE))
            return self._start(t, lambda: {"joints": list(self.profile.joint_names)}, failed)
        try:
            if action == "status":
                return {"seen": self.actuator.calibration_seen()}
            return {"calibration": self.actuator.calibration_result(grippers)}
        except BackendError as exc:
            raise Refused("invalid_state", str(exc)) from None

    def _end_cartesian(self, ns: str) -> None:
        tm = self.twist_motions.get(ns)
        if tm is not None:
            tm.cancel()
        nc = self.native_cartesian.get(ns)
        if nc is not None:
            was_busy = self.is_busy
            nc.cancel()
            if was_busy and not self.is_busy:  # the command pre-empted a native move
                self._push_state()

    def _native_cartesian_command(self, cmd: str, ns: str, data: dict) -> Any:
        """A cartesian command for a backend that does cartesian control itself: no IK, no
        mapping; the backend receives the pose or twist (core/native_cartesian.py)."""
        self._check_can_move(ns, cmd)
        if cmd == "move_cp":
            try:
                p, q = parse_pose(ns, cmd, data)
            except ValueError as exc:
                raise Refused("bad_request", str(exc)) from None
            check = self.actuator.goal_check_steps(ns, cmd, np.concatenate([p, q])) if self.traits.goal_check else None
            if check is not None:  # the device's own limits first; the move starts when they agree
                return self._start(self._goal_check(check), lambda: self._native_accept(cmd, ns, data),
                                   self._goal_refused)
        return self._native_accept(cmd, ns, data)

    def _goal_check(self, steps: Steps) -> Transition:
        return Transition(self.robot, Lifecycle.GOAL_CHECK, steps,
                          self.traits.timeout_s(Lifecycle.GOAL_CHECK))

    def _goal_refused(self, exc: Exception) -> Refused:
        """A GOAL_CHECK that refused the goal (or could not ask): the move is refused, the robot
        holds where it is (no FAULT: nothing moved)."""
        self._checked_seq = None
        if isinstance(exc, CommandError):
            return Refused(exc.code, exc.message)
        return Refused("out_of_limits", f"{self.robot}: move refused: the device could not check the goal "
                       f"against its own limits: {exc}")

    def _native_accept(self, cmd: str, ns: str, data: dict) -> Any:
        nc = self.native_cartesian[ns]
        m = nc.motion
        was_busy = self.is_busy
        was_free = m.mode is Mode.FREE
        try:
            nc.command(cmd, data, self.clock(), self.feedback.cartesian)  # the joints hold: the backend drives them now
        except ValueError as exc:
            raise Refused("bad_request", str(exc)) from None
        except CommandError as exc:
            raise Refused(exc.code, exc.message) from None
        if was_free:
            m.setpoint_p[:] = self.feedback.position[m.idx]
        tm = self.twist_motions.get(ns)
        if tm is not None:
            tm.cancel()
        if cmd == "move_cp":
            self._move_edge()
            return {"busy_seq": self.busy_seq}
        if was_busy and not self.is_busy:  # a stream pre-empted a move
            self._push_state()
        return None

    def _twist_command(self, cmd: str, ns: Any, data: dict) -> None:
        """servo_cv / interpolate_cv: the twist is kept and mapped every cycle (core/twist.py)."""
        m = self.namespaces.get(ns)
        if m is None:
            raise Refused("unknown_namespace", f"{self.robot}: unknown namespace {ns!r} (have: {', '.join(self.namespaces)})")
        tm = self.twist_motions.get(ns)
        if tm is None:
            raise Refused("unsupported", f"{ns}: {cmd} is not supported: the namespace has no kinematics section")
        if not self.can("velocity", ns):
            raise Refused("unsupported", f"{ns}: {cmd} is not supported: no velocity or position control")
        self._check_can_move(ns, cmd)
        try:
            twist, frame = parse_twist(ns, cmd, data)
        except ValueError as exc:
            raise Refused("bad_request", str(exc)) from None
        if m.mode is Mode.FREE:
            m.reset(self.feedback.position[m.idx])  # start from where the joints are
        was_busy = self.is_busy
        if cmd == "servo_cv":
            tm.servo(twist, frame, self.clock())
        else:
            tm.interpolate(twist, frame, self.clock())
        if was_busy and not self.is_busy:  # the stream pre-empted a move
            self._push_state()
        return None

    def _motion(self, cmd: str, m: NamespaceMotion, vec: np.ndarray | None, data: dict, ns: str, now: float) -> Any:
        was_busy = self.is_busy
        if cmd == "servo_jp":
            ff = data.get("velocity")
            v = self._vector(ns, cmd, m, ff, "velocity") if ff else None
            self._check_step(m, vec, m.setpoint_p, cmd)
            m.servo_p(self._clip(m, vec), v, now)
        elif cmd == "servo_jr":
            # relative to the latest servo target (the setpoint follows it at velocity_max)
            p = (m.servo_target if m.mode is Mode.SERVO_P else m.setpoint_p) + vec
            self._check_step(m, p, m.setpoint_p, cmd)
            m.servo_p(self._clip(m, p), None, now)
        elif cmd == "servo_jv":
            m.servo_v(vec, now)
        elif cmd == "servo_jf":
            m.servo_f(vec, now)
        elif cmd in ("interpolate_jp", "interpolate_jr"):
            base = m.goal_p if m.mode is Mode.INTERP_P else m.setpoint_p
            goal = vec if cmd == "interpolate_jp" else base + vec
            self._check_step(m, goal, base, cmd)
            m.interpolate_p(self._clip(m, goal), now)
        elif cmd == "interpolate_jv":
            m.interpolate_v(vec, now)
        elif cmd == "interpolate_jf":
            m.interpolate_f(vec, now)
        elif cmd == "move_jp":
            return self._move(m, vec)
        elif cmd == "move_jr":
            # relative to the current goal while a move runs, else to the setpoint
            return self._move(m, (m.goal_p if m.mode is Mode.MOVE else m.setpoint_p) + vec)
        elif cmd == "hold":
            m.stop()  # what moves brakes at the stop deceleration; position streams hold at once
            if m.level is None:  # nothing commanded yet: hold the measured position
                m.setpoint_p[:] = self.feedback.position[m.idx]
                m.level = Mode.HOLD
                m.setpoint_stamp = now
        elif cmd == "free":
            m.free()
        if was_busy and not self.is_busy:  # the command pre-empted a move
            self._push_state()
        return None

    def _hold_anyway(self, ns: str) -> bool:
        """``hold`` where motion commands are refused (homing, a lifecycle transition under way,
        not homed, PAUSED): a stop is never refused. What moves there is robot-wide (home, a
        shutdown park, a pause's braking), so it all stops; a native home is aborted; a paused arm
        at rest is held already (a no-op). True: handled (reply ok)."""
        if self.state is OperatingState.PAUSED:
            if not self.in_motion():
                return True  # nothing moves: already stopped, a stop is never refused
        elif self.state is not OperatingState.ENABLED:
            return False  # torque is off or going off: nothing to stop, refused as before
        run = self._running
        if not (self.homing or run is not None or not self.is_homed or self.state is OperatingState.PAUSED):
            return False  # the ordinary hold
        if run is not None and run.transition.kind in (Lifecycle.HOME, Lifecycle.GOAL_CHECK):
            self._abort_running(f"{run.transition.kind.value} aborted by hold")
        self._stop_all()
        self._end_cartesian(ns)
        return True

    def _check_can_move(self, ns: str, cmd: str) -> None:
        if self.state is not OperatingState.ENABLED:
            hint = {"DISABLED": "enable it first", "PAUSED": "resume it first", "FAULT": "enable to retry"}
            raise Refused(
                "invalid_state", f"{ns}: {cmd} refused: robot is {self.state.value} ({hint[self.state.value]})"
            )
        if not self.is_homed:
            raise Refused("not_homed", f"{ns}: {cmd} refused: robot is not homed (run home first)")
        if self.homing:
            raise Refused("invalid_state", f"{ns}: {cmd} refused: homing in progress")
        if self._running is not None:
            raise Refused("invalid_state", f"{ns}: {cmd} refused: {self._running.transition.kind.value} "
                          "in progress")

    def _vector(self, ns: str, cmd: str, motion: NamespaceMotion, values: Any, field: str) -> np.ndarray:
        if not isinstance(values, (list, tuple)) or len(values) != motion.n:
            got = len(values) if isinstance(values, (list, tuple)) else type(values).__name__
            raise Refused(
                "bad_request",
                f"{ns}: {cmd} needs {field} with {motion.n} values ({', '.join(motion.joint_names)}), got {got}",
            )
        try:
            vec = np.array(values, dtype=float)
        except (TypeError, ValueError):
            raise Refused("bad_request", f"{ns}: {cmd} {field} must be numbers") from None
        if not np.all(np.isfinite(vec)):
            raise Refused("bad_request", f"{ns}: {cmd} {field} contains a non-finite value")
        return vec

    def _check_step(self, m: NamespaceMotion, p: np.ndarray, base: np.ndarray, cmd: str) -> None:
        step = np.abs(p - base)
        worst = int(np.argmax(step))
        if step[worst] > self.safety.servo_step_max:
            raise Refused(
                "step_too_large",
                f"{m.name}: {cmd} refused: joint {m.joint_names[worst]!r} would jump {fmt_number(step[worst])} rad "
                f"from {fmt_number(base[worst])} (safety.servo_step_max = {self.safety.servo_step_max})",
            )

    def _clip(self, m: NamespaceMotion, p: np.ndarray) -> np.ndarray:
        clipped = np.clip(p, m.pos_min, m.pos_max)
        now = self.clock()
        if np.any(clipped != p) and now - m.last_clip_warning >= _WARN_INTERVAL_S:
            m.last_clip_warning = now
            j = int(np.argmax(np.abs(clipped - p)))
            self._event(
                "warning", "limit_clipped",
                f"{m.name}: setpoint of joint {m.joint_names[j]!r} ({fmt_number(p[j])} rad) clipped to its limit "
                f"[{fmt_number(m.pos_min[j])}, {fmt_number(m.pos_max[j])}]", m.name, joint=m.joint_names[j], value=float(p[j]),
            )
        return clipped

    def _move(self, m: NamespaceMotion, goal: np.ndarray) -> dict:
        bad = np.flatnonzero((goal < m.pos_min) | (goal > m.pos_max))
        if bad.size:
            j = int(bad[0])
            raise Refused(
                "out_of_limits",
                f"{m.name}: move refused: goal {fmt_number(goal[j])} rad for joint {m.joint_names[j]!r} is outside "
                f"its limits [{fmt_number(m.pos_min[j])}, {fmt_number(m.pos_max[j])}]",
            )
        check = self.actuator.goal_check_steps(m.name, "move_jp", goal) if self.traits.goal_check else None
        if check is not None:  # the device's own limits first; the move starts when they agree
            return self._start(self._goal_check(check), lambda: self._start_move(m, goal), self._goal_refused)
        return self._start_move(m, goal)

    def _start_move(self, m: NamespaceMotion, goal: np.ndarray) -> dict:
        if m.mode is Mode.FREE:
            m.reset(self.feedback.position[m.idx])
        m.start_move(goal, self.clock())
        self._move_edge()
        return {"busy_seq": self.busy_seq}

    def _move_edge(self) -> None:
        """The busy=True edge of a move starting now, before its reply: a new busy_seq, unless
        the GOAL_CHECK the move waited on raised it already (one move, one busy_seq, one edge
        each way: is_busy stays true from the check into the move)."""
        checked, self._checked_seq = self._checked_seq, None
        if checked == self.busy_seq and self._busy_reported:
            return
        self.busy_seq += 1
        self._push_state()

    def _state_command(self, cmd: StateCommand) -> Any:
        t = transition(self.state, cmd)
        if t.target is None:
            raise Refused("invalid_state", f"{self.robot}: {cmd.value} is not valid in state {self.state.value}")
        run = self._running
        if cmd in (StateCommand.DISABLE, StateCommand.PAUSE):  # a stop is never refused
            if run is not None and run.transition.kind is Lifecycle.DISABLE:
                if cmd is StateCommand.PAUSE:
                    return self.operating_state()  # torque is going off: more than a pause
                if run.rids:
                    run.rids.append(self._rid)  # a disable is already under way: the same reply
                    return _DEFERRED
            if run is not None:
                self._abort_running(f"{run.transition.kind.value} aborted by {cmd.value}")
        elif run is not None and cmd is not StateCommand.UNHOME:
            if cmd.value == run.transition.kind.value and run.rids:
                run.rids.append(self._rid)  # the same transition under way: the same reply
                return _DEFERRED
            raise Refused("invalid_state", f"{self.robot}: {cmd.value} refused: "
                          f"{run.transition.kind.value} in progress")
        if cmd is StateCommand.ENABLE:
            if self.state is not OperatingState.ENABLED:
                return self._enable()
        elif cmd is StateCommand.DISABLE:
            return self._disable(retry=t.retry)
        elif cmd is StateCommand.PAUSE:
            if self.state is OperatingState.ENABLED:
                self._stop_all()
                self.homing = False
                return self._start(self.actuator.begin(Lifecycle.PAUSE), self._paused, self._failed("pause"))
            self._stop_all()  # PAUSED: whatever moves (a shutdown park) stops too
        elif cmd is StateCommand.RESUME:
            return self._start(self.actuator.begin(Lifecycle.RESUME), self._resumed, self._failed("resume"))
        elif cmd is StateCommand.HOME:
            return self._home()
        elif cmd is StateCommand.UNHOME:
            if self.is_homed:
                self.is_homed = False
                self._push_state()
        return self.operating_state()

    # ---- lifecycle transitions ----
    def _start(self, t: Transition, on_done: Callable[[], Any], on_fail: Callable[[Exception], Refused],
               reply: bool = True) -> Any:
        """Run transition ``t``: its first step now (a quick one ends in this cycle, as the
        blocking calls used to), the rest one per cycle in :meth:`step`. Returns _DEFERRED: the
        reply to the request being handled is sent when ``t`` ends."""
        run = _Running(t, self.clock() + t.timeout_s, on_done, on_fail, [self._rid] if reply else [])
        self._running = run
        if not self._advance(run):
            self.busy_seq += 1
            self._push_state()  # is_busy edge: the state stays until the transition ends
            if t.kind is Lifecycle.GOAL_CHECK:
                self._checked_seq = self.busy_seq  # the move it starts keeps this busy_seq
        return _DEFERRED

    def _advance(self, run: _Running) -> bool:
        """One step of ``run``; True once it ended (replies and events are out)."""
        run.stepped = self._cycle
        try:
            finished = run.transition.step()
        except Exception as exc:  # BackendError, or an SDK surprise: a failed transition
            self._running = None
            self._ended(run, exc)
            return True
        if finished:
            self._running = None
            self._ended(run, None)
            return True
        if self.clock() > run.deadline:
            run.transition.abort()
            self._running = None
            kind = run.transition.kind.value
            self._ended(run, BackendError(
                f"{self.robot}: {kind} did not finish within {run.transition.timeout_s:g} s "
                f"(the {self.profile.backend_type} backend's limit for {kind})"))
            return True
        return False

    def _ended(self, run: _Running, exc: Exception | None) -> None:
        try:
            if exc is not None:
                raise run.on_fail(exc)
            data = run.on_done()
        except Refused as refused:
            for rid in run.rids:
                self.outbox.append({"id": rid, "ok": False, "error": {"code": refused.code, "message": str(refused)}})
        else:
            for rid in run.rids:
                self.outbox.append({"id": rid, "ok": True, "data": data})
        if self._busy_reported and not self.is_busy:
            self._push_state()  # is_busy false edge (when no state change carried it)

    def _abort_running(self, why: str) -> None:
        run = self._running
        if run is None:
            return
        run.transition.abort()
        self._running = None
        for rid in run.rids:
            self.outbox.append({"id": rid, "ok": False, "error": {"code": "aborted", "message": f"{self.robot}: {why}"}})

    def abort_transition(self) -> None:
        """Abandon the running transition (shutdown): its requests get an ``aborted`` error."""
        self._abort_running("aborted by shutdown")

    def _sequence(self, kinds: tuple[Lifecycle, ...]) -> Steps:
        """The backend's transitions ``kinds`` one after the other (FAULT_RESET, then ENABLE)."""
        for kind in kinds:
            t = self.actuator.begin(kind, self.feedback if kind is Lifecycle.ENABLE else None)
            try:
                while not t.step():
                    yield
            finally:
                t.abort()

    def _enable(self) -> Any:
        kinds = (Lifecycle.FAULT_RESET, Lifecycle.ENABLE) if self.state is OperatingState.FAULT else (Lifecycle.ENABLE,)
        timeout = sum(self.traits.timeout_s(k) for k in kinds)
        t = Transition(self.robot, Lifecycle.ENABLE, self._sequence(kinds), timeout)
        return self._start(t, self._enabled, self._failed("enable"))

    def _enabled(self) -> dict:
        # hold exactly where the joints are NOW: the cycle's sample may be stale (a failed read,
        # or a joint that sagged while torque was off), and the first write must not drive the
        # arm back to it
        # a loaded host may miss one reply: a few bounded attempts (each at most one packet
        # timeout, on this rare path only) rather than a FAULT for one late byte
        for _ in range(ENABLE_FRESH_READ_ATTEMPTS):
            fault = self.actuator.read(self._fresh)
            if fault is None:
                break
        if fault is not None:
            raise self._failed("enable")(BackendError(f"no fresh position after torque on: {fault.message}"))
        self.on_read(self._fresh, None)
        for m in self.namespaces.values():
            m.reset(self.feedback.position[m.idx])
        self.fault_cause = None
        self._consecutive_bus_errors = 0
        self._tracking_cycles = 0
        self._written = False
        self._set_state(OperatingState.ENABLED)
        return self.operating_state()

    def _failed(self, kind: str) -> Callable[[Exception], Refused]:
        """What a failed ``kind`` transition (enable, pause, resume, home) does: FAULT with code
        ``<kind>_failed`` and the backend's fault reaction (never leave torque on unsaid), and the
        request's ``fault`` refusal."""
        def failed(exc: Exception) -> Refused:
            self._enter_fault(Fault(f"{kind}_failed", str(exc), transient=False))
            return Refused("fault", f"{self.robot}: {kind} failed: {exc}")
        return failed

    def _disable(self, retry: bool) -> Any:
        self._abort_motion()

        def failed(exc: Exception) -> Refused:
            if retry:  # FAULT -> DISABLED (retry) failed: stay in FAULT
                return Refused("fault", f"{self.robot}: disable failed, still FAULT: {exc}")
            self._enter_fault(Fault("disable_failed", str(exc), transient=False))
            return Refused("fault", f"{self.robot}: disable failed: {exc}")

        return self._start(self.actuator.begin(Lifecycle.DISABLE), self._disabled, failed)

    def _disabled(self) -> dict:
        self.fault_cause = None
        self._torque_unconfirmed = False
        self._set_state(OperatingState.DISABLED)
        return self.operating_state()

    def _paused(self) -> dict:
        self._set_state(OperatingState.PAUSED)
        return self.operating_state()

    def _resumed(self) -> dict:
        stopped_itself = self.traits.stops_itself_on_pause
        for m in self.namespaces.values():  # a device that stops itself holds where its own stop ended
            if any(stopped_itself[i] for i in m.idx):
                m.reset(self.feedback.position[m.idx])
        self._set_state(OperatingState.ENABLED)
        return self.operating_state()

    def _home(self) -> Any:
        if self.traits.native_homing:
            def homed() -> dict:
                self.is_homed = True
                for m in self.namespaces.values():
                    m.reset(self.feedback.position[m.idx])
                self._push_state()
                return self.operating_state()

            self._stop_all()
            return self._start(self.actuator.begin(Lifecycle.HOME), homed, self._failed("home"))
        if not all(c.position for c in self.ns_caps.values()):
            raise Refused("unsupported", f"{self.robot}: home unsupported without position control")
        missing = [name for m in self.namespaces.values() for name in m.no_home]
        if missing:  # a joint's zero is not always a safe pose (a UR's is the arm stretched out)
            raise Refused("unsupported", f"{self.robot}: home refused: no home pose in the profile for joint"
                          f"{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))} (key `home`, "
                          f"rad, beside the joint's limits); add a safe pose, or move_jp there")
        now = self.clock()
        for m in self.namespaces.values():
            if m.mode is Mode.FREE:
                m.reset(self.feedback.position[m.idx])
            m.start_move(m.home.copy(), now)
        self.homing = True
        self.busy_seq += 1
        self._push_state()
        return self.operating_state()

    def _abort_motion(self) -> None:
        was_busy = self.is_busy
        self.homing = False
        for m in self.namespaces.values():
            m.invalidate()
        for nc in self.native_cartesian.values():
            nc.cancel()  # a native move ends too: the push that follows carries is_busy false
        if was_busy:
            self._busy_reported = False

    def _stop_all(self) -> None:
        was_busy = self.is_busy
        for m in self.namespaces.values():
            m.stop()
        for nc in self.native_cartesian.values():
            nc.cancel()  # the backend's cartesian motion stops now, not when a transition ends
        self.homing = False
        if was_busy:
            self._push_state()

    def park(self) -> bool:
        """Shutdown park (``shutdown.action: park``): a jerk-limited move of every torqued
        namespace to the profile's rest pose, with busy edges. Returns False (nothing started)
        unless the robot is ENABLED or PAUSED with no lifecycle transition under way; a namespace
        left ``free`` stays free."""
        if self.state not in (OperatingState.ENABLED, OperatingState.PAUSED) or self._running is not None:
            return False  # (a lifecycle transition under way: the shutdown aborts it, torque off)
        rest = self.profile.shutdown.rest
        now = self.clock()
        self.homing = False
        for nc in self.native_cartesian.values():
            nc.cancel()  # the joints park from where the backend left them
        started = False
        for m in self.namespaces.values():
            if m.mode is Mode.FREE:
                continue
            here = m.setpoint_p  # a joint the rest pose does not name stops where it is
            m.start_move(np.array([rest.get(name, here[k]) for k, name in enumerate(m.joint_names)]), now)
            started = True
        if started:
            self.busy_seq += 1
            self._push_state()
        return started

    def in_motion(self) -> bool:
        """A move runs or a namespace is still braking (after pause, hold)."""
        return self.is_busy or any(m.mode is Mode.STOP for m in self.namespaces.values())

    def at_rest_pose(self) -> bool:
        """Every parked namespace's setpoint is at its move goal (the park move finished)."""
        return all(m.mode is Mode.FREE or np.allclose(m.setpoint_p, m.goal_p, atol=1e-6)
                   for m in self.namespaces.values())

    def _client_lost(self) -> None:
        """The controlling session went away. Commands with an end (a move, home, an
        interpolate_jp/jr goal) run to it; commands without one (servo streams, velocity and
        effort setpoints and goals) stop and hold (docs/protocol.md, Client loss)."""
        endless = [m for m in self.namespaces.values() if m.streaming and m.mode is not Mode.INTERP_P]
        native = [nc for nc in self.native_cartesian.values() if nc.active and not nc.busy]  # a native move runs on
        if self.state is OperatingState.ENABLED and (endless or native):
            for m in endless:
                m.stop()
            for nc in native:
                nc.cancel()
            names = [m.name for m in endless] + [nc.motion.name for nc in native]
            self._event("warning", "control_released",
                        f"{self.robot}: controlling client disconnected; holding {', '.join(names)}")

    def _enter_fault(self, fault: Fault) -> None:
        """FAULT with ``fault`` as the cause, and the fault reaction: torque off (DISABLE)."""
        self.fault_cause = fault
        run = self._running
        torque_going_off = run is not None and run.transition.kind is Lifecycle.DISABLE and not run.rids
        if run is not None and not torque_going_off:
            self._abort_running(f"{run.transition.kind.value} aborted: {fault.message}")
        self._abort_motion()
        message = fault.message
        if not torque_going_off:  # every backend's reaction: torque off (the DISABLE transition)
            message += self._torque_off()
        self._event("error", fault.code, message, joint=fault.joint, register=fault.register,
                    value=fault.value)
        self._set_state(OperatingState.FAULT)

    def _torque_off(self) -> str:
        """Start the DISABLE transition of a fault (no request waits for it). Returns what to add
        to the fault's message when its first step could not confirm torque off."""
        said: list[str] = []
        first = [True]

        def done() -> None:
            if self._torque_unconfirmed:
                self._event("status", "torque_off_confirmed", f"{self.robot}: torque off confirmed on every joint")
            self._torque_unconfirmed = False

        def failed(exc: Exception) -> Refused:  # the bus may be gone: say so, retry once it answers
            if not self._torque_unconfirmed:
                text = f"; torque off not confirmed ({exc}); retrying when the bus answers"
                if first[0]:
                    said.append(text)  # goes into the fault's own error event
                else:
                    self._event("error", "torque_off_unconfirmed", f"{self.robot}{text}")
            self._torque_unconfirmed = True
            return Refused("fault", str(exc))

        self._start(self.actuator.begin(Lifecycle.DISABLE), done, failed, reply=False)
        first[0] = False
        return said[0] if said else ""

    def _retry_torque_off(self) -> None:
        """In FAULT with torque off unconfirmed: the bus answered again, switch torque off now."""
        if self._running is None:
            self._torque_off()

    def _device_status(self, status: DeviceStatus, cause: Fault | None) -> None:
        """What the device reported, mapped onto the CRTK state by ``state.DEVICE_STATUS``."""
        target, kind, code = DEVICE_STATUS[(self.state, status)]
        if target is OperatingState.FAULT:
            if self.state is not OperatingState.FAULT:
                self._enter_fault(cause or Fault("device_fault", f"{self.robot}: the device reports a fault",
                                                 transient=False))
            return
        if kind is not None:
            what = _STATUS_TEXT[status]
            message = f"{self.robot}: {what}" + (f": {cause.message}" if cause is not None else "")
            self._event(kind, code, message, joint=cause.joint if cause else None)
        if target is OperatingState.PAUSED and self.state is OperatingState.ENABLED:
            self._abort_running("aborted: the device paused itself")
            self._stop_all()
            self.homing = False
            self._set_state(OperatingState.PAUSED)
        elif target is OperatingState.DISABLED and self.state is not OperatingState.DISABLED:
            self._abort_running("aborted: the device powered itself off")
            self._abort_motion()
            # the device is off already; the transition only brings the backend's side along
            self._start(self.actuator.begin(Lifecycle.DISABLE), lambda: None,
                        lambda exc: Refused("fault", str(exc)), reply=False)
            self.fault_cause = None
            self._set_state(OperatingState.DISABLED)

    # ------------------------------------------------------------------ the cycle
    def on_read(self, feedback: JointFeedback, fault: Fault | None) -> None:
        """Account for this cycle's read. A fault (after ``safety.bus_errors_max`` transient ones
        in a row, or at once for a non-transient one) puts the robot in FAULT, torque off. A joint
        whose measured position stays farther than ``safety.tracking_error_max`` from its position
        command for TRACKING_CYCLES cycles does too (not while the backend homes natively: the
        drive moves by itself then, and core takes the homed position when it ends)."""
        self._cycle += 1
        active = self.state in (OperatingState.ENABLED, OperatingState.PAUSED)
        news = self.actuator.take_status()
        if fault is not None:
            self._consecutive_bus_errors += 1
            if active and (not fault.transient or self._consecutive_bus_errors >= self.safety.bus_errors_max):
                self._enter_fault(fault)
            if news is not None:
                self._device_status(*news)
            return
        if news is not None:
            self._device_status(*news)
        self._consecutive_bus_errors = 0
        speed = self.actuator.speed_fraction if self.traits.speed_scaling else math.nan
        if speed == speed and abs(speed - self._speed_fraction) >= 0.005 or (speed == speed) != (
                self._speed_fraction == self._speed_fraction):
            self._speed_fraction = speed  # the operator moved the slider: clients hear of it
            self._push_state()
        if self._torque_unconfirmed and self.state is OperatingState.FAULT:
            now = self.clock()
            if now - self._last_torque_retry >= 1.0:  # acknowledged writes: at most once a second
                self._last_torque_retry = now
                self._retry_torque_off()
        f = self.feedback
        f.position[:] = feedback.position
        f.velocity[:] = feedback.velocity
        f.effort[:] = feedback.effort
        f.stamp = feedback.stamp
        if f.cartesian is not None and feedback.cartesian is not None:
            f.cartesian.copy_from(feedback.cartesian)  # the tip pose a native cartesian backend measures
        run = self._running
        native_home = run is not None and run.transition.kind is Lifecycle.HOME  # the drive moves itself
        if active and self._written and not native_home:
            cmd = self.command
            err = np.abs(f.position - cmd.position)
            err[cmd.mode != CommandMode.POSITION] = 0.0
            j = int(np.argmax(err))
            if err[j] > self.safety.tracking_error_max:
                self._tracking_cycles += 1
                if self._tracking_cycles >= TRACKING_CYCLES:
                    name = self.profile.joints[j].name
                    self._enter_fault(Fault(
                        "tracking_error",
                        f"{self.robot}: joint {name!r} is {fmt_number(err[j], 3)} rad from its setpoint {fmt_number(cmd.position[j], 3)} "
                        f"(safety.tracking_error_max = {self.safety.tracking_error_max}): blocked or not following",
                        joint=name, value=float(err[j]), transient=False))
            else:
                self._tracking_cycles = 0

    def on_write(self, fault: Fault | None) -> None:
        """Account for this cycle's write: as for reads, ``safety.bus_errors_max`` failed writes in
        a row (or one non-transient) put the robot in FAULT; counted apart from reads, so good
        reads cannot hide a bus that takes no commands."""
        if fault is None:
            self._consecutive_write_errors = 0
            return
        self._consecutive_write_errors += 1
        if self.state in (OperatingState.ENABLED, OperatingState.PAUSED) and (
            not fault.transient or self._consecutive_write_errors >= self.safety.bus_errors_max
        ):
            self._enter_fault(fault)

    def step(self) -> bool:
        """Advance the running lifecycle transition by one step (at most one per cycle) and
        motion by one cycle, and fill ``self.command``. Returns True if it must be written: while
        ENABLED / PAUSED, and in every state for a backend with ``cyclic_write`` (every joint in
        CommandMode.NONE outside ENABLED / PAUSED)."""
        run = self._running
        if run is not None and run.stepped != self._cycle:
            self._advance(run)
        if self.state is not OperatingState.ENABLED:
            for nc in self.native_cartesian.values():
                nc.cancel()  # paused, disabled, fault: the backend gets no cartesian setpoint
        if self.state not in (OperatingState.ENABLED, OperatingState.PAUSED):
            self._written = False
            if self.traits.cyclic_write:
                self.command.mode[:] = _NONE
                if self.command.cartesian is not None:
                    self.command.cartesian.mode[:] = _NONE
                return True
            return False
        now = self.clock()
        cmd = self.command
        measured = self.feedback.position
        for m in self.namespaces.values():
            if m.mode is Mode.FREE:
                m.setpoint_p[:] = measured[m.idx]  # follow the hand: leaving free is bumpless
            tm = self.twist_motions.get(m.name)
            if tm is not None:
                tm.update()  # a twist stream: joint velocities mapped at this cycle's setpoint
            nc = self.native_cartesian.get(m.name)
            if nc is not None:
                msg = nc.update(now, measured[m.idx], self.feedback.cartesian)
                if msg:
                    self._event("warning", "servo_timeout", msg, m.name)
            msg = m.step(now, measured[m.idx])
            if msg:
                self._event("warning", "servo_timeout", msg, m.name)
            if m.error is not None:
                self._event("error", "trajectory_failed", m.error, m.name)
                m.error = None
            m.fill(cmd)
            if nc is not None:
                nc.fill(cmd.mode, cmd.cartesian)  # the backend's cartesian row; its joints left to it
        if self.homing and not any(m.busy for m in self.namespaces.values()):
            self.homing = False
            self.is_homed = True
        if self._busy_reported and not self.is_busy:
            self._push_state()  # busy=False edge (also carries is_homed after home)
        self._written = True
        return True

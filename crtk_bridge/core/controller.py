"""The CRTK controller: operating-state machine and joint motion, one step per loop cycle.

It is the logic of the control process without the process: it owns no socket and no clock of
its own, so tests drive it directly with a fake actuator. The loop (``core/loop.py``) feeds it
one measured sample per cycle, the requests that arrived, and sends what it puts in ``outbox``.

Messages (dicts, see docs/protocol.md):
* request: ``{"id", "cmd", "ns", "data"}`` -> exactly one reply appended to ``outbox``:
  ``{"id", "ok": True, "data"}`` or ``{"id", "ok": False, "error": {"code", "message"}}``;
* events appended to ``outbox`` in causal order: ``{"event": "operating_state", "data"}``,
  ``{"event": "warning"|"error"|"status", "data": {"stamp", "ns", "code", "message"}}``.

Motion per namespace lives in ``motion.py``. Safety here:
* servo and interpolate positions outside the joint limits are clipped with a rate-limited
  warning; a ``servo_jp`` / ``interpolate_jp`` step larger than ``safety.servo_step_max`` from the
  last setpoint (or goal) is refused; a stream silent for ``safety.servo_timeout_s`` holds;
* move goals outside the joint limits are refused naming joint and limit;
* faults (bus, servo error bits, tracking error beyond ``safety.tracking_error_max``) put the
  robot in FAULT with the cause in an ``error`` event, torque off.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from ..errors import BackendError, fmt_number
from ..profile import Profile
from .actuator import Actuator, Capabilities, CommandMode, Fault, JointFeedback
from .motion import Mode, NamespaceMotion
from .state import OperatingState, StateCommand, transition
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
_WARN_INTERVAL_S = 1.0  # at most one clipping warning per namespace per second
TRACKING_CYCLES = 3  # consecutive cycles beyond the bound before FAULT (one glitch is not a fault)


class Refused(Exception):
    """A request refused; becomes an error reply with ``code``."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


class Controller:
    """Operating-state machine + motion layer. Not thread-safe; one call at a time.

    ``actuator`` is used on the lifecycle path only (enable / disable, which may block);
    the loop does the real-time read and write.
    """

    def __init__(self, profile: Profile, actuator: Actuator, clock: Callable[[], float]):
        self.profile = profile
        self.actuator = actuator
        self.caps = actuator.capabilities
        self.clock = clock
        self.robot = profile.name
        self.dt = 1.0 / profile.loop.rate_hz
        self.safety = profile.safety
        self.state = OperatingState.DISABLED
        self.is_homed = not self.caps.needs_homing
        self.homing = False
        self.busy_seq = 0
        self._busy_reported = False
        self.state_stamp = clock()
        self.outbox: list[dict] = []
        #: what each namespace's joints can do together: commands are offered and refused per namespace
        self.ns_caps = {ns.name: actuator.capabilities_of([profile.joint_index(j) for j in ns.joints])
                        for ns in profile.namespaces}
        self.namespaces: dict[str, NamespaceMotion] = {
            ns.name: NamespaceMotion(ns.name, [profile.joint_index(j) for j in ns.joints], profile, self.dt,
                                     self.ns_caps[ns.name])
            for ns in profile.namespaces
        }
        # servo_cv / interpolate_cv, mapped every cycle (core/twist.py); namespaces with kinematics
        self.twist_motions = build_twist_motions(profile, self.namespaces)
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

    # ------------------------------------------------------------------ queries
    @property
    def is_busy(self) -> bool:
        return self.homing or any(m.busy for m in self.namespaces.values())

    def operating_state(self) -> dict[str, Any]:
        return {
            "state": self.state.value,
            "is_homed": self.is_homed,
            "is_busy": self.is_busy,
            "busy_seq": self.busy_seq,
            "stamp": self.state_stamp,
        }

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
        try:
            data = self._dispatch(request.get("cmd"), request.get("ns"), request.get("data") or {})
        except Refused as exc:
            self.outbox.append({"id": rid, "ok": False, "error": {"code": exc.code, "message": str(exc)}})
        except Exception as exc:  # a bug must not kill the loop: report it
            self.outbox.append({"id": rid, "ok": False, "error": {"code": "internal", "message": f"{self.robot}: {exc!r}"}})
        else:
            self.outbox.append({"id": rid, "ok": True, "data": data})

    def _dispatch(self, cmd: Any, ns: Any, data: dict) -> Any:
        if cmd in STATE_COMMANDS:
            return self._state_command(StateCommand(cmd))
        if cmd == "_client_lost":
            self._client_lost()
            return None
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
                       if not self._allows(self.actuator.joint_capabilities(int(i)), need)]
            where = (f"joint{'s' if len(lacking) > 1 else ''} {', '.join(map(repr, lacking))}" if lacking
                     else f"the {self.profile.backend_type} backend")
            raise Refused("unsupported", f"{ns}: {cmd} is not supported: no {what} on {where}")
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
        tm = self.twist_motions.get(ns)
        if tm is not None:
            tm.cancel()  # a joint command takes over from a twist stream
        return result

    def _twist_command(self, cmd: str, ns: Any, data: dict) -> None:
        """servo_cv / interpolate_cv: the twist is kept and mapped every cycle (core/twist.py)."""
        m = self.namespaces.get(ns)
        if m is None:
            raise Refused("unknown_namespace", f"{self.robot}: unknown namespace {ns!r} (have: {', '.join(self.namespaces)})")
        tm = self.twist_motions.get(ns)
        if tm is None:
            raise Refused("unsupported", f"{ns}: {cmd} is not supported: the namespace has no kinematics section")
        if not self.can("velocity"):
            raise Refused("unsupported", f"{ns}: {cmd} is not supported: the {self.profile.backend_type} backend "
                          "has no velocity or position control")
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
            m.stop() if m.mode is Mode.MOVE else m.hold()
            if m.level is None:  # nothing commanded yet: hold the measured position
                m.setpoint_p[:] = self.feedback.position[m.idx]
                m.level = Mode.HOLD
                m.setpoint_stamp = now
        elif cmd == "free":
            m.free()
        if was_busy and not self.is_busy:  # the command pre-empted a move
            self._push_state()
        return None

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
        if m.mode is Mode.FREE:
            m.reset(self.feedback.position[m.idx])
        m.start_move(goal, self.clock())
        self.busy_seq += 1
        self._push_state()  # busy=True edge, before the reply
        return {"busy_seq": self.busy_seq}

    def _state_command(self, cmd: StateCommand) -> dict:
        t = transition(self.state, cmd)
        if t.target is None:
            raise Refused("invalid_state", f"{self.robot}: {cmd.value} is not valid in state {self.state.value}")
        if cmd is StateCommand.ENABLE:
            if self.state is not OperatingState.ENABLED:
                self._enable()
        elif cmd is StateCommand.DISABLE:
            self._disable(retry=t.retry)
        elif cmd is StateCommand.PAUSE:
            if self.state is OperatingState.ENABLED:
                self._stop_all()
                self.homing = False
                self._set_state(OperatingState.PAUSED)
        elif cmd is StateCommand.RESUME:
            self._set_state(OperatingState.ENABLED)
        elif cmd is StateCommand.HOME:
            self._home()
        elif cmd is StateCommand.UNHOME:
            if self.is_homed:
                self.is_homed = False
                self._push_state()
        return self.operating_state()

    def _enable(self) -> None:
        try:
            self.actuator.enable(self.feedback)
            # hold exactly where the joints are NOW: the cycle's sample may be stale (a failed
            # read, or a joint that sagged while torque was off), and the first write must not
            # drive the arm back to it
            fault = self.actuator.read(self._fresh)
            if fault is not None:
                raise BackendError(f"no fresh position after torque on: {fault.message}")
        except Exception as exc:  # BackendError, or an SDK surprise: never leave torque on unsaid
            self._enter_fault(Fault("enable_failed", str(exc), transient=False))
            raise Refused("fault", f"{self.robot}: enable failed: {exc}") from exc
        self.on_read(self._fresh, None)
        for m in self.namespaces.values():
            m.reset(self.feedback.position[m.idx])
        self.fault_cause = None
        self._consecutive_bus_errors = 0
        self._tracking_cycles = 0
        self._written = False
        self._set_state(OperatingState.ENABLED)

    def _disable(self, retry: bool) -> None:
        self._abort_motion()
        try:
            self.actuator.disable()
        except BackendError as exc:
            if retry:  # FAULT -> DISABLED (retry) failed: stay in FAULT
                raise Refused("fault", f"{self.robot}: disable failed, still FAULT: {exc}") from exc
            self._enter_fault(Fault("disable_failed", str(exc), transient=False))
            raise Refused("fault", f"{self.robot}: disable failed: {exc}") from exc
        self.fault_cause = None
        self._set_state(OperatingState.DISABLED)

    def _home(self) -> None:
        if not all(c.position for c in self.ns_caps.values()):
            raise Refused("unsupported", f"{self.robot}: home unsupported without position control")
        now = self.clock()
        for m in self.namespaces.values():
            if m.mode is Mode.FREE:
                m.reset(self.feedback.position[m.idx])
            m.start_move(m.home.copy(), now)
        self.homing = True
        self.busy_seq += 1
        self._push_state()

    def _abort_motion(self) -> None:
        was_busy = self.is_busy
        self.homing = False
        for m in self.namespaces.values():
            m.invalidate()
        if was_busy:
            self._busy_reported = False

    def _stop_all(self) -> None:
        was_busy = self.is_busy
        for m in self.namespaces.values():
            m.stop()
        self.homing = False
        if was_busy:
            self._push_state()

    def park(self) -> bool:
        """Shutdown park (``shutdown.action: park``): a jerk-limited move of every torqued
        namespace to the profile's rest pose, with busy edges. Returns False (nothing started)
        unless the robot is ENABLED or PAUSED; a namespace left ``free`` stays free."""
        if self.state not in (OperatingState.ENABLED, OperatingState.PAUSED):
            return False
        rest = self.profile.shutdown.rest
        now = self.clock()
        self.homing = False
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
        if self.state is OperatingState.ENABLED and endless:
            for m in endless:
                m.stop()
            self._event("warning", "control_released",
                        f"{self.robot}: controlling client disconnected; holding {', '.join(m.name for m in endless)}")

    def _enter_fault(self, fault: Fault) -> None:
        self.fault_cause = fault
        self._abort_motion()
        message = fault.message
        try:
            self.actuator.disable()
            self._torque_unconfirmed = False
        except Exception as exc:  # the bus may be gone: say so, and retry once it answers again
            self._torque_unconfirmed = True
            message += f"; torque off not confirmed ({exc}); retrying when the bus answers"
        self._event("error", fault.code, message, joint=fault.joint, register=fault.register,
                    value=fault.value)
        self._set_state(OperatingState.FAULT)

    def _retry_torque_off(self) -> None:
        """In FAULT with torque off unconfirmed: the bus answered again, switch torque off now."""
        try:
            self.actuator.disable()
        except Exception:
            return  # still not confirmed: next good read tries again
        self._torque_unconfirmed = False
        self._event("status", "torque_off_confirmed", f"{self.robot}: torque off confirmed on every joint")

    # ------------------------------------------------------------------ the cycle
    def on_read(self, feedback: JointFeedback, fault: Fault | None) -> None:
        """Account for this cycle's read. A fault (after ``safety.bus_errors_max`` transient ones
        in a row, or at once for a non-transient one) puts the robot in FAULT, torque off. A joint
        whose measured position stays farther than ``safety.tracking_error_max`` from its position
        command for TRACKING_CYCLES cycles does too."""
        active = self.state in (OperatingState.ENABLED, OperatingState.PAUSED)
        if fault is not None:
            self._consecutive_bus_errors += 1
            if active and (not fault.transient or self._consecutive_bus_errors >= self.safety.bus_errors_max):
                self._enter_fault(fault)
            return
        self._consecutive_bus_errors = 0
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
        if active and self._written:
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
        """Advance motion by one cycle and fill ``self.command``. Returns True if it must be written."""
        if self.state not in (OperatingState.ENABLED, OperatingState.PAUSED):
            self._written = False
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
            msg = m.step(now, measured[m.idx])
            if msg:
                self._event("warning", "servo_timeout", msg, m.name)
            m.fill(cmd)
        if self.homing and not any(m.busy for m in self.namespaces.values()):
            self.homing = False
            self.is_homed = True
        if self._busy_reported and not self.is_busy:
            self._push_state()  # busy=False edge (also carries is_homed after home)
        self._written = True
        return True

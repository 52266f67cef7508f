"""The CRTK controller: operating-state machine and joint motion, one step per loop cycle.

It is the logic of the control process without the process: it owns no socket and no clock of
its own, so tests drive it directly with a fake actuator. The loop (``core/loop.py``) feeds it
one measured sample per cycle, the requests that arrived, and sends what it puts in ``outbox``.

Messages (dicts, see docs/protocol.md):
* request: ``{"id", "cmd", "ns", "data"}`` -> exactly one reply appended to ``outbox``:
  ``{"id", "ok": True, "data"}`` or ``{"id", "ok": False, "error": {"code", "message"}}``;
* events appended to ``outbox`` in causal order: ``{"event": "operating_state", "data"}``,
  ``{"event": "warning"|"error"|"status", "data": {"stamp", "ns", "code", "message"}}``.

Motion per namespace (arm and gripper each have their own setpoints and trajectory generator,
sharing one operating state):
* ``servo_jp`` / ``servo_jr``: latest wins, applied on this cycle's write; a step larger than
  ``safety.servo_step_max`` from the last setpoint is refused; setpoints outside the joint limits
  are clipped with a rate-limited warning; a stream silent for ``safety.servo_timeout_s`` holds.
* ``move_jp`` / ``move_jr``: ruckig jerk-limited trajectory from the current setpoint state to the
  goal, ending at rest, re-planned from the current state when a new goal arrives mid-motion. Goals
  outside the joint limits are refused.
"""

from __future__ import annotations

import enum
import math
from typing import Any, Callable

import numpy as np
from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig

from ..errors import BackendError
from ..profile import Profile
from .actuator import Actuator, CommandMode, Fault, JointCommand, JointFeedback
from .state import OperatingState, StateCommand, transition

STATE_COMMANDS = tuple(c.value for c in StateCommand)
MOTION_COMMANDS = ("servo_jp", "servo_jr", "move_jp", "move_jr")
_WARN_INTERVAL_S = 1.0  # at most one clipping warning per namespace per second


class Refused(Exception):
    """A request refused; becomes an error reply with ``code``."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


class Mode(enum.Enum):
    HOLD = 0  # keep the last setpoint
    SERVO = 1  # follow servo_jp / servo_jr
    MOVE = 2  # follow a ruckig trajectory
    STOP = 3  # decelerate to rest (pause, client loss), then HOLD


class NamespaceMotion:
    """Setpoint bookkeeping and trajectory generator of one CRTK namespace."""

    def __init__(self, name: str, indices: list[int], profile: Profile, dt: float):
        self.name = name
        self.idx = np.asarray(indices, dtype=np.intp)
        self.joint_names = [profile.joints[i].name for i in indices]
        joints = [profile.joints[i] for i in indices]
        self.n = len(indices)
        self.pos_min = np.array([j.limits.position_min for j in joints])
        self.pos_max = np.array([j.limits.position_max for j in joints])
        self.home = np.array([j.home for j in joints])
        self.mode = Mode.HOLD
        self.level: str | None = None  # command level that produced the setpoint (spec 4.2.5)
        self.setpoint_p = np.zeros(self.n)
        self.setpoint_v = np.zeros(self.n)
        self.setpoint_stamp = 0.0
        self.setpoint_has_v = False
        self.goal_p = np.zeros(self.n)
        self.goal_stamp = 0.0
        self.last_servo_time = 0.0
        self.last_clip_warning = -math.inf
        self.otg = Ruckig(self.n, dt)
        self.inp = InputParameter(self.n)
        self.out = OutputParameter(self.n)
        self.inp.max_velocity = [j.limits.velocity_max for j in joints]
        self.inp.max_acceleration = [j.limits.acceleration_max for j in joints]
        self.inp.max_jerk = [j.limits.jerk_max for j in joints]

    def reset(self, measured_p: np.ndarray) -> None:
        """Hold where the joints are (on enable): no surprise motion."""
        self.mode = Mode.HOLD
        self.level = None
        self.setpoint_p[:] = measured_p
        self.setpoint_v[:] = 0.0
        self.setpoint_has_v = False
        self.setpoint_stamp = 0.0
        self.goal_stamp = 0.0

    def invalidate(self) -> None:
        """Torque off: setpoints and goals become invalid (stamp 0)."""
        self.mode = Mode.HOLD
        self.level = None
        self.setpoint_stamp = 0.0
        self.goal_stamp = 0.0
        self.setpoint_v[:] = 0.0

    def start_move(self, goal: np.ndarray, now: float) -> None:
        inp = self.inp
        if self.mode is not Mode.MOVE and self.mode is not Mode.STOP:
            # start from rest at the current setpoint
            inp.current_position = self.setpoint_p
            inp.current_velocity = np.zeros(self.n)
            inp.current_acceleration = np.zeros(self.n)
        # else: re-plan from the trajectory's current state (already in inp via pass_to_input)
        inp.control_interface = ControlInterface.Position
        inp.target_position = goal
        inp.target_velocity = np.zeros(self.n)
        inp.target_acceleration = np.zeros(self.n)
        self.goal_p[:] = goal
        self.goal_stamp = now
        self.mode = Mode.MOVE
        self.level = "move_jp"

    def start_stop(self) -> None:
        """Decelerate a running trajectory to rest (jerk-limited), then hold."""
        if self.mode is Mode.MOVE:
            self.inp.control_interface = ControlInterface.Velocity
            self.inp.target_velocity = np.zeros(self.n)
            self.inp.target_acceleration = np.zeros(self.n)
            self.mode = Mode.STOP
        elif self.mode is Mode.SERVO:
            self.mode = Mode.HOLD
            self.setpoint_v[:] = 0.0

    def step_trajectory(self, now: float) -> bool:
        """Advance MOVE / STOP by one cycle. Returns True when the trajectory has finished."""
        result = self.otg.update(self.inp, self.out)
        if result is Result.Error or result is Result.ErrorInvalidInput:
            # cannot happen with validated limits; hold rather than move unpredictably
            self.mode = Mode.HOLD
            self.setpoint_v[:] = 0.0
            return True
        self.setpoint_p[:] = self.out.new_position
        self.setpoint_v[:] = self.out.new_velocity
        self.setpoint_has_v = True
        self.setpoint_stamp = now
        self.out.pass_to_input(self.inp)
        if result is Result.Finished:
            self.mode = Mode.HOLD
            self.setpoint_v[:] = 0.0
            return True
        return False

    @property
    def busy(self) -> bool:
        return self.mode is Mode.MOVE


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
        self.namespaces: dict[str, NamespaceMotion] = {
            ns.name: NamespaceMotion(ns.name, [profile.joint_index(j) for j in ns.joints], profile, self.dt)
            for ns in profile.namespaces
        }
        self.command = actuator.new_command()
        self.feedback = actuator.new_feedback()  # latest sample, copied in by step()
        self.fault_cause: Fault | None = None
        self._consecutive_bus_errors = 0

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

    def supported_commands(self) -> list[str]:
        cmds = list(STATE_COMMANDS)
        if self.caps.position:
            cmds += list(MOTION_COMMANDS)
        return cmds

    # ------------------------------------------------------------------ events
    def _push_state(self) -> None:
        self.state_stamp = self.clock()
        self._busy_reported = self.is_busy
        self.outbox.append({"event": "operating_state", "data": self.operating_state()})

    def _event(self, kind: str, code: str, message: str, ns: str | None = None) -> None:
        self.outbox.append(
            {"event": kind, "data": {"stamp": self.clock(), "ns": ns or self.robot, "code": code, "message": message}}
        )

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
        if cmd not in MOTION_COMMANDS:
            raise Refused("unknown_command", f"{self.robot}: unknown command {cmd!r}")
        motion = self.namespaces.get(ns)
        if motion is None:
            raise Refused("unknown_namespace", f"{self.robot}: unknown namespace {ns!r} (have: {', '.join(self.namespaces)})")
        if not self.caps.position:
            raise Refused("unsupported", f"{ns}: {cmd} unsupported: the backend has no position control")
        self._check_can_move(ns, cmd)
        vec = self._vector(ns, cmd, motion, data.get("position"), "position")
        if cmd == "servo_jp":
            ff = data.get("velocity")
            v = self._vector(ns, cmd, motion, ff, "velocity") if ff else None
            return self._servo(motion, vec, v)
        if cmd == "servo_jr":
            return self._servo(motion, motion.setpoint_p + vec, None)
        if cmd == "move_jp":
            return self._move(motion, vec)
        # move_jr: relative to the current goal while a move runs, else to the setpoint
        base = motion.goal_p if motion.mode is Mode.MOVE else motion.setpoint_p
        return self._move(motion, base + vec)

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

    def _servo(self, m: NamespaceMotion, p: np.ndarray, v: np.ndarray | None) -> None:
        now = self.clock()
        step = np.abs(p - m.setpoint_p)
        worst = int(np.argmax(step))
        if step[worst] > self.safety.servo_step_max:
            raise Refused(
                "step_too_large",
                f"{m.name}: servo step refused: joint {m.joint_names[worst]!r} would jump {step[worst]:.4f} rad "
                f"from its setpoint {m.setpoint_p[worst]:.4f} (safety.servo_step_max = {self.safety.servo_step_max})",
            )
        clipped = np.clip(p, m.pos_min, m.pos_max)
        if np.any(clipped != p) and now - m.last_clip_warning >= _WARN_INTERVAL_S:
            m.last_clip_warning = now
            j = int(np.argmax(np.abs(clipped - p)))
            self._event(
                "warning", "limit_clipped",
                f"{m.name}: servo setpoint of joint {m.joint_names[j]!r} ({p[j]:.4f} rad) clipped to its limit "
                f"[{m.pos_min[j]:.4f}, {m.pos_max[j]:.4f}]", m.name,
            )
        was_busy = self.is_busy
        m.mode = Mode.SERVO
        m.level = "servo_jp"
        m.setpoint_p[:] = clipped
        m.setpoint_has_v = v is not None
        m.setpoint_v[:] = v if v is not None else 0.0
        m.setpoint_stamp = now
        m.goal_stamp = 0.0  # no interpolate/move goal while servoing
        m.last_servo_time = now
        if was_busy and not self.is_busy:  # the servo pre-empted a move
            self._push_state()
        return None

    def _move(self, m: NamespaceMotion, goal: np.ndarray) -> dict:
        bad = np.flatnonzero((goal < m.pos_min) | (goal > m.pos_max))
        if bad.size:
            j = int(bad[0])
            raise Refused(
                "out_of_limits",
                f"{m.name}: move refused: goal {goal[j]:.4f} rad for joint {m.joint_names[j]!r} is outside "
                f"its limits [{m.pos_min[j]:.4f}, {m.pos_max[j]:.4f}]",
            )
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
        except BackendError as exc:
            self._enter_fault(Fault("enable_failed", str(exc), transient=False))
            raise Refused("fault", f"{self.robot}: enable failed: {exc}") from exc
        for m in self.namespaces.values():
            m.reset(self.feedback.position[m.idx])
        self.fault_cause = None
        self._consecutive_bus_errors = 0
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
        if not self.caps.position:
            raise Refused("unsupported", f"{self.robot}: home unsupported without position control")
        now = self.clock()
        for m in self.namespaces.values():
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
            m.start_stop()
        self.homing = False
        if was_busy:
            self._push_state()

    def _client_lost(self) -> None:
        """The controlling session went away: stop moves, hold servo streams."""
        moving = [m.name for m in self.namespaces.values() if m.mode in (Mode.MOVE, Mode.SERVO)]
        if self.state is OperatingState.ENABLED and moving:
            self._stop_all()
            self._event("warning", "control_released",
                        f"{self.robot}: controlling client disconnected; holding {', '.join(moving)}")

    def _enter_fault(self, fault: Fault) -> None:
        self.fault_cause = fault
        self._abort_motion()
        try:
            self.actuator.disable()
        except Exception:
            pass  # best effort: the bus may be gone
        self._event("error", fault.code, fault.message)
        self._set_state(OperatingState.FAULT)

    # ------------------------------------------------------------------ the cycle
    def on_read(self, feedback: JointFeedback, fault: Fault | None) -> None:
        """Account for this cycle's read. A fault (after ``safety.bus_errors_max`` transient ones
        in a row, or at once for a non-transient one) puts the robot in FAULT, torque off."""
        if fault is None:
            self._consecutive_bus_errors = 0
            f = self.feedback
            f.position[:] = feedback.position
            f.velocity[:] = feedback.velocity
            f.effort[:] = feedback.effort
            f.stamp = feedback.stamp
            return
        self._consecutive_bus_errors += 1
        if self.state in (OperatingState.ENABLED, OperatingState.PAUSED) and (
            not fault.transient or self._consecutive_bus_errors >= self.safety.bus_errors_max
        ):
            self._enter_fault(fault)

    def step(self) -> bool:
        """Advance motion by one cycle and fill ``self.command``. Returns True if it must be written."""
        if self.state not in (OperatingState.ENABLED, OperatingState.PAUSED):
            return False
        now = self.clock()
        cmd = self.command
        for m in self.namespaces.values():
            if m.mode is Mode.MOVE or m.mode is Mode.STOP:
                m.step_trajectory(now)
            elif m.mode is Mode.SERVO and now - m.last_servo_time > self.safety.servo_timeout_s:
                m.mode = Mode.HOLD
                m.setpoint_v[:] = 0.0
                self._event("warning", "servo_timeout",
                            f"{m.name}: no servo command for {self.safety.servo_timeout_s} s; holding position", m.name)
            cmd.mode[m.idx] = CommandMode.POSITION
            cmd.position[m.idx] = m.setpoint_p
            cmd.velocity[m.idx] = m.setpoint_v
        if self.homing and not any(m.busy for m in self.namespaces.values()):
            self.homing = False
            self.is_homed = True
        if self._busy_reported and not self.is_busy:
            self._push_state()  # busy=False edge (also carries is_homed after home)
        return True

    # ------------------------------------------------------------------ views for the snapshot
    def setpoint_fields(self, m: NamespaceMotion) -> tuple[bool, bool, bool]:
        """Which of position / velocity / effort setpoint_js carries (spec 4.2.5 summary)."""
        if m.setpoint_stamp == 0.0 or m.level is None:
            return (False, False, False)
        return (True, m.setpoint_has_v, False)

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
from typing import Any, Callable

import numpy as np

from ...profile import Profile, stop_deceleration
from ..actuator import Actuator, Capabilities, CommandMode, Fault, Lifecycle
from ..motion import Mode, NamespaceMotion
from ..native_cartesian import NATIVE_COMMANDS, build_native_cartesian
from ..state import OperatingState, StateCommand
from ..twist import TWIST_COMMANDS, build_twist_motions
from .common import DEFERRED, MOTION_COMMANDS, STATE_COMMANDS, Refused
from .park import ParkMixin
from .relays import RelaysMixin
from .supervisor import SupervisorMixin
from .transitions import _Running, TransitionsMixin
from .validation import ValidationMixin

_DEFERRED = DEFERRED
_NONE = int(CommandMode.NONE)


class Controller(TransitionsMixin, SupervisorMixin, RelaysMixin, ParkMixin, ValidationMixin):
    """Operating-state machine + motion layer. Not thread-safe; one call at a time.

    ``actuator`` is used on the lifecycle path only (transitions, stepped one per cycle);
    the loop does the real-time read and write. Its concerns live in the modules of this
    package (transitions, supervisor, relays, park, validation), mixed in here over one state.
    """

    def __init__(self, profile: Profile, actuator: Actuator, clock: Callable[[], float], period_s: float):
        self.profile = profile
        self.actuator = actuator
        #: what the backend declares (immutable, final once open): read here and nowhere else
        self.traits = traits = actuator.traits
        self.caps = traits.capabilities
        self.clock = clock
        self.robot = profile.name
        #: the cycle period (s): :func:`~crtk_bridge.core.actuator.effective_period_s`, the loop's
        self.dt = float(period_s)
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
        #: per namespace, what the cycle steps (its motion, twist mapping, native cartesian or
        #: None), and its joints' measured positions (a view when they are consecutive, as usual)
        self._steps = [(m, self.twist_motions.get(name), self.native_cartesian.get(name), m.cols)
                       for name, m in self.namespaces.items()]
        self.command = actuator.new_command()
        # its position, velocity and effort: the rows of one block, filled per namespace in one copy
        self._command_block = np.zeros((3, len(profile.joints)))
        self.command.position, self.command.velocity, self.command.effort = self._command_block
        self.feedback = actuator.new_feedback()  # latest sample, copied in by on_read()
        #: its position, velocity and effort: the rows of one block (published in one copy)
        self.measured_block = np.zeros((3, len(profile.joints)))
        self.feedback.position, self.feedback.velocity, self.feedback.effort = self.measured_block
        self.fault_cause: Fault | None = None
        self._consecutive_bus_errors = 0
        self._tracking_cycles = 0
        self._written = False  # self.command holds what was written last cycle
        self._torque_unconfirmed = False  # a fault's torque off did not reach the bus
        self._last_torque_retry = -math.inf
        self._consecutive_write_errors = 0
        self._running: _Running | None = None  # the lifecycle transition in progress
        #: the command modes the backend follows as it is (:meth:`_switch_modes`), as bytes
        self._modes_ok = b""
        self._next_modes = self.command.mode.copy()  # a motion command's modes, before its fill
        self._cycle = 0  # counts on_read calls: one transition step per cycle
        self._rid: Any = None  # id of the request being handled
        self._speed_fraction = float("nan")  # the device's speed slider as last reported (NaN: none)
        self._device_notices: dict[str, dict[str, Any]] = {}  # joint -> its device's latest NOTICE

    # ------------------------------------------------------------------ queries
    @property
    def is_busy(self) -> bool:
        run = self._running  # an operating-mode switch is not: servo commands never raise is_busy
        return self.homing or (run is not None and run.transition.kind is not Lifecycle.MODE_SWITCH) \
            or any(m.busy for m in self.namespaces.values()) or any(nc.busy for nc in self.native_cartesian.values())

    @property
    def measured_valid(self) -> bool:
        """The latest sample stands for the device: fewer than ``safety.bus_errors_max`` failed
        reads in a row (a missed read leaves the last sample, honestly stamped)."""
        return self._consecutive_bus_errors < self.safety.bus_errors_max

    @property
    def torque_unconfirmed(self) -> bool:
        """In FAULT, the fault reaction's torque off has not been confirmed by the bus yet."""
        return self._torque_unconfirmed

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
        if self._device_notices:  # what a device last said of its work (a gripper's grasp)
            out["device_notices"] = {j: dict(n) for j, n in self._device_notices.items()}
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
    def push_state(self) -> None:
        """An ``operating_state`` event with the state as it is now."""
        self.state_stamp = self.clock()
        self._busy_reported = self.is_busy
        self.outbox.append({"event": "operating_state", "data": self.operating_state()})

    def event(self, kind: str, code: str, message: str, ns: str | None = None, **cause: Any) -> None:
        """A ``warning`` / ``error`` / ``status`` event (``ns`` None: the robot's), with the
        ``cause`` fields that are not None (joint, register, value)."""
        data = {"stamp": self.clock(), "ns": ns or self.robot, "code": code, "message": message}
        data.update((k, v) for k, v in cause.items() if v is not None)
        self.outbox.append({"event": kind, "data": data})

    def _set_state(self, state: OperatingState) -> None:
        if state is not self.state:
            self.state = state
            self.event("status", "state_changed", f"{self.robot}: {state.value}")
        self.push_state()

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
        if result is not _DEFERRED and self._running is None and self.state is OperatingState.ENABLED:
            modes = self._next_modes
            modes[:] = self.command.mode
            modes[m.idx] = m.command_mode()
            if modes.tobytes() != self._modes_ok:  # the device may need another operating mode
                return self._switch_modes(modes, result)
        return result

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
            self.push_state()
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

    def _move(self, m: NamespaceMotion, goal: np.ndarray) -> dict:
        self._check_goal(m, goal)
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
        self.push_state()

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
            self.push_state()

    # ------------------------------------------------------------------ the cycle
    def torque_switched_off(self) -> None:
        """The loop switched torque off outside any transition (shutdown): motion ends, the robot
        is DISABLED, and clients hear of it."""
        self._abort_motion()
        self.state = OperatingState.DISABLED
        self.push_state()

    def torque_off_failed(self, exc: Exception) -> None:
        """The loop's torque off at shutdown failed (``exc`` names the joint): motion ends, the
        robot is FAULT with torque off unconfirmed, and clients hear it as an error; never DISABLED."""
        self._abort_motion()
        message = (f"{self.robot}: shutdown: torque off not confirmed ({exc}); the joint may still hold "
                   "torque: check it and switch its power off")
        self.fault_cause = Fault("torque_off_unconfirmed", message, transient=False)
        self._torque_unconfirmed = True
        self.event("error", "torque_off_unconfirmed", message)
        self._set_state(OperatingState.FAULT)

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
        for m, tm, nc, rows in self._steps:
            here = measured[rows]  # this namespace's joints (a view, or a copy: read only below)
            if m.mode is Mode.FREE:
                m.setpoint_p[:] = here  # follow the hand: leaving free is bumpless
            if tm is not None:
                tm.update()  # a twist stream: joint velocities mapped at this cycle's setpoint
            if nc is not None:
                msg = nc.update(now, here, self.feedback.cartesian)
                if msg:
                    self.event("warning", "servo_timeout", msg, m.name)
            msg = m.step(now, here)
            if msg:
                self.event("warning", "servo_timeout", msg, m.name)
            if m.error is not None:
                self.event("error", "trajectory_failed", m.error, m.name)
                m.error = None
            m.fill(cmd, self._command_block)
            if nc is not None:
                nc.fill(cmd.mode, cmd.cartesian)  # the backend's cartesian row; its joints left to it
        if self._running is None and cmd.mode.tobytes() != self._modes_ok:
            self._switch_modes(cmd.mode, None, request=False)  # a stop, a watchdog, a park changed a joint's mode
        if self.homing and not any(m.busy for m in self.namespaces.values()):
            self.homing = False
            self.is_homed = True
        if self._busy_reported and not self.is_busy:
            self.push_state()  # busy=False edge (also carries is_homed after home)
        self._written = True
        return True

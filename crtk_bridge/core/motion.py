"""Joint motion of one CRTK namespace: servo, interpolate and move, with setpoint / goal bookkeeping.

Each namespace (an arm, its gripper) has its own setpoints, goals and trajectory generator, so a
gripper move never disturbs the arm's servo stream (the dVRK jaw lesson), while all namespaces
share one operating state (see ``control/controller.py``).

Levels and what they produce each cycle (crtk-spec 4.1.1, setpoint fields per 4.2.5):

| mode | source | setpoint_js fields | native command |
|---|---|---|---|
| SERVO_P  | latest servo_jp / servo_jr (+ optional velocity feed-forward), followed at <= velocity_max | p (+v) | position |
| SERVO_V  | latest servo_jv; integrated into p on position-only hardware | v (+p) | velocity or position |
| SERVO_F  | latest servo_jf | f | effort |
| INTERP_P | linear interpolation to each interpolate_jp goal over one estimated command period (``loop.interpolation: smooth``: averaged over that period; ``predict``: to the goal extrapolated one step, averaged) | p, v | position |
| INTERP_V | setpoint velocity ramps to each interpolate_jv goal at the acceleration limit | v (+p) | velocity or position |
| INTERP_F | linear ramp to each interpolate_jf goal over one estimated command period | f | effort |
| MOVE     | ruckig jerk-limited trajectory to the move goal, ending at rest | p, v | position |
| STOP     | brakes to rest at the joints' stop deceleration (pause, hold, client loss, watchdog), then HOLD | p, v | position |
| HOLD     | the last position setpoint | p | position |
| FREE     | nothing: torque off on these joints (`free`) | – | free |

Limits in one place (docs/architecture.md): this layer's output (:meth:`NamespaceMotion.fill`)
is the one guarantee of the profile's limits -- positions within ``[position_min,
position_max]`` (or coming back toward them), velocities within ``velocity_max``, efforts within
``effort_max`` -- and :meth:`~crtk_bridge.core.actuator.Actuator.write` refuses a non-finite
setpoint for every backend; backends clamp only to their devices' own ranges.

Velocity bounds, on every path: every velocity that enters this layer (servo_jv, interpolate_jv
goals, the servo_jp feed-forward, the velocity a new interpolate_jv ramp or move starts from) is
clipped to each joint's ``velocity_max``, and the position setpoint never moves faster than
``velocity_max``: servo_jp / servo_jr targets are followed at most ``velocity_max * dt`` per
cycle (a 500 Hz stream is otherwise bounded only per message by ``safety.servo_step_max``),
interpolate_jp likewise, velocity integration clips its velocity, ruckig plans within the limits.

Stops (``stop``: hold, pause, a stream's watchdog, client loss): a stop is not a trajectory. What
moves with a velocity of its own (a move, an integrated servo_jv / interpolate_jv or twist stream)
brakes at each joint's stop deceleration (``limits.stop_deceleration_max``, default a few times
``acceleration_max`` bounded by the hardware: ``profile.stop_deceleration``), jerk-unlimited,
every joint reaching rest at the same instant (each decelerates at ``|v| / T``, T the longest
joint's braking time), so the joints keep their direction of motion while braking; a stopped
move's joints end at its goal at the latest (a stop deceleration below the move's acceleration
would brake past it). Position
streams (servo_jp / interpolate_jp) hold the setpoint where it is: it never passes the client's
own positions. The stopping distance from ``velocity_max`` is ``v^2 / (2 d)`` plus one cycle
(docs/protocol.md, Safety).

Interpolation of a position stream (interpolate_jp): a reference moves linearly from where it
is to each goal over one estimated command period (an exponential average of the
inter-arrival times, clamped to [loop period, servo_timeout_s]), at most ``velocity_max``;
with ``loop.interpolation: linear`` (the default) the setpoint is that reference: it passes
through every goal, its velocity stepping at each one, one period of latency. With ``smooth``
the setpoint is the reference averaged over the last command period (a moving average: the
quadratic B-spline of the stream), so its velocity is continuous: it changes linearly over a
period instead of stepping at each goal, where a 30 Hz stream makes the bare linear
interpolation move in kinks (issue 21); half a period more latency, and a sharp corner of the
stream is rounded by up to ``|change of velocity| * period / 8``. Being an average of
positions the reference held, the setpoint never passes a goal, never leaves the position
limits nor exceeds ``velocity_max``, and reaches the last goal exactly (then holds it).

``predict`` (opt-in: it extrapolates) removes that latency: the reference heads for each goal
carried one more step, ``a_k + (a_k - a_{k-1})`` (the stream's velocity over one estimated
period: never more than its last step, less for a goal that came after a gap longer than the
period and a cycle, but never short of the last aim where that is within the step: a stream
never heads back; nothing for a stream's first goal, clipped to the position limits), reaching
it one estimated period after goal k came, and the setpoint averages it as ``smooth`` does, over
the period less two loop periods. The reference then follows the stream about where the
client's goals will be, and its average lags them by half a period less one loop period: a
staircase of the goals written at once (LeRobot's direct writes) lags them by half a period,
and the loop period is the daemon's own delay (a goal waits for the next cycle, the bus holds
each setpoint for a period), so the servo lags the goals about as much as with direct writes.
The velocity stays continuous, changing over the shorter window. The reference holds the
extrapolated goal until two estimated periods (the estimate before or after the goal, whichever
is longer, or the longest of the last four inter-arrival times, and two loop periods) after the
last goal came, so a goal late by up to
a period (a hiccup, goals arriving in bursts) finds it still there and the setpoint never moves
back against a monotonic stream; with no new goal by then (a clearly late goal, an ended
stream) the reference returns to the last goal over the next period, so the stream ends
exactly on its last goal and holds it; the price is an overshoot past the client's goals on a
stop or a reversal of at most one step of the stream. A stop (hold) of a predict stream holds
where the setpoint is, at most one step past the last goal. A stream's watchdog waits until the
setpoint reached its last goal (up to 2 periods; predict 4 and two loop periods, longer for
goals in bursts).
"""

from __future__ import annotations

import enum

import numpy as np
from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig

from ..profile import Profile, stop_deceleration
from .actuator import Capabilities, CommandMode, JointCommand, ruckig_update


def _clip(a, lo, hi, out: np.ndarray) -> np.ndarray:
    """``np.clip(a, lo, hi, out=out)`` (NaN stays NaN; ``lo`` > ``hi`` gives ``hi``) in two ufunc
    calls: np.clip's Python wrapper costs several times the work on a few joints, in every cycle."""
    return np.minimum(np.maximum(a, lo, out=out), hi, out=out)


class Mode(enum.Enum):
    HOLD = "hold"
    SERVO_P = "servo_jp"
    SERVO_V = "servo_jv"
    SERVO_F = "servo_jf"
    INTERP_P = "interpolate_jp"
    INTERP_V = "interpolate_jv"
    INTERP_F = "interpolate_jf"
    MOVE = "move_jp"
    STOP = "stop"
    FREE = "free"


STREAMS = (Mode.SERVO_P, Mode.SERVO_V, Mode.SERVO_F, Mode.INTERP_P, Mode.INTERP_V, Mode.INTERP_F)
VELOCITY_MODES = (Mode.SERVO_V, Mode.INTERP_V)
EFFORT_MODES = (Mode.SERVO_F, Mode.INTERP_F)
#: per cycle, how far interpolate_jp's averaging window moves toward the period estimate
_WIDTH_GAIN = 0.05
_PERIOD_GAIN = 0.3  # weight of the newest inter-arrival time in the command-period estimate
# predict: loop periods, past two command periods, a stream's reference holds the extrapolated goal
# before returning to the last goal (a goal arrives on a cycle: a goal a period late may be seen
# up to a cycle after two periods)
_RETURN_MARGIN = 2.0
_GAPS = 4  # predict: inter-arrival times a stream's hold before the return lasts at least (bursts)
# An integrated velocity advances over the time really elapsed since the last cycle (a loop that
# skipped cycles after an overrun must not shorten the path: on a loaded host, with the bus I/O
# of a cycle taking 20 ms, that lost a tenth of every velocity path), but over no more than
# 50 ms (or 3 periods on a slower loop) at once: a stalled loop must not make the setpoint jump.
_INTEGRATE_MAX_GAP_S = 0.05
_INTEGRATE_MAX_PERIODS = 3.0


class NamespaceMotion:
    """Setpoints, goals and trajectory generator of one namespace. All vectors in rad, rad/s, N*m."""

    def __init__(self, name: str, indices: list[int], profile: Profile, dt: float, caps: Capabilities,
                 stop_dec: np.ndarray | None = None):
        self.name = name
        #: an error the controller reports (and clears) after the cycle's step: a failed plan
        self.error: str | None = None
        self.idx = np.asarray(indices, dtype=np.intp)
        # the joints as a slice when they are consecutive (as usual: indexing is then a view)
        self.cols = (slice(indices[0], indices[0] + len(indices))
                     if len(indices) and list(indices) == list(range(indices[0], indices[0] + len(indices)))
                     else self.idx)
        joints = [profile.joints[i] for i in indices]
        self.joint_names = [j.name for j in joints]
        self.n = n = len(indices)
        self.dt = dt
        self.caps = caps
        self.timeout = profile.safety.servo_timeout_s
        self.pos_min = np.array([j.limits.position_min for j in joints])
        self.pos_max = np.array([j.limits.position_max for j in joints])
        self.vel_max = np.array([j.limits.velocity_max for j in joints])
        self.acc_max = np.array([j.limits.acceleration_max for j in joints])
        self.eff_max = np.array([j.limits.effort_max if j.limits.effort_max is not None else np.inf for j in joints])
        #: rad/s^2 a stop brakes each joint at (the controller passes the hardware-bounded values)
        self.stop_dec = (np.asarray(stop_dec, dtype=float) if stop_dec is not None
                         else np.array([stop_deceleration(j.limits) for j in joints]))
        self._brake_dec = np.zeros(n)  # rad/s^2 each joint decelerates at in the running stop
        # where the running stop ends at the latest, per joint: a move's goal (brake)
        self._brake_lo = np.full(n, -np.inf)
        self._brake_hi = np.full(n, np.inf)
        #: the pose `home` moves to; None: a joint of the profile has no `home` key
        self.home = (np.array([j.home for j in joints]) if all(j.home is not None for j in joints) else None)
        self.no_home = [j.name for j in joints if j.home is None]
        self.mode = Mode.HOLD
        self.level: Mode | None = None  # command level that produced the setpoint (None: invalid)
        #: setpoint p, v, f and goal p, v, f: the rows of one block, in the snapshot's order, so
        #: the loop publishes the six in one copy and :meth:`fill` bounds v and f in one clip
        #: (core/loop.py; each numpy call on a few joints costs microseconds in a cold cycle)
        self.block = np.zeros((6, n))
        self.setpoint_p, self.setpoint_v, self.setpoint_f, self.goal_p, self.goal_v, self.goal_f = self.block
        self._vf = self.block[1:3]  # setpoint v and f
        self._pvf = self.block[:3]  # setpoint p, v and f
        self.has_v_ff = False  # servo_jp carried a velocity feed-forward
        self.servo_target = np.zeros(n)  # latest servo_jp / servo_jr position; setpoint_p follows it
        self.servo_rate = np.zeros(n)  # rad/s the position setpoint really moved at last cycle (SERVO_P)
        self.setpoint_stamp = 0.0
        self.goal_level: Mode | None = None  # interpolate_* or move that set the goal
        self.goal_stamp = 0.0
        self.last_cmd_time = 0.0
        self.last_clip_warning = -np.inf
        self.cmd_period = 0.02  # estimated interpolate command period, s
        self.interp_start = np.zeros(n)  # where the interpolation (interpolate_jp's reference, interpolate_jf) starts
        self.interp_t0 = 0.0
        # interpolate_jp: the reference (linear to each goal) and its positions over the last
        # servo_timeout_s, written twice (rows i and i + rows) so the averaging window (the last
        # command period) is always one slice
        self._ref = np.zeros(n)
        self._ref_rows = int(np.ceil(self.timeout / dt)) + 1
        self._ref_hist = np.zeros((2 * self._ref_rows, n))
        self._ref_i = 0
        self._width = 1.0  # rows the average spans now (cmd_period / dt, followed slowly)
        # smooth and predict average the reference over the period; linear: the average spans one row
        self._smooth = profile.loop.interpolation in ("smooth", "predict")
        self._predict = profile.loop.interpolation == "predict"
        # rows predict's average spans less than the period: 2, one loop period less lag (the
        # daemon's own delay: a goal waits for the next cycle, the bus holds each setpoint a period)
        self._shorten = 2.0 if self._predict else 0.0
        # interpolate_jp: where the reference heads (the goal; predict: the extrapolated goal)
        # predict: the stream's last few inter-arrival times (s, at most servo_timeout_s)
        self._gaps = np.zeros(_GAPS)
        self._hold_s = 0.0  # predict: s after the last goal the reference holds the aim (then returns)
        self._aim = np.zeros(n)
        self.otg = Ruckig(n, dt)
        self.inp = InputParameter(n)
        self.out = OutputParameter(n)
        self.inp.max_velocity = self.vel_max
        self.inp.max_acceleration = self.acc_max
        self.inp.max_jerk = [j.limits.jerk_max for j in joints]
        self._zeros = np.zeros(n)
        self._tmp = np.zeros(n)
        # the limits stage lets a setpoint outside the limits (a joint enabled or freed there)
        # come back at the motion's own rate, never snap to the limit: [min(lower, last), max(upper, last)]
        self._filled = np.zeros(n)  # the position setpoint the last fill wrote
        self._lo = np.zeros(n)
        self._hi = np.zeros(n)
        self._integrated_at = 0.0  # clock of the last velocity integration (0: none yet)
        self._integrate_max_s = max(_INTEGRATE_MAX_GAP_S, _INTEGRATE_MAX_PERIODS * dt)
        self._step_max = self.vel_max * dt  # rad: the farthest a position setpoint moves in one cycle
        # the negated bounds, made once (a negation per clip was an array made in every cycle)
        self._vel_min = -self.vel_max
        self._eff_min = -self.eff_max
        self._step_min = -self._step_max
        self._vf_max = np.array([self.vel_max, self.eff_max])  # the bounds of setpoint v and f
        self._vf_min = -self._vf_max

    # ------------------------------------------------------------------ fields (spec 4.2.5)
    def setpoint_fields(self) -> tuple[bool, bool, bool]:
        """Which of position / velocity / effort setpoint_js carries now."""
        lv = self.level
        if lv is None or self.setpoint_stamp == 0.0:
            return (False, False, False)
        integrated = not self.caps.velocity  # velocity modes integrate into a position setpoint
        if lv is Mode.SERVO_P or lv is Mode.HOLD:
            return (True, self.has_v_ff, False)
        if lv in VELOCITY_MODES:
            return (integrated, True, False)
        if lv in EFFORT_MODES:
            return (False, False, True)
        return (True, True, False)  # INTERP_P, MOVE, STOP: p(t), v(t)

    def goal_fields(self) -> tuple[bool, bool, bool]:
        g = self.goal_level
        if g is None or self.goal_stamp == 0.0:
            return (False, False, False)
        if g in VELOCITY_MODES:
            return (False, True, False)
        if g in EFFORT_MODES:
            return (False, False, True)
        return (True, False, False)

    @property
    def busy(self) -> bool:
        return self.mode is Mode.MOVE

    @property
    def streaming(self) -> bool:
        return self.mode in STREAMS

    # ------------------------------------------------------------------ transitions
    def reset(self, measured_p: np.ndarray) -> None:
        """Hold where the joints are (on enable, or when leaving FREE): no surprise motion."""
        self.mode = Mode.HOLD
        self.level = None
        self.setpoint_p[:] = measured_p
        self._filled[:] = measured_p
        self.setpoint_v[:] = 0.0
        self.setpoint_f[:] = 0.0
        self.has_v_ff = False
        self.setpoint_stamp = 0.0
        self.goal_level = None
        self.goal_stamp = 0.0

    def invalidate(self) -> None:
        """Torque off: setpoints and goals become invalid (stamp 0)."""
        self.mode = Mode.HOLD
        self.level = None
        self.setpoint_stamp = 0.0
        self.goal_level = None
        self.goal_stamp = 0.0
        self.setpoint_v[:] = 0.0
        self.setpoint_f[:] = 0.0

    def _enter(self, mode: Mode, now: float) -> None:
        """Switch to a command level; a stream estimates its command period from arrivals."""
        if mode is self.mode and mode in STREAMS:
            dtc = now - self.last_cmd_time
            if 0.0 < dtc <= self.timeout:
                est = (1 - _PERIOD_GAIN) * self.cmd_period + _PERIOD_GAIN * dtc
                self.cmd_period = min(max(est, self.dt), self.timeout)
        elif mode in STREAMS:
            self.cmd_period = max(0.02, self.dt)  # first command of a stream: assume 50 Hz
        if mode is not self.mode:
            self._integrated_at = 0.0  # a new level integrates its first cycle over one period
        if mode not in EFFORT_MODES:
            self.setpoint_f[:] = 0.0
        self.mode = mode
        self.level = mode
        self.last_cmd_time = now
        self.setpoint_stamp = now

    def servo_p(self, p: np.ndarray, v: np.ndarray | None, now: float) -> None:
        """A servo_jp target: the position setpoint follows it at most ``velocity_max`` per
        second (see :meth:`_step_servo_p`); the feed-forward is clipped to ``velocity_max``."""
        if self.mode is not Mode.SERVO_P:
            self.servo_rate[:] = 0.0
        self._enter(Mode.SERVO_P, now)
        self.servo_target[:] = p
        self.has_v_ff = v is not None
        if v is not None:
            _clip(v, self._vel_min, self.vel_max, self.setpoint_v)
        else:
            self.setpoint_v[:] = 0.0
        self.goal_level = None
        self.goal_stamp = 0.0

    def servo_v(self, v: np.ndarray, now: float) -> None:
        self._enter(Mode.SERVO_V, now)
        _clip(v, self._vel_min, self.vel_max, self.setpoint_v)
        self.goal_level = None
        self.goal_stamp = 0.0

    def servo_f(self, f: np.ndarray, now: float) -> None:
        self._enter(Mode.SERVO_F, now)
        _clip(f, self._eff_min, self.eff_max, self.setpoint_f)
        self.goal_level = None
        self.goal_stamp = 0.0

    def interpolate_p(self, goal: np.ndarray, now: float) -> None:
        streaming = self.mode is Mode.INTERP_P
        if not streaming:
            # a new stream: the reference and its history start at the setpoint (no jump)
            self._ref[:] = self.setpoint_p
            self._ref_hist[:] = self.setpoint_p
            # the first period estimate (below)
            self._width = max(1.0, max(0.02, self.dt) / self.dt - self._shorten) if self._smooth else 1.0
        period, since = self.cmd_period, now - self.last_cmd_time  # before this arrival updates them
        self._enter(Mode.INTERP_P, now)
        self.interp_start[:] = self._ref
        self.interp_t0 = now
        aim = self._aim
        if not streaming:
            self._gaps[:] = 0.0
        elif 0.0 < since <= self.timeout:
            self._gaps[1:] = self._gaps[:-1]
            self._gaps[0] = since
        if self._predict and streaming and since > 0.0:
            # the stream's last step carried one more estimated period: the goal's velocity, the
            # step over the time it took, times the period; never more than that one step (a goal
            # after a gap extrapolates less), and within the position limits
            step = goal - self.goal_p
            # where the last aim is within this step past the goal, it is kept (the reference
            # never heads back against the stream: a goal after a short gap, bursts, extrapolates
            # less than the one before it did)
            kept = np.clip(aim, np.minimum(goal, goal + step), np.maximum(goal, goal + step))
            np.multiply(step, min(1.0, (period + self.dt) / since), out=aim)
            aim += goal
            aim[:] = np.where(step > 0.0, np.maximum(aim, kept), np.minimum(aim, kept))
            lo, hi = self._bounds(goal)
            _clip(aim, lo, hi, aim)
        else:
            aim[:] = goal  # the first goal of a stream, linear, smooth: the goal itself
        if self._predict:
            longest = max(period if streaming else 0.0, self.cmd_period)
            self._hold_s = max(2.0 * longest, self._gaps.max()) + _RETURN_MARGIN * self.dt
        self.goal_p[:] = goal
        self.goal_level = Mode.INTERP_P
        self.goal_stamp = now

    def interpolate_v(self, goal: np.ndarray, now: float) -> None:
        if self.mode is not Mode.INTERP_V:
            # the ramp starts from the velocity the setpoint really has, never from a feed-forward
            self.setpoint_v[:] = self.carried_velocity()
        self._enter(Mode.INTERP_V, now)
        _clip(goal, -self.vel_max, self.vel_max, self.goal_v)
        self.goal_level = Mode.INTERP_V
        self.goal_stamp = now

    def interpolate_f(self, goal: np.ndarray, now: float) -> None:
        start = self.setpoint_f.copy() if self.mode in EFFORT_MODES else np.zeros(self.n)
        self._enter(Mode.INTERP_F, now)
        self.interp_start[:] = start
        self.setpoint_f[:] = start
        self.interp_t0 = now
        _clip(goal, -self.eff_max, self.eff_max, self.goal_f)
        self.goal_level = Mode.INTERP_F
        self.goal_stamp = now

    def start_move(self, goal: np.ndarray, now: float) -> None:
        inp = self.inp
        if self.mode is Mode.MOVE:
            pass  # re-plan from the trajectory's current state (kept in inp by pass_to_input)
        else:  # a stream, or a stop braking: from the setpoint and the velocity it really has
            inp.current_position = self.setpoint_p
            # start from the current setpoint velocity (a servo/interpolate stream in progress)
            inp.current_velocity = self.carried_velocity()
            inp.current_acceleration = self._zeros
        inp.control_interface = ControlInterface.Position
        inp.target_position = goal
        inp.target_velocity = self._zeros
        inp.target_acceleration = self._zeros
        self.goal_p[:] = goal
        self.goal_level = Mode.MOVE
        self.goal_stamp = now
        self.mode = Mode.MOVE
        self.level = Mode.MOVE
        self.setpoint_f[:] = 0.0

    def carried_velocity(self) -> np.ndarray:
        """The velocity the position setpoint really has now, within ``velocity_max``: what a new
        interpolate_jv ramp or move starts from. A servo_jp feed-forward is a claim, not motion:
        what counts is how fast the rate-limited setpoint moved."""
        mode = self.mode
        if mode is Mode.SERVO_P:
            src = self.servo_rate
        elif mode in (Mode.SERVO_V, Mode.INTERP_V, Mode.INTERP_P, Mode.MOVE, Mode.STOP):
            src = self.setpoint_v
        else:
            return np.zeros(self.n)
        return np.clip(src, -self.vel_max, self.vel_max)

    def stop(self) -> None:
        """Come to rest: a move and an integrated velocity stream brake at the stop deceleration
        (:meth:`brake`); position streams hold where they are."""
        if self.mode is Mode.MOVE or (self.mode in VELOCITY_MODES and not self.caps.velocity):
            self.brake()
        elif self.mode in (Mode.SERVO_P, Mode.INTERP_P, Mode.SERVO_V, Mode.INTERP_V):
            self.hold()
        elif self.mode in EFFORT_MODES:
            if self.caps.position:
                self.hold()  # the position setpoint follows the joint in effort modes
            else:
                self.setpoint_f[:] = 0.0

    def brake(self) -> None:
        """Brake the position setpoint from the velocity it has to rest (mode STOP, then HOLD):
        jerk-unlimited at the stop deceleration, every joint at rest at the same instant (the
        slowest joint's braking time T; each decelerates at |v| / T, within its own)."""
        v = self.carried_velocity()
        t = float(np.max(np.abs(v) / self.stop_dec)) if self.n else 0.0
        if not t > 0.0:
            self.hold()
            return
        self.setpoint_v[:] = v
        np.divide(np.abs(v), t, out=self._brake_dec)
        # a move's stop ends at its goal at the latest: a stop deceleration below the move's own
        # acceleration (the profile's, or a servo's low acceleration register) must not carry a
        # joint that heads for its goal past it (one moving away, as a move started against the
        # stream it replaced does at first, brakes as any stop)
        self._brake_lo.fill(-np.inf)
        self._brake_hi.fill(np.inf)
        if self.mode is Mode.MOVE:
            p, goal = self.setpoint_p, self.goal_p
            np.copyto(self._brake_hi, goal, where=(v > 0) & (goal >= p))
            np.copyto(self._brake_lo, goal, where=(v < 0) & (goal <= p))
        self.has_v_ff = False
        self.setpoint_f[:] = 0.0
        self.mode = Mode.STOP
        self.level = Mode.STOP

    def hold(self) -> None:
        """Servo to the current position setpoint (dVRK `hold`)."""
        self.mode = Mode.HOLD
        if self.level is not None:
            self.level = Mode.HOLD
        self.has_v_ff = False
        self.setpoint_v[:] = 0.0
        self.setpoint_f[:] = 0.0

    def free(self) -> None:
        self.invalidate()
        self.mode = Mode.FREE

    # ------------------------------------------------------------------ one cycle
    def step(self, now: float, measured_p: np.ndarray) -> str | None:
        """Advance one cycle. Returns a watchdog message when a stream just timed out."""
        mode = self.mode
        msg = None
        if mode in EFFORT_MODES or (mode in VELOCITY_MODES and self.caps.velocity):
            # native velocity / effort control: the position setpoint follows the joint, so a
            # later position-level command (hold, stop, move, servo_jr) starts where it is
            self.setpoint_p[:] = measured_p
        # the watchdog lets an interpolate_jp setpoint reach its goal first (a bounded motion,
        # the last goal of a stream; interpolation takes up to 2 command periods, predict 4 and 2 cycles or more)
        if mode in STREAMS and now - self.last_cmd_time > self.timeout and not self.interpolating:
            msg = f"{self.name}: no {mode.value} command for {self.timeout} s; "
            if mode in EFFORT_MODES and self.caps.position:
                self.setpoint_p[:] = measured_p
                self.hold()
                msg += "holding position"
            elif mode in EFFORT_MODES:
                self.setpoint_f[:] = 0.0
                msg += "effort set to zero"
            elif mode in VELOCITY_MODES and self.caps.velocity and not self.caps.position:
                self.setpoint_v[:] = 0.0
                msg += "velocity set to zero"
            elif mode in VELOCITY_MODES and not self.caps.velocity:
                self.brake()  # an integrated velocity: brake at the stop deceleration, then hold
                msg += "braking to rest, then holding position"
            else:
                if mode in VELOCITY_MODES and self.caps.velocity:
                    self.setpoint_p[:] = measured_p  # native velocity: hold where the joint is
                self.hold()
                msg += "holding position"
            self.last_cmd_time = now  # say it once
            mode = self.mode
        if mode is Mode.MOVE:
            self._step_trajectory(now)
        elif mode is Mode.STOP:
            self._step_brake(now)
        elif mode is Mode.INTERP_P:
            self._step_interpolate_p(now)
        elif mode is Mode.SERVO_P:
            self._step_servo_p(now)
        elif mode is Mode.SERVO_V:
            self._integrate(now)
        elif mode is Mode.INTERP_V:
            # ramp the setpoint velocity toward the goal at the acceleration limit
            dv = np.clip(self.goal_v - self.setpoint_v, -self.acc_max * self.dt, self.acc_max * self.dt)
            self.setpoint_v += dv
            self._integrate(now)
        elif mode is Mode.INTERP_F:
            a = min(1.0, (now - self.interp_t0) / self.cmd_period)
            self.setpoint_f[:] = self.interp_start + a * (self.goal_f - self.interp_start)
            self.setpoint_stamp = now
        return msg

    def _integrate(self, now: float) -> None:
        # whatever the velocity came from (a command, a ramp, a mode switch): within velocity_max
        _clip(self.setpoint_v, self._vel_min, self.vel_max, self.setpoint_v)
        if self.caps.velocity:
            # native velocity control: nothing to integrate, but the position limits still hold:
            # brake so that the joint can stop at its limit (v <= sqrt(2 a d)), zero beyond it
            p = self.setpoint_p  # follows the measured position in native velocity mode
            room_up = np.sqrt(2.0 * self.acc_max * np.maximum(self.pos_max - p, 0.0))
            room_down = np.sqrt(2.0 * self.acc_max * np.maximum(p - self.pos_min, 0.0))
            _clip(self.setpoint_v, -room_down, room_up, self.setpoint_v)
            self.setpoint_stamp = now
            return
        p = self.setpoint_p
        dt = now - self._integrated_at
        if not 0.0 < dt <= self._integrate_max_s:
            dt = self.dt if self._integrated_at == 0.0 or dt <= 0.0 else self._integrate_max_s
        self._integrated_at = now
        lo, hi = self._bounds(p)  # outside the limits: back toward them, never a jump onto them
        p += self.setpoint_v * dt
        at_limit = (p <= lo) | (p >= hi)
        _clip(p, lo, hi, p)
        self.setpoint_v[at_limit] = 0.0
        self.setpoint_stamp = now

    def _bounds(self, last: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The position limits widened to include ``last`` (a setpoint outside them)."""
        np.minimum(self.pos_min, last, out=self._lo)
        np.maximum(self.pos_max, last, out=self._hi)
        return self._lo, self._hi

    def _step_servo_p(self, now: float) -> None:
        """Move the position setpoint toward the servo target, at most ``velocity_max * dt``."""
        step = self._tmp
        np.subtract(self.servo_target, self.setpoint_p, out=step)
        _clip(step, self._step_min, self._step_max, step)
        self.setpoint_p += step
        np.divide(step, self.dt, out=self.servo_rate)
        self.setpoint_stamp = now

    def _step_interpolate_p(self, now: float) -> None:
        """One cycle of interpolate_jp: the reference moves linearly toward the goal (predict: the
        extrapolated goal, held for one more period and two cycles, then back to the goal over one
        more period if no goal came), reached
        one estimated command period after the goal came, at most ``velocity_max``; the setpoint
        is the mean of the reference over the last command period (module docstring)."""
        a = (now - self.interp_t0) / self.cmd_period
        target = self._tmp
        if a >= 1.0 and not self._predict:
            target[:] = self.goal_p  # exactly
        elif a >= 1.0:
            # predict: the reference holds the aim until the stream is clearly late, two periods
            # (the estimate before or after the goal, whichever is longer: a goal of a burst
            # shortens it; or the longest of the last few inter-arrival times) and two loop
            # periods after the goal came (a goal late by up to a period, or the next burst, finds
            # it still there: it never moves back against the stream); then back
            # to the goal over one period, so that an ended stream ends exactly on its last goal
            r = (now - self.interp_t0 - self._hold_s) / self.cmd_period
            if r >= 1.0:
                target[:] = self.goal_p  # exactly
            elif r > 0.0:
                np.subtract(self.goal_p, self._aim, out=target)
                target *= r
                target += self._aim
            else:
                target[:] = self._aim
        else:
            np.subtract(self._aim, self.interp_start, out=target)
            target *= a
            target += self.interp_start
        # never faster than the joint can go: a goal arriving early or far is followed at v_max
        ref = self._ref
        d = target - ref
        ref[:] = np.where(np.abs(d) <= self._step_max, target, ref + np.clip(d, -self._step_max, self._step_max))
        rows, hist = self._ref_rows, self._ref_hist
        i = self._ref_i = (self._ref_i + 1) % rows
        hist[i] = ref
        hist[i + rows] = ref
        # the window: the last cmd_period / dt rows, the oldest weighted by the fraction, its
        # width following the period estimate slowly (a window that changed with the estimate at
        # each goal would shift the average by a fraction of a step each time); the mean as the
        # reference minus the mean of its lead over each row: exactly the goal once all rows hold it
        if self._smooth:
            self._width += _WIDTH_GAIN * (min(max(1.0, self.cmd_period / self.dt - self._shorten), rows - 1.0)
                                          - self._width)
        width = self._width
        k = int(width)
        lead = (ref - hist[i + rows - k + 1:i + rows + 1]).sum(axis=0)
        lead += (width - k) * (ref - hist[i + rows - k])
        lead /= width
        # within velocity_max again: a window shortened at once (the period estimate dropping)
        # would otherwise move the average faster
        new = ref - lead
        step = np.clip(new - self.setpoint_p, -self._step_max, self._step_max, out=lead)
        np.copyto(new, self.setpoint_p + step, where=step != new - self.setpoint_p)  # exact when not clipped
        np.subtract(new, self.setpoint_p, out=self.setpoint_v)
        self.setpoint_v /= self.dt
        self.setpoint_p[:] = new
        self.setpoint_stamp = now

    @property
    def interpolating(self) -> bool:
        """An interpolate_jp setpoint still on its way to the goal."""
        return self.mode is Mode.INTERP_P and not np.array_equal(self.setpoint_p, self.goal_p)

    def _step_trajectory(self, now: float) -> bool:
        result = ruckig_update(self.otg, self.inp, self.out)
        if result is not Result.Working and result is not Result.Finished:
            # invalid input cannot happen with validated limits, and a plan ruckig cannot make is
            # retried from nudged positions (above): hold where the setpoint is, don't guess; say so
            self.hold()
            self.error = (f"{self.name}: no trajectory to the move's goal could be planned from the current "
                          f"setpoint (ruckig: {result!s}); holding position")
            return True
        self.setpoint_p[:] = self.out.new_position
        self.setpoint_v[:] = self.out.new_velocity
        self.setpoint_stamp = now
        self.out.pass_to_input(self.inp)
        if result is Result.Finished:
            self.mode = Mode.HOLD
            self.setpoint_v[:] = 0.0
            return True
        return False

    def _step_brake(self, now: float) -> None:
        """One cycle of a stop (:meth:`brake`): each joint's speed down by its deceleration * dt,
        the position by the mean velocity over the cycle; at rest: HOLD."""
        v = self.setpoint_v
        v0 = self._tmp
        v0[:] = v
        speed = np.abs(v) - self._brake_dec * self.dt
        np.maximum(speed, 0.0, out=speed)
        np.copysign(speed, v0, out=v)
        p = self.setpoint_p
        lo, hi = self._bounds(p)  # a stop never carries a joint past its limit, nor a move's goal
        np.maximum(lo, self._brake_lo, out=lo)
        np.minimum(hi, self._brake_hi, out=hi)
        p += 0.5 * (v0 + v) * self.dt
        at_limit = (p <= lo) | (p >= hi)
        _clip(p, lo, hi, p)
        v[at_limit] = 0.0
        self.setpoint_stamp = now
        if not np.any(v):
            self.mode = Mode.HOLD
            self.level = Mode.HOLD

    def command_mode(self) -> CommandMode:
        """The native command mode :meth:`fill` gives this namespace's joints now."""
        mode = self.mode
        if mode is Mode.FREE:
            return CommandMode.FREE
        if mode in EFFORT_MODES:
            return CommandMode.EFFORT
        if mode in VELOCITY_MODES and self.caps.velocity:
            return CommandMode.VELOCITY
        return CommandMode.POSITION

    def fill(self, cmd: JointCommand, block: np.ndarray) -> None:
        """Write this namespace's setpoints into the native command, in the hardware's terms:
        its modes into ``cmd``, its position, velocity and effort into ``block``, the rows of one
        (3, joints) array that are ``cmd``'s position, velocity and effort (the controller's), in
        one copy."""
        idx = self.idx
        mode = self.mode
        if mode is Mode.FREE:
            cmd.mode[idx] = CommandMode.FREE
            self._filled[:] = self.setpoint_p
            return
        native = self.command_mode()
        cmd.mode[idx] = native
        if native is CommandMode.POSITION:
            if mode is not Mode.HOLD:
                # the limits stage; HOLD is exempt: a joint enabled (or freed) outside its limits
                # is held where it is, never snapped to the limit; commands then bring it back at
                # their own (velocity-bounded) rate: it may not go farther out, nor jump onto the limit
                lo, hi = self._bounds(self._filled)
                _clip(self.setpoint_p, lo, hi, self.setpoint_p)
        # the velocity and effort stage: every path bounds them already (above); this is the
        # output's own guarantee, so no backend clamps to a profile limit
        _clip(self._vf, self._vf_min, self._vf_max, self._vf)
        self._filled[:] = self.setpoint_p
        block[:, self.cols] = self._pvf

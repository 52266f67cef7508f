"""The simulated UR arm behind the controller's ports: modes, kinematics and joint motion.

No sockets here (``crtk_bridge.sim.ur`` serves them) and no script parsing
(``crtk_bridge.sim.ur_script`` plays the uploaded ``rtde_control`` program). One
:class:`URRobot` is stepped once per controller tick (2 ms on e-Series, 8 ms on CB3) by the
serving thread, under its lock.

Mode tables: Universal Robots, RTDE guide (robot_mode, safety_mode, runtime_state,
robot_status_bits, safety_status_bits) and dashboard server manual; see
docs/architecture.md, "Sources": Universal Robots. How the modes move:

- ``power on`` (dashboard): POWER_OFF -> POWER_ON -> IDLE after ``power_on_s``;
  ``brake release``: IDLE -> RUNNING after ``brake_release_s``; from POWER_OFF (or while powering
  on) it powers the arm on first and releases the brakes once IDLE, as the controller does (so a
  script may send ``power on`` and ``brake release`` back to back); ``power off``: POWER_OFF at once.
- Protective stop (injected, the script's ``protective_stop()``, or a joint leaving its safety
  limits): safety PROTECTIVE_STOP, the arm stops, the program stops; ``unlock protective stop``
  is refused until ``unlock_delay_s`` (5 s on a real controller) after the stop.
- Safeguard stop: the arm stops and the program pauses (runtime PAUSED); on release it resumes
  where it was (a servo target streamed before the stop is chased again, as on the real arm).
- Emergency stops (robot / system), FAULT and VIOLATION: power off, program stopped; an e-stop
  is released from the control socket, FAULT/VIOLATION need ``restart safety``.

Motion (one generator at a time, a real controller has one too): ``servoj`` is a first-order
chase of the latest target with time constant ``lookahead_time``; ``speedj``/``speedl`` ramp the
joint / tool velocity at the given acceleration; ``movej`` is a phase-synchronised trajectory
(ruckig: all joints start and stop together on a line in joint space, high jerk so the profile
is trapezoidal like the controller's); ``movel`` moves the TCP on a
straight line with a 1-DOF ruckig profile along it, IK (pinocchio, damped least squares) each
tick from the previous joints; ``stopj`` decelerates. Joint speeds are capped at the UR5e's
180 deg/s times the speed slider (``target_speed_fraction``), which also slows trajectories.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin
import ruckig

from ..backends.ur.tables import RobotMode, RuntimeState, SafetyMode  # noqa: F401 - re-exported
from ..profile import shipped_profiles_dir

log = logging.getLogger(__name__)

#: the arm model this controller simulates (written from UR's published DH parameters)
#: (the shipped profiles' URDF: installed with the package, profile.shipped_profiles_dir)
UR5E_URDF = shipped_profiles_dir() / "urdf" / "ur5e.urdf"
TIP_FRAME = "tool0"
N = 6
JOINT_SPEED_MAX = math.pi  # rad/s, every UR5e joint (180 deg/s)
REACH_M = 0.85  # UR5e reach from the shoulder axis


#: safety mode -> safety_status_bits (bit 0 normal, 1 reduced, 2 protective, 3 recovery,
#: 4 safeguard, 5 system e-stop, 6 robot e-stop, 7 any e-stop, 8 violation, 9 fault,
#: 10 stopped due to safety)
SAFETY_BITS = {
    SafetyMode.NORMAL: 1 << 0,
    SafetyMode.REDUCED: 1 << 1,
    SafetyMode.PROTECTIVE_STOP: 1 << 2 | 1 << 10,
    SafetyMode.RECOVERY: 1 << 3 | 1 << 10,
    SafetyMode.SAFEGUARD_STOP: 1 << 4 | 1 << 10,
    SafetyMode.SYSTEM_EMERGENCY_STOP: 1 << 5 | 1 << 7 | 1 << 10,
    SafetyMode.ROBOT_EMERGENCY_STOP: 1 << 6 | 1 << 7 | 1 << 10,
    SafetyMode.VIOLATION: 1 << 8 | 1 << 10,
    SafetyMode.FAULT: 1 << 9 | 1 << 10,
}
#: joint_mode values (RTDE guide): per joint
JOINT_POWER_OFF, JOINT_RUNNING, JOINT_IDLE = 239, 253, 255
#: which injected stop puts which safety mode
STOPS = {
    "protective": SafetyMode.PROTECTIVE_STOP,
    "safeguard": SafetyMode.SAFEGUARD_STOP,
    "robot_estop": SafetyMode.ROBOT_EMERGENCY_STOP,
    "system_estop": SafetyMode.SYSTEM_EMERGENCY_STOP,
    "fault": SafetyMode.FAULT,
    "violation": SafetyMode.VIOLATION,
}
_MOVING_SAFETY = (SafetyMode.NORMAL, SafetyMode.REDUCED)


def pose_to_se3(pose) -> pin.SE3:
    """UR pose [x, y, z, rx, ry, rz] (m, rotation vector in rad) -> SE3."""
    p = np.asarray(pose, dtype=float)
    return pin.SE3(pin.exp3(p[3:6]), p[0:3].copy())


def se3_to_pose(m: pin.SE3) -> list[float]:
    return [*m.translation.tolist(), *pin.log3(m.rotation).tolist()]


class Kinematics:
    """FK, Jacobian and IK of the UR5e at its TCP (flange ``tool0`` times the TCP offset)."""

    def __init__(self, urdf: Path = UR5E_URDF):
        self.model = pin.buildModelFromUrdf(str(urdf))
        self.data = self.model.createData()
        self.frame = self.model.getFrameId(TIP_FRAME)
        self.tcp_version = 0  # counts changes of the TCP offset (URRobot's per-tick caches)
        self.tcp = pin.SE3.Identity()  # set_tcp
        self.lower = self.model.lowerPositionLimit.copy()
        self.upper = self.model.upperPositionLimit.copy()

    @property
    def tcp(self) -> pin.SE3:
        """The TCP offset from the flange (the program's ``set_tcp``)."""
        return self._tcp

    @tcp.setter
    def tcp(self, value: pin.SE3) -> None:
        self._tcp = value
        self.tcp_version += 1

    def fk(self, q) -> pin.SE3:
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        return self.data.oMf[self.frame] * self.tcp

    def jacobian(self, q) -> np.ndarray:
        """6x6 TCP Jacobian in the base orientation (linear; angular), at ``q``."""
        q = np.asarray(q, dtype=float)
        pin.computeJointJacobians(self.model, self.data, q)
        pin.framesForwardKinematics(self.model, self.data, q)
        j = pin.getFrameJacobian(self.model, self.data, self.frame, pin.LOCAL_WORLD_ALIGNED)
        # move the reference point from the flange to the TCP
        r = self.data.oMf[self.frame].rotation @ self.tcp.translation
        j = j.copy()
        j[0:3] -= pin.skew(r) @ j[3:6]  # v_tcp = v + w x r
        return j

    def gravity_torques(self, q) -> np.ndarray:
        """N*m holding the arm against gravity at ``q`` (the URDF's masses; no payload)."""
        return pin.computeGeneralizedGravity(self.model, self.data, np.asarray(q, dtype=float)).copy()

    def ik(self, target: pin.SE3, q0, iterations: int = 100, tol: float = 1e-6) -> tuple[np.ndarray, bool]:
        """Damped-least-squares IK from ``q0``. Returns (q, converged within 0.1 mm / 1 mrad)."""
        q = np.asarray(q0, dtype=float).copy()
        damp = 1e-6
        for _ in range(iterations):
            err = pin.log6(self.fk(q).actInv(target)).vector  # in the TCP frame
            if np.dot(err, err) < tol * tol:
                break
            pin.computeJointJacobians(self.model, self.data, q)
            j = pin.getFrameJacobian(self.model, self.data, self.frame, pin.LOCAL)
            j = self.tcp.inverse().action @ j  # to the TCP frame
            dq = j.T @ np.linalg.solve(j @ j.T + damp * np.eye(6), err)
            q = pin.integrate(self.model, q, dq)
        final = self.fk(q).actInv(target)
        ok = np.linalg.norm(final.translation) < 1e-4 and np.linalg.norm(pin.log3(final.rotation)) < 1e-3
        return q, bool(ok)


# ---- motion generators: step(robot, dt) moves robot.q / robot.qd, returns True when done ----

class Motion:
    blocking_done = False  # a finished blocking move (the script waits on it)

    def step(self, robot: URRobot, dt: float) -> bool:
        raise NotImplementedError


class Servo(Motion):
    """servoj / servol: chase the latest target (first order, time constant lookahead_time)."""

    def __init__(self, target, lookahead_s: float):
        self.target = np.asarray(target, dtype=float)
        self.lookahead_s = lookahead_s

    def step(self, robot, dt):
        tau = max(self.lookahead_s, dt)
        v = (self.target - robot.q) * (min(1.0, dt / tau) / dt)
        robot.move_with_velocity(v, dt)
        return False


class JointSpeed(Motion):
    """speedj: ramp the joint velocities to ``target`` at ``acc`` rad/s^2 (until replaced/stopped)."""

    def __init__(self, target, acc: float):
        self.target = np.asarray(target, dtype=float)
        self.acc = max(acc, 1e-3)

    def step(self, robot, dt):
        robot.move_with_velocity(_ramp(robot.qd, self.target, self.acc * dt), dt)
        return False


class ToolSpeed(Motion):
    """speedl: ramp the TCP twist ``target`` (base frame, m/s and rad/s) at ``acc``; joints by
    the Jacobian."""

    def __init__(self, target, acc: float):
        self.target = np.asarray(target, dtype=float)
        self.acc = max(acc, 1e-3)
        self.current = None

    def step(self, robot, dt):
        if self.current is None:
            self.current = robot.kin.jacobian(robot.q) @ robot.qd
        self.current = _ramp(self.current, self.target, self.acc * dt)
        j = robot.kin.jacobian(robot.q)
        qd = j.T @ np.linalg.solve(j @ j.T + 1e-4 * np.eye(6), self.current)
        robot.move_with_velocity(qd, dt)
        return False


class Stop(Motion):
    """stopj / stopl / speed_stop: decelerate every joint to rest at ``dec`` rad/s^2."""

    def __init__(self, dec: float):
        self.dec = max(dec, 1e-3)

    def step(self, robot, dt):
        robot.move_with_velocity(_ramp(robot.qd, np.zeros(N), self.dec * dt), dt)
        return not robot.qd.any()


class JointMove(Motion):
    """movej: a phase-synchronised trajectory to ``goal`` (ruckig), slowed by the speed slider."""

    def __init__(self, robot: URRobot, goal, vel: float, acc: float):
        self.goal = np.asarray(goal, dtype=float)
        inp = ruckig.InputParameter(N)
        inp.current_position = robot.q.tolist()
        inp.current_velocity = robot.qd.tolist()
        inp.target_position = self.goal.tolist()
        inp.max_velocity = [min(vel, JOINT_SPEED_MAX)] * N
        inp.max_acceleration = [max(acc, 1e-3)] * N
        inp.max_jerk = [max(acc, 1e-3) * 100.0] * N  # near-trapezoidal, as movej
        inp.synchronization = ruckig.Synchronization.Phase  # a straight line in joint space, as movej
        self.traj = ruckig.Trajectory(N)
        result = ruckig.Ruckig(N).calculate(inp, self.traj)
        if result not in (ruckig.Result.Working, ruckig.Result.Finished):
            raise ValueError(f"movej: no trajectory ({result})")
        self.t = 0.0

    def step(self, robot, dt):
        self.t = min(self.t + dt * robot.speed_fraction, self.traj.duration)
        pos, vel, _ = self.traj.at_time(self.t)
        robot.set_joints(np.asarray(pos), np.asarray(vel) * robot.speed_fraction)
        if self.t >= self.traj.duration:
            robot.set_joints(self.goal, np.zeros(N))
            return True
        return False


class LinearMove(Motion):
    """movel: the TCP on a straight line (position linear, rotation by the shortest arc) with a
    1-DOF ruckig profile along the longer of its length (m) and its turn (rad); IK per tick."""

    def __init__(self, robot: URRobot, goal: pin.SE3, vel: float, acc: float):
        self.start = robot.kin.fk(robot.q)
        self.goal = goal
        self.dp = goal.translation - self.start.translation
        self.dr = pin.log3(self.start.rotation.T @ goal.rotation)
        self.length = max(float(np.linalg.norm(self.dp)), float(np.linalg.norm(self.dr)), 1e-9)
        inp = ruckig.InputParameter(1)
        inp.current_position = [0.0]
        inp.target_position = [self.length]
        inp.max_velocity = [max(vel, 1e-3)]
        inp.max_acceleration = [max(acc, 1e-3)]
        inp.max_jerk = [max(acc, 1e-3) * 100.0]
        self.traj = ruckig.Trajectory(1)
        ruckig.Ruckig(1).calculate(inp, self.traj)
        self.t = 0.0

    def step(self, robot, dt):
        self.t = min(self.t + dt * robot.speed_fraction, self.traj.duration)
        s = self.traj.at_time(self.t)[0][0] / self.length
        target = pin.SE3(self.start.rotation @ pin.exp3(self.dr * s), self.start.translation + self.dp * s)
        q, ok = robot.kin.ik(target, robot.q, iterations=20)
        if not ok:
            robot.script_error(f"movel: no inverse kinematics solution on the line at s={s:.3f}")
            return True
        robot.set_joints(q, (q - robot.q) / dt)
        return self.t >= self.traj.duration


class Hand(Motion):
    """Teach mode: a hand pushes the arm to ``goal`` at ``speed`` rad/s (control socket)."""

    def __init__(self, goal, speed: float):
        self.goal = np.asarray(goal, dtype=float)
        self.speed = speed

    def step(self, robot, dt):
        err = self.goal - robot.q
        step = np.clip(err, -self.speed * dt, self.speed * dt)
        robot.set_joints(robot.q + step, step / dt)
        return not err.any()


def _ramp(current: np.ndarray, target: np.ndarray, max_step: float) -> np.ndarray:
    """``current`` moved toward ``target`` by at most ``max_step`` along the difference."""
    d = target - current
    n = float(np.abs(d).max())
    return target.copy() if n <= max_step else current + d * (max_step / n)


@dataclass
class Timings:
    """How long the controller's slow steps take (seconds)."""

    power_on_s: float = 0.3  # POWER_ON -> IDLE
    brake_release_s: float = 0.5  # IDLE -> RUNNING
    unlock_delay_s: float = 5.0  # a protective stop cannot be unlocked earlier (UR: 5 s)


@dataclass
class Limits:
    """The controller's safety configuration: joint position limits (rad), from the profile."""

    lower: np.ndarray = field(default_factory=lambda: np.full(N, -2 * math.pi))
    upper: np.ndarray = field(default_factory=lambda: np.full(N, 2 * math.pi))


class URRobot:
    """State of the simulated arm and controller. Not thread-safe: the caller holds one lock."""

    def __init__(self, q0, limits: Limits, timings: Timings, *, clock):
        self.kin = Kinematics()
        self.limits = limits
        self.timings = timings
        self.clock = clock
        self.q = np.asarray(q0, dtype=float).copy()
        self.qd = np.zeros(N)
        self.target_q = self.q.copy()
        self.robot_mode = RobotMode.POWER_OFF
        self.safety_mode = SafetyMode.NORMAL
        self.runtime_state = RuntimeState.STOPPED
        self.speed_fraction = 1.0  # the pendant's speed slider (target_speed_fraction)
        #: the program's main loop takes no command (a controller too busy to answer); the arm
        #: goes on with its motion, and the RTDE watchdog still watches the inputs
        self.script_stalled = False
        self.step_s = 0.002  # the controller tick (set by the server: 2 ms e-Series, 8 ms CB3)
        self.teach_mode = False
        self.tcp_force = np.zeros(6)  # injected external wrench at the TCP (base frame)
        self._pose_key: tuple | None = None  # tcp_pose's and tcp_speed's last inputs, and answers
        self._pose: list[float] = []
        self._speed_key: tuple | None = None
        self._speed: list[float] = []
        self.motion: Motion | None = None
        self.stop_cause = ""  # why the last safety stop happened (control socket dump)
        self.program: str | None = None  # name of the running / paused program
        self.loaded_program: str | None = None  # dashboard "load"
        self.script = None  # the rtde_control behaviour while its program runs (ur_script)
        self.last_error = ""
        self._mode_at: tuple[float, RobotMode] | None = None  # a pending robot mode change
        self._release_when_idle = False  # a brake release asked for while powering on
        self._stopped_at = -math.inf  # clock of the last protective stop

    # ---- derived state ----
    @property
    def may_move(self) -> bool:
        return (self.robot_mode == RobotMode.RUNNING and self.safety_mode in _MOVING_SAFETY
                and self.runtime_state == RuntimeState.PLAYING)

    @property
    def robot_status_bits(self) -> int:
        powered = self.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.BACKDRIVE, RobotMode.RUNNING)
        return int(powered) | (int(self.runtime_state == RuntimeState.PLAYING) << 1)

    @property
    def safety_status_bits(self) -> int:
        return SAFETY_BITS[self.safety_mode]

    @property
    def joint_mode(self) -> list[int]:
        m = {RobotMode.RUNNING: JOINT_RUNNING, RobotMode.IDLE: JOINT_IDLE}.get(self.robot_mode, JOINT_POWER_OFF)
        return [m] * N

    def tcp_pose(self) -> list[float]:
        """The TCP pose; kinematics only when the joints or the TCP offset changed since the last
        call (every tick asks: an arm at rest, powered off or holding, is most ticks)."""
        key = (self.q.tobytes(), self.kin.tcp_version)
        if key != self._pose_key:
            self._pose_key, self._pose = key, se3_to_pose(self.kin.fk(self.q))
        return list(self._pose)

    def tcp_speed(self) -> list[float]:
        """The TCP twist (base frame); zero at rest without the Jacobian, which is made only when
        the joints, their speeds or the TCP offset changed since the last call."""
        qd = self.qd
        if not qd.any():
            return [0.0] * N
        key = (self.q.tobytes(), qd.tobytes(), self.kin.tcp_version)
        if key != self._speed_key:
            self._speed_key, self._speed = key, (self.kin.jacobian(self.q) @ qd).tolist()
        return list(self._speed)

    # ---- motion primitives used by the generators ----
    def move_with_velocity(self, v: np.ndarray, dt: float) -> None:
        vmax = JOINT_SPEED_MAX * self.speed_fraction
        v = np.clip(v, -vmax, vmax)
        self.set_joints(self.q + v * dt, v)

    def set_joints(self, q: np.ndarray, qd: np.ndarray) -> None:
        self.q = np.asarray(q, dtype=float)
        self.qd = np.asarray(qd, dtype=float)
        self.target_q = self.q.copy()

    # ---- the tick ----
    def step(self, dt: float) -> None:
        now = self.clock()
        if self._mode_at is not None and now >= self._mode_at[0]:
            self.robot_mode = self._mode_at[1]
            self._mode_at = None
            if self.robot_mode == RobotMode.POWER_ON:
                self._mode_at = (now + self.timings.power_on_s, RobotMode.IDLE)
            elif self.robot_mode == RobotMode.IDLE and self._release_when_idle:
                self._release_when_idle = False
                self.brake_release()
        if self.script is not None and self.runtime_state == RuntimeState.PLAYING:
            self.script.tick(now)
        if self.teach_mode and isinstance(self.motion, Hand):
            if self.motion.step(self, dt):
                self.motion = None
        elif self.motion is not None and self.may_move:
            if self.motion.step(self, dt):
                self.motion.blocking_done = True
                if not isinstance(self.motion, (Servo, JointSpeed, ToolSpeed)):
                    done, self.motion = self.motion, None
                    if self.script is not None:
                        self.script.motion_done(done)
        else:
            self.qd = np.zeros(N)
        self._check_limits()

    def _check_limits(self) -> None:
        low, high = self.limits.lower, self.limits.upper
        if (self.q < low - 1e-9).any() or (self.q > high + 1e-9).any():
            j = int(np.argmax((low - self.q).clip(0) + (self.q - high).clip(0)))
            self.q = np.clip(self.q, low, high)
            self.protective_stop(f"joint {j} position {self.q[j]:.4f} rad reached its safety limit")

    # ---- dashboard / safety ----
    def power_on(self) -> None:
        if self.safety_mode not in _MOVING_SAFETY and self.safety_mode != SafetyMode.PROTECTIVE_STOP:
            return  # e-stopped / faulted: nothing powers on
        if self.robot_mode == RobotMode.POWER_OFF:
            self.robot_mode = RobotMode.POWER_ON
            self._mode_at = (self.clock() + self.timings.power_on_s, RobotMode.IDLE)

    def brake_release(self) -> None:
        """Dashboard ``brake release``: IDLE -> RUNNING after ``brake_release_s``. As on the
        controller, from POWER_OFF it powers the arm on, and while powering on it proceeds once
        IDLE. Nothing happens while a safety stop other than reduced mode holds the arm."""
        if self.safety_mode not in _MOVING_SAFETY:
            return
        if self.robot_mode == RobotMode.POWER_OFF:
            self.power_on()
        powering = self.robot_mode in (RobotMode.BOOTING, RobotMode.POWER_ON) or (
            self._mode_at is not None and self._mode_at[1] in (RobotMode.POWER_ON, RobotMode.IDLE))
        if powering:
            self._release_when_idle = True
        elif self.robot_mode == RobotMode.IDLE and self._mode_at is None:
            self._mode_at = (self.clock() + self.timings.brake_release_s, RobotMode.RUNNING)

    def power_off(self) -> None:
        self.stop_program("power off")
        self.robot_mode = RobotMode.POWER_OFF
        self._mode_at = None
        self._release_when_idle = False
        self.teach_mode = False

    def inject_stop(self, kind: str, cause: str) -> None:
        mode = STOPS[kind]
        if mode == SafetyMode.PROTECTIVE_STOP:
            self.protective_stop(cause)
            return
        self.stop_cause = cause
        if mode == SafetyMode.SAFEGUARD_STOP:
            if self.safety_mode in _MOVING_SAFETY:
                self.safety_mode = mode
                self.qd = np.zeros(N)
                if self.runtime_state == RuntimeState.PLAYING:
                    self.runtime_state = RuntimeState.PAUSED
            return
        self.safety_mode = mode
        self.power_off()

    def release_stop(self, kind: str) -> bool:
        """The operator resets a safeguard stop or releases an e-stop button. False if that
        stop is not active (protective stops are unlocked over the dashboard)."""
        if self.safety_mode != STOPS.get(kind):
            return False
        if kind == "safeguard":
            self.safety_mode = SafetyMode.NORMAL
            if self.runtime_state == RuntimeState.PAUSED:
                self.runtime_state = RuntimeState.PLAYING  # the program resumes where it was
            return True
        if kind in ("robot_estop", "system_estop"):
            self.safety_mode = SafetyMode.NORMAL  # power stays off: power on again
            return True
        return False

    def protective_stop(self, cause: str) -> None:
        self.stop_cause = cause
        if self.safety_mode in (SafetyMode.NORMAL, SafetyMode.REDUCED, SafetyMode.SAFEGUARD_STOP):
            self.safety_mode = SafetyMode.PROTECTIVE_STOP
            self._stopped_at = self.clock()
            self.qd = np.zeros(N)
            self.stop_program(f"protective stop: {cause}")
            log.warning("protective stop: %s", cause)

    def unlock_protective_stop(self) -> str:
        if self.safety_mode != SafetyMode.PROTECTIVE_STOP:
            return "Protective stop releasing"
        if self.clock() - self._stopped_at < self.timings.unlock_delay_s:
            return (f"Cannot unlock protective stop until {self.timings.unlock_delay_s:g}s after occurrence. "
                    "Always inspect cause of protective stop before unlocking")
        self.safety_mode = SafetyMode.NORMAL
        return "Protective stop releasing"

    def restart_safety(self) -> None:
        self.power_off()
        self.safety_mode = SafetyMode.NORMAL

    # ---- programs ----
    def start_program(self, name: str, script=None) -> bool:
        """Start a program (``script``: the rtde_control behaviour, or None for a program the
        simulator only shows as running). False, with :attr:`last_error`, when the arm is not
        ready (not RUNNING or stopped by safety), as a real controller refuses to play."""
        if self.robot_mode != RobotMode.RUNNING or self.safety_mode not in _MOVING_SAFETY:
            self.last_error = (f"program {name}: not started, robot mode {self.robot_mode.name}, "
                               f"safety mode {self.safety_mode.name}")
            log.warning("%s", self.last_error)
            return False
        self.stop_program("another program starts")
        self.program = name
        self.script = script
        self.runtime_state = RuntimeState.PLAYING
        self.teach_mode = False
        if script is not None:
            script.start(self.clock())
        return True

    def stop_program(self, why: str) -> None:
        if self.runtime_state != RuntimeState.STOPPED:
            log.info("program %s stopped: %s", self.program, why)
        self.runtime_state = RuntimeState.STOPPED
        self.motion = None
        self.qd = np.zeros(N)
        self.script = None
        self.program = None
        self.teach_mode = False

    def pause_program(self) -> None:
        if self.runtime_state == RuntimeState.PLAYING:
            self.runtime_state = RuntimeState.PAUSED

    def script_error(self, message: str) -> None:
        """A runtime error in the program (IK failure...): it stops, as the controller's do."""
        self.last_error = message
        log.warning("program error: %s", message)
        self.stop_program(message)

    def within_joint_limits(self, q) -> bool:
        q = np.asarray(q, dtype=float)
        return bool(((q >= self.limits.lower) & (q <= self.limits.upper)).all())

    def pose_within_limits(self, pose) -> bool:
        """A simple pose check: within the reach sphere around the shoulder and reachable by IK
        with joints inside the safety limits (a real controller checks its safety planes)."""
        target = pose_to_se3(pose)
        if np.linalg.norm(target.translation - np.array([0, 0, 0.1625])) > REACH_M + 0.1:
            return False
        q, ok = self.kin.ik(target, self.q)
        return ok and self.within_joint_limits(q)

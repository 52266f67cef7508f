"""Universal Robots arms over RTDE, on ur_rtde (``rtde_receive``, ``rtde_control``, ``dashboard_client``).

Three connections to the controller at ``backend.host`` (the ports are fixed by UR):

* ``RTDEReceiveInterface`` (RTDE 30004), opened with the backend: joint and TCP state, robot /
  safety mode, runtime state and the speed slider, one packet every 2 ms (e-Series, 500 Hz) or
  8 ms (CB3, 125 Hz). Its packets PACE THE LOOP (``paces_cycle``): :meth:`UrBackend.wait_cycle`
  returns when the packet's timestamp moved on, and counts the packets skipped.
* ``DashboardClient`` (29999): power on / off, brake release, unlock protective stop, restart
  safety, play (lifecycle path only).
* ``RTDEControlInterface`` (RTDE 30004 + script 30003), built on the first enable: ur_rtde uploads
  its control script and talks to it through RTDE registers.

Real-time path (every cycle, nothing blocks): ``read`` copies the latest packet (ur_rtde's own
thread receives them); ``write`` sends ONE realtime script command, which ur_rtde writes to the
RTDE input registers without waiting for an answer:

| CRTK | what the cycle sends |
|---|---|
| servo_jp / interpolate_jp / move_jp / hold | ``servoJ(q, 0, 0, dt, lookahead_time, gain)`` of the daemon's own setpoint (ruckig, velocity-bounded) |
| servo_jv / interpolate_jv | ``speedJ(qd, speed_acceleration, 0)`` |
| servo_cp / interpolate_cp | ``servoL(pose, 0, 0, dt, lookahead_time, gain)`` |
| servo_cv / interpolate_cv | ``speedL(twist, speedl_acceleration, 0)`` (a body-frame twist turned into base axes with the measured TCP orientation) |
| move_cp | this backend's own jerk-limited straight-line trajectory (ruckig on the path parameter, orientation by the geodesic), streamed with ``servoL`` |
| free | ``teachMode()`` (the whole arm), ``endTeachMode()`` on the next command |

Why servoJ's ``lookahead_time`` 0.05 s and ``gain`` 600 (profile keys ``servo_lookahead_time_s``,
``servo_gain``): the stream is already smooth (jerk-limited moves, velocity-bounded servo
targets) and arrives every controller cycle, so the controller's look-ahead filter has nothing to
smooth and only adds lag, about the look-ahead time: 0.05 s keeps that small. The minimum 0.03 s
with a high gain is where UR users report joint vibration; a gain of 600 (range 100-2000) follows
a 500 Hz stream stiffly without the overshoot seen above ~1000 at short look-ahead.

Why move_cp is the daemon's trajectory and not ``moveL``: ``moveL`` is a non-realtime script
command (ur_rtde waits for the script's acknowledgement, a blocking round trip, in the cycle),
its progress is only coarse, and stopping it is another blocking call. The trajectory here is
stopped by a pause in the next cycle, its duration is known when it starts (its time limit:
1.5 x the duration + 2 s; a pose not reached by then faults the robot, code ``move_timeout``),
and ``is_busy`` falls when the measured TCP pose is at the goal.

Lifecycle (blocking ur_rtde and dashboard calls run on a worker thread, one at a time, through
:meth:`UrBackend._job`; while one runs the cycle sends no command on the control interface and
the robot keeps following its last target):

* ENABLE = power on (dashboard) -> robot mode IDLE -> brake release -> RUNNING -> control script
  uploaded (``RTDEControlInterface``, or ``reuploadScript``; a NEW ``RTDEControlInterface``
  after a link loss: the old one is never called again, see below) -> runtime state PLAYING; the arm
  is then held where it is. Each wait is on the robot mode / runtime state read from RTDE.
* DISABLE = stop the motion and the script, power off (dashboard), until robot mode POWER_OFF.
  It is also the fault reaction: the arm stops and its brakes engage. ``configure`` does the
  same to an arm found powered at start (the robot starts DISABLED).
* FAULT_RESET (enable from FAULT): reconnect a lost link; unlock a protective stop (retried:
  e-Series refuses within 5 s of the stop), restart safety after a violation or safety fault;
  an e-stop or recovery mode is refused with what to do by hand. ENABLE from DISABLED does the
  same first when such a stop outlived its FAULT (``disable`` from FAULT, then ``enable``).
* RESUME: waits until the safeguard stop is reset and the script plays again (dashboard
  ``play`` if it was paused); core re-seeds every setpoint from the measured pose
  (``stops_itself_on_pause``), so the arm does not rush to where it was going when it stopped.

The script's RTDE watchdog (``backend.watchdog_hz``, ur_rtde ``setWatchdog``) is set at every
enable and fed by the cycle (its commands, else ``kickWatchdog``): a control process that stops
cycling stops the script and the arm within 1 / watchdog_hz s.

State: :mod:`.state` maps link, robot mode, safety mode and runtime state onto a device status
(protective stop and e-stops -> FAULT naming the cause, safeguard stop -> PAUSED, link loss ->
FAULT in the cycle that sees it). Every command is gated on the link being up, the safety mode
NORMAL / REDUCED and the script PLAYING, because ``servoJ`` returns True while the link is down.
The RTDE link reconnects by itself (``reconnect_interval_s``), on a worker; the fault stays until
``enable``.

ur_rtde 1.6.5 is not safe across a link loss in-process: each interface's own receive thread
handles the loss (disconnect; the control interface then tries its own reconnect) while other
threads may call it, and a call racing that corrupts the heap or throws through
``std::terminate``: the process aborts. So: the receive interface's thread is joined
(``disconnect``) before ``reconnect``; a control interface that lived through a loss is never
called, reconnected, disconnected or freed again (``_abandon``), enable builds a new one; and no
interface is freed. What remains is the instant of the loss itself (the cycle's servoJ or
watchdog kick as the control interface's thread closes its socket): the heap it corrupts aborts
the control process then or at a later allocation (seen at the next enable's new interface:
1 link loss in ~60 under test, ~1 in 4 before); the script's watchdog stops the arm within
1 / watchdog_hz and the front reports FAULT and exits non-zero (tests/test_ur_process_abort.py,
tests/test_e2e_processes.py). Only ur_rtde in a process of its own would remove it.

Move goals are checked by the controller before they start (:meth:`UrBackend.goal_check_steps`):
``isJointsWithinSafetyLimits`` for move_jp (the refusal names the first joint whose goal alone is
refused), ``isPoseWithinSafetyLimits`` for move_cp (naming the pose). Streams are not checked per
message (a script round trip per 2 ms sample is not possible): the profile's joint limits bound
them, and the controller protective-stops on anything beyond its own limits (-> FAULT).

Frames: ``measured_cp`` is ``actual_TCP_pose``, the TCP in the controller's base frame (the URDF's
``base`` link, x/y as on the robot's base label; not ROS's ``base_link``, turned by pi about z);
``measured_cf`` is ``actual_TCP_force`` (N, N*m, at the TCP, base frame axes). The TCP is the
flange (``tool0``) unless the controller's installation sets a TCP offset. Units: rad, rad/s,
m, axis-angle (UR) <-> unit quaternion [x, y, z, w] (CRTK) converted here.
"""

from __future__ import annotations

import ctypes
import dataclasses
import math
import threading
import time
from typing import Annotated, Any, Callable, Literal

import msgspec
import numpy as np
import pinocchio as pin
from ruckig import InputParameter, OutputParameter, Result, Ruckig

from ...core.actuator import (
    FRAME_BODY,
    Actuator,
    ActuatorInfo,
    Capabilities,
    CartesianMode,
    CommandMode,
    DeviceStatus,
    Fault,
    JointCommand,
    JointFeedback,
    Lifecycle,
    SimWiring,
    background_thread,
    Steps,
    DEFAULT_TRANSITION_TIMEOUTS_S,
)
from ...errors import BackendError, CommandError, ProfileError, fmt_number
from ...profile import Profile, backend_config, unknown_key_message
from .state import device_state
from .tables import MOVABLE, RobotMode, RuntimeState, SafetyMode

try:  # the SDK; the registry names the pip extra when it is missing
    import dashboard_client
    import rtde_control
    import rtde_receive
except ImportError as _exc:  # pragma: no cover - exercised by the registry's message
    raise ImportError(_exc.msg, name="ur_rtde") from _exc

N_JOINTS = 6
SERIES_RATE_HZ = {"e-series": 500.0, "cb3": 125.0}  # RTDE's highest rate per controller generation
#: the RTDE outputs read every cycle (a small recipe: ur_rtde's default asks for ~58)
VARIABLES = ["timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "actual_TCP_force", "robot_mode",
             "safety_mode", "runtime_state", "target_speed_fraction", "robot_status_bits",
             "safety_status_bits"]
_POSITION, _VELOCITY, _FREE, _NONE = (int(CommandMode.POSITION), int(CommandMode.VELOCITY),
                                      int(CommandMode.FREE), int(CommandMode.NONE))
_C_POSE, _C_TWIST, _C_MOVE = int(CartesianMode.POSE), int(CartesianMode.TWIST), int(CartesianMode.MOVE)
#: safety modes that enable resets over the dashboard (unlock protective stop, restart safety)
_RESETTABLE = (SafetyMode.PROTECTIVE_STOP, SafetyMode.VIOLATION, SafetyMode.FAULT)
_MOVE_DONE_POSITION_M = 0.002  # a move_cp ends once the TCP is this close to the goal...
_MOVE_DONE_ROTATION_RAD = 0.02  # ...and turned this little from it


def _abandon(obj: Any) -> None:
    """Keep ``obj`` alive for the life of the process, past interpreter finalization (an extra
    reference no one releases): a ur_rtde interface that cannot be disconnected safely."""
    ctypes.pythonapi.Py_IncRef(ctypes.py_object(obj))


class Config(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """The ``backend:`` section of a profile with ``type: ur``."""

    host: str  # the controller's address (RTDE 30004, dashboard 29999, script 30003); --sim sets it
    series: Literal["e-series", "cb3"] = "e-series"  # controller generation (its RTDE rate, the simulator's)
    # RTDE rate; None: the series' own, 500 on e-Series (PolyScope 5), 125 on CB3. The packets pace the loop
    rate_hz: Annotated[float, msgspec.Meta(gt=0, le=500)] | None = None
    servo_lookahead_time_s: Annotated[float, msgspec.Meta(ge=0.03, le=0.2)] = 0.05  # servoJ / servoL
    servo_gain: Annotated[float, msgspec.Meta(ge=100, le=2000)] = 600.0  # servoJ / servoL
    speed_acceleration: Annotated[float, msgspec.Meta(gt=0)] | None = None  # rad/s^2 of speedJ; None: joints' least
    speedl_acceleration: Annotated[float, msgspec.Meta(gt=0)] = 0.5  # m/s^2 of speedL
    move_linear_speed: Annotated[float, msgspec.Meta(gt=0)] = 0.25  # m/s: move_cp's TCP speed
    move_linear_acceleration: Annotated[float, msgspec.Meta(gt=0)] = 0.5  # m/s^2
    move_angular_speed: Annotated[float, msgspec.Meta(gt=0)] = 0.8  # rad/s: move_cp's TCP turn rate
    move_angular_acceleration: Annotated[float, msgspec.Meta(gt=0)] = 1.6  # rad/s^2
    reconnect_interval_s: Annotated[float, msgspec.Meta(gt=0)] = 0.5  # RTDE link retries after a loss
    # no RTDE packet for this long is a lost link (ur_rtde's isConnected() alone misses a silent one)
    link_timeout_s: Annotated[float, msgspec.Meta(gt=0)] = 0.1
    # the control script's RTDE watchdog (ur_rtde setWatchdog): no input from the daemon for
    # 1 / watchdog_hz s stops the script, and the arm (a dead or stalled control process must not
    # leave a speedJ running); it cannot be switched off (0 is refused, as CANopen's master heartbeat)
    watchdog_hz: Annotated[float, msgspec.Meta(ge=0)] = 10.0


def _pose6(position: np.ndarray, quat_xyzw: np.ndarray) -> list[float]:
    """CRTK pose -> UR pose [x, y, z, rx, ry, rz] (axis-angle)."""
    x, y, z, w = quat_xyzw
    rot = pin.log3(pin.Quaternion(w, x, y, z).normalized().toRotationMatrix())
    return [float(position[0]), float(position[1]), float(position[2]),
            float(rot[0]), float(rot[1]), float(rot[2])]


def _quat_xyzw(rotvec: np.ndarray, out: np.ndarray) -> None:
    """UR axis-angle -> unit quaternion [x, y, z, w], into ``out``."""
    angle = math.sqrt(rotvec[0] ** 2 + rotvec[1] ** 2 + rotvec[2] ** 2)
    if angle < 1e-12:
        out[:] = (0.0, 0.0, 0.0, 1.0)
        return
    s = math.sin(angle / 2.0) / angle
    out[0], out[1], out[2], out[3] = rotvec[0] * s, rotvec[1] * s, rotvec[2] * s, math.cos(angle / 2.0)


class _CartesianMove:
    """move_cp: a straight TCP line with the orientation turned along its geodesic, timed by ruckig
    on the path parameter s in [0, 1] so that the TCP's speed, acceleration and turn rate stay
    within the backend's ``move_*`` limits. One :meth:`step` per cycle gives the pose to servoL."""

    def __init__(self, dt: float, cfg: Config):
        self.cfg = cfg
        self.otg = Ruckig(1, dt)
        self.inp = InputParameter(1)
        self.out = OutputParameter(1)
        self.p0 = np.zeros(3)
        self.dp = np.zeros(3)
        self.r0 = np.eye(3)
        self.w = np.zeros(3)
        self.goal_p = np.zeros(3)
        self.goal_r = np.eye(3)
        self.seq = 0
        self.finished = True
        self.deadline = 0.0
        self.duration = 0.0

    def start(self, seq: int, p0: np.ndarray, r0: np.ndarray, goal_p: np.ndarray, goal_q: np.ndarray,
              now: float) -> None:
        cfg = self.cfg
        x, y, z, w = goal_q
        self.goal_r = pin.Quaternion(w, x, y, z).normalized().toRotationMatrix()
        self.goal_p[:] = goal_p
        self.p0[:] = p0
        self.r0 = r0.copy()
        self.dp = goal_p - p0
        self.w = pin.log3(r0.T @ self.goal_r)
        length, angle = float(np.linalg.norm(self.dp)), float(np.linalg.norm(self.w))
        # path-parameter limits: the stricter of the linear and the angular ones
        v = min(cfg.move_linear_speed / max(length, 1e-9), cfg.move_angular_speed / max(angle, 1e-9))
        a = min(cfg.move_linear_acceleration / max(length, 1e-9), cfg.move_angular_acceleration / max(angle, 1e-9))
        inp = self.inp
        inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [0.0], [0.0]
        inp.target_position, inp.target_velocity, inp.target_acceleration = [1.0], [0.0], [0.0]
        inp.max_velocity, inp.max_acceleration, inp.max_jerk = [min(v, 1e6)], [min(a, 1e6)], [min(10.0 * a, 1e7)]
        self.seq = seq
        self.finished = False
        self.otg.reset()
        self.duration = 0.0
        self.deadline = now + 2.0  # refined by the first step, once ruckig knows the duration

    def step(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        """The next (position, rotation matrix) of the path."""
        if not self.finished:
            result = self.otg.update(self.inp, self.out)
            if self.duration == 0.0 and result in (Result.Working, Result.Finished):
                self.duration = float(self.out.trajectory.duration)
                self.deadline = now + 1.5 * self.duration + 2.0
            if result is Result.Working:
                self.out.pass_to_input(self.inp)
            else:
                self.finished = True
        s = float(self.out.new_position[0]) if not self.finished else 1.0
        return self.p0 + s * self.dp, self.r0 @ pin.exp3(s * self.w)

    def reached(self, p: np.ndarray, r: np.ndarray) -> bool:
        return (self.finished and float(np.linalg.norm(p - self.goal_p)) <= _MOVE_DONE_POSITION_M
                and float(np.linalg.norm(pin.log3(r.T @ self.goal_r))) <= _MOVE_DONE_ROTATION_RAD)


class UrBackend(Actuator):
    """One UR arm (six joints) through ur_rtde. See the module docstring.

    Constructing validates the profile (raises ProfileError naming the key); nothing connects
    before :meth:`open`.
    """

    capabilities = Capabilities(position=True, velocity=True, effort=False, measures_velocity=True,
                                measures_effort=False, needs_homing=False, can_free=True,
                                native_rate_hz=500.0, native_cartesian=True, measures_wrench=True)
    extra = "ur"
    fault_reaction = Actuator.fault_reaction  # the DISABLE transition: stop, power off, brakes on
    paces_cycle = True
    simulator = SimWiring(device="ur", endpoint_key="host", host_ports=(30004, 29999, 30003))
    stops_itself_on_pause = True  # a safeguard stop stops the arm by itself: resume from where it is
    transition_timeouts_s = {**DEFAULT_TRANSITION_TIMEOUTS_S, Lifecycle.ENABLE: 20.0, Lifecycle.DISABLE: 6.0,
                             Lifecycle.RESUME: 3.0, Lifecycle.FAULT_RESET: 12.0, Lifecycle.GOAL_CHECK: 2.0}

    def __init__(self, profile: Profile, *, source: str = "<profile>"):
        super().__init__(profile, source=source)
        self.source = source
        given = set(profile.backend) - {"type"}
        fields = Config.__struct_fields__
        for key in sorted(given - set(fields)):
            raise ProfileError(f"{source}: backend.{key}: {unknown_key_message(key, ['type', *fields], 'the ur backend')}")
        if "host" not in given:
            raise ProfileError(f"{source}: backend.host: required, the UR controller's address (e.g. 192.168.1.10)")
        self.config = cfg = backend_config(profile, Config, source)
        if cfg.watchdog_hz == 0:
            raise ProfileError(f"{source}: backend.watchdog_hz: 0 would switch the control script's RTDE watchdog "
                               f"off, and a dead or stalled control process would then leave the arm following "
                               f"its last speedJ / servoJ; not offered (give a rate in Hz, default 10)")
        if self.n != N_JOINTS:
            raise ProfileError(f"{source}: joints: a UR arm has {N_JOINTS} joints (base .. wrist 3), "
                               f"the profile lists {self.n}")
        for i, j in enumerate(profile.joints):
            if j.backend:
                raise ProfileError(f"{source}: joints[{i}] ({j.name}).{next(iter(j.backend))}: a UR joint has "
                                   "no backend keys (the controller numbers its joints base to wrist 3)")
        self.rate_hz = cfg.rate_hz or SERIES_RATE_HZ[cfg.series]
        self.capabilities = dataclasses.replace(self.capabilities, native_rate_hz=self.rate_hz)
        self.dt = 1.0 / self.rate_hz
        self._speed_acc = cfg.speed_acceleration or min(j.limits.acceleration_max for j in profile.joints)
        self._pos_min = np.array([j.limits.position_min for j in profile.joints])
        self._pos_max = np.array([j.limits.position_max for j in profile.joints])
        self._vel_max = np.array([j.limits.velocity_max for j in profile.joints])
        self._rcv: Any = None
        self._dash: Any = None
        self._ctl: Any = None
        # latest packet
        self._ts = -1.0  # controller timestamp of the last packet seen (s)
        self._arrived = 0.0  # perf_counter when it was seen
        self.packets = 0
        self.missed_packets = 0
        self._link = False
        self.robot_mode = int(RobotMode.NO_CONTROLLER)
        self.safety_mode = int(SafetyMode.UNDEFINED_SAFETY_MODE)
        self.runtime_state = int(RuntimeState.STOPPED)
        #: the controller's speed slider (0..1), NaN before the first packet; core reports it
        self.speed_fraction = math.nan
        self._tcp_p = np.zeros(3)
        self._tcp_r = np.eye(3)
        self._tcp_rotvec = np.zeros(3)
        self._state_code: str | None = None
        # blocking calls on a worker (one at a time)
        self._ctl_thread: threading.Thread | None = None  # a blocking call on the control interface
        self._cycle_job = False  # it was started by the cycle's write (teach mode), not a transition
        self._job_box: dict[str, Any] = {}
        self._job_what = ""
        self._job_after: tuple[Callable[[Any], None], Any] = (lambda arg: None, None)
        self._reconnecting = False
        self._reconnect_thread: threading.Thread | None = None
        self._ctl_link_lost = False  # the control interface lived through a lost link
        self._next_reconnect = 0.0
        # command side
        self._target = np.zeros(N_JOINTS)  # last servoJ target (rad)
        self._teach = False  # teach mode on
        self._last_kind = ""  # "servoj", "speedj", "servol", "speedl": what ran last
        self._move = _CartesianMove(self.dt, cfg)
        self._done_seq = 0
        self._move_fault: Fault | None = None
        #: the device paused itself (safeguard stop): hold the pose it stopped at until resume
        self._paused_hold = False
        self._last_sent = 0.0  # perf_counter of the last RTDE input to the script (its watchdog)

    #: the defaults of ``link_timeout_s`` and ``watchdog_hz`` on the simulated controller
    #: (``sim_profile``; a profile that sets them keeps its own): the simulator is a Python
    #: process on the daemon's own PC, and neither runs with real-time scheduling there, so a
    #: loaded host's scheduling hiccups pause its packets, the daemon's receive thread and
    #: ur_rtde's own threads for over 0.1 s (measured with two busy cores: link_lost, and the
    #: script's watchdog stopping it at the end of an enable); a real controller streams from a
    #: real-time system, and the daemon's control process runs SCHED_FIFO
    SIM_DEFAULTS = {"link_timeout_s": 0.5, "watchdog_hz": 2.0}

    @classmethod
    def sim_profile(cls, profile: Profile, endpoint: str) -> Profile:
        """``profile`` wired to the simulated controller at ``endpoint``, with
        :attr:`SIM_DEFAULTS` where it sets no value of its own."""
        wired = super().sim_profile(profile, endpoint)
        return msgspec.structs.replace(wired, backend={**cls.SIM_DEFAULTS, **wired.backend})

    # ------------------------------------------------------------------ start-up path
    @property
    def host(self) -> str:
        return self.config.host

    def _open_hook(self) -> None:
        cfg = self.config
        try:
            self._rcv = rtde_receive.RTDEReceiveInterface(cfg.host, self.rate_hz, VARIABLES)
        except RuntimeError as exc:
            raise BackendError(f"{self.robot}: backend.host: cannot open RTDE to the UR controller at "
                               f"{cfg.host}:30004 at {self.rate_hz:g} Hz (backend.series / rate_hz): {exc}") from exc
        try:
            dash = dashboard_client.DashboardClient(cfg.host)
            dash.connect()
        except RuntimeError as exc:
            self._rcv.disconnect()
            self._rcv = None
            raise BackendError(f"{self.robot}: backend.host: cannot reach the UR dashboard server at "
                               f"{cfg.host}:29999: {exc}") from exc
        self._dash = dash
        self._refresh()

    def _configure_hook(self) -> None:
        """The robot starts DISABLED: an arm found powered (by the pendant, or left so by a daemon
        that died ENABLED) is stopped and powered off, as ``disable`` does (the serial backends
        switch torque off here). Blocks. Raises BackendError when it cannot confirm it."""
        deadline = time.monotonic() + self.config.link_timeout_s + 1.0
        while not self._refresh() and time.monotonic() < deadline:
            time.sleep(self.dt)  # the first packet of a fresh link
        if self._link and self.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.BACKDRIVE,
                                              RobotMode.RUNNING):
            self.disable()

    def _close_hook(self) -> None:
        # ur_rtde's interfaces throw C++ exceptions out of disconnect() and out of their
        # destructors once their link broke ("write: Broken pipe", also from the control
        # interface's own reconnect thread), which aborts the process (std::terminate). So: a
        # blocking control call is waited for; an interface is disconnected only while its link
        # is healthy; and none is ever freed (_abandon: one per backend, the daemon's control
        # process ends with os._exit anyway).
        self._wait_job(8.0)
        if self._reconnect_thread is not None:
            self._reconnect_thread.join(5.0)
        busy = self._ctl_thread is not None and self._ctl_thread.is_alive()
        if self._ctl is not None and self._ctl_link_lost and not busy:
            # its own thread reconnects once the controller answers again: let it, then
            # disconnect it properly, else it lingers on, reconnecting to this host forever
            deadline = time.monotonic() + 1.0
            while not self._ctl.isConnected() and time.monotonic() < deadline:
                time.sleep(0.05)
            self._ctl_link_lost = not self._ctl.isConnected()
        for name in ("_ctl", "_rcv", "_dash"):
            obj = getattr(self, name)
            setattr(self, name, None)
            if obj is None:
                continue
            _abandon(obj)
            healthy = not (name == "_ctl" and (busy or self._ctl_link_lost)) and obj.isConnected()
            if healthy:
                try:
                    obj.disconnect()  # sleeps 0.5 s (ur_rtde), on the way out only
                except Exception:
                    pass
        self._link = False

    def info(self) -> ActuatorInfo:
        details = {"host": self.host, "rate_hz": self.rate_hz, "packets": self.packets,
                   "missed_packets": self.missed_packets}
        return ActuatorInfo(list(self.joint_names), self.capabilities, details)

    # ------------------------------------------------------------------ pacing
    def cycle_period_s(self) -> float:
        return self.dt

    def wait_cycle(self, timeout_s: float) -> bool:
        """Until the next RTDE packet (its timestamp moved on), at most ``timeout_s``. Sleeps
        until shortly before the packet is due, then polls every 0.1 ms. Counts skipped
        packets in ``missed_packets``."""
        clock = time.perf_counter
        start = clock()
        deadline = start + timeout_s
        r = self._rcv
        if r is None or self._reconnecting or not self._link:
            time.sleep(min(timeout_s, self.dt))
            return False
        due = self._arrived + self.dt - 0.0003
        if due > start:
            time.sleep(min(due, deadline) - start)
        while True:
            if self._new_packet(r):
                return True
            now = clock()
            if now >= deadline:
                return False
            time.sleep(min(0.0001, deadline - now))

    def _new_packet(self, r: Any) -> bool:
        """True when a packet newer than the last one seen arrived (counts skipped ones)."""
        ts = r.getTimestamp()
        last = self._ts
        if ts == last:
            return False
        if last >= 0.0:
            skipped = int(round((ts - last) / self.dt)) - 1
            if skipped > 0:
                self.missed_packets += skipped
        self.packets += 1
        self._ts = ts
        self._arrived = time.perf_counter()
        return True

    # ------------------------------------------------------------------ real-time path
    def _refresh(self) -> bool:
        """Copy the modes and the speed slider from the latest packet. Never blocks. False: no link."""
        r = self._rcv
        if r is None or self._reconnecting:
            self._link = False
            return False
        # isConnected() alone is not enough: after a failed reconnect() it says True with no data
        # coming (and a pulled cable sends no FIN): the packets must keep arriving too
        self._link = bool(r.isConnected()) and (self._new_packet(r) or
                                                time.perf_counter() - self._arrived < self.config.link_timeout_s)
        if not self._link:
            return False
        try:
            self.robot_mode = int(r.getRobotMode())
            self.safety_mode = int(r.getSafetyMode())
            self.runtime_state = int(r.getRuntimeState())
            self.speed_fraction = float(r.getTargetSpeedFraction())
        except RuntimeError:  # the link went down since isConnected() said yes
            self._link = False
        return self._link

    def _movable(self) -> bool:
        """Commands may go out: link up, safety NORMAL / REDUCED, robot RUNNING, script PLAYING."""
        return (self._link and self.safety_mode in MOVABLE and self.robot_mode == RobotMode.RUNNING
                and self.runtime_state == RuntimeState.PLAYING)

    def _read(self, feedback: JointFeedback) -> Fault | None:
        if self._rcv is None:
            return Fault("link_lost", f"{self.robot}: the RTDE link is closed", transient=False)
        link = self._refresh()
        state = device_state(link, self.robot_mode, self.safety_mode, self.runtime_state, self._enabled)
        if state.code != self._state_code:
            self._state_code = state.code
            cause = None
            if state.code is not None:
                cause = Fault(state.code, f"{self.robot}: {state.text} (UR controller at {self.host}; robot mode "
                              f"{_name(RobotMode, self.robot_mode)}, safety mode {_name(SafetyMode, self.safety_mode)}, "
                              f"runtime {_name(RuntimeState, self.runtime_state)})", transient=False)
            if state.status is DeviceStatus.OK and self.device_status is DeviceStatus.FAULT:
                self.report_status(DeviceStatus.FAULT_CLEARED)
            else:
                self.report_status(state.status, cause)
        if not link:
            return self._link_lost()
        r = self._rcv
        try:
            q, qd, pose = r.getActualQ(), r.getActualQd(), r.getActualTCPPose()
            wrench = r.getActualTCPForce()
        except RuntimeError:  # the link went down since isConnected() said yes
            self._link = False
            return self._link_lost()
        feedback.position[:] = q
        feedback.velocity[:] = qd
        feedback.stamp = self.now()
        if self._enabled:
            self._feed_watchdog()
        if state.status is DeviceStatus.PAUSED and not self._paused_hold and self._enabled:
            self._paused_hold = True  # where the arm stopped: the target until resume (see _write)
            self._target[:] = feedback.position
        cart = feedback.cartesian
        if cart is not None:
            cart.position[0] = pose[:3]
            self._tcp_rotvec[:] = pose[3:]
            _quat_xyzw(self._tcp_rotvec, cart.orientation[0])
            cart.wrench[0] = wrench
            cart.done_seq[0] = self._done_seq
            cart.stamp = feedback.stamp
        self._tcp_p[:] = pose[:3]
        self._tcp_r = pin.exp3(self._tcp_rotvec)
        return None

    def _feed_watchdog(self) -> None:
        """The script's watchdog wants an RTDE input at least every 1 / watchdog_hz s: the cycle's
        commands are that; when none went out for 20 ms (teach mode, a paused program, a
        transition), a kick. So it stops the arm only when the control process stops cycling."""
        now = time.perf_counter()
        if now - self._last_sent < 0.02 or self._ctl is None or not self._ctl.isConnected():
            return
        t = self._ctl_thread
        if t is not None and t.is_alive():
            return  # a blocking call's own inputs feed it
        try:
            self._ctl.kickWatchdog()
        except RuntimeError:
            return  # the link is going: the state table reports it
        self._last_sent = now

    def _link_lost(self) -> Fault:
        self._ctl_link_lost = self._ctl is not None  # see _close_hook
        self._maybe_reconnect()
        return Fault("link_lost", f"{self.robot}: RTDE link to the UR controller at {self.host} lost "
                     "(reconnecting by itself; enable once it is back)", transient=False)

    def _write(self, command: JointCommand) -> Fault | None:
        if not self._enabled or self._ctl is None:
            return None
        if self._ctl_thread is not None:  # a blocking call owns the control interface
            if self._ctl_thread.is_alive() or not self._cycle_job:
                return None  # (a transition's job is collected by the transition's own steps)
            fault = self._end_job()
            if fault is not None:
                return fault
        if self._move_fault is not None:
            fault, self._move_fault = self._move_fault, None
            return fault
        if self._paused_hold:
            # Paused by the device: the script's servo target becomes the pose the arm stopped at,
            # written even while the program is paused, so that when the safeguard is reset the
            # program resumes on THAT target instead of rushing to the one it had before the stop
            # (what UR users report). Core's setpoint no longer matters; resume re-seeds it.
            if (self._link and self.robot_mode == RobotMode.RUNNING and self.runtime_state in
                    (RuntimeState.PLAYING, RuntimeState.PAUSED, RuntimeState.PAUSING) and self._ctl.isConnected()):
                cfg = self.config
                try:
                    self._ctl.servoJ(self._target.tolist(), 0.0, 0.0, self.dt, cfg.servo_lookahead_time_s,
                                     cfg.servo_gain)
                except RuntimeError:
                    return None  # the link went down: the state table reports it
                self._last_kind = "servoj"
                self._last_sent = time.perf_counter()
            return None
        if not self._movable():
            return None  # gated: servoJ would "succeed" with the link down; the state table says why
        if not self._ctl.isConnected():  # (a servoJ then tries to reconnect, blocking the cycle)
            return Fault("link_lost", f"{self.robot}: the RTDE control link to {self.host} is down "
                         "(reconnecting by itself)", transient=True)
        try:
            return self._send(command)
        except RuntimeError as exc:  # it went down meanwhile
            return Fault("link_lost", f"{self.robot}: the RTDE control link to {self.host} failed: {exc}",
                         transient=True)

    def _send(self, command: JointCommand) -> Fault | None:
        """This cycle's one realtime script command (the gates passed)."""
        cart = command.cartesian
        if cart is not None and cart.mode[0] != _NONE:
            return self._write_cartesian(cart)
        mode = command.mode
        # a blocking call started as the link dies waits for its answer for minutes (ur_rtde),
        # spinning: teach-mode switches start only on a link whose packet came this cycle
        fresh = time.perf_counter() - self._arrived < 2.0 * self.dt
        if np.all(mode == _FREE):
            if not self._teach and fresh:
                self._start_job(self._ctl.teachMode, "teach mode", self._set_teach, True)
            return None
        if np.any(mode == _FREE):
            return Fault("invalid_command", f"{self.robot}: free applies to the whole UR arm (teach mode), "
                         "not to some joints", transient=False)
        if self._teach:
            if fresh:
                self._start_job(self._ctl.endTeachMode, "end of teach mode", self._set_teach, False)
            return None
        ok = True
        if np.any(mode == _VELOCITY):
            qd = np.where(mode == _VELOCITY, command.velocity, 0.0)
            bad = _first_bad(qd)
            if bad is not None:
                return self._invalid(bad, "velocity", qd[bad])
            np.clip(qd, -self._vel_max, self._vel_max, out=qd)
            ok = self._ctl.speedJ(qd.tolist(), self._speed_acc, 0.0)
            self._last_kind = "speedj"
            self._target[:] = command.position  # a later hold starts from core's (measured) setpoint
        else:
            q = self._target
            fault = None
            for i in range(N_JOINTS):
                if mode[i] == _POSITION:
                    v = command.position[i]
                    if not math.isfinite(v):
                        fault = fault or self._invalid(i, "position", v)
                        continue  # this joint keeps its last target; the others are sent
                    q[i] = min(max(v, self._pos_min[i]), self._pos_max[i])
            cfg = self.config
            ok = self._ctl.servoJ(q.tolist(), 0.0, 0.0, self.dt, cfg.servo_lookahead_time_s, cfg.servo_gain)
            self._last_kind = "servoj"
            self._last_sent = time.perf_counter()
            if fault is not None:
                return fault
        if not ok:
            return Fault("command_refused", f"{self.robot}: the UR control script refused {self._last_kind}",
                         transient=True)
        self._last_sent = time.perf_counter()
        return None

    def _write_cartesian(self, cart) -> Fault | None:
        cfg = self.config
        m = int(cart.mode[0])
        if m == _C_TWIST:
            xd = np.concatenate([cart.linear[0], cart.angular[0]])
            if not np.all(np.isfinite(xd)):
                return Fault("invalid_command", f"{self.robot}: servo_cv twist is not finite", transient=False)
            if int(cart.frame[0]) == FRAME_BODY:  # speedL takes base-frame axes
                xd[:3] = self._tcp_r @ xd[:3]
                xd[3:] = self._tcp_r @ xd[3:]
            ok = self._ctl.speedL(xd.tolist(), cfg.speedl_acceleration, 0.0)
            self._last_kind = "speedl"
        else:
            if m == _C_MOVE:
                now = time.monotonic()
                mv = self._move
                if int(cart.seq[0]) != mv.seq or (mv.finished and self._done_seq < mv.seq):
                    if int(cart.seq[0]) != mv.seq:
                        mv.start(int(cart.seq[0]), self._tcp_p, self._tcp_r, cart.position[0], cart.orientation[0], now)
                p, rot = mv.step(now)
                if mv.reached(self._tcp_p, self._tcp_r):
                    self._done_seq = mv.seq
                elif now > mv.deadline:
                    self._done_seq = mv.seq
                    return Fault("move_timeout", f"{self.robot}: move_cp did not reach its pose within "
                                 f"{1.5 * mv.duration + 2.0:.1f} s (1.5 x its duration {mv.duration:.2f} s + 2 s); "
                                 f"TCP at {np.round(self._tcp_p, 4).tolist()} m", transient=False)
                pose = [float(p[0]), float(p[1]), float(p[2]), *map(float, pin.log3(rot))]
            else:
                if not (np.all(np.isfinite(cart.position[0])) and np.all(np.isfinite(cart.orientation[0]))):
                    return Fault("invalid_command", f"{self.robot}: servo_cp pose is not finite", transient=False)
                pose = _pose6(cart.position[0], cart.orientation[0])
            ok = self._ctl.servoL(pose, 0.0, 0.0, self.dt, cfg.servo_lookahead_time_s, cfg.servo_gain)
            self._last_kind = "servol"
        self._last_sent = time.perf_counter()
        if not ok:
            return Fault("command_refused", f"{self.robot}: the UR control script refused {self._last_kind}",
                         transient=True)
        return None

    def _invalid(self, i: int, field: str, value: float) -> Fault:
        name = self.joint_names[i]
        return Fault("invalid_command", f"{self.robot}: joint {name!r}: {field} setpoint {value!r} is not finite; "
                     "not sent", joint=name, value=float(value), transient=False)

    def _set_teach(self, on: bool) -> None:
        self._teach = on
        if not on:
            self._target[:] = self._rcv.getActualQ() if self._rcv is not None else self._target

    # ------------------------------------------------------------------ worker jobs
    @staticmethod
    def _spawn(fn: Callable[[], Any], what: str) -> tuple[threading.Thread, dict]:
        """``fn()`` on a daemon thread; its result or exception lands in the returned box."""
        box: dict[str, Any] = {}

        def run() -> None:
            try:
                box["result"] = fn()
            except BaseException as exc:  # carried to the cycle / the transition
                box["error"] = exc

        thread = background_thread(run, f"ur {what}")
        thread.start()
        return thread, box

    def _start_job(self, fn: Callable[[], Any], what: str, after: Callable[[Any], None], arg: Any) -> None:
        """The cycle's own blocking call (a teach-mode switch) on a worker; the control interface
        is its until the cycle collects it (:meth:`_end_job`), then ``after(arg)`` runs."""
        self._ctl_thread, self._job_box = self._spawn(fn, what)
        self._job_what, self._job_after, self._cycle_job = what, (after, arg), True

    def _end_job(self) -> Fault | None:
        self._ctl_thread = None
        exc = self._job_box.get("error")
        if exc is None:
            after, arg = self._job_after
            after(arg)
            return None
        return Fault("command_failed", f"{self.robot}: {self._job_what} failed on the UR controller at "
                     f"{self.host}: {exc}", transient=False)

    def _wait_job(self, timeout_s: float) -> None:
        t = self._ctl_thread
        if t is not None:
            t.join(timeout_s)
            if not t.is_alive():
                self._ctl_thread = None

    def _job(self, fn: Callable[[], Any], what: str, retry_s: float = 0.0, ctl: bool = True) -> Steps:
        """Steps running ``fn()`` on a worker, yielding every cycle until it returns; its error
        raised as a BackendError naming ``what``. ``ctl``: it uses the control interface, which
        is one caller's at a time (the cycle sends nothing on it meanwhile); dashboard calls do
        not wait for it. ``retry_s`` > 0: a failure is retried every 0.3 s for that long
        (e-Series refuses to unlock a protective stop within 5 s of it)."""
        if ctl:
            while self._ctl_thread is not None and self._ctl_thread.is_alive():
                yield  # a teach-mode switch of the cycle's own is finishing
            self._ctl_thread = None
        give_up = time.monotonic() + retry_s
        while True:
            thread, box = self._spawn(fn, what)
            if ctl:
                self._ctl_thread, self._cycle_job = thread, False
            try:
                while thread.is_alive():
                    yield
            finally:
                if ctl and self._ctl_thread is thread and not thread.is_alive():
                    self._ctl_thread = None
            exc = box.get("error")
            if exc is None:
                return
            if time.monotonic() >= give_up:
                raise BackendError(f"{self.robot}: {what} failed on the UR controller at {self.host}: {exc}") from exc
            pause = time.monotonic() + 0.3
            while time.monotonic() < pause:
                yield

    def _until(self, done: Callable[[], bool], what: str) -> Steps:
        """Yield until ``done()`` (evaluated on freshly read modes); the transition's time limit
        bounds it. Raises BackendError when the link is lost meanwhile."""
        while True:
            link = self._refresh()
            if not link:
                raise BackendError(f"{self.robot}: RTDE link to {self.host} lost while waiting for {what}")
            if done():
                return
            yield

    def _maybe_reconnect(self) -> None:
        """After a link loss: ``reconnect()`` on a worker every ``reconnect_interval_s``. The cycle
        does not touch the receive interface meanwhile (``_reconnecting``)."""
        now = time.monotonic()
        if self._reconnecting or now < self._next_reconnect or self._rcv is None:
            return
        self._next_reconnect = now + self.config.reconnect_interval_s
        self._reconnecting = True
        r = self._rcv

        def run() -> None:
            try:
                if not r.isConnected():
                    # its own receive thread ended the link: join it (disconnect) before
                    # reconnect() starts another, or both run on one socket (heap corruption)
                    r.disconnect()
                r.reconnect()
            except RuntimeError:
                pass  # still down: the next attempt after reconnect_interval_s
            finally:
                self._ts = -1.0
                self._arrived = time.perf_counter()  # its packets have link_timeout_s to show up
                self._reconnecting = False

        self._reconnect_thread = background_thread(run, "ur rtde reconnect")
        self._reconnect_thread.start()

    # ------------------------------------------------------------------ lifecycle transitions
    def _require_link(self, what: str) -> None:
        if not self._refresh():
            raise BackendError(f"{self.robot}: {what} refused: no RTDE link to the UR controller at {self.host}")

    def _enable_steps(self, feedback: JointFeedback) -> Steps:
        self._require_link("enable")
        if self.safety_mode in _RESETTABLE:
            # a stop that outlived the FAULT it caused (disable from FAULT, then enable): enable
            # clears it as enable from FAULT does (a latched error: as a Dynamixel REBOOT, a
            # CiA 402 fault reset); e-stops stay refused below
            yield from self._fault_reset_steps()
        state = device_state(True, self.robot_mode, self.safety_mode, self.runtime_state, False)
        if state.status is not DeviceStatus.OK and state.status is not DeviceStatus.PAUSED:
            raise BackendError(f"{self.robot}: enable refused: {state.text}")
        if self.safety_mode not in MOVABLE:
            raise BackendError(f"{self.robot}: enable refused: {state.text}; reset it first")
        if self.robot_mode != RobotMode.RUNNING:
            if self.robot_mode != RobotMode.IDLE:
                yield from self._job(self._dash.powerOn, "power on", ctl=False)
                yield from self._until(lambda: self.robot_mode in (RobotMode.IDLE, RobotMode.RUNNING),
                                       "robot mode IDLE after power on")
            if self.robot_mode != RobotMode.RUNNING:
                yield from self._job(self._dash.brakeRelease, "brake release", ctl=False)
                yield from self._until(lambda: self.robot_mode == RobotMode.RUNNING,
                                       "robot mode RUNNING after brake release")
        yield from self._job(self._start_script, "control script upload")
        # ur_rtde refuses commands until ITS connection saw the program run (a packet later, maybe)
        yield from self._until(lambda: self.runtime_state == RuntimeState.PLAYING and self._ctl.isProgramRunning(),
                               "the control script to run")
        if self.config.watchdog_hz > 0:  # from now on the cycle feeds it (_write, _feed_watchdog)
            self._last_sent = time.perf_counter()
            yield from self._job(lambda: self._ctl.setWatchdog(self.config.watchdog_hz), "setWatchdog")
        self._hold_here()

    def _start_script(self) -> None:
        """Worker: the control interface up and its script running (built, reconnected or re-uploaded)."""
        ctl = self._ctl
        if ctl is None:
            self._ctl = rtde_control.RTDEControlInterface(self.host, self.rate_hz)
            return
        if self._ctl_link_lost or not ctl.isConnected():
            # never reconnect() (nor call, nor free) an interface that lived through a link loss:
            # its own receive thread handles the loss (disconnect, its own reconnect attempt) and
            # races any call made meanwhile, corrupting the heap (seen: malloc aborts). A new one.
            _abandon(ctl)
            self._ctl = None
            self._ctl = ctl = rtde_control.RTDEControlInterface(self.host, self.rate_hz)
            self._ctl_link_lost = False
        if not ctl.isProgramRunning():
            ctl.reuploadScript()

    def _hold_here(self) -> None:
        """The arm holds where it is: the next servoJ target is the measured pose."""
        if self._rcv is not None and self._link:
            self._target[:] = self._rcv.getActualQ()
        self._teach = False
        self._last_kind = ""
        self._paused_hold = False
        self._move.finished = True
        self._done_seq = self._move.seq

    def _disable_steps(self) -> Steps:
        self._paused_hold = False
        self._move.finished = True
        self._done_seq = self._move.seq
        if self._dash is None:
            return
        link = self._refresh()
        if (self._ctl is not None and link and self.runtime_state == RuntimeState.PLAYING
                and not self._ctl_link_lost and self._ctl.isConnected()):
            # (not on an interface that lived through a link loss: see _start_script; the
            # script's watchdog has stopped its program, power off below stops the rest)
            yield from self._job(self._stop_script, "stop")
        elif not link:
            yield from self._job(self._dash.powerOff, "power off", ctl=False)
            raise BackendError(f"{self.robot}: power off sent, but not confirmed: no RTDE link to {self.host}")
        if self.robot_mode != RobotMode.POWER_OFF:
            yield from self._job(self._dash.powerOff, "power off", ctl=False)
            yield from self._until(lambda: self.robot_mode == RobotMode.POWER_OFF, "robot mode POWER_OFF")
        self._teach = False

    def _stop_script(self) -> None:
        """Worker: decelerate whatever runs, leave teach mode, end the control script."""
        ctl = self._ctl
        try:
            if self._teach:
                ctl.endTeachMode()
            if self._last_kind in ("speedj", "speedl"):
                ctl.speedStop(4.0)
            elif self._last_kind in ("servoj", "servol"):
                ctl.servoStop(4.0)
        finally:
            ctl.stopScript()

    def _fault_reset_steps(self) -> Steps:
        if not self._refresh():
            if self._rcv is None:
                raise BackendError(f"{self.robot}: enable refused: the RTDE link is closed")
            self._next_reconnect = 0.0
            self._maybe_reconnect()  # now, on the worker the cycle's reads stay away from
            while self._reconnecting:
                yield
            self._require_link("enable")
        if not self._dash.isConnected():
            yield from self._job(self._dash.connect, "dashboard reconnect", ctl=False)
        mode = self.safety_mode
        if mode == SafetyMode.PROTECTIVE_STOP:
            yield from self._job(self._dash.closeSafetyPopup, "close safety popup", ctl=False)
            yield from self._job(self._dash.unlockProtectiveStop, "unlock protective stop", retry_s=7.0, ctl=False)
            yield from self._until(lambda: self.safety_mode in MOVABLE, "the protective stop to clear")
        elif mode in (SafetyMode.VIOLATION, SafetyMode.FAULT):
            yield from self._job(self._dash.closeSafetyPopup, "close safety popup", ctl=False)
            yield from self._job(self._dash.restartSafety, "restart safety", ctl=False)
            yield from self._until(lambda: self.safety_mode in MOVABLE, "the safety system to restart")
        elif mode in (SafetyMode.SYSTEM_EMERGENCY_STOP, SafetyMode.ROBOT_EMERGENCY_STOP):
            raise BackendError(f"{self.robot}: enable refused: the emergency stop is still engaged; release it first")
        elif mode == SafetyMode.RECOVERY:
            raise BackendError(f"{self.robot}: enable refused: safety recovery mode; move the arm back inside "
                               "its limits by hand (teach mode on the pendant) first")
        # the control interface reconnects (and uploads its script) in ENABLE, once the arm runs

    def _resume_steps(self) -> Steps:
        self._require_link("resume")
        if self.safety_mode not in MOVABLE:
            yield from self._until(lambda: self.safety_mode in MOVABLE, "the safeguard stop to be reset")
        if self.runtime_state in (RuntimeState.PAUSED, RuntimeState.PAUSING):
            yield from self._job(self._dash.play, "play", ctl=False)
            yield from self._until(lambda: self.runtime_state == RuntimeState.PLAYING, "the control script to resume")
        self._hold_here()  # from the measured pose: no rush to where it was going when stopped

    # ------------------------------------------------------------------ goal checks
    def goal_check_steps(self, ns: str, cmd: str, goal: np.ndarray) -> Steps | None:
        """The controller's own safety limits, asked before a move starts (see the module
        docstring). ``goal``: the namespace's joint positions (move_jp) or the pose [x, y, z,
        qx, qy, qz, qw] (move_cp). Raises CommandError("out_of_limits") naming the joint / pose."""
        if self._ctl is None:
            return None
        return self._goal_check(ns, cmd, np.array(goal, dtype=float))

    def _goal_check(self, ns: str, cmd: str, goal: np.ndarray) -> Steps:
        box: dict[str, Any] = {}
        ctl = self._ctl
        if cmd == "move_cp":
            pose = _pose6(goal[:3], goal[3:])

            def check() -> None:
                box["ok"] = ctl.isPoseWithinSafetyLimits(pose)

            yield from self._job(check, "isPoseWithinSafetyLimits")
            if not box["ok"]:
                raise CommandError("out_of_limits", f"{ns}: {cmd} refused: the pose "
                                   f"[{', '.join(fmt_number(v) for v in pose)}] (x, y, z m, rx, ry, rz rad) is "
                                   f"outside the UR controller's safety limits (isPoseWithinSafetyLimits)")
            return
        here = list(self._rcv.getActualQ())

        def check_joints() -> None:
            box["ok"] = ctl.isJointsWithinSafetyLimits(goal.tolist())
            if not box["ok"]:  # which joint: the first whose goal alone is refused
                for i in range(N_JOINTS):
                    q = list(here)
                    q[i] = float(goal[i])
                    if not ctl.isJointsWithinSafetyLimits(q):
                        box["joint"] = i
                        return

        yield from self._job(check_joints, "isJointsWithinSafetyLimits")
        if not box["ok"]:
            i = box.get("joint")
            what = (f"goal {fmt_number(goal[i])} rad for joint {self.joint_names[i]!r}" if i is not None
                    else f"goal [{', '.join(fmt_number(v) for v in goal)}] rad")
            raise CommandError("out_of_limits", f"{ns}: {cmd} refused: {what} is outside the UR controller's "
                               "safety limits (isJointsWithinSafetyLimits)")


def _first_bad(v: np.ndarray) -> int | None:
    bad = np.flatnonzero(~np.isfinite(v))
    return int(bad[0]) if bad.size else None


def _name(enum_type: type, value: int) -> str:
    try:
        return enum_type(value).name
    except ValueError:
        return str(value)

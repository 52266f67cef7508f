"""Universal Robots arms over RTDE, on ur_rtde (``rtde_receive``, ``rtde_control``, ``dashboard_client``)
run in a worker process of its own.

ur_rtde never runs in the control process: :mod:`.worker` (``python -m
crtk_bridge.backends.ur.worker``, exec'd by :meth:`UrBackend._open_hook`, never a fork) holds every
ur_rtde object, and the backend talks to it over :mod:`.channel` (the newest package in shared
memory under a seqlock, a wake-up and everything else on a socketpair). Why: ur_rtde 1.6.5
corrupts its heap when a link drops while it is called (each interface handles the loss on its
own thread), and its constructors hold the GIL for ~16 ms. In the worker, an abort ends the
worker only (FAULT ``worker_died`` naming the signal, in the cycle that sees it; the script's
watchdog stops the arm), and nothing it does can stall the cycle. The worker's three connections
to the controller at ``backend.host`` (the ports are fixed by UR):

* ``RTDEReceiveInterface`` (RTDE 30004), opened with the backend: joint and TCP state, robot /
  safety mode, runtime state and the speed slider, one packet every 2 ms (e-Series, 500 Hz) or
  8 ms (CB3, 125 Hz). Its packets PACE THE LOOP (``traits.clock`` is the device's): the worker forwards each as it
  comes, and :meth:`UrBackend.wait_cycle` blocks until it does (and counts the packets skipped).
* ``DashboardClient`` (29999): power on / off, brake release, unlock protective stop, restart
  safety, play (lifecycle path only).
* ``RTDEControlInterface`` (RTDE 30004 + script 30003), built on the first enable: ur_rtde uploads
  its control script and talks to it through RTDE registers.

Real-time path (every cycle, nothing blocks): ``read`` takes the newest packet the worker
forwarded; ``write`` sends ONE realtime script command to the worker (never blocking: a worker
whose channel is full gets it dropped and the robot FAULTs, ``worker_stalled``), which hands it
to ur_rtde, which writes the RTDE input registers without waiting for an answer. A command the
same as the last one (a hold) goes out again only every ``_keepalive_s`` (20 ms; a fifth of the
script's watchdog period when that is shorter): the script's servo / speed thread repeats its
last command every controller tick by itself, and a changed command goes out in its cycle:

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

Lifecycle (blocking ur_rtde and dashboard calls are requests to the worker, which runs each on a
thread of its own and replies; :meth:`UrBackend._job` yields every cycle until the reply; while
one on the control interface runs the cycle sends no command and the robot keeps following its
last target):

* ENABLE = power on (dashboard) -> robot mode IDLE -> brake release -> RUNNING -> control script
  uploaded (the worker builds its ``RTDEControlInterface``, or calls ``reuploadScript``) ->
  runtime state PLAYING; the arm
  is then held where it is. Each wait is on the robot mode / runtime state read from RTDE.
* DISABLE = stop the motion and the script, power off (dashboard), until robot mode POWER_OFF.
  It is also the fault reaction: the arm stops and its brakes engage. ``configure`` does the
  same to an arm found powered at start (the robot starts DISABLED).
* FAULT_RESET (enable from FAULT): a fresh worker if the link is down; unlock a protective stop (retried:
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

A link loss (the worker's receive or control link drops, or no package for ``link_timeout_s``)
or a dead worker is a FAULT in the cycle that sees it; the worker is ended there (killed if still
running: ur_rtde is never asked to reconnect in place, where its own threads race our calls, and
no interface outlives its link, so nothing leaks) and a fresh worker is started on a thread every
``reconnect_interval_s`` until one connects (``fault_cleared``); the fault stays until ``enable``.
The worker dies with the control process (it sees the socket close), and never moves the arm
on its own: it sends only what a cycle asked, once.

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

import importlib.util
import math
import os
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
    Clock,
    CommandMode,
    DeviceStatus,
    Fault,
    JointCommand,
    JointFeedback,
    Lifecycle,
    SimWiring,
    background_thread,
    Steps,
    Traits,
    ruckig_update,
)
from ...errors import BackendError, CommandError, ProfileError, fmt_number
from ...profile import Profile, backend_config, unknown_key_message
from .channel import (CTL_CONNECTED, CTL_RUNNING, CTL_UP, KICK, OP_NAMES, SERVOJ, SERVOL, SPEEDJ, SPEEDL, WorkerHandle,
                      encode)
from .state import device_state
from .tables import MOVABLE, RobotMode, RuntimeState, SafetyMode

# the SDK runs in the worker process only (never imported here); the registry names the pip
# extra when it is missing
for _sdk in ("rtde_receive", "rtde_control", "dashboard_client"):
    if importlib.util.find_spec(_sdk) is None:  # pragma: no cover - exercised by the registry's message
        raise ImportError(f"No module named {_sdk!r}", name="ur_rtde")

N_JOINTS = 6
SERIES_RATE_HZ = {"e-series": 500.0, "cb3": 125.0}  # RTDE's highest rate per controller generation
_POSITION, _VELOCITY, _FREE, _NONE = (int(CommandMode.POSITION), int(CommandMode.VELOCITY),
                                      int(CommandMode.FREE), int(CommandMode.NONE))
_C_POSE, _C_TWIST, _C_MOVE = int(CartesianMode.POSE), int(CartesianMode.TWIST), int(CartesianMode.MOVE)
#: safety modes that enable resets over the dashboard (unlock protective stop, restart safety)
_RESETTABLE = (SafetyMode.PROTECTIVE_STOP, SafetyMode.VIOLATION, SafetyMode.FAULT)
_MOVE_DONE_POSITION_M = 0.002  # a move_cp ends once the TCP is this close to the goal...
_MOVE_DONE_ROTATION_RAD = 0.02  # ...and turned this little from it
_ZERO6 = (0.0,) * 6


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
    reconnect_interval_s: Annotated[float, msgspec.Meta(gt=0)] = 0.5  # a fresh ur_rtde worker this often after a link loss
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


def _quat_xyzw(rx: float, ry: float, rz: float, out: np.ndarray) -> None:
    """UR axis-angle (Python floats: numpy scalars cost several times as much per operation, in
    every cycle) -> unit quaternion [x, y, z, w], into ``out``."""
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-12:
        out[:] = (0.0, 0.0, 0.0, 1.0)
        return
    s = math.sin(angle / 2.0) / angle
    out[:] = (rx * s, ry * s, rz * s, math.cos(angle / 2.0))


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
        self.failed = False  # no plan could be made: the path stays where it was (never jumps to s = 1)
        self.s = 1.0
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
        self.failed = False
        self.s = 0.0
        self.otg.reset()
        self.duration = 0.0
        self.deadline = now + 2.0  # refined by the first step, once ruckig knows the duration

    def step(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        """The next (position, rotation matrix) of the path."""
        if not self.finished:
            result = ruckig_update(self.otg, self.inp, self.out)
            if self.duration == 0.0 and result in (Result.Working, Result.Finished):
                self.duration = float(self.out.trajectory.duration)
                self.deadline = now + 1.5 * self.duration + 2.0
            if result is Result.Working:
                self.s = float(self.out.new_position[0])
                self.out.pass_to_input(self.inp)
            elif result is Result.Finished:
                self.s = 1.0
                self.finished = True
            else:  # no plan: stay where the path is (a jump to the goal would be a surprise motion)
                self.finished = self.failed = True
        s = self.s
        return self.p0 + s * self.dp, self.r0 @ pin.exp3(s * self.w)

    def reached(self, p: np.ndarray, r: np.ndarray) -> bool:
        return (self.finished and float(np.linalg.norm(p - self.goal_p)) <= _MOVE_DONE_POSITION_M
                and float(np.linalg.norm(pin.log3(r.T @ self.goal_r))) <= _MOVE_DONE_ROTATION_RAD)


class UrBackend(Actuator):
    """One UR arm (six joints) through ur_rtde in a worker process. See the module docstring.

    Constructing validates the profile (raises ProfileError naming the key); nothing connects
    before :meth:`open`.
    """

    simulator = SimWiring(endpoint_key="host", host_ports=(30004, 29999, 30003), tool_port=54321)
    #: what every UR arm declares (:meth:`_traits_hook`): the controller's packets pace the loop; a
    #: safeguard stop stops the arm by itself (resume from where it is); the controller checks move
    #: goals against its safety limits; its speed slider scales every motion. A FAULT runs the
    #: DISABLE transition: stop, power off, brakes on.
    TRAITS = Traits(
        joints=(Capabilities(position=True, velocity=True, effort=False, measures_velocity=True,
                             measures_effort=False, needs_homing=False, can_free=True, native_cartesian=True,
                             measures_wrench=True),) * N_JOINTS,
        clock=Clock.DEVICE, stops_itself_on_pause=True, goal_check=True, speed_scaling=True,
        transition_timeouts_s={Lifecycle.ENABLE: 20.0, Lifecycle.DISABLE: 6.0, Lifecycle.RESUME: 3.0,
                               Lifecycle.FAULT_RESET: 12.0, Lifecycle.GOAL_CHECK: 2.0})

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
        self.dt = 1.0 / self.rate_hz
        self._speed_acc = cfg.speed_acceleration or min(j.limits.acceleration_max for j in profile.joints)
        #: the ur_rtde worker process (None: none up, e.g. after a link loss until a new one is)
        self._w: WorkerHandle | None = None
        self._opened = False
        self._dispose: list[WorkerHandle] = []  # ended workers, reaped off the cycle
        self._down: tuple[str, str] | None = None  # (fault code, text) of the link's loss
        self._rt_priority = 0  # SCHED_FIFO priority for the worker's package thread (0: none)
        self._rt_checked = False
        # latest package
        self._ts = -1.0  # controller timestamp of the last package seen (s)
        self._arrived = 0.0  # perf_counter when it was seen
        self._taken = False  # wait_cycle took a package the cycle's read has not looked at yet
        self.packets = 0
        self.missed_packets = 0
        self._link = False
        self.robot_mode = int(RobotMode.NO_CONTROLLER)
        self.safety_mode = int(SafetyMode.UNDEFINED_SAFETY_MODE)
        self.runtime_state = int(RuntimeState.STOPPED)
        self._flags = 0  # the control interface in the worker: CTL_UP | CTL_CONNECTED | CTL_RUNNING
        #: the controller's speed slider (0..1), NaN before the first packet; core reports it
        self.speed_fraction = math.nan
        # the package's joints, joint speeds, TCP pose and TCP wrench: views of one array, filled
        # in one copy per package
        self._measured = np.zeros(4 * N_JOINTS)
        self._q, self._qd, self._pose, self._wrench = np.split(self._measured, 4)
        self._rotvec = (0.0, 0.0, 0.0)  # the package's TCP rotation vector (floats)
        self._tcp_p = np.zeros(3)
        self._tcp_rotvec = np.zeros(3)
        self._tcp_rm: np.ndarray | None = np.eye(3)  # its rotation matrix, made when asked (_tcp_r)
        self._device: tuple = ()  # device_state's inputs last cycle, and its answer
        self._state_code: str | None = None
        # blocking calls, run by the worker (one at a time on the control interface)
        self._ctl_job: int | None = None  # id of the request in flight on the control interface
        self._cycle_job = False  # it was started by the cycle's write (teach mode), not a transition
        self._job_what = ""
        self._job_after: tuple[Callable[[Any], None], Any] = (lambda arg: None, None)
        self._reconnecting = False
        self._reconnect_thread: threading.Thread | None = None
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
        #: the script's RTDE watchdog gets an input at least this often: an unchanged realtime
        #: command is repeated (WorkerHandle.command), a cycle that sends none kicks it
        #: (_feed_watchdog); a fifth of its period, at most 20 ms
        self._keepalive_s = min(0.02, 0.2 / cfg.watchdog_hz)

    #: the defaults of ``link_timeout_s`` and ``watchdog_hz`` on the simulated controller
    #: (``sim_profile``; a profile that sets them keeps its own): the simulator is a Python
    #: process on the daemon's own PC, and neither runs with real-time scheduling there, so a
    #: loaded host's scheduling hiccups pause its packets, the daemon's receive thread and
    #: ur_rtde's own threads for over 0.1 s (measured with two busy cores: link_lost, and the
    #: script's watchdog stopping it at the end of an enable); a real controller streams from a
    #: real-time system, and the daemon's control process runs SCHED_FIFO
    SIM_DEFAULTS = {"link_timeout_s": 0.5, "watchdog_hz": 2.0}

    # ------------------------------------------------------------------ start-up path
    @property
    def host(self) -> str:
        return self.config.host

    @property
    def worker_pid(self) -> int | None:
        """The process id of the ur_rtde worker now up (None: none is)."""
        w = self._w
        return w.proc.pid if w is not None and w.proc is not None else None

    def _open_hook(self) -> None:
        w = WorkerHandle(self.config.host, self.rate_hz, self._rt_priority)
        try:
            w.start()
        except OSError as exc:
            w.close()
            raise BackendError(f"{self.robot}: cannot start the ur_rtde worker process: {exc}") from exc
        error = w.hello()
        if error is not None:
            w.close()
            raise BackendError(f"{self.robot}: backend.host: {error}")
        self._w, self._down, self._opened = w, None, True
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
        # a blocking control call (the disable's stop) is let finish, then the worker ends: its
        # socket closes and it exits without running ur_rtde's destructors (they throw on a
        # broken link); the controller sees the connections close
        deadline = time.monotonic() + 8.0
        while self._ctl_busy() and time.monotonic() < deadline:
            time.sleep(0.005)
        self._opened = False
        t = self._reconnect_thread
        if t is not None:
            t.join(15.0)
        w, self._w = self._w, None
        for h in [w, *self._dispose]:
            if h is not None:
                h.close()
        self._dispose.clear()
        self._link = False

    def info(self) -> ActuatorInfo:
        details = {"host": self.host, "rate_hz": self.rate_hz, "packets": self.packets,
                   "missed_packets": self.missed_packets, "worker_pid": self.worker_pid}
        return ActuatorInfo(list(self.joint_names), details)

    def _traits_hook(self) -> Traits:
        return self.TRAITS

    # ------------------------------------------------------------------ pacing
    def cycle_period_s(self) -> float:
        return self.dt

    def wait_cycle(self, deadline: float) -> bool:
        """Until the worker forwards the next RTDE package (its timestamp moved on), expected at
        ``deadline`` (the runner's schedule, ``time.perf_counter``) and given up one period
        after it (after now, when the deadline has passed: a late cycle still waits for its
        package): blocks in poll() on the worker's socket. Counts skipped packages in
        ``missed_packets``. Without a link: one period (the cycle goes on, reporting it)."""
        if not self._rt_checked:
            self._note_realtime()
        clock = time.perf_counter
        w = self._w
        if w is None or not self._link:
            time.sleep(self.dt)
            return False
        deadline = max(deadline, clock()) + self.dt
        # a package already there (a late cycle) is taken at once, with every message waiting;
        # otherwise poll() wakes on its wake-up (or on a reply, or the worker's end), and the one
        # message it woke on is taken (pump_one: no receive that finds the socket empty, a
        # system call per cycle), then the newest package. A message left queued (a reply that
        # came with the wake-up) wakes the next cycle's poll() at once.
        if w.fresh() and self._take(w):
            self._taken = True  # the cycle's read takes no second look (_refresh)
            return True
        while True:
            if w.dead:
                return False
            left = deadline - clock()
            if left <= 0:
                return False
            w.wait(left)
            w.pump_one()
            if w.fresh() and self._take(w, pump=False):
                self._taken = True
                return True

    def _note_realtime(self) -> None:
        """Once, on the loop's thread: when it runs SCHED_FIFO, the worker's package thread and
        ur_rtde's threads run one priority below it (as a backend's threads in the control
        process do), now and in every worker started later."""
        self._rt_checked = True
        try:
            if os.sched_getscheduler(0) == os.SCHED_FIFO:
                self._rt_priority = max(1, os.sched_getparam(0).sched_priority - 1)
        except OSError:
            return
        w = self._w
        if self._rt_priority and w is not None:
            w.send(encode(b"P", self._rt_priority))

    def _take(self, w: WorkerHandle, pump: bool = True) -> bool:
        """Take the worker's messages (``pump``: every one waiting) and its newest package; True
        when that package is newer than the last one seen (counts skipped ones). Never blocks."""
        if pump:
            w.pump()
        st = w.read_state()
        if st is None:
            return False
        ts = st[0]
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
        self._measured[:] = st[1:25]  # q, qd, TCP pose, TCP wrench
        self._rotvec = st[16:19]
        self.robot_mode, self.safety_mode, self.runtime_state = st[25], st[26], st[27]
        self.speed_fraction = st[28]
        self._flags = st[29]
        return True

    # ------------------------------------------------------------------ real-time path
    def _refresh(self) -> bool:
        """Take the newest package (modes, speed slider, joints, TCP). Never blocks. False: no
        link (no worker, a worker that ended, or no package for ``link_timeout_s``)."""
        w = self._w
        if w is None:
            self._link = False
            return False
        if self._taken:  # wait_cycle took this cycle's package a moment ago, and the messages with it
            self._taken = False
            fresh = True
        else:
            fresh = self._take(w)
        if w.dead:
            if self._down is None:
                self._down = w.cause()
            self._link = False
            return False
        if self._flags & CTL_UP and not self._flags & CTL_CONNECTED:
            # the control interface's link dropped (the worker is ending itself on it): lost NOW,
            # before a write or a transition meets it
            if self._down is None:
                self._down = ("link_lost", "RTDE control link lost")
            self._link = False
            return False
        # a pulled cable sends no FIN: the packages must keep arriving
        if not fresh and time.perf_counter() - self._arrived >= self.config.link_timeout_s:
            if self._down is None:
                self._down = ("link_lost", f"RTDE link lost (no data package for {self.config.link_timeout_s:g} s)")
            self._link = False
            return False
        self._link = True
        return True

    def _movable(self) -> bool:
        """Commands may go out: link up, safety NORMAL / REDUCED, robot RUNNING, script PLAYING."""
        return (self._link and self.safety_mode in MOVABLE and self.robot_mode == RobotMode.RUNNING
                and self.runtime_state == RuntimeState.PLAYING)

    def _read(self, feedback: JointFeedback) -> Fault | None:
        if not self._opened:
            return Fault("link_lost", f"{self.robot}: the RTDE link is closed", transient=False)
        link = self._refresh()
        key = (link, self.robot_mode, self.safety_mode, self.runtime_state, self._enabled)
        last = self._device
        if last[:5] == key:  # as last cycle (nearly always): its answer, without the table's enum compares
            state = last[5]
        else:
            state = device_state(*key)
            self._device = (*key, state)
        code, text = state.code, state.text
        if not link and self._down is not None:
            code, text = self._down
        if code != self._state_code:
            self._state_code = code
            cause = None
            if code is not None:
                cause = Fault(code, f"{self.robot}: {text} (UR controller at {self.host}; robot mode "
                              f"{_name(RobotMode, self.robot_mode)}, safety mode {_name(SafetyMode, self.safety_mode)}, "
                              f"runtime {_name(RuntimeState, self.runtime_state)})", transient=False)
            if state.status is DeviceStatus.OK and self.device_status is DeviceStatus.FAULT:
                self.report_status(DeviceStatus.FAULT_CLEARED)
            else:
                self.report_status(state.status, cause)
        if not link:
            return self._link_lost()
        feedback.position[:] = self._q
        feedback.velocity[:] = self._qd
        feedback.stamp = self.now()
        if self._enabled:
            self._feed_watchdog()
        if state.status is DeviceStatus.PAUSED and not self._paused_hold and self._enabled:
            self._paused_hold = True  # where the arm stopped: the target until resume (see _write)
            self._target[:] = feedback.position
        pose = self._pose
        cart = feedback.cartesian
        if cart is not None:
            cart.position[0] = pose[:3]
            _quat_xyzw(*self._rotvec, cart.orientation[0])
            cart.wrench[0] = self._wrench
            cart.done_seq[0] = self._done_seq
            cart.stamp = feedback.stamp
        self._tcp_p[:] = pose[:3]
        self._tcp_rm = None  # pin.exp3 costs ~10 us: made only for a cartesian command (_tcp_r)
        return None

    @property
    def _tcp_r(self) -> np.ndarray:
        """The TCP's rotation matrix in the base frame, of the package the last read took."""
        rm = self._tcp_rm
        if rm is None:
            self._tcp_rotvec[:] = self._pose[3:]
            rm = self._tcp_rm = pin.exp3(self._tcp_rotvec)
        return rm

    def _feed_watchdog(self) -> None:
        """The script's watchdog wants an RTDE input at least every 1 / watchdog_hz s: the cycle's
        commands are that (an unchanged one repeated every ``_keepalive_s``); when none went out
        for that long (teach mode, a paused program, a transition), a kick. So it stops the arm
        only when the control process stops cycling."""
        now = time.perf_counter()
        if now - self._last_sent < self._keepalive_s or not self._flags & CTL_CONNECTED or self._ctl_busy():
            return  # (a blocking call's own inputs feed it)
        w = self._w
        if w is not None and w.command(KICK, _ZERO6):
            self._last_sent = now

    def _link_lost(self) -> Fault:
        """The link is down: the worker is ended now (killed: it stops talking to the controller
        at once) and a fresh one started once the controller answers (:meth:`_maybe_reconnect`)."""
        w = self._w
        if w is not None:
            self._w = None
            w.kill()
            self._dispose.append(w)  # reaped on the restart's thread
        self._ctl_job = None
        self._flags = 0
        self._maybe_reconnect()
        code, text = self._down or ("link_lost", "RTDE link lost")
        if code == "link_lost":
            return Fault(code, f"{self.robot}: RTDE link to the UR controller at {self.host} lost "
                         "(reconnecting by itself; enable once it is back)", transient=False)
        return Fault(code, f"{self.robot}: {text}, talking to the UR controller at {self.host} (a new worker "
                     "starts by itself; enable once it is back)", transient=False)

    def _maybe_reconnect(self) -> None:
        """After a link loss: a fresh worker, started on a thread every ``reconnect_interval_s``
        until one connects (the old one is reaped there). The cycle sees no link meanwhile."""
        now = time.monotonic()
        if self._reconnecting or now < self._next_reconnect or not self._opened or self._w is not None:
            return
        self._next_reconnect = now + self.config.reconnect_interval_s
        self._reconnecting = True
        dispose = self._dispose

        def run() -> None:
            try:
                while dispose:
                    dispose.pop().close()
                w = WorkerHandle(self.config.host, self.rate_hz, self._rt_priority)
                try:
                    w.start()
                except OSError:
                    w.close()
                    return  # the next attempt after reconnect_interval_s
                if w.hello() is not None or not self._opened:
                    w.close()  # still down: the next attempt after reconnect_interval_s
                    return
                self._ts = -1.0
                self._arrived = time.perf_counter()  # its packages have link_timeout_s to show up
                self._down = None
                self._w = w
            finally:
                self._reconnecting = False

        self._reconnect_thread = background_thread(run, "ur worker restart")
        self._reconnect_thread.start()

    def _write(self, command: JointCommand) -> Fault | None:
        w = self._w
        if not self._enabled or w is None or not self._flags & CTL_UP:
            return None
        if self._ctl_job is not None:  # a blocking call owns the control interface
            if self._ctl_busy() or not self._cycle_job:
                return None  # (a transition's job is collected by the transition's own steps)
            fault = self._end_job()
            if fault is not None:
                return fault
        if w.refused is not None:
            op, error = w.refused
            w.refused = None
            return Fault("command_refused", f"{self.robot}: the UR control script refused {_op_name(op)}"
                         + (f": {error}" if error else ""), transient=True)
        if self._move_fault is not None:
            fault, self._move_fault = self._move_fault, None
            return fault
        cfg = self.config
        if self._paused_hold:
            # Paused by the device: the script's servo target becomes the pose the arm stopped at,
            # written even while the program is paused, so that when the safeguard is reset the
            # program resumes on THAT target instead of rushing to the one it had before the stop
            # (what UR users report). Core's setpoint no longer matters; resume re-seeds it.
            if (self._link and self.robot_mode == RobotMode.RUNNING and self.runtime_state in
                    (RuntimeState.PLAYING, RuntimeState.PAUSED, RuntimeState.PAUSING) and self._flags & CTL_CONNECTED):
                self._last_kind = "servoj"
                return self._out(SERVOJ, self._target, 0.0, self.dt, cfg.servo_lookahead_time_s, cfg.servo_gain)
            return None
        if not self._movable():
            return None  # gated: servoJ would "succeed" with the link down; the state table says why
        if not self._flags & CTL_CONNECTED:  # the worker ends itself on that: a new one comes
            return Fault("link_lost", f"{self.robot}: the RTDE control link to {self.host} is down", transient=True)
        return self._send(command)

    def _out(self, op: int, values: Any, a: float = 0.0, t: float = 0.0, lookahead: float = 0.0,
             gain: float = 0.0) -> Fault | None:
        """One realtime command to the worker. Never blocks: a worker whose channel is full (it
        takes no commands) gets the command DROPPED and the robot faults. The same command as
        the last one goes out again only every ``_keepalive_s`` (the script repeats it by itself
        meanwhile: WorkerHandle.command); a changed one at once."""
        w = self._w
        if w is None or not w.command(op, values, a, t, lookahead, gain, self._keepalive_s):
            if w is not None and w.dead:
                return None  # the next read reports it
            # ended like a lost link (a fresh worker starts by itself): a worker whose reader is
            # stuck while its packages still flow would otherwise refuse every stop and enable, and
            # run its newest queued command whenever it came unstuck
            if self._down is None:
                self._down = ("worker_stalled", f"the ur_rtde worker takes no commands (its channel is full); "
                              f"{_op_name(op)} dropped and the worker ended")
            return self._link_lost()
        self._last_sent = time.perf_counter()
        return None

    def _send(self, command: JointCommand) -> Fault | None:
        """This cycle's one realtime script command (the gates passed)."""
        cart = command.cartesian
        if cart is not None and cart.mode[0] != _NONE:
            return self._write_cartesian(cart)
        mode = command.mode
        modes = mode.tolist()  # a list: a few joints' checks cost a tenth of numpy's (bench_cpu.py)
        if modes.count(_NONE) == len(modes):
            # nothing to follow (a cartesian row the write gate refused, its joints in NONE): send
            # nothing new, the script keeps its last command. A servoJ here would go to the last
            # JOINT target, stale while servoL ran (the cycle still feeds the watchdog: _feed_watchdog)
            return None
        # a blocking call started as the link dies waits for its answer (ur_rtde), and the
        # worker is then ended: teach-mode switches start only on a link whose packet came this cycle
        fresh = time.perf_counter() - self._arrived < 2.0 * self.dt
        if _FREE in modes and modes.count(_FREE) == len(modes):
            if not self._teach and fresh:
                self._start_job("teachMode", "teach mode", self._set_teach, True)
            return None
        if _FREE in modes:
            return Fault("invalid_command", f"{self.robot}: free applies to the whole UR arm (teach mode), "
                         "not to some joints", transient=False)
        if self._teach:
            if fresh:
                self._start_job("endTeachMode", "end of teach mode", self._set_teach, False)
            return None
        if _VELOCITY in modes:
            qd = np.where(mode == _VELOCITY, command.velocity, 0.0)
            self._last_kind = "speedj"
            self._target[:] = command.position  # a later hold starts from core's (measured) setpoint
            return self._out(SPEEDJ, qd, self._speed_acc, 0.0)
        q = self._target
        if modes.count(_POSITION) == len(modes):
            q[:] = command.position
        else:
            np.copyto(q, command.position, where=mode == _POSITION)  # a joint in NONE keeps its last target
        cfg = self.config
        self._last_kind = "servoj"
        return self._out(SERVOJ, q, 0.0, self.dt, cfg.servo_lookahead_time_s, cfg.servo_gain)

    def _write_cartesian(self, cart) -> Fault | None:
        cfg = self.config
        m = int(cart.mode[0])
        if m == _C_TWIST:
            xd = np.concatenate([cart.linear[0], cart.angular[0]])
            if int(cart.frame[0]) == FRAME_BODY:  # speedL takes base-frame axes
                xd[:3] = self._tcp_r @ xd[:3]
                xd[3:] = self._tcp_r @ xd[3:]
            self._last_kind = "speedl"
            return self._out(SPEEDL, xd, cfg.speedl_acceleration, 0.0)
        if m == _C_MOVE:
            now = time.monotonic()
            mv = self._move
            if int(cart.seq[0]) != mv.seq or (mv.finished and self._done_seq < mv.seq):
                if int(cart.seq[0]) != mv.seq:
                    mv.start(int(cart.seq[0]), self._tcp_p, self._tcp_r, cart.position[0], cart.orientation[0], now)
            p, rot = mv.step(now)
            if mv.failed and self._done_seq < mv.seq:
                self._done_seq = mv.seq
                return Fault("trajectory_failed", f"{self.robot}: move_cp: no path to the pose "
                             f"{np.round(mv.goal_p, 4).tolist()} m could be planned (ruckig); stopped on "
                             f"the way, TCP at {np.round(self._tcp_p, 4).tolist()} m", transient=False)
            if mv.reached(self._tcp_p, self._tcp_r):
                self._done_seq = mv.seq
            elif now > mv.deadline:
                self._done_seq = mv.seq
                return Fault("move_timeout", f"{self.robot}: move_cp did not reach its pose within "
                             f"{1.5 * mv.duration + 2.0:.1f} s (1.5 x its duration {mv.duration:.2f} s + 2 s); "
                             f"TCP at {np.round(self._tcp_p, 4).tolist()} m", transient=False)
            pose = [float(p[0]), float(p[1]), float(p[2]), *map(float, pin.log3(rot))]
        else:
            pose = _pose6(cart.position[0], cart.orientation[0])
        self._last_kind = "servol"
        return self._out(SERVOL, pose, 0.0, self.dt, cfg.servo_lookahead_time_s, cfg.servo_gain)

    def _set_teach(self, on: bool) -> None:
        self._teach = on
        if not on:
            self._target[:] = self._q

    # ------------------------------------------------------------------ worker jobs
    def _ctl_busy(self) -> bool:
        """A blocking call on the control interface is in flight (its reply not in yet)."""
        rid = self._ctl_job
        if rid is None:
            return False
        w = self._w
        if w is None or w.dead:
            return False
        w.pump()
        return rid not in w.replies

    def _start_job(self, name: str, what: str, after: Callable[[Any], None], arg: Any) -> None:
        """The cycle's own blocking call (a teach-mode switch), run by the worker; the control
        interface is its until the cycle collects the reply (:meth:`_end_job`), then ``after(arg)``."""
        rid = self._w.request(name)
        if rid is not None:
            self._ctl_job, self._cycle_job = rid, True
            self._job_what, self._job_after = what, (after, arg)

    def _end_job(self) -> Fault | None:
        rid, self._ctl_job = self._ctl_job, None
        w = self._w
        error, _ = (w.replies.pop(rid, None) if w is not None else None) or ("the ur_rtde worker ended", None)
        if error is None:
            after, arg = self._job_after
            after(arg)
            return None
        return Fault("command_failed", f"{self.robot}: {self._job_what} failed on the UR controller at "
                     f"{self.host}: {error}", transient=False)

    def _job(self, name: str, what: str, *args: Any, retry_s: float = 0.0, ctl: bool = True) -> Steps:
        """Steps sending request ``name`` (channel.REQUESTS) to the worker and yielding every
        cycle until its reply; returns its result, raises its error as a BackendError naming
        ``what``. ``ctl``: it uses the control interface, which is one caller's at a time (the
        cycle sends nothing on it meanwhile); dashboard calls do not wait for it. ``retry_s`` > 0:
        a failure is retried every 0.3 s for that long (e-Series refuses to unlock a protective
        stop within 5 s of it)."""
        if ctl:
            while self._ctl_busy():
                yield  # a teach-mode switch of the cycle's own is finishing
            self._ctl_job = None
        give_up = time.monotonic() + retry_s
        while True:
            w = self._w
            rid = w.request(name, *args) if w is not None and not w.dead else None
            if rid is None:
                if w is not None and not w.dead:
                    raise BackendError(f"{self.robot}: {what} failed: the ur_rtde worker takes no requests (its "
                                       "channel is full)")
                why = self._down[1] if self._down else "no link"
                raise BackendError(f"{self.robot}: {what} failed: no ur_rtde worker talking to the UR controller "
                                   f"at {self.host} ({why})")
            if ctl:
                self._ctl_job, self._cycle_job = rid, False
            try:
                while True:
                    w.pump()
                    got = w.replies.pop(rid, None)
                    if got is not None:
                        break
                    if w.dead or self._w is not w:
                        raise BackendError(f"{self.robot}: {what} failed on the UR controller at {self.host}: "
                                           f"{(self._down or w.cause())[1]}")
                    yield
            finally:
                if ctl and self._ctl_job == rid:
                    self._ctl_job = None
            error, result = got
            if error is None:
                return result
            if time.monotonic() >= give_up:
                raise BackendError(f"{self.robot}: {what} failed on the UR controller at {self.host}: {error}")
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
                yield from self._job("powerOn", "power on", ctl=False)
                yield from self._until(lambda: self.robot_mode in (RobotMode.IDLE, RobotMode.RUNNING),
                                       "robot mode IDLE after power on")
            if self.robot_mode != RobotMode.RUNNING:
                yield from self._job("brakeRelease", "brake release", ctl=False)
                yield from self._until(lambda: self.robot_mode == RobotMode.RUNNING,
                                       "robot mode RUNNING after brake release")
        # the worker builds the control interface (uploading its script) or re-uploads the script
        yield from self._job("start_script", "control script upload")
        # ur_rtde refuses commands until ITS connection saw the program run (a packet later, maybe)
        yield from self._until(lambda: self.runtime_state == RuntimeState.PLAYING and bool(self._flags & CTL_RUNNING),
                               "the control script to run")
        if self.config.watchdog_hz > 0:  # from now on the cycle feeds it (_write, _feed_watchdog)
            self._last_sent = time.perf_counter()
            yield from self._job("setWatchdog", "setWatchdog", float(self.config.watchdog_hz))
        self._hold_here()

    def _hold_here(self) -> None:
        """The arm holds where it is: the next servoJ target is the measured pose."""
        if self._link:
            self._target[:] = self._q
        self._teach = False
        self._last_kind = ""
        self._paused_hold = False
        self._move.finished = True
        self._done_seq = self._move.seq

    def _disable_steps(self) -> Steps:
        self._paused_hold = False
        self._move.finished = True
        self._done_seq = self._move.seq
        if not self._opened:
            return
        link = self._refresh()
        if (link and self._flags & CTL_UP and self._flags & CTL_CONNECTED
                and self.runtime_state == RuntimeState.PLAYING):
            yield from self._job("stop_script", "stop", self._teach, self._last_kind)
        elif not link:
            # no worker can reach the controller: the script's watchdog has stopped the arm (no
            # input for 1 / watchdog_hz s); power off follows once the link is back (core retries)
            raise BackendError(f"{self.robot}: power off not confirmed: no RTDE link to {self.host}")
        if self.robot_mode != RobotMode.POWER_OFF:
            yield from self._job("powerOff", "power off", ctl=False)
            yield from self._until(lambda: self.robot_mode == RobotMode.POWER_OFF, "robot mode POWER_OFF")
        self._teach = False

    def _fault_reset_steps(self) -> Steps:
        if not self._refresh():
            if not self._opened:
                raise BackendError(f"{self.robot}: enable refused: the RTDE link is closed")
            if self._w is not None:
                self._link_lost()  # a silent worker: ended here, a fresh one below
            self._next_reconnect = 0.0
            self._maybe_reconnect()  # now: a fresh worker, on a thread
            while self._reconnecting:
                yield
            self._require_link("enable")
        yield from self._job("dashboard_connect", "dashboard reconnect", ctl=False)
        mode = self.safety_mode
        if mode == SafetyMode.PROTECTIVE_STOP:
            yield from self._job("closeSafetyPopup", "close safety popup", ctl=False)
            yield from self._job("unlockProtectiveStop", "unlock protective stop", retry_s=7.0, ctl=False)
            yield from self._until(lambda: self.safety_mode in MOVABLE, "the protective stop to clear")
        elif mode in (SafetyMode.VIOLATION, SafetyMode.FAULT):
            yield from self._job("closeSafetyPopup", "close safety popup", ctl=False)
            yield from self._job("restartSafety", "restart safety", ctl=False)
            yield from self._until(lambda: self.safety_mode in MOVABLE, "the safety system to restart")
        elif mode in (SafetyMode.SYSTEM_EMERGENCY_STOP, SafetyMode.ROBOT_EMERGENCY_STOP):
            raise BackendError(f"{self.robot}: enable refused: the emergency stop is still engaged; release it first")
        elif mode == SafetyMode.RECOVERY:
            raise BackendError(f"{self.robot}: enable refused: safety recovery mode; move the arm back inside "
                               "its limits by hand (teach mode on the pendant) first")
        # the control interface (and its script) comes up in ENABLE, once the arm runs

    def _resume_steps(self) -> Steps:
        self._require_link("resume")
        if self.safety_mode not in MOVABLE:
            yield from self._until(lambda: self.safety_mode in MOVABLE, "the safeguard stop to be reset")
        if self.runtime_state in (RuntimeState.PAUSED, RuntimeState.PAUSING):
            yield from self._job("play", "play", ctl=False)
            yield from self._until(lambda: self.runtime_state == RuntimeState.PLAYING, "the control script to resume")
        self._hold_here()  # from the measured pose: no rush to where it was going when stopped

    # ------------------------------------------------------------------ goal checks
    def goal_check_steps(self, ns: str, cmd: str, goal: np.ndarray) -> Steps | None:
        """The controller's own safety limits, asked before a move starts (see the module
        docstring). ``goal``: the namespace's joint positions (move_jp) or the pose [x, y, z,
        qx, qy, qz, qw] (move_cp). Raises CommandError("out_of_limits") naming the joint / pose."""
        if not self._flags & CTL_UP:
            return None
        return self._goal_check(ns, cmd, np.array(goal, dtype=float))

    def _goal_check(self, ns: str, cmd: str, goal: np.ndarray) -> Steps:
        if cmd == "move_cp":
            pose = _pose6(goal[:3], goal[3:])
            ok = yield from self._job("isPoseWithinSafetyLimits", "isPoseWithinSafetyLimits", pose)
            if not ok:
                raise CommandError("out_of_limits", f"{ns}: {cmd} refused: the pose "
                                   f"[{', '.join(fmt_number(v) for v in pose)}] (x, y, z m, rx, ry, rz rad) is "
                                   f"outside the UR controller's safety limits (isPoseWithinSafetyLimits)")
            return
        found = yield from self._job("joints_within", "isJointsWithinSafetyLimits", goal.tolist(), self._q.tolist())
        if not found["ok"]:
            i = found.get("joint")
            what = (f"goal {fmt_number(goal[i])} rad for joint {self.joint_names[i]!r}" if i is not None
                    else f"goal [{', '.join(fmt_number(v) for v in goal)}] rad")
            raise CommandError("out_of_limits", f"{ns}: {cmd} refused: {what} is outside the UR controller's "
                               "safety limits (isJointsWithinSafetyLimits)")


def _op_name(op: int) -> str:
    return OP_NAMES.get(op, str(op))


def _name(enum_type: type, value: int) -> str:
    try:
        return enum_type(value).name
    except ValueError:
        return str(value)

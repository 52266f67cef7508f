"""What ur_rtde's uploaded ``rtde_control`` program does, played by the simulated controller.

ur_rtde (``RTDEControlInterface``) sends ``def rtde_control(): ... end`` over port 30003 and then
talks to it through RTDE registers (docs/architecture.md, "Sources": Universal Robots, and
ur_rtde's ``scripts/rtde_control.script`` / ``rtde.h``, and the script 1.6.5 actually uploads,
read for the facts below):

- ``output_int_register_0`` (+ offset): 1 = ready for a command, 2 = done with it;
  ``input_int_register_0``: the command id, its arguments in ``input_double_register_0..`` and
  ``input_int_register_1..``; results in ``output_int_register_1`` and
  ``output_double_register_0..5``; ``output_int_register_2``: the async-operation word.
- The program's main loop, once per controller tick: realtime commands (servoj, speedj, ...)
  are applied every tick and leave the program ready (1); any other command runs once, then the
  program says done (2) and waits for command 0 to be ready again. A synchronous move blocks
  that loop until the arm arrives (ur_rtde waits for the 2).
- The register offset is 0, or 24 with ``FLAG_UPPER_RANGE_REGISTERS`` (written into the script).
- ``rtde_set_watchdog(input_int_register_0, f, "stop")``: no RTDE input package for
  ``1/f`` s stops the program.

A command this simulator does not model stops the program with an error naming it (ur_rtde then
reports failure at once), instead of pretending it worked.
"""

from __future__ import annotations

import enum
import logging
import re

import numpy as np

from .ur_robot import (JointMove, JointSpeed, LinearMove, Motion, N, Servo, Stop, ToolSpeed, URRobot, pose_to_se3,
                       se3_to_pose)

log = logging.getLogger(__name__)

READY, DONE = 1, 2
PROGRAM = re.compile(r"^def\s+(\w+)\s*\(\s*\)\s*:", re.M)
_OFFSET = re.compile(r"global\s+reg_offset_int\s*=\s*(\d+)")


class Cmd(enum.IntEnum):
    """Command ids of ur_rtde's control script (rtde.h, RobotCommand::Type)."""

    NO_CMD = 0
    MOVEJ = 1
    MOVEJ_IK = 2
    MOVEL = 3
    MOVEL_FK = 4
    SPEEDJ = 9
    SPEEDL = 10
    SERVOJ = 11
    SPEED_STOP = 15
    SERVO_STOP = 16
    SET_PAYLOAD = 17
    TEACH_MODE = 18
    END_TEACH_MODE = 19
    SERVOL = 24
    GET_STEPTIME = 26
    SET_TCP = 29
    GET_INVERSE_KINEMATICS_ARGS = 30
    PROTECTIVE_STOP = 31
    STOPL = 33
    STOPJ = 34
    SET_WATCHDOG = 35
    IS_POSE_WITHIN_SAFETY_LIMITS = 36
    IS_JOINTS_WITHIN_SAFETY_LIMITS = 37
    GET_JOINT_TORQUES = 38
    GET_TCP_OFFSET = 40
    GET_FORWARD_KINEMATICS_DEFAULT = 43
    GET_FORWARD_KINEMATICS_ARGS = 44
    GET_INVERSE_KINEMATICS_DEFAULT = 46
    IS_STEADY = 47
    FREEDRIVE_MODE = 52
    END_FREEDRIVE_MODE = 53
    GET_ACTUAL_TOOL_FLANGE_POSE = 58
    STOP_SCRIPT = 255


#: applied every tick, never waited for (the realtime list of the script ur_rtde 1.6.5 uploads)
REALTIME = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
#: commands the 1.6.5 script itself leaves empty (direct torque, mass matrix, Jacobian...)
NO_OPS = frozenset({66, 67, 68, 69, 70, 71})


def program_name(text: str) -> str | None:
    """The name of the program a script-port text defines (``def name():``), else None."""
    m = PROGRAM.search(text)
    return m.group(1) if m else None


class ControlScript:
    """The running ``rtde_control`` program. ``registers`` is the controller's register file
    (``ints``/``doubles`` inputs, ``out_ints``/``out_doubles`` outputs) shared with RTDE."""

    def __init__(self, robot: URRobot, registers, text: str = ""):
        self.robot = robot
        self.reg = registers
        m = _OFFSET.search(text)
        self.offset = int(m.group(1)) if m else 0
        self.executing = False
        self.blocking: Motion | None = None  # a synchronous move the loop waits on
        self.async_motion: Motion | None = None  # an asynchronous move running beside the loop
        self.watchdog_s = 0.0
        self.async_count = 0
        self.async_op = 0

    # ---- registers (with the script's offset) ----
    def _in_int(self, i: int) -> int:
        return self.reg.ints[i + self.offset]

    def _in_double(self, i: int) -> float:
        return self.reg.doubles[i + self.offset]

    def _doubles(self, start: int, n: int = N) -> np.ndarray:
        return np.array([self._in_double(start + k) for k in range(n)])

    def _out_int(self, i: int, v: int) -> None:
        self.reg.out_ints[i + self.offset] = int(v)

    def _out_doubles(self, values) -> None:
        for k, v in enumerate(values):
            self.reg.out_doubles[k + self.offset] = float(v)

    def _async(self, value: int) -> None:
        """The async-operation word: change count (bits 16-22), operation id (bits 24-30),
        bit 15 = running with the progress in bits 0-14; -1 = finished, 0 = started."""
        self.async_count = (self.async_count + 1) % 128
        if value == 0:
            self.async_op = (self.async_op + 1) % 128
        word = self.async_count << 16 | self.async_op << 24
        if value >= 0:
            word |= 0x8000 | min(value, 0x7FFF)
        self._out_int(2, word)

    # ---- the program ----
    def start(self, now: float) -> None:
        self._async(-1)
        self._out_int(0, READY)
        self.reg.input_at = now  # the watchdog counts from the start

    def tick(self, now: float) -> None:
        """One pass of the program's main loop (robot.runtime_state is PLAYING)."""
        if self.watchdog_s and now - self.reg.input_at > self.watchdog_s:
            self.robot.script_error(f"RTDE watchdog: no input package for {now - self.reg.input_at:.3f} s")
            return
        if self.blocking is not None or self.robot.script_stalled:
            return  # inside a synchronous move (motion_done() finishes it), or stalled
        cmd = self._in_int(0)
        if cmd in REALTIME:
            self._process(cmd)
            if self.robot.script is self:
                self._out_int(0, READY)
        elif cmd == 0:
            self.executing = False
            self._out_int(0, READY)
        elif not self.executing:
            self.executing = True
            if self._process(cmd) and self.blocking is None and self.robot.script is self:
                self._out_int(0, DONE)

    def motion_done(self, motion: Motion) -> None:
        if motion is self.blocking:
            self.blocking = None
            self._out_int(0, DONE)
        elif motion is self.async_motion:
            self.async_motion = None
            self._async(-1)  # an asynchronous move arrived

    def _set_motion(self, motion: Motion | None) -> None:
        """Replace the arm's motion; an asynchronous move cut short is reported finished."""
        if self.async_motion is not None and self.robot.motion is self.async_motion:
            self._async(-1)
        self.async_motion = None
        self.robot.teach_mode = False
        self.robot.motion = motion

    def _move(self, motion: Motion, asynchronous: bool) -> None:
        self._set_motion(motion)
        if asynchronous:  # runs beside the loop; ur_rtde polls the async word
            self.async_motion = motion
            self._async(0)
        else:
            self.blocking = motion

    def _process(self, cmd: int) -> bool:
        """Run command ``cmd`` once. False when it stopped the program."""
        r = self.robot
        if cmd in NO_OPS:
            return True
        try:
            c = Cmd(cmd)
        except ValueError:
            r.script_error(f"rtde_control: command {cmd} is not simulated")
            return False
        if c in (Cmd.MOVEJ, Cmd.MOVEL_FK):
            q = self._doubles(0)
            if not r.within_joint_limits(q):
                r.protective_stop(f"movej target {np.round(q, 4).tolist()} outside the joint limits")
                return False
            if c == Cmd.MOVEJ:
                self._move(JointMove(r, q, self._in_double(6), self._in_double(7)), self._in_int(1) == 1)
            else:
                self._move(LinearMove(r, r.kin.fk(q), self._in_double(6), self._in_double(7)),
                           self._in_int(1) == 1)
        elif c in (Cmd.MOVEJ_IK, Cmd.MOVEL):
            target = pose_to_se3(self._doubles(0))
            if c == Cmd.MOVEL:
                self._move(LinearMove(r, target, self._in_double(6), self._in_double(7)), self._in_int(1) == 1)
            else:
                q, ok = r.kin.ik(target, r.q)
                if not ok:
                    r.script_error("movej(get_inverse_kin(...)): no solution")
                    return False
                self._move(JointMove(r, q, self._in_double(6), self._in_double(7)), self._in_int(1) == 1)
        elif c in (Cmd.SERVOJ, Cmd.SERVOL):
            if c == Cmd.SERVOJ:
                q = self._doubles(0)
            else:
                seed = r.motion.target if isinstance(r.motion, Servo) else r.q
                q, ok = r.kin.ik(pose_to_se3(self._doubles(0)), seed, iterations=30)
                if not ok:
                    r.script_error("servol: get_inverse_kin found no solution")
                    return False
            if isinstance(r.motion, Servo):
                r.motion.target = q
                r.motion.lookahead_s = self._in_double(9)
            else:
                self._set_motion(Servo(q, self._in_double(9)))
        elif c in (Cmd.SPEEDJ, Cmd.SPEEDL):  # d0..5 joint velocities / TCP twist, d6 acceleration
            kind = JointSpeed if c == Cmd.SPEEDJ else ToolSpeed
            target, acc = self._doubles(0), max(self._in_double(6), 1e-3)
            if type(r.motion) is kind:
                r.motion.target, r.motion.acc = target, acc
            else:
                self._set_motion(kind(target, acc))
        elif c in (Cmd.STOPJ, Cmd.STOPL):  # recipe: int0, d0 = deceleration, int1 = async
            self._move(Stop(self._in_double(0)), self._in_int(1) == 1)
        elif c == Cmd.SPEED_STOP:  # stopj / stopl inside the loop: blocks until at rest
            if isinstance(r.motion, (JointSpeed, ToolSpeed)):
                self._move(Stop(self._in_double(0)), False)
        elif c == Cmd.SERVO_STOP:  # the servo thread is killed: the arm comes to rest
            if isinstance(r.motion, Servo):
                self._set_motion(Stop(self._in_double(0)))
        elif c in (Cmd.TEACH_MODE, Cmd.FREEDRIVE_MODE):
            self._set_motion(None)
            r.teach_mode = True
        elif c in (Cmd.END_TEACH_MODE, Cmd.END_FREEDRIVE_MODE):
            r.teach_mode = False
        elif c == Cmd.SET_TCP:
            r.kin.tcp = pose_to_se3(self._doubles(0))
        elif c == Cmd.SET_PAYLOAD:
            pass  # no dynamics modelled: the payload changes nothing observable here
        elif c in (Cmd.GET_INVERSE_KINEMATICS_ARGS, Cmd.GET_INVERSE_KINEMATICS_DEFAULT):
            seed = self._doubles(6) if c == Cmd.GET_INVERSE_KINEMATICS_ARGS else r.q
            q, ok = r.kin.ik(pose_to_se3(self._doubles(0)), seed)
            if not ok:
                r.script_error("get_inverse_kin: no solution")
                return False
            self._out_doubles(q)
        elif c == Cmd.GET_FORWARD_KINEMATICS_DEFAULT:
            self._out_doubles(r.tcp_pose())
        elif c == Cmd.GET_FORWARD_KINEMATICS_ARGS:
            saved = r.kin.tcp
            r.kin.tcp = pose_to_se3(self._doubles(6))
            self._out_doubles(se3_to_pose(r.kin.fk(self._doubles(0))))
            r.kin.tcp = saved
        elif c == Cmd.PROTECTIVE_STOP:
            r.protective_stop("protective_stop() called by the program")
            return False
        elif c == Cmd.SET_WATCHDOG:
            f = self._in_double(0)
            self.watchdog_s = 1.0 / f if f > 0 else 0.0
        elif c == Cmd.IS_JOINTS_WITHIN_SAFETY_LIMITS:
            self._out_int(1, r.within_joint_limits(self._doubles(0)))
        elif c == Cmd.IS_POSE_WITHIN_SAFETY_LIMITS:
            self._out_int(1, r.pose_within_limits(self._doubles(0)))
        elif c == Cmd.IS_STEADY:
            self._out_int(1, not np.abs(r.qd).max() > 1e-4)
        elif c == Cmd.GET_STEPTIME:
            self._out_doubles([r.step_s])
        elif c == Cmd.GET_JOINT_TORQUES:  # gravity only: the arm model has no other load
            self._out_doubles(r.kin.gravity_torques(r.q))
        elif c == Cmd.GET_TCP_OFFSET:
            self._out_doubles(se3_to_pose(r.kin.tcp))
        elif c == Cmd.GET_ACTUAL_TOOL_FLANGE_POSE:
            self._out_doubles(se3_to_pose(r.kin.fk(r.q) * r.kin.tcp.inverse()))
        elif c == Cmd.STOP_SCRIPT:
            r.stop_program("stop script command")
            return False
        return True

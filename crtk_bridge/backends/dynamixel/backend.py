"""Dynamixel X-series backend (Protocol 2.0; XL330-M288 / -M077, XL430-W250, XM430-W350), e.g. the Koch v1.1.

Uses the vendor SDK (``dynamixel_sdk`` 4.x, pip ``dynamixel-sdk``) for packet framing (CRC-16,
byte stuffing) with the shared port fixes of :mod:`..serial_servo`. One cycle is normally two
bus transactions:

* ``read``: ONE sync read of registers 126..135 (10 bytes per servo: Present_Current -- or
  Present_Load on the XL430 -- Present_Velocity, Present_Position). A Fast Sync Read (0x8A, one
  status packet for all servos) when ``fast_sync_read`` allows it: ``auto`` uses it when every
  servo's firmware supports it (X430 >= 45, X330 >= 46). The SDK's own group reader is not used:
  it throws the status ERR bytes away (so a hardware-error Alert would go unseen) and raises
  IndexError when a fast reply is short; this backend calls the SDK's packet functions, keeps
  the ERR bytes and checks each servo's CRC in a fast reply (the SDK checks only the last, the
  packet's). A failed fast read is retried (``read_retries``) as a plain sync read, whose
  per-servo replies name the silent or corrupt servo.
* ``write``: ONE sync write of the goals of the joints with a command: Goal_Position (4 bytes) in
  the position modes, Goal_Velocity (4) in velocity mode, Goal_Current (2) in current mode. When
  joints in different modes are commanded in the same cycle, ONE bulk write (0x93) instead.

Operating mode per joint follows the command's :class:`CommandMode`: POSITION -> position mode
(3), or extended position (4) / current-based position (5) where ``position_mode`` /
``joint_position_modes`` ask; VELOCITY -> velocity mode (1); EFFORT -> current mode (0); FREE ->
torque off (one sync write; leaving it in the same mode: the goal, then one sync write of torque
on). A change of operating mode is NOT made in ``write`` (nothing there waits for an
acknowledgement): core asks :meth:`DynamixelBackend.mode_switch_steps` when a command's modes
change and runs the steps it returns as a MODE_SWITCH transition, one joint per cycle, as the
servo requires (Operating_Mode is EEPROM, writable with torque off only): Torque_Enable 0 ->
Operating_Mode -> Goal_Position = Present_Position (position modes) or a zero velocity/current
goal -> Torque_Enable 1, each acknowledged; the joint is unpowered within its own step only, and
``write`` leaves the switching joints alone until the last one is done. A switch that fails
faults the robot (FAULT, torque off everywhere), naming the joint and register: the joint may
already be unpowered, so it is not retried.

Units (raw units never leave this module), per joint with the profile's ``calibration``:

* position rad   = direction * (ticks - offset) * 2*pi / 4096
* velocity rad/s = direction * Present_Velocity * 0.229 rev/min
* effort N*m     = direction * Present_Current * unit * effort_per_amp, unit = 1 mA (XL330),
  2.69 mA (XM430). An ESTIMATE (current is not torque: friction, gear losses). The XL430 has no
  current sensor, only Present_Load (0.1 % of its maximum torque, which depends on the supply
  voltage): it is NOT turned into an effort; see "capabilities".
* effort commands: Goal_Current = effort / effort_per_amp / unit, clamped to Current_Limit.
* velocity commands: Goal_Velocity in 0.229 rev/min, clamped to Velocity_Limit.

Capabilities per joint (``traits.joints``): position and velocity always; ``effort``
and ``measures_effort`` on a joint with current control (not the XL430) and an
``effort_per_amp``. Core offers a namespace the commands all its joints can follow: on a Koch
v1.1 the gripper (XL330) has servo_jf / interpolate_jf and measured effort, the arm (two XL430s)
has neither; an all-XL330/XM430 arm with ``effort_per_amp`` on every joint has both.

Hardware errors: a status packet's Alert bit (0x80) means Hardware_Error_Status (70) is set; the
backend then reads register 70 of that servo (one extra transaction, only when the Alert first
appears) and returns a non-transient ``servo_error`` Fault naming the bits. The servo has shut
down (torque off) and only a REBOOT clears it: ``enable`` (the way out of FAULT) reads register 70
of every servo, REBOOTs (0x08) those with an error, waits for each to answer a ping again, writes
the configuration registers again (a reboot restores RAM defaults) and then enables as usual.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Annotated, Literal

import msgspec
import numpy as np
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    PortHandler,
)
from dynamixel_sdk.protocol2_packet_handler import Protocol2PacketHandler

from ...core.actuator import (
    Capabilities,
    CommandMode,
    Fault,
    JointCommand,
    JointFeedback,
    Lifecycle,
    SimWiring,
    Steps,
    Traits,
)
from ...errors import BackendError
from ...profile import Profile
from ..serial_servo import EepromDiff, LastStatus, SerialPortFixes, SerialServoBackend
from ..servo_keys import PortMatch, ServoJoint
from . import tables as T
from .tables import OperatingMode

Byte = Annotated[int, msgspec.Meta(ge=0, le=254)]
PositionModeName = Literal["position", "extended_position", "current_based_position"]
_POSITION_MODE = {
    "position": OperatingMode.POSITION,
    "extended_position": OperatingMode.EXTENDED_POSITION,
    "current_based_position": OperatingMode.CURRENT_BASED_POSITION,
}

# Bauds both the servo (register 8 codes) and the SDK's PortHandler.getCFlagBaud accept.
_SDK_BAUDS = {9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000}
SUPPORTED_BAUDS = sorted(set(T.BAUD_CODES) & _SDK_BAUDS)

_NONE = int(CommandMode.NONE)
_POSITION = int(CommandMode.POSITION)
_VELOCITY = int(CommandMode.VELOCITY)
_EFFORT = int(CommandMode.EFFORT)
_FREE = int(CommandMode.FREE)
_BLOCK = T.PRESENT_BLOCK_START
_BLOCK_LEN = T.PRESENT_BLOCK_LEN
_GOAL = {  # operating mode -> goal register (name, address, size)
    OperatingMode.CURRENT: ("Goal_Current", 102, 2),
    OperatingMode.VELOCITY: ("Goal_Velocity", 104, 4),
    OperatingMode.POSITION: ("Goal_Position", 116, 4),
    OperatingMode.EXTENDED_POSITION: ("Goal_Position", 116, 4),
    OperatingMode.CURRENT_BASED_POSITION: ("Goal_Position", 116, 4),
}
REBOOT_TIMEOUT_S = 2.0  # a rebooting X servo answers again within ~0.5 s


class FastPortHandler(SerialPortFixes, PortHandler):
    """dynamixel_sdk PortHandler with the shared serial fixes (see :class:`SerialPortFixes`)."""


class XPacketHandler(LastStatus, Protocol2PacketHandler):
    """dynamixel_sdk's protocol 2.0 packet handler, keeping the last status packet."""

    def status_params(self) -> int:
        # FF FF FD 00 ID LEN_L LEN_H INST ERR params.. CRC_L CRC_H; LEN (after the SDK removed the
        # byte stuffing) counts INST, ERR, params and CRC
        s = self.last_status
        return (s[5] | s[6] << 8) - 4 if len(s) > 6 else -1


class Config(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """The ``backend:`` section of a profile with ``type: dynamixel``."""

    # serial device, e.g. /dev/ttyUSB0 or a /dev/serial/by-id/ link, or {serial_number: ...} (the USB
    # adapter\'s, resolved at open)
    port: str | PortMatch  # e.g. /dev/ttyUSB0 (U2D2) or a simulator's pty
    baudrate: int = 1_000_000  # must match the servos' Baud_Rate register
    timeout_ms: Annotated[float, msgspec.Meta(gt=0, le=1000)] | None = None  # None = 10 ms
    read_retries: Annotated[int, msgspec.Meta(ge=0, le=10)] = 1
    # "auto": Fast Sync Read when every servo's firmware has it; "on" / "off" force it.
    fast_sync_read: Literal["auto", "on", "off"] = "auto"
    # Operating mode for position commands, for every joint / per joint name:
    position_mode: PositionModeName = "position"
    joint_position_modes: dict[str, PositionModeName] = {}
    # Registers written in configure() (RAM except Return_Delay_Time):
    return_delay: Byte = 0  # Return_Delay_Time, x2 us (factory 250 = 500 us)
    profile_velocity: Annotated[int, msgspec.Meta(ge=0)] = 0  # 0 = no on-servo profile
    profile_acceleration: Annotated[int, msgspec.Meta(ge=0)] = 0


class DynamixelBackend(SerialServoBackend):
    """Dynamixel X-series servos on one Protocol 2.0 bus. See the module docstring."""

    vendor = "dynamixel"
    ACCELERATION_KEY = "profile_acceleration"
    SOFTWARE_DRIVE_MODE = False  # the servo's Drive_Mode register reverses it (LeRobot writes it there)
    simulator = SimWiring()  # --sim sets backend.port to its simulator's pty (crtk-sim dynamixel)
    Config = Config
    MODEL_NUMBERS = T.MODEL_NUMBERS
    RESOLUTION = T.RESOLUTION
    MAX_ID = T.MAX_ID
    SUPPORTED_BAUDS = SUPPORTED_BAUDS
    BAUD_CODES = T.BAUD_CODES
    FACTORY_BAUD = 57_600  # X series: Baud_Rate 1 (servos.md section 5)
    HOMING_OFFSET_MAX = 1_044_479
    RX_TIMEOUT = COMM_RX_TIMEOUT
    RX_CORRUPT = COMM_RX_CORRUPT

    def __init__(self, profile: Profile, *, source: str = "<profile>"):
        super().__init__(profile, source=source)
        joints = self.joint_keys
        n = self.n
        self._models = [j.model for j in joints]
        self._tables = [T.CONTROL_TABLES[m] for m in self._models]
        self._pos_mode = [self._joint_position_mode(name) for name in self.joint_names]
        lo, hi = [], []
        for j, mode in zip(joints, self._pos_mode):
            span = (0, 4095) if mode is OperatingMode.POSITION else \
                (-T.POSITION_EXTENDED_LIMIT, T.POSITION_EXTENDED_LIMIT)
            r = j.calibration.range
            lo.append(max(span[0], r[0]) if r else span[0])
            hi.append(min(span[1], r[1]) if r else span[1])
        self._goal_min = np.array(lo, dtype=float)
        self._goal_max = np.array(hi, dtype=float)
        self._has_current = [T.CURRENT_UNIT_A[m] is not None for m in self._models]
        # effort per joint: current control (not the XL430) and an effort_per_amp
        self._effort_j = [c and j.effort_per_amp is not None for c, j in zip(self._has_current, joints)]
        unit = np.array([T.CURRENT_UNIT_A[m] or 0.0 for m in self._models])
        epa = np.array([j.effort_per_amp or 0.0 for j in joints])
        self._nm_per_unit = np.where(self._effort_j, self._direction * unit * epa, 0.0)
        self._unit_per_nm = np.divide(1.0, self._nm_per_unit, out=np.zeros(n), where=self._nm_per_unit != 0)
        self._effort = any(self._effort_j)  # some joint reports effort: decode currents
        self._joint_caps = [Capabilities(position=True, velocity=True, effort=e, measures_velocity=True,
                                         measures_effort=e, needs_homing=False, can_free=True)
                            for e in self._effort_j]
        self._vel_per_rad_s = self._direction / T.VELOCITY_UNIT_RAD_S
        self._rad_s_per_vel = self._direction * T.VELOCITY_UNIT_RAD_S
        self._vel_limit = np.array([T.VELOCITY_LIMIT_DEFAULT[m] for m in self._models], dtype=float)
        self._cur_limit = np.array([T.CURRENT_LIMIT_DEFAULT.get(m, 0) for m in self._models], dtype=float)
        # real-time state (buffers shared with Feetech: SerialServoBackend)
        self._errors = [0] * n  # status ERR byte of each servo, last read
        self._hw_bits = [0] * n  # Hardware_Error_Status read when the Alert appeared
        self._op_mode: list[OperatingMode | None] = [None] * n  # mode the servo is in (None: unknown)
        self._switching = [False] * n  # joints of a mode switch under way (held by its steps)
        self._fast = False
        self._id_param = list(self._ids)
        self._fast_reply_len = (_BLOCK_LEN + 4) * n
        length = 1 + self._fast_reply_len  # the status packet's LEN field
        self._fast_header = [0xFF, 0xFF, 0xFD, 0x00, T.BROADCAST_ID, length & 0xFF, length >> 8, T.INST_STATUS]

    def _joint_position_mode(self, name: str) -> OperatingMode:
        return _POSITION_MODE[self.config.joint_position_modes.get(name, self.config.position_mode)]

    # ------------------------------------------------------------------ hooks
    def _check_joint(self, i: int, key: str, j: ServoJoint, problems: list[str]) -> None:
        name = self.profile.joints[i].name
        cfg = self.config
        names = set(self.profile.joint_names)
        if i == 0:
            for other in cfg.joint_position_modes:
                if other not in names:
                    problems.append(f"backend.joint_position_modes.{other}: unknown joint "
                                    f"(joints: {', '.join(self.profile.joint_names)})")
        mode = self._joint_position_mode(name)
        if mode not in T.OPERATING_MODES[j.model]:
            where = (f"backend.joint_position_modes.{name}" if name in cfg.joint_position_modes
                     else "backend.position_mode")
            problems.append(f"{where}: {mode.name.lower()} mode is not available on {key}, a {j.model}")
        if mode is OperatingMode.POSITION:
            super()._check_joint(i, key, j, problems)
        else:  # multi-turn: ticks beyond one turn are fine
            self._check_homing_offset(key, j, problems)

    def _make_port(self, margin_ms: float) -> FastPortHandler:
        return FastPortHandler(self._port_path, margin_ms=margin_ms)

    def _make_packet_handler(self):
        return XPacketHandler()

    def _discover(self) -> dict[int, tuple[int, int | None]]:
        """Protocol 2.0's broadcast ping: every servo answers in turn with model and firmware."""
        self._port.is_using = False
        found, _ = self._ph.broadcastPing(self._port)  # no reply at all: an empty dict
        return {sid: (model, firmware) for sid, (model, firmware) in found.items()}

    def _broadcast_ping(self) -> tuple[dict[int, int], bool]:
        """Protocol 2.0's broadcast ping (the SDK's, listening its full window, ~0.8 s)."""
        self._port.is_using = False
        found, result = self._ph.broadcastPing(self._port)
        self._port.is_using = False
        return {sid: model for sid, (model, _) in found.items()}, result == COMM_RX_CORRUPT

    def _limits_apply(self, i: int) -> bool:
        return self._pos_mode[i] is OperatingMode.POSITION  # the extended modes ignore them

    EEPROM_REGISTERS = (*SerialServoBackend.EEPROM_REGISTERS, "Drive_Mode")

    def _vendor_eeprom_diffs(self, i: int, key: str, regs: dict[str, int]) -> list[EepromDiff]:
        """Drive_Mode bit 0 (reverse: the servo flips its own direction; the profile's
        calibration.direction says it instead). Not Operating_Mode: the backend switches it at
        run time with each joint's command mode, so the EEPROM holds whatever the last run left."""
        name, sid = self.joint_names[i], self._ids[i]
        out = []
        drive = regs["Drive_Mode"]
        if drive & 1:
            out.append(EepromDiff(name, sid, "Drive_Mode", drive, f"bit 0 clear ({drive & ~1})",
                                  f"{key}.calibration.direction", True,
                                  "bit 0 (reverse) flips every position and command on the servo",
                                  f"clear it with the vendor's tool and say the direction in "
                                  f"{key}.calibration.direction (the daemon never rewrites EEPROM)"))
        return out

    def _identify(self, sid: int, model: str | None, firmware: int | None) -> tuple[str | None, bool | None]:
        """Firmware (from the ping, else read) and Torque_Enable (same address on every X model)."""
        table = T.CONTROL_TABLES[model or "xm430-w350"]
        if firmware is None:
            firmware = self._read_id(sid, table["Firmware_Version"].address)
        torque = self._read_id(sid, table["Torque_Enable"].address)
        return (None if firmware is None else str(firmware), None if torque is None else torque != 0)

    def _register(self, i: int, name: str) -> tuple[int, int]:
        try:
            reg = self._tables[i][name]
        except KeyError:
            raise BackendError(f"{self.robot}: {self._label[i]}: a {self._models[i]} has no register "
                               f"{name}") from None
        return reg.address, reg.size

    def _encode(self, i: int, name: str, value: int) -> int:
        reg = self._tables[i][name]
        return T.to_raw(value, reg.size) if reg.signed else int(value)

    def _decode(self, i: int, name: str, raw: int) -> int:
        reg = self._tables[i][name]
        return T.to_signed(raw, reg.size) if reg.signed else raw

    def _error_text(self, error: int) -> str | None:
        if error & T.ERR_ALERT:
            return "a hardware error (Alert bit)"
        return None

    def _after_open(self) -> None:
        firmware = [self._read_register(i, "Firmware_Version") for i in range(self.n)]
        mode = self.config.fast_sync_read
        if mode == "auto":
            self._fast = all(fw >= T.FAST_SYNC_READ_FIRMWARE[m] for fw, m in zip(firmware, self._models))
        else:
            self._fast = mode == "on"
        self._op_mode = [None] * self.n
        self._details = {"firmware": dict(zip(self.joint_names, firmware)), "fast_sync_read": self._fast}

    # ------------------------------------------------------------------ lifecycle
    def _configure_hook(self) -> None:
        """Torque off, then operating mode (position flavour of each joint) and the configuration
        registers on every servo, each acknowledged. Reads Velocity_Limit / Current_Limit for the
        command clamps. Blocks. Raises BackendError."""
        self._require_open("configure")
        self._disable_hook()
        for i in range(self.n):
            self._configure_servo(i)

    def deceleration_limit(self, i: int) -> float:
        """Profile_Acceleration (``backend.profile_acceleration``, 214.577 rev/min^2 units in the
        velocity-based profile; 0 = no on-servo profile) bounds how fast the servo follows a
        braking setpoint: the default stop deceleration's bound (core/motion.py, Stops)."""
        acc = self.config.profile_acceleration
        if acc == 0:
            return float("inf")
        return acc * T.PROFILE_ACCELERATION_RAD_S2

    def _configure_servo(self, i: int) -> None:
        cfg = self.config
        self._write_register(i, "Return_Delay_Time", cfg.return_delay)
        self._write_register(i, "Operating_Mode", int(self._pos_mode[i]))
        self._op_mode[i] = self._pos_mode[i]
        self._write_register(i, "Profile_Velocity", cfg.profile_velocity)
        self._write_register(i, "Profile_Acceleration", cfg.profile_acceleration)
        self._vel_limit[i] = self._read_register(i, "Velocity_Limit")
        if self._has_current[i]:
            self._cur_limit[i] = self._read_register(i, "Current_Limit")

    def _traits_hook(self) -> Traits:
        """ENABLE may reboot every servo (each up to REBOOT_TIMEOUT_S to answer again)."""
        traits = super()._traits_hook()
        enable = traits.timeout_s(Lifecycle.ENABLE) + self.n * REBOOT_TIMEOUT_S
        return dataclasses.replace(traits, transition_timeouts_s={**traits.transition_timeouts_s,
                                                                   Lifecycle.ENABLE: enable})

    def _before_enable(self) -> Steps:
        """Servo by servo, one per cycle: Hardware_Error_Status read; if nonzero, REBOOT, wait
        for it to answer a ping (one ping per cycle, up to REBOOT_TIMEOUT_S), write its
        configuration again (a reboot restores RAM defaults). Raises BackendError naming the
        joint and the error."""
        for i in range(self.n):
            bits = yield from self._retrying(self._read_register, i, "Hardware_Error_Status")
            if bits:
                yield from self._reboot(i, bits)
            yield
        self._hw_bits = [0] * self.n

    def _hold_here(self, i: int) -> None:
        """Position mode of joint ``i`` if it is in another, then Goal_Position = a fresh
        Present_Position, acknowledged and error-checked."""
        if self._op_mode[i] != self._pos_mode[i]:
            self._write_register(i, "Torque_Enable", 0)
            self._write_register(i, "Operating_Mode", int(self._pos_mode[i]))
            self._op_mode[i] = self._pos_mode[i]
        present = self._read_register(i, "Present_Position")
        self._write_register(i, "Goal_Position", present, check_error=True)

    def _reboot(self, i: int, bits: int) -> Steps:
        """REBOOT joint ``i`` (clears a latched hardware error), wait until it answers, configure."""
        what = T.describe_hardware_error(bits)
        result, _ = self._txrx(self._ph.reboot, self._ids[i])
        if result != COMM_SUCCESS:
            raise BackendError(f"{self.robot}: {self._label[i]} ({what}, Hardware_Error_Status="
                               f"0x{bits:02X}) did not acknowledge REBOOT on {self._where}: "
                               f"{self._result_text(result)}")
        deadline = time.monotonic() + REBOOT_TIMEOUT_S
        while True:
            yield  # the servo restarts; the loop's reads go on meanwhile
            _, result, _ = self._ph.ping(self._port, self._ids[i])
            self._port.is_using = False
            if result == COMM_SUCCESS:
                break
            if time.monotonic() > deadline:
                raise BackendError(f"{self.robot}: {self._label[i]} did not answer within "
                                   f"{REBOOT_TIMEOUT_S} s of a REBOOT (to clear {what})")
        bits = self._read_register(i, "Hardware_Error_Status")
        if bits:
            raise BackendError(f"{self.robot}: {self._label[i]} still reports "
                               f"{T.describe_hardware_error(bits)} (Hardware_Error_Status=0x{bits:02X}) "
                               f"after a REBOOT: check the cause (load, supply, temperature)")
        self._op_mode[i] = None  # Operating_Mode is EEPROM and survives, but re-check it
        self._configure_servo(i)

    # ------------------------------------------------------------------ real-time path
    def _read(self, feedback: JointFeedback) -> Fault | None:
        """ONE (fast) sync read of 126..135 of every servo, decoded into ``feedback`` in place.

        Returns a transient ``bus_timeout`` / ``bus_corrupt`` Fault (``feedback`` untouched), or a
        non-transient ``servo_error`` Fault naming the Hardware_Error_Status bits when a servo's
        status carries the Alert bit (``feedback`` filled: the data is valid).
        """
        if self._lost is not None and self._still_lost():
            return self._lost  # the port is gone (hot replug): no bus I/O until it is back
        port = self._port
        if port is None:
            return Fault("bus_timeout", f"{self.robot}: read on a closed bus", transient=False)
        port.last_os_error = None
        result = COMM_SUCCESS
        blocks = None
        fast = self._fast
        for _ in range(self._attempts):
            port.is_using = False
            stamp = time.time()
            blocks, result = self._fast_read() if fast else self._plain_read()
            if result == COMM_SUCCESS:
                break
            fast = False  # a retry reads plainly: its per-servo replies name a silent servo
        if result != COMM_SUCCESS:
            return self._sync_read_fault(result, blocks or {}, _BLOCK_LEN)
        self._failed_run = None
        raw_pos, raw_vel, raw_cur = self._raw_pos, self._raw_vel, self._raw_cur
        alert = False
        for i, sid in enumerate(self._ids):
            b = blocks[sid]
            raw_cur[i] = int.from_bytes(b[0:2], "little", signed=True)
            raw_vel[i] = int.from_bytes(b[2:6], "little", signed=True)
            raw_pos[i] = int.from_bytes(b[6:10], "little", signed=True)
            if self._errors[i] & T.ERR_ALERT:
                alert = True
        if self._cal is not None:  # a calibration sweep: follow the ticks (in place)
            self._cal.track(raw_pos)
        np.subtract(raw_pos, self._offset_ticks, out=self._tmp)
        np.multiply(self._tmp, self._rad_per_tick, out=feedback.position)
        np.multiply(raw_vel, self._rad_s_per_vel, out=feedback.velocity)
        if self._effort:
            np.multiply(raw_cur, self._nm_per_unit, out=feedback.effort)
        feedback.stamp = stamp
        fault = self._alert_fault() if alert else None
        self._error_status(fault)
        return fault

    def _plain_read(self) -> tuple[dict, int]:
        """Sync Read (0x82): one status packet per servo, in request order."""
        ph, port = self._ph, self._port
        result = ph.syncReadTx(port, _BLOCK, _BLOCK_LEN, self._id_param, self.n, False)
        blocks: dict = {}
        if result != COMM_SUCCESS:
            return blocks, result
        for i, sid in enumerate(self._ids):
            data, result, error = ph.readRx(port, sid, _BLOCK_LEN)
            blocks[sid] = data
            if result != COMM_SUCCESS:
                return blocks, result
            if len(data) < _BLOCK_LEN:
                return blocks, COMM_RX_CORRUPT
            self._errors[i] = error
        return blocks, COMM_SUCCESS

    def _fast_read(self) -> tuple[dict, int]:
        """Fast Sync Read (0x8A): one status packet carrying ``ERR ID data CRC`` per servo."""
        ph, port = self._ph, self._port
        result = ph.syncReadTx(port, _BLOCK, _BLOCK_LEN, self._id_param, self.n, True)
        if result != COMM_SUCCESS:
            return {}, result
        raw, result, _ = ph.fastSyncReadRx(port, T.BROADCAST_ID, self._fast_reply_len)
        if result != COMM_SUCCESS:
            return {}, result
        if len(raw) < self._fast_reply_len:
            return {}, COMM_RX_CORRUPT
        blocks: dict = {}
        k = 0
        step = _BLOCK_LEN + 4
        # Each servo's CRC covers the packet so far; the SDK checks only the last (the packet
        # CRC), so a servo's bad CRC would go unseen: check every one.
        crc = ph.updateCRC(0, self._fast_header, len(self._fast_header))
        for i, sid in enumerate(self._ids):
            if raw[k + 1] != sid:  # replies come in request order
                return blocks, COMM_RX_CORRUPT
            end = k + 2 + _BLOCK_LEN
            crc = ph.updateCRC(crc, raw[k:end], end - k)
            if crc != raw[end] | raw[end + 1] << 8:
                return blocks, COMM_RX_CORRUPT  # blocks stops before this servo: it is named
            crc = ph.updateCRC(crc, raw[end:end + 2], 2)
            self._errors[i] = raw[k]
            blocks[sid] = raw[k + 2: end]
            k += step
        return blocks, COMM_SUCCESS

    def _alert_fault(self) -> Fault:
        bad = []
        for i in range(self.n):
            if not self._errors[i] & T.ERR_ALERT:
                self._hw_bits[i] = 0
                continue
            if not self._hw_bits[i]:  # read register 70 once per Alert, not every cycle
                value, result, _ = self._ph.read1ByteTxRx(self._port, self._ids[i],
                                                          self._tables[i]["Hardware_Error_Status"].address)
                self._port.is_using = False
                ours = result == COMM_SUCCESS and self._ph.status_params() == 1  # not a late reply
                self._hw_bits[i] = value if ours and value else -1
            bad.append(i)
        parts = []
        for i in bad:
            bits = self._hw_bits[i]
            if bits > 0:
                parts.append(f"{self._label[i]} reports {T.describe_hardware_error(bits)} "
                             f"(Hardware_Error_Status=0x{bits:02X})")
            else:
                parts.append(f"{self._label[i]} reports a hardware error (status Alert bit; "
                             f"Hardware_Error_Status unreadable)")
        i = bad[0]
        return Fault("servo_error", f"{self.robot}: " + "; ".join(parts), joint=self.joint_names[i],
                     register="Hardware_Error_Status", value=max(self._hw_bits[i], 0), transient=False)

    def _write(self, command: JointCommand) -> Fault | None:
        """Goals of every commanded joint in ONE sync write (one bulk write if modes are mixed).

        Joints in NONE are not written (they keep their goal); FREE turns torque off; a change of
        a joint's command mode switches its operating mode first (see the module docstring).
        Nothing is sent while disabled. Setpoints arrive finite and within the profile's limits
        (``Actuator.write``, core's motion output); goals are clamped to the servo's own ranges.
        """
        if not self._enabled or self._port is None:
            return None
        mode = command.mode
        fault = None
        goal = self._goal
        np.multiply(command.position, self._tick_per_rad, out=goal)
        np.add(goal, self._offset_ticks, out=goal)
        np.rint(goal, out=goal)
        np.clip(goal, self._goal_min, self._goal_max, out=goal)
        writes = None  # (joint, address, size, raw) of this cycle
        freeing = None
        holding = None
        for i in range(self.n):
            m = mode[i]
            if m == _NONE:
                continue
            if m == _FREE:
                if not self._free[i]:
                    freeing = (freeing or []) + [i]
                continue
            if m == _POSITION:
                want = self._pos_mode[i]
                g = goal[i]
            elif m == _VELOCITY:  # velocity, effort: clamped BEFORE round(), which a huge value overflows
                want = OperatingMode.VELOCITY
                value = command.velocity[i]
                lim = self._vel_limit[i]
                g = round(min(max(value * self._vel_per_rad_s[i], -lim), lim))
            elif m == _EFFORT and self._effort_j[i]:
                want = OperatingMode.CURRENT
                value = command.effort[i]
                lim = self._cur_limit[i]
                g = round(min(max(value * self._unit_per_nm[i], -lim), lim))
            else:
                continue
            if want != self._op_mode[i] or self._switching[i]:
                # waits for the mode switch (mode_switch_steps), which core runs when no other
                # transition does (a PAUSE, a native HOME or a goal check may run for seconds
                # first); meanwhile a joint still in velocity / current mode gets a zero goal every
                # cycle, so it never keeps its last speed or current while it waits
                cur = self._op_mode[i]
                if cur in (OperatingMode.VELOCITY, OperatingMode.CURRENT) and not self._free[i]:
                    name, address, size = _GOAL[cur]
                    writes = (writes or []) + [(i, address, size, 0)]
                continue
            if self._free[i]:  # leaving FREE in the same mode: torque on after this goal
                holding = (holding or []) + [i]
            name, address, size = _GOAL[want]
            writes = (writes or []) + [(i, address, size, int(g))]
        if writes:
            f = self._send_goals(writes)
            if f is not None:
                return f
        if freeing:
            fault = self._torque_off(freeing) or fault
        if holding:
            # the controller commands a joint leaving FREE its measured position (nothing jumps)
            if self._torque_sync_write(holding, 1) != COMM_SUCCESS:
                return Fault("bus_timeout", f"{self.robot}: sync write of Torque_Enable=1 on {self._where} "
                             f"failed", transient=True)
            for i in holding:
                self._free[i] = False
        return fault

    def _wanted_mode(self, i: int, m: int) -> OperatingMode | None:
        """The operating mode joint ``i`` needs for command mode ``m`` (None: any, it is not driven)."""
        if m == _POSITION:
            return self._pos_mode[i]
        if m == _VELOCITY:
            return OperatingMode.VELOCITY
        if m == _EFFORT and self._effort_j[i]:
            return OperatingMode.CURRENT
        return None

    def mode_switch_steps(self, modes: np.ndarray) -> Steps | None:
        """Prepare (no bus): the joints whose operating mode differs from what ``modes`` needs.
        Perform (the steps, one joint per cycle): first ONE sync write of a zero goal to every
        switching joint in velocity or current mode (they stop at once, none keeps moving while
        it waits for its turn), then per joint, in its own step, the servo's own sequence, each
        acknowledged: Torque_Enable 0 (Operating_Mode is EEPROM, written with torque off) ->
        Operating_Mode -> Goal_Position = a fresh Present_Position (position modes) or a zero
        velocity / current goal -> Torque_Enable 1. The joint is unpowered within its step only;
        switched joints hold their goal until the last one is done (``_write`` leaves them
        alone). Raises BackendError naming the joint and the register (core faults the robot)."""
        todo = []
        for i in range(self.n):
            want = self._wanted_mode(i, int(modes[i]))
            if want is not None and want != self._op_mode[i]:
                todo.append((i, want))
        return self._switch_steps(todo) if todo else None

    def _switch_steps(self, todo: list[tuple[int, OperatingMode]]) -> Steps:
        self._require_open("switch operating modes")
        for i, _ in todo:
            self._switching[i] = True
        try:
            stop = [(i, *_GOAL[self._op_mode[i]][1:], 0) for i, _ in todo
                    if self._op_mode[i] in (OperatingMode.VELOCITY, OperatingMode.CURRENT) and not self._free[i]]
            if stop:
                self._send_goals(stop)  # unacknowledged: each joint's own step below is
            for k, (i, want) in enumerate(todo):
                if k:
                    yield
                self._switch(i, want)
        finally:
            for i, _ in todo:
                self._switching[i] = False

    def _switch(self, i: int, want: OperatingMode) -> None:
        """Operating-mode switch of joint ``i`` (one step of :meth:`mode_switch_steps`), holding
        it. Raises BackendError naming the joint and the register whose transaction failed: from
        the Torque_Enable=0 write on (or when the joint was FREE) it may be unpowered."""
        register = "Torque_Enable"
        try:
            if not self._free[i]:
                self._write_register(i, "Torque_Enable", 0)
            register = "Operating_Mode"
            self._write_register(i, "Operating_Mode", int(want))
            self._op_mode[i] = want
            if want in T.POSITION_MODES:
                register = "Present_Position"
                present = self._read_register(i, "Present_Position")
                register = "Goal_Position"
                self._write_register(i, "Goal_Position", present)
            elif want is OperatingMode.VELOCITY:
                register = "Goal_Velocity"
                self._write_register(i, "Goal_Velocity", 0)
            else:
                register = "Goal_Current"
                self._write_register(i, "Goal_Current", 0)
            register = "Torque_Enable"
            self._write_register(i, "Torque_Enable", 1)
        except BackendError as exc:
            self._op_mode[i] = None
            raise BackendError(f"{exc} (switching joint {self.joint_names[i]!r} to {want.name.lower()} "
                               f"mode, register {register}; its torque may be off)") from exc
        self._free[i] = False

    def _send_goals(self, writes: list) -> Fault | None:
        ph, port = self._ph, self._port
        port.is_using = False
        address, size = writes[0][1], writes[0][2]
        if all(w[1] == address for w in writes):
            param = []
            for i, _, _, raw in writes:
                param.append(self._ids[i])
                param.extend((raw & ((1 << (8 * size)) - 1)).to_bytes(size, "little"))
            result = ph.syncWriteTxOnly(port, address, size, param, len(param))
            what = "sync write"
        else:
            param = []
            for i, addr, sz, raw in writes:
                param.append(self._ids[i])
                param.extend((addr & 0xFF, addr >> 8, sz & 0xFF, sz >> 8))
                param.extend((raw & ((1 << (8 * sz)) - 1)).to_bytes(sz, "little"))
            result = ph.bulkWriteTxOnly(port, param, len(param))
            what = "bulk write"
        port.is_using = False
        if result != COMM_SUCCESS:
            return Fault("bus_timeout", f"{self.robot}: {what} of goals on {self._where} failed: "
                         f"{self._result_text(result)}", transient=True)
        return None

    def _torque_off(self, joints: list[int]) -> Fault | None:
        """One sync write of Torque_Enable = 0 (entering `free`), no acknowledgement."""
        result = self._torque_sync_write(joints, 0)
        if result != COMM_SUCCESS:
            return Fault("bus_timeout", f"{self.robot}: sync write of Torque_Enable=0 on {self._where} "
                         f"failed: {self._result_text(result)}", transient=True)
        for i in joints:
            self._free[i] = True
        return None

"""Feetech STS/SMS servo bus backend (SO-101: six STS3215 on one half-duplex bus).

Uses the vendor SDK (``scservo_sdk``, pip ``feetech-servo-sdk``) for packet framing, with the
port fixes of :mod:`.port`. One cycle is exactly two bus transactions:

* ``read``: ONE sync read (0x82) of the present-state block, registers 56..70 (15 bytes per
  servo: position, velocity, load, voltage, temperature, status, moving, current);
* ``write``: ONE sync write (0x83) of Goal_Position (2 bytes per servo), no reply.

Units (raw units never leave this module), per joint with the profile's ``calibration``:

* position  rad   = direction * (ticks - offset) * 2*pi / resolution
* velocity  rad/s = direction * Present_Velocity(ticks/s) * 2*pi / resolution
* effort    N*m   = direction * sign(Present_Load) * Present_Current * 6.5 mA * effort_per_amp.
  An ESTIMATE: current is not torque (friction, gearbox losses, back-EMF), and the STS reports
  its current magnitude only; the sign is the load's. Reported only when every joint has
  ``effort_per_amp``; otherwise ``effort`` stays 0 and ``measures_effort`` is False.
* commands: position rad -> ticks, rounded, clamped to ``calibration.range`` and to 0..4095.

The STS3215 in position mode has no effort or velocity command, so only position commands are
advertised. Register configuration (Return_Delay_Time, Acceleration, P/I/D...) is written to the
servos' RAM on every ``configure``; the EEPROM Lock is left alone, so nothing is persisted to
flash (no wear, and a power cycle restores the servo's own settings).

Endianness: ``StsPacketHandler()`` (as ``PacketHandler(0)``) sets the SDK's module-GLOBAL byte order to little-endian
(STS/SMS). An SCS-series (big-endian) bus in the same process would break this one.
"""

from __future__ import annotations

import time
from typing import Annotated

import msgspec
import numpy as np
from scservo_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupSyncRead,
    GroupSyncWrite,
)

from ...core.actuator import (
    Capabilities,
    CommandMode,
    Fault,
    JointCommand,
    JointFeedback,
    SimWiring,
)
from ...profile import Profile
from ..serial_servo import EepromDiff, SerialServoBackend
from ..servo_keys import PortMatch
from . import tables
from .port import FastPortHandler, StsPacketHandler

Byte = Annotated[int, msgspec.Meta(ge=0, le=254)]

# Bauds both the servo (register 6 codes) and the SDK's PortHandler.getCFlagBaud accept.
_SDK_BAUDS = {4800, 9600, 14400, 19200, 38400, 57600, 115200, 128000, 250000, 500000, 1000000}
SUPPORTED_BAUDS = sorted(set(tables.BAUD_CODES) & _SDK_BAUDS)

_FAULT_MASK = 0
for _bit in tables.ERROR_BITS:
    _FAULT_MASK |= _bit

_POSITION = int(CommandMode.POSITION)
_FREE = int(CommandMode.FREE)
_BLOCK = tables.PRESENT_BLOCK_START
_BLOCK_LEN = tables.PRESENT_BLOCK_LEN


def _offset(name: str) -> int:
    """Byte offset of register ``name`` inside the present-state block."""
    reg = tables.STS_CONTROL_TABLE[name]
    assert _BLOCK <= reg.address and reg.address + reg.size <= _BLOCK + _BLOCK_LEN, name
    return reg.address - _BLOCK


_O_POS = _offset("Present_Position")
_O_VEL = _offset("Present_Velocity")
_O_LOAD = _offset("Present_Load")
_O_STATUS = _offset("Status")
_O_CUR = _offset("Present_Current")
_LOAD_SIGN = 1 << tables.SIGN_BITS["Present_Load"]


class Config(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """The ``backend:`` section of a profile with ``type: feetech``."""

    # serial device, e.g. /dev/ttyACM0 or a /dev/serial/by-id/ link, or {serial_number: ...} (the USB
    # adapter\'s, resolved at open)
    port: str | PortMatch  # e.g. /dev/ttyACM0 (or a simulator's pty)
    baudrate: int = 1_000_000  # must match the servos' Baud_Rate register
    # Allowance in ms beyond the wire time of the expected reply bytes before a reply counts as
    # missing (USB latency + servo turnaround). None = 10 ms. The SDK's own is ~34 ms.
    timeout_ms: Annotated[float, msgspec.Meta(gt=0, le=1000)] | None = None
    # Immediate re-sends of a failed sync read within one cycle (also used for lifecycle
    # transactions). Each failed attempt costs up to wire time + timeout_ms.
    read_retries: Annotated[int, msgspec.Meta(ge=0, le=10)] = 1
    # Registers written in configure() (servo RAM; LeRobot's SO-101 follower values):
    return_delay: Byte = 0  # Return_Delay_Time, x2 us
    acceleration: Byte = 254  # Acceleration, x100 ticks/s^2 (0 = unlimited)
    max_acceleration: Byte = 254  # Maximum_Acceleration
    p_coefficient: Byte = 16  # position loop P (factory 32)
    i_coefficient: Byte = 0
    d_coefficient: Byte = 32


class FeetechBackend(SerialServoBackend):
    """Feetech STS servos on one serial bus, position control. See the module docstring.

    Constructing validates the profile (raises ProfileError naming ``backend.<key>`` or the joint
    key); nothing touches the bus before :meth:`open`.
    """

    vendor = "feetech"
    simulator = SimWiring()  # --sim sets backend.port to its simulator's pty (crtk-sim feetech)
    Config = Config
    MODEL_NUMBERS = tables.MODEL_NUMBERS
    RESOLUTION = tables.RESOLUTION
    MAX_ID = 253
    ACCELERATION_KEY = "acceleration"
    SUPPORTED_BAUDS = SUPPORTED_BAUDS
    BAUD_CODES = tables.BAUD_CODES
    FACTORY_BAUD = 1_000_000  # STS3215 (servos.md section 2)
    HOMING_OFFSET_MAX = 2047  # sign-magnitude, sign in bit 11
    RX_TIMEOUT = COMM_RX_TIMEOUT
    RX_CORRUPT = COMM_RX_CORRUPT

    def __init__(self, profile: Profile, *, source: str = "<profile>"):
        super().__init__(profile, source=source)
        joints = self.joint_keys
        n = self.n
        lo = [max(0, j.calibration.range[0]) if j.calibration.range else 0 for j in joints]
        hi = [min(tables.RESOLUTION[j.model] - 1, j.calibration.range[1]) if j.calibration.range
              else tables.RESOLUTION[j.model] - 1 for j in joints]
        self._goal_min = np.array(lo, dtype=float)
        self._goal_max = np.array(hi, dtype=float)
        epa = [j.effort_per_amp for j in joints]
        self._measures_effort = all(e is not None for e in epa)
        self._nm_per_unit = (
            self._direction * tables.CURRENT_UNIT_A * np.array(epa, dtype=float)
            if self._measures_effort else np.zeros(n)
        )
        self._joint_caps = [Capabilities(position=True, velocity=False, effort=False, measures_velocity=True,
                                         measures_effort=self._measures_effort, needs_homing=False,
                                         can_free=True)] * n
        self._last_goal = [0] * n  # ticks last sent / written at enable (int)
        self._sync_read: GroupSyncRead | None = None
        self._sync_write: GroupSyncWrite | None = None

    # ------------------------------------------------------------------ hooks
    def deceleration_limit(self, i: int) -> float:
        """The servo's own Acceleration register (``backend.acceleration`` x 100 ticks/s^2, 0 =
        unlimited) bounds how fast it follows a braking setpoint: 254 is 38.96 rad/s^2 on a
        4096-tick servo, the default stop deceleration's bound (core/motion.py, Stops)."""
        acc = self.config.acceleration
        if acc == 0:  # (computed from the config only: the base __init__ checks the profile with it)
            return float("inf")
        return acc * 100.0 * abs(float(self._rad_per_tick[i]))

    def _make_port(self, margin_ms: float) -> FastPortHandler:
        return FastPortHandler(self._port_path, margin_ms=margin_ms)

    def _make_packet_handler(self):
        return StsPacketHandler()  # sets the SDK's global byte order: little-endian (STS)

    def _register(self, i: int, name: str) -> tuple[int, int]:
        reg = tables.STS_CONTROL_TABLE[name]
        return reg.address, reg.size

    def _identify(self, sid: int, model: str | None, firmware: int | None) -> tuple[str | None, bool | None]:
        """Firmware Major.Minor and Torque_Enable, read (the STS table; SCS servos share them)."""
        t = tables.STS_CONTROL_TABLE
        major = self._read_id(sid, t["Firmware_Major_Version"].address)
        minor = self._read_id(sid, t["Firmware_Minor_Version"].address)
        torque = self._read_id(sid, t["Torque_Enable"].address)
        return (None if major is None or minor is None else f"{major}.{minor}",
                None if torque is None else torque != 0)

    def _broadcast_ping(self) -> tuple[dict[int, int], bool]:
        """A PING to the broadcast id (the pip SDK has no broadcast ping), every status read for
        the wire time of MAX_ID + 2 of them plus 50 ms (the servos answer at once, as LeRobot's
        broadcast ping assumes), then each one's Model_Number read. A corrupt status counts as
        garbled."""
        ph, port = self._ph, self._port
        port.is_using = False
        result = ph.txPacket(port, [0, 0, tables.BROADCAST_ID, 2, tables.INST_PING, 0])
        if result != COMM_SUCCESS:
            port.is_using = False
            return {}, False
        # listen as LeRobot does (50 ms beyond the wire time): a command-line scan, not the cycle
        port.setPacketTimeoutMillis(port.tx_time_per_byte * 6 * (self.MAX_ID + 2) + max(port.margin_ms, 50.0))
        ids, garbled = [], False
        while True:
            packet, result = ph.rxPacket(port)
            if result == COMM_SUCCESS:
                ids.append(packet[2])
            elif result == COMM_RX_CORRUPT:
                garbled = True
            if result == COMM_RX_TIMEOUT or port.isPacketTimeout():
                break
        port.is_using = False
        found = {}
        model = tables.STS_CONTROL_TABLE["Model_Number"].address
        for sid in ids:
            number = self._read_id(sid, model, 2)
            if number is None:
                garbled = True
            else:
                found[sid] = number
        return found, garbled

    EEPROM_REGISTERS = (*SerialServoBackend.EEPROM_REGISTERS, "Operating_Mode", "Phase")

    def _vendor_eeprom_diffs(self, i: int, key: str, regs: dict[str, int]) -> list[EepromDiff]:
        """Operating_Mode (the backend drives position mode 0 and writes it at start-up); Phase
        bit 4 (multi-turn angle feedback: positions leave 0..4095; LeRobot clears it too)."""
        name, sid = self.joint_names[i], self._ids[i]
        out = []
        mode = regs["Operating_Mode"]
        if mode != 0:
            out.append(EepromDiff(name, sid, "Operating_Mode", mode, "0 (position)", f"{key}.model", False,
                                  "not position mode", "the daemon sets it at start-up until the next "
                                  "power cycle"))
        phase = regs["Phase"]
        if phase & 0x10:
            out.append(EepromDiff(name, sid, "Phase", phase, f"bit 4 clear ({phase & ~0x10})", f"{key}.model",
                                  True, "bit 4 (multi-turn angle feedback) makes positions leave 0..4095",
                                  "clear bit 4 with the vendor's tool (the daemon never rewrites EEPROM)"))
        return out

    def _unlock_eeprom(self, i: int, sid: int) -> None:
        """Lock = 0: EEPROM writes persist (STS; LeRobot does the same before writing ids)."""
        self._write_register(i, "Lock", 0, sid=sid)

    def _lock_eeprom(self, i: int, sid: int) -> None:
        self._write_register(i, "Lock", 1, sid=sid)

    @staticmethod
    def _no_limits(low: int, high: int) -> bool:
        return low == 0 and high == 0  # 0/0: no angle limits (multi-turn)

    def _encode(self, i: int, name: str, value: int) -> int:
        if name in tables.SIGN_BITS:
            return tables.encode_sign_magnitude(value, tables.SIGN_BITS[name])
        return int(value)

    def _decode(self, i: int, name: str, raw: int) -> int:
        if name in tables.SIGN_BITS:
            return tables.decode_sign_magnitude(raw, tables.SIGN_BITS[name])
        return raw

    def _error_text(self, error: int) -> str | None:
        return _describe(error) if error & _FAULT_MASK else None

    def _after_open(self) -> None:
        port = self._port
        self._sync_read = GroupSyncRead(port, self._ph, _BLOCK, _BLOCK_LEN)
        self._sync_write = GroupSyncWrite(
            port, self._ph, tables.STS_CONTROL_TABLE["Goal_Position"].address, 2
        )
        for sid in self._ids:
            self._sync_read.addParam(sid)
            self._sync_write.addParam(sid, [0, 0])

    # ------------------------------------------------------------------ lifecycle
    def _configure_hook(self) -> None:
        """Torque off, then write the configuration registers to every servo. Blocks. Raises."""
        self._require_open("configure")
        cfg = self.config
        registers = (
            ("Return_Delay_Time", cfg.return_delay),
            ("Operating_Mode", 0),  # position mode: the only one this backend drives
            ("Acceleration", cfg.acceleration),
            ("Maximum_Acceleration", cfg.max_acceleration),
            ("P_Coefficient", cfg.p_coefficient),
            ("I_Coefficient", cfg.i_coefficient),
            ("D_Coefficient", cfg.d_coefficient),
        )
        self._disable_hook()
        for i in range(self.n):
            for name, value in registers:
                self._write_register(i, name, value)

    def _hold_here(self, i: int) -> None:
        """Goal_Position of servo ``i`` = a fresh read of its Present_Position (not the cycle's
        sample, which may be a cycle old), acknowledged; a servo reporting an error bit refuses
        the enable. Also the sync write's goal, so the first cycle re-sends the same."""
        present = self._read_register(i, "Present_Position")
        self._write_register(i, "Goal_Position", present, check_error=True)
        self._last_goal[i] = present
        raw = tables.encode_sign_magnitude(present, tables.SIGN_BITS["Goal_Position"])
        self._sync_write.changeParam(self._ids[i], [raw & 0xFF, raw >> 8])

    def _close_hook(self) -> None:
        super()._close_hook()
        self._sync_read = None
        self._sync_write = None

    # ------------------------------------------------------------------ real-time path
    def _read(self, feedback: JointFeedback) -> Fault | None:
        """ONE sync read of registers 56..70 of every servo (retried ``read_retries`` times at
        once on failure), decoded into ``feedback`` in place. Never sleeps beyond the packet
        deadline. ``stamp`` = time.time() when the request went out.

        Returns a transient ``bus_timeout`` / ``bus_corrupt`` Fault (``feedback`` untouched: the
        SDK keeps stale data for servos after a failed one, so nothing of a failed read is used),
        or a non-transient ``servo_error`` Fault when a servo's Status register has an error bit
        (``feedback`` filled: the data is valid).
        """
        if self._lost is not None and self._still_lost():
            return self._lost  # the port is gone (hot replug): no bus I/O until it is back
        gsr = self._sync_read
        if gsr is None:
            return Fault("bus_timeout", f"{self.robot}: read on a closed bus", transient=False)
        port = self._port
        port.last_os_error = None
        port.is_using = False  # we own the port alone: a leftover flag would mean PORT_BUSY forever
        result = COMM_SUCCESS
        for _ in range(self._attempts):
            stamp = time.time()
            result = gsr.txRxPacket()
            if result == COMM_SUCCESS:
                break
        if result != COMM_SUCCESS:
            return self._bus_fault(result)
        self._failed_run = None
        data = gsr.data_dict
        raw_pos, raw_vel, raw_cur = self._raw_pos, self._raw_vel, self._raw_cur
        status_any = 0
        i = 0
        for sid in self._ids:
            b = data[sid]
            if len(b) < _BLOCK_LEN:
                return Fault("bus_corrupt",
                             f"{self.robot}: {self._label[i]} sent {len(b)} of {_BLOCK_LEN} bytes "
                             f"on {self._where}", joint=self.joint_names[i], transient=True)
            v = b[_O_POS] | (b[_O_POS + 1] << 8)
            raw_pos[i] = -(v & 0x7FFF) if v & 0x8000 else v
            v = b[_O_VEL] | (b[_O_VEL + 1] << 8)
            raw_vel[i] = -(v & 0x7FFF) if v & 0x8000 else v
            v = (b[_O_CUR] | (b[_O_CUR + 1] << 8)) & 0x7FFF
            raw_cur[i] = -v if (b[_O_LOAD] | (b[_O_LOAD + 1] << 8)) & _LOAD_SIGN else v
            status_any |= b[_O_STATUS]
            i += 1
        if self._cal is not None:  # a calibration sweep: follow the ticks (in place)
            self._cal.track(raw_pos)
        np.subtract(raw_pos, self._offset_ticks, out=self._tmp)
        np.multiply(self._tmp, self._rad_per_tick, out=feedback.position)
        np.multiply(raw_vel, self._rad_per_tick, out=feedback.velocity)
        if self._measures_effort:
            np.multiply(raw_cur, self._nm_per_unit, out=feedback.effort)
        feedback.stamp = stamp
        fault = self._status_fault(data) if status_any & _FAULT_MASK else None
        self._error_status(fault)
        return fault

    def _bus_fault(self, result: int) -> Fault:
        return self._sync_read_fault(result, self._sync_read.data_dict, _BLOCK_LEN)

    def _status_fault(self, data: dict) -> Fault:
        bad = []
        for i, sid in enumerate(self._ids):
            bits = data[sid][_O_STATUS] & _FAULT_MASK
            if bits:
                bad.append((i, bits))
        i, bits = bad[0]
        msg = f"{self.robot}: {self._label[i]} reports {_describe(bits)} (Status=0x{bits:02X})"
        for k, other in bad[1:]:
            msg += f"; {self._label[k]} reports {_describe(other)} (Status=0x{other:02X})"
        return Fault("servo_error", msg, joint=self.joint_names[i], register="Status",
                     value=bits, transient=False)

    def _write(self, command: JointCommand) -> Fault | None:
        """ONE sync write of Goal_Position to every servo, no reply. Never sleeps.

        Joints in mode POSITION get ``command.position`` (rad) converted to ticks, clamped to
        ``calibration.range`` and 0..4095. Joints in mode NONE get their last goal re-sent (the
        servo holds it anyway; re-sending keeps one fixed packet and repairs a lost one). When
        no joint is in POSITION mode nothing is sent. Nothing is sent while disabled: an STS
        takes a goal even with torque off, and enable sets fresh goals itself. Setpoints arrive
        finite and within the profile's limits (``Actuator.write``, core's motion output).
        """
        if not self._enabled or self._sync_write is None:
            return None
        mode = command.mode
        goal = self._goal
        np.multiply(command.position, self._tick_per_rad, out=goal)
        np.add(goal, self._offset_ticks, out=goal)
        np.rint(goal, out=goal)
        np.clip(goal, self._goal_min, self._goal_max, out=goal)
        gsw = self._sync_write
        last = self._last_goal
        fault = None
        send = False
        freeing = None  # joints entering / leaving FREE this cycle (rare: lists only then)
        holding = None
        for i in range(self.n):
            if mode[i] == _FREE:
                if not self._free[i]:
                    freeing = (freeing or []) + [i]
                continue
            if self._free[i] and mode[i] == _POSITION:
                holding = (holding or []) + [i]
            if mode[i] == _POSITION:
                send = True
                t = int(goal[i])
                if t != last[i]:
                    last[i] = t
                    gsw.changeParam(self._ids[i], [t & 0xFF, t >> 8])
        if send:
            self._port.is_using = False
            result = gsw.txPacket()
            if result != COMM_SUCCESS:
                return Fault("bus_timeout",
                             f"{self.robot}: sync write of Goal_Position on {self._where} "
                             f"failed: {self._result_text(result)}", transient=True)
        # `free`: torque off on joints entering FREE; torque back on for joints leaving it, AFTER
        # the goal above (the controller commands their measured position, so nothing jumps)
        if freeing:
            fault = self._torque_sync(freeing, 0) or fault
        if holding:
            fault = self._torque_sync(holding, 1) or fault
        return fault

    def _torque_sync(self, joints: list[int], value: int) -> Fault | None:
        """One sync write of Torque_Enable to ``joints`` (transitions of `free` only), no
        acknowledgement (:meth:`SerialServoBackend._torque_sync_write`: its parameter list is
        reused, nothing is built per call)."""
        result = self._torque_sync_write(joints, value)
        if result != COMM_SUCCESS:
            return Fault("bus_timeout", f"{self.robot}: sync write of Torque_Enable={value} on {self._where} "
                         f"failed: {self._result_text(result)}", transient=True)
        for i in joints:
            self._free[i] = value == 0
        return None


def _describe(bits: int) -> str:
    return ", ".join(name for bit, name in tables.ERROR_BITS.items() if bits & bit)

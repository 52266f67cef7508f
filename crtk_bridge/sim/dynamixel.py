"""Dynamixel X-series bus (Protocol 2.0) simulated at the wire level on a pseudo-terminal.

:class:`DynamixelSimulator` answers the real Protocol 2.0 packets ``dynamixel_sdk`` sends, byte
for byte (docs/architecture.md, "Sources": Dynamixel): header ``FF FF FD 00``, CRC-16 (poly 0x8005),
byte stuffing (``FF FF FD`` -> ``FF FF FD FD`` in instruction and status payloads; not in Fast
Sync Read replies, as on hardware), and the instructions PING, READ, WRITE, REG_WRITE, ACTION,
REBOOT, SYNC_READ, FAST_SYNC_READ, SYNC_WRITE, BULK_READ and BULK_WRITE. Each servo is an
X-series control table (XL330-M288, XL430-W250 or XM430-W350, layout from
:mod:`crtk_bridge.backends.dynamixel.tables`) plus a little physics, advanced lazily from the
monotonic clock whenever a packet or a caller touches it:

- position modes (3 position, 4 extended, 5 current-based), torque on: Present_Position tracks
  Goal_Position as a first-order lag (``TAU_S``) with the speed capped at Velocity_Limit (or
  Profile_Velocity when nonzero); mode 3 clamps the goal into Min/Max_Position_Limit;
- velocity mode (1): Present_Velocity follows Goal_Velocity (clamped to Velocity_Limit), first order;
- current mode (0): an unloaded motor: the speed settles at ``TICKS_PER_S_PER_MA`` per mA of
  Goal_Current; Present_Current = Goal_Current;
- torque off: the joint stays where it is (no gravity), unless moved by hand (control ``hand``). Present_Current (Present_Load on the
  XL430) grows with the tracking error; Moving is 1 while the servo moves.

Bus behaviour: broadcast id 0xFE (no reply, except PING and the sync/bulk reads), Status_Return_
Level (0 ping only, 1 + reads, 2 all), CRC errors ignored, garbage skipped, a half-received packet
dropped after ``FRAME_TIMEOUT_S`` of silence, unknown ids silent. Status ERR byte: bit 7 (Alert)
while Hardware_Error_Status (70) is nonzero; error 7 (access) for a write to a read-only address
or to EEPROM (< 64) with torque on, and nothing is written.

Faults (control socket or :meth:`DynamixelSimulator.set_fault`), the same kinds as the STS
simulator: ``silent`` (the servo receives but never replies; in a Fast Sync Read the reply stops
before its slot, as the following servos wait for it), ``corrupt`` (its replies carry a bad CRC),
``late_reply`` (its previous status goes out again just ahead of its next one, once),
``error_bits`` (OR bits into Hardware_Error_Status: a latched hardware error; if they are in the
Shutdown mask (63) torque goes off; only a REBOOT clears it, so ``clear_faults`` does not),
``freeze`` (the joint stops moving), and ``unplug`` of the whole bus. A REBOOT restores the RAM
defaults (torque off, goal = present position, error cleared) and leaves the servo deaf for
``REBOOT_S``.

EEPROM (addresses below 64: id, baud rate, return delay, drive and operating mode, homing offset,
limits...) is written only with torque off (else error 7, access) and then persists, as on an X
servo; a power cycle (``power_cycle``, or ``attach`` of a detached servo) restores the RAM defaults
only. A factory-fresh servo (``add_servo``) has id 1 and 57600 baud (Baud_Rate 1; servos.md
section 5). A servo whose Baud_Rate is not the client's rate neither hears nor answers.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterable

from ..backends.dynamixel import tables as T
from ..profile import Profile
from . import SimulatorError
from .bus import BITS_PER_BYTE, FRAME_TIMEOUT_S, BusServo, BusSimulator, FaultKind, Reply, approach

__all__ = ["DynamixelSimulator", "SimServo", "FaultKind", "crc16", "stuff", "unstuff", "packet",
           "FRAME_TIMEOUT_S", "BITS_PER_BYTE"]

log = logging.getLogger(__name__)

TAU_S = 0.030  # first-order tracking time constant
TICKS_PER_S_PER_RAW_VEL = 0.229 * 4096 / 60  # one Goal_Velocity unit in ticks/s
TICKS_PER_S_PER_MA = 12.0  # unloaded speed per mA in current mode (~0.02 rad/s per mA)
CURRENT_MA_PER_TICK = 0.8  # Present_Current (mA) per tick of tracking error in position modes
LOAD_PER_TICK = 4.0  # XL430 Present_Load (0.1 %) per tick of tracking error
HOLDING_MA = 5.0
REBOOT_S = 0.05  # deaf after a REBOOT
FIRMWARE = 52  # new enough for Fast Sync Read on every modelled series
HEADER = b"\xff\xff\xfd\x00"

_CRC_TABLE = []
for _i in range(256):
    _c = _i << 8
    for _ in range(8):
        _c = ((_c << 1) ^ 0x8005) if _c & 0x8000 else (_c << 1)
    _CRC_TABLE.append(_c & 0xFFFF)


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """Dynamixel Protocol 2.0 CRC-16 (polynomial 0x8005, init 0, not reflected)."""
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(payload: bytes | bytearray) -> bytes:
    """Byte stuffing: each ``FF FF FD`` in ``payload`` gets an extra ``FD``."""
    out = bytearray()
    for b in payload:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-2] == 0xFF and out[-3] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(payload: bytes | bytearray) -> bytes:
    out = bytearray()
    i = 0
    n = len(payload)
    while i < n:
        b = payload[i]
        out.append(b)
        if b == 0xFD and i + 1 < n and payload[i + 1] == 0xFD and len(out) >= 3 \
                and out[-2] == 0xFF and out[-3] == 0xFF:
            i += 1  # drop the stuffed FD
        i += 1
    return bytes(out)


def packet(sid: int, inst: int, params: bytes | bytearray = b"") -> bytes:
    """A Protocol 2.0 packet (instruction or status): stuffed, with its CRC."""
    body = stuff(bytes((inst,)) + bytes(params))
    head = HEADER + bytes((sid, (len(body) + 2) & 0xFF, (len(body) + 2) >> 8))
    pkt = head + body
    crc = crc16(pkt)
    return pkt + bytes((crc & 0xFF, crc >> 8))


_A = {name: reg.address for name, reg in T.CONTROL_TABLES["xm430-w350"].items()}
_TORQUE = _A["Torque_Enable"]
_MODE = _A["Operating_Mode"]
_HW_ERROR = _A["Hardware_Error_Status"]
_STATUS_LEVEL = _A["Status_Return_Level"]
_RETURN_DELAY = _A["Return_Delay_Time"]
_BAUD = _A["Baud_Rate"]
_ID = _A["ID"]
_SHUTDOWN = _A["Shutdown"]


class SimServo(BusServo):
    """One simulated X-series servo: control table memory and physical state.

    :meth:`read` / :meth:`write` (by register name) are thread-safe and update the physics first.
    """

    def __init__(self, sim: DynamixelSimulator, servo_id: int, model: str, position: int,
                 baudrate: int | None = None, return_delay: int = 0):
        super().__init__(sim)
        self.model = model
        self.table = T.CONTROL_TABLES[model]
        self._writable = bytearray(256)
        for reg in self.table.values():
            if reg.writable:
                self._writable[reg.address: reg.address + reg.size] = b"\x01" * reg.size
        self.deaf_until = 0.0
        self._pos = float(position)
        self._vel = 0.0
        self._err_ticks = 0.0  # tracking error (ticks), drives Present_Current / Present_Load
        self._eeprom_defaults(servo_id, baudrate or sim.baudrate, return_delay)
        self._ram_defaults()

    # --- defaults ---
    def _put(self, name: str, value: int) -> None:
        reg = self.table[name]
        raw = T.to_raw(value, reg.size) if reg.signed else int(value)
        self.registers[reg.address: reg.address + reg.size] = raw.to_bytes(reg.size, "little")

    def _actual(self, present: int) -> float:
        return float(present - self._get("Homing_Offset"))  # Present = Actual + Homing_Offset

    def _get(self, name: str) -> int:
        reg = self.table[name]
        raw = int.from_bytes(self.registers[reg.address: reg.address + reg.size], "little")
        return T.to_signed(raw, reg.size) if reg.signed else raw

    def _eeprom_defaults(self, servo_id: int, baudrate: int, return_delay: int) -> None:
        m = self.model
        self._put("Model_Number", T.MODEL_NUMBERS[m])
        self._put("Firmware_Version", FIRMWARE)
        self._put("ID", servo_id)
        self._put("Baud_Rate", T.BAUD_CODES[baudrate])
        # the simulated arm's servos: 0, as the backends set it; a factory-fresh one: 250 (x2 us)
        self._put("Return_Delay_Time", return_delay)
        self._put("Operating_Mode", int(T.OperatingMode.POSITION))
        self._put("Protocol_Type", 2)
        self._put("Moving_Threshold", 10)
        self._put("Temperature_Limit", 70 if m.startswith("xl330") else 80)
        self._put("Max_Voltage_Limit", 70 if m.startswith("xl330") else 140)
        self._put("Min_Voltage_Limit", 35 if m.startswith("xl330") else 60)
        self._put("PWM_Limit", 885)
        if "Current_Limit" in self.table:
            self._put("Current_Limit", T.CURRENT_LIMIT_DEFAULT[m])
        self._put("Velocity_Limit", T.VELOCITY_LIMIT_DEFAULT[m])
        self._put("Max_Position_Limit", 4095)
        self._put("Min_Position_Limit", 0)
        self._put("Shutdown", 53 if m.startswith("xl330") else 52)

    def _ram_defaults(self) -> None:
        """Power-on / reboot RAM state: torque off, goal = present position, no error."""
        r = self.registers
        r[64:256] = bytes(192)
        self._put("Status_Return_Level", 2)
        self._put("Position_P_Gain", T.POSITION_P_DEFAULT[self.model])
        self._put("Velocity_P_Gain", 100)
        self._put("Velocity_I_Gain", 1000)
        if "Goal_Current" in self.table:
            self._put("Goal_Current", self._get("Current_Limit"))
        self._put("Present_Input_Voltage", 50 if self.model.startswith("xl330") else 120)
        self._put("Present_Temperature", 30)
        self._vel = 0.0
        self._put("Goal_Position", round(self._pos) + self._get("Homing_Offset"))
        self._refresh(0.0)

    # --- BusServo hooks (caller holds the lock) ---
    def _set(self, name: str, value: int) -> None:
        try:
            self._put(name, value)
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from None
        if name == "Present_Position":
            self._pos = float(value - self._get("Homing_Offset"))

    # --- bus side (caller holds the lock) ---
    def _bus_write(self, addr: int, data: bytes) -> int:
        """A WRITE payload. Returns the status error number (0 = written)."""
        data = self._delay_torque(addr, data)
        end = addr + len(data)
        if end > 256 or not all(self._writable[addr:end]):
            return T.ERRNUM_ACCESS
        if addr < 64 and self.registers[_TORQUE]:
            return T.ERRNUM_ACCESS  # EEPROM area is locked while torque is on
        if addr <= _TORQUE < end and data[_TORQUE - addr] and self.registers[_HW_ERROR]:
            data = bytearray(data)
            data[_TORQUE - addr] = 0  # a servo in shutdown refuses torque until rebooted
        self.registers[addr:end] = data
        return 0

    def _err(self) -> int:
        return T.ERR_ALERT if self.registers[_HW_ERROR] else 0

    def _status(self, params: bytes = b"", errnum: int = 0) -> bytes:
        pkt = packet(self.id, T.INST_STATUS, bytes((self._err() | errnum,)) + params)
        if self.corrupt:
            pkt = pkt[:-1] + bytes((pkt[-1] ^ 0xFF,))
        return self._deliver(pkt)

    def _update(self, now: float) -> None:
        self._torque_due(now)
        dt = max(0.0, now - self._t)
        self._t = now
        self._step(dt)
        self._refresh(dt)

    def _step(self, dt: float) -> None:
        r = self.registers
        if r[_HW_ERROR] & r[_SHUTDOWN]:
            r[_TORQUE] = 0
        self._err_ticks = 0.0
        if not r[_TORQUE] or self.frozen or dt <= 0.0:
            if not r[_TORQUE] or self.frozen:
                self._vel = 0.0
            if not r[_TORQUE] and self._hand is not None and dt > 0.0:  # a hand turns the horn
                new = self._hand_step(self._pos, dt)
                self._vel = (new - self._pos) / dt
                self._pos = new
            return
        mode = r[_MODE]
        vlim = max(1, self._get("Velocity_Limit")) * TICKS_PER_S_PER_RAW_VEL
        offset = self._get("Homing_Offset")
        if mode in (3, 4, 5):
            goal = self._get("Goal_Position")
            if mode == 3:
                lo, hi = self._get("Min_Position_Limit"), self._get("Max_Position_Limit")
                goal = min(max(goal, lo), hi)
            pv = self._get("Profile_Velocity")
            vmax = min(vlim, pv * TICKS_PER_S_PER_RAW_VEL) if pv else vlim
            err = goal - offset - self._pos
            a = approach(err, dt, vmax, TAU_S)
            new = goal - offset - math.copysign(a, err)
            self._vel = (new - self._pos) / dt
            self._pos = new
            self._err_ticks = math.copysign(a, err)
        elif mode in (0, 1):
            if mode == 1:
                target = max(-vlim, min(vlim, self._get("Goal_Velocity") * TICKS_PER_S_PER_RAW_VEL))
            else:
                target = max(-vlim, min(vlim, self._goal_current_ma() * TICKS_PER_S_PER_MA))
            k = math.exp(-dt / TAU_S)
            v0 = self._vel
            v1 = target + (v0 - target) * k
            # exact integral of the first-order velocity over dt
            self._pos += target * dt + (v0 - target) * TAU_S * (1 - k)
            self._vel = v1
            self._err_ticks = (target - v1) * TAU_S

    def _goal_current_ma(self) -> float:
        unit = T.CURRENT_UNIT_A[self.model]
        return self._get("Goal_Current") * unit * 1000.0 if unit else 0.0

    def _present_exact(self) -> float:
        return self._pos + self._get("Homing_Offset")

    def _refresh(self, dt: float) -> None:
        r = self.registers
        self._put("Present_Position", max(-(1 << 31), min((1 << 31) - 1,
                                                          round(self._pos) + self._get("Homing_Offset"))))
        self._put("Present_Velocity", int(round(self._vel / TICKS_PER_S_PER_RAW_VEL)))
        moving = abs(self._vel) / TICKS_PER_S_PER_RAW_VEL > self._get("Moving_Threshold") or \
            abs(self._err_ticks) > 0.5
        r[_A["Moving"]] = 1 if (moving and r[_TORQUE]) else 0
        unit = T.CURRENT_UNIT_A[self.model]
        if unit is None:
            load = min(1000.0, abs(self._err_ticks) * LOAD_PER_TICK) if r[_TORQUE] else 0.0
            self._put("Present_Load", int(math.copysign(load, self._err_ticks)))
            return
        if not r[_TORQUE]:
            ma = 0.0
        elif r[_MODE] == 0:
            ma = self._goal_current_ma()
        else:
            ma = math.copysign(min(abs(self._err_ticks) * CURRENT_MA_PER_TICK + HOLDING_MA, 5000.0),
                               self._err_ticks or 1.0)
            limit = self._get("Current_Limit") * unit * 1000.0
            if r[_MODE] == 5:
                limit = min(limit, abs(self._goal_current_ma()))
            ma = max(-limit, min(limit, ma))
        self._put("Present_Current", int(round(ma / 1000.0 / unit)))


class DynamixelSimulator(BusSimulator):
    """A bus of simulated X-series servos on a pty; see the module docstring for the model.

    ``servos``: id -> model name ("xl330-m288", "xl430-w250", "xm430-w350"). ``start()`` creates
    the pty (``link``, ``control`` socket) and the serving thread; ``stop()`` is idempotent. With
    ``emulate_baud`` each reply leaves no earlier than request and reply would take on a real wire
    at ``baudrate`` (10 bits per byte) plus each replying servo's Return_Delay_Time.
    """

    vendor = "dynamixel"
    BAUD_CODES = T.BAUD_CODES
    FACTORY_BAUD = 57_600  # X series: Baud_Rate code 1 (servos.md section 5)
    DEFAULT_MODEL = "xl430-w250"
    ID_ADDRESS = _ID
    BAUD_ADDRESS = _BAUD
    RETURN_DELAY_ADDRESS = _RETURN_DELAY
    TORQUE_ADDRESS = _TORQUE
    MAX_ID = T.MAX_ID

    def __init__(
        self,
        servos: dict[int, str] | Iterable[int] = (1,),
        baudrate: int = 1_000_000,
        link: str | os.PathLike | None = None,
        control: str | os.PathLike | None = None,
        emulate_baud: bool = False,
        initial_positions: dict[int, int] | None = None,
    ):
        if not isinstance(servos, dict):
            servos = {sid: "xm430-w350" for sid in servos}
        for sid, model in servos.items():
            if not 0 <= sid <= T.MAX_ID:
                raise SimulatorError(f"servo id {sid} is not a valid Dynamixel id (0..{T.MAX_ID})")
            if model not in T.CONTROL_TABLES:
                raise SimulatorError(f"servo {sid}: unknown model {model!r} "
                                     f"(known: {', '.join(T.CONTROL_TABLES)})")
        super().__init__(baudrate, link, control, emulate_baud)
        positions = initial_positions or {}
        self._servos: dict[int, SimServo] = {
            sid: SimServo(self, sid, model, int(positions.get(sid, 2048))) for sid, model in servos.items()
        }

    @classmethod
    def from_profile(cls, profile: Profile, link=None, control=None, emulate_baud: bool = False
                     ) -> DynamixelSimulator:
        """One servo per joint with an ``id``, of the joint's ``model``, resting at its joint zero."""
        joints, baud = cls._profile_joints(profile)
        servos = {}
        for j in joints:
            model = (j.model or "xm430-w350").lower()
            if model not in T.CONTROL_TABLES:
                raise SimulatorError(f"profile {profile.name!r}: servo {j.id}: unknown model "
                                     f"{j.model!r} (known: {', '.join(T.CONTROL_TABLES)})")
            servos[j.id] = model
        return cls(servos, baudrate=baud, link=link, control=control, emulate_baud=emulate_baud,
                   initial_positions={j.id: j.calibration.offset for j in joints})

    # --- vendor hooks (see BusSimulator) ---
    def _register_name(self, servo: SimServo, register: object) -> str:
        names = {n.lower(): n for n in servo.table}
        name = names.get(str(register if register is not None else "").lower())
        if name is None:
            raise SimulatorError(f"servo {servo.id}: unknown register {register!r} on a {servo.model}")
        return name

    def _snapshot(self, servo: SimServo) -> dict:
        return {"model": servo.model, **{n.lower(): servo._get(n) for n in servo.table}}

    def _error_bits(self, servo: SimServo) -> int:
        return servo.registers[_HW_ERROR]

    def _set_error_bits(self, servo: SimServo, bits: int) -> None:
        # A latched hardware error: Alert in every ERR byte; torque off if in the Shutdown mask.
        if not 0 < bits <= 0xFF:
            raise SimulatorError(f"error_bits: bits {bits} must be in 1..255 "
                                 f"(Hardware_Error_Status bits)")
        servo.registers[_HW_ERROR] |= bits
        servo._update(self.clock())  # shutdown: torque off now

    def _clear_error_bits(self, servo: SimServo) -> None:
        """Nothing: Hardware_Error_Status stays latched until a REBOOT, as on hardware."""

    def _new_servo(self, servo_id: int, model: str, baudrate: int, position: int) -> SimServo:
        model = model.lower()
        if model not in T.CONTROL_TABLES:
            raise SimulatorError(f"unknown model {model!r} (known: {', '.join(T.CONTROL_TABLES)})")
        return SimServo(self, servo_id, model, position, baudrate=baudrate, return_delay=250)

    def _power_cycle(self, servo: SimServo) -> None:
        servo._pending = None
        servo._torque_on_at = None
        servo._ram_defaults()  # the EEPROM persisted with every write

    # --- the bus ---
    def _parse(self, buf: bytearray, now: float) -> list[Reply]:
        """Consume every complete packet in ``buf``; return (deadline, reply) per answered one."""
        replies = []
        n = len(buf)
        i = 0
        while True:
            start = buf.find(HEADER, i)
            if start < 0:
                i = max(i, n - 3)  # a header may be split across reads
                break
            if n - start < 10:
                i = start
                break
            length = buf[start + 5] | buf[start + 6] << 8
            if length < 3 or length > 1024:
                i = start + 3
                continue
            end = start + 7 + length
            if end > n:
                i = start
                break
            crc = buf[end - 2] | buf[end - 1] << 8
            if crc16(buf[start:end - 2]) != crc:
                log.debug("ignored packet with a bad CRC: %s", buf[start:end].hex(" "))
                i = start + 3
                continue
            payload = unstuff(buf[start + 7:end - 2])
            reply = self._dispatch(buf[start + 4], payload[0], payload[1:], end - start, now)
            if reply is not None:
                replies.append(reply)
            i = end
        if i:
            del buf[:i]
        return replies

    def _reachable(self, s: SimServo | None, now: float) -> bool:
        return s is not None and s.deaf_until <= now and \
            (self._baud_code is None or s.registers[_BAUD] == self._baud_code)

    def _dispatch(self, sid: int, inst: int, p: bytes, req_len: int, now: float):
        out: list[bytes] = []
        repliers: list[SimServo] = []
        with self._lock:
            if self.unplugged:
                return None
            sim_now = self.clock()
            servos = self._servos
            broadcast = sid == T.BROADCAST_ID
            if broadcast:
                targets = [s for s in servos.values() if self._reachable(s, now)]
            else:
                s = servos.get(sid)
                if not self._reachable(s, now):
                    return self._no_reply(req_len, now)
                targets = [s]
            for s in targets:
                s._update(sim_now)

            def answer(s: SimServo, params: bytes = b"", errnum: int = 0, level: int = 2) -> None:
                if s.registers[_STATUS_LEVEL] >= level and not s.silent:
                    out.append(s._status(params, errnum))
                    repliers.append(s)

            if inst == T.INST_PING:
                for s in targets:
                    model = T.MODEL_NUMBERS[s.model]
                    answer(s, bytes((model & 0xFF, model >> 8, s.registers[6])), level=0)
            elif inst == T.INST_READ and len(p) == 4 and not broadcast:
                addr, ln = p[0] | p[1] << 8, p[2] | p[3] << 8
                s = targets[0]
                if addr + ln <= 256:
                    answer(s, bytes(s.registers[addr:addr + ln]), level=1)
                else:
                    answer(s, errnum=T.ERRNUM_ACCESS, level=1)
            elif inst in (T.INST_WRITE, T.INST_REG_WRITE) and len(p) >= 3:
                addr, data = p[0] | p[1] << 8, p[2:]
                for s in targets:
                    if inst == T.INST_WRITE:
                        old = s.id
                        err = s._bus_write(addr, data)
                        self._rekey(s, old)
                    else:
                        s._pending, err = (addr, data), 0
                        s.registers[_A["Registered_Instruction"]] = 1
                    if not broadcast:
                        answer(s, errnum=err)
            elif inst == T.INST_ACTION:
                for s in targets:
                    if s._pending is not None:
                        s._bus_write(*s._pending)
                        s._pending = None
                        s.registers[_A["Registered_Instruction"]] = 0
                if not broadcast:
                    answer(targets[0])
            elif inst == T.INST_REBOOT:
                for s in targets:
                    if not broadcast:
                        answer(s)
                    s._ram_defaults()
                    s.deaf_until = now + REBOOT_S
            elif inst in (T.INST_SYNC_READ, T.INST_FAST_SYNC_READ) and broadcast and len(p) >= 5:
                addr, ln = p[0] | p[1] << 8, p[2] | p[3] << 8
                if addr + ln > 256:
                    return self._no_reply(req_len, now)
                chosen = []
                for tid in p[4:]:  # replies in request order
                    s = servos.get(tid)
                    if self._reachable(s, now):
                        s._update(sim_now)
                        chosen.append(s)
                if inst == T.INST_SYNC_READ:
                    for s in chosen:
                        answer(s, bytes(s.registers[addr:addr + ln]), level=1)
                else:
                    fast = self._fast_reply(chosen, addr, ln)
                    if fast:
                        out.append(fast)
                        repliers.extend(s for s in chosen if not s.silent)
            elif inst == T.INST_BULK_READ and broadcast:
                for k in range(0, len(p) - 4, 5):
                    s = servos.get(p[k])
                    addr, ln = p[k + 1] | p[k + 2] << 8, p[k + 3] | p[k + 4] << 8
                    if self._reachable(s, now) and addr + ln <= 256:
                        s._update(sim_now)
                        answer(s, bytes(s.registers[addr:addr + ln]), level=1)
            elif inst == T.INST_SYNC_WRITE and broadcast and len(p) >= 4:
                addr, ln = p[0] | p[1] << 8, p[2] | p[3] << 8
                for k in range(4, len(p) - ln, ln + 1):
                    s = servos.get(p[k])
                    if self._reachable(s, now):
                        old = s.id
                        s._update(sim_now)
                        s._bus_write(addr, p[k + 1:k + 1 + ln])
                        self._rekey(s, old)
            elif inst == T.INST_BULK_WRITE and broadcast:
                k = 0
                while k + 5 <= len(p):
                    s = servos.get(p[k])
                    addr, ln = p[k + 1] | p[k + 2] << 8, p[k + 3] | p[k + 4] << 8
                    if self._reachable(s, now):
                        old = s.id
                        s._update(sim_now)
                        s._bus_write(addr, p[k + 5:k + 5 + ln])
                        self._rekey(s, old)
                    k += 5 + ln
            else:
                return self._no_reply(req_len, now)  # unknown instruction: a servo stays silent
            delay_s = self._turnaround_s(repliers)
        return self._reply(out, req_len, now, delay_s)

    @staticmethod
    def _fast_reply(chosen: list[SimServo], addr: int, ln: int) -> bytes:
        """ONE status packet: header, then ``ERR ID data CRC`` per servo; each CRC covers the
        whole packet so far; not stuffed. A silent servo cuts the packet short at its slot."""
        if not chosen:
            return b""
        length = 1 + len(chosen) * (ln + 4)
        pkt = bytearray(HEADER + bytes((T.BROADCAST_ID, length & 0xFF, length >> 8, T.INST_STATUS)))
        for s in chosen:
            if s.silent:
                break
            pkt += bytes((s._err(), s.id)) + s.registers[addr:addr + ln]
            crc = crc16(pkt)
            if s.corrupt:
                crc ^= 0xFFFF
            pkt += bytes((crc & 0xFF, crc >> 8))
        return bytes(pkt) if len(pkt) > 8 else b""


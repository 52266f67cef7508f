"""Feetech STS3215 servo bus simulated at the wire level on a pseudo-terminal.

:class:`FeetechSimulator` answers the real FT-SCS packets the ``scservo_sdk`` sends (PING, READ,
WRITE, REG_WRITE, ACTION, SYNC_READ, SYNC_WRITE; docs/architecture.md, "Sources": Feetech),
byte for byte, from one background thread blocked in poll() on the pty master. Each servo is a
256-byte control table (layout from :mod:`crtk_bridge.backends.feetech.tables`) plus a little
physics, advanced lazily from the monotonic clock whenever a packet or a caller touches it:

- position mode (Operating_Mode 0), torque on: Present_Position tracks the goal (clamped into
  Min/Max_Position_Limit) as a first-order lag (time constant ``TAU_S``) with the speed capped at
  ``VELOCITY_MAX_TPS`` (STS3215 no-load speed at 7.4 V) or at Goal_Velocity when that is nonzero;
- constant-speed mode (Operating_Mode 1), torque on: turns at Goal_Velocity (wraps 0..4095);
- torque off (or any other mode): the joint stays where it is (no gravity), unless moved by hand
  (control ``hand``: toward a position at a bounded speed);
- Present_Velocity is the instantaneous rate, Present_Current / Present_Load grow with the
  tracking error, Moving is 1 while the servo is still closing in; Present = Actual - Homing_Offset.
- enabling torque drives to whatever Goal_Position holds (it is not reset to Present_Position), so
  a backend must write Goal = Present before enabling, as on hardware. Torque_Enable 128 makes the
  current position read 2048 (writes Homing_Offset) and leaves torque off.

Bus behaviour modelled: broadcast id 0xFE (no status reply, except PING and SYNC_READ where every
addressed servo answers in turn), Response_Status_Level 0 (answer only reads and pings), bad
checksums ignored, garbage skipped (resync on the next ``FF FF``), a half-received packet dropped
after ``FRAME_TIMEOUT_S`` of silence, unknown ids silent, a servo whose Baud_Rate code differs
from the rate the client talks at deaf and mute, writes to read-only registers ignored, the status
ERR byte = the Status register (65).

EEPROM (the registers the table marks EEPROM: id, baud rate, return delay, limits, homing offset,
operating mode...): a write takes effect at once; it is also persisted ("flash") only while Lock
(55) is 0, as on the STS. A power cycle (``power_cycle``, or ``attach`` of a detached servo) brings
the EEPROM back from flash and the RAM to its power-on defaults (torque off, Lock 1, goal =
present). A factory-fresh servo (``add_servo``) has id 1 and 1 Mbps (servos.md section 2).

Faults (control socket or :meth:`FeetechSimulator.set_fault`): ``silent`` (servo receives but
never replies), ``corrupt`` (its replies carry a bad checksum), ``late_reply`` (its previous
status goes out again just ahead of its next one, once), ``error_bits`` (OR bits into
Status, hence into every ERR byte), ``freeze`` (the joint stops moving, as if stalled), and
``unplug`` of the whole bus (nothing is received or answered).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterable

from ..backends.feetech import tables as T
from ..profile import Profile
from . import SimulatorError
from .bus import BITS_PER_BYTE, FRAME_TIMEOUT_S, BusServo, BusSimulator, FaultKind, Reply, approach

__all__ = ["FeetechSimulator", "SimServo", "FaultKind", "FRAME_TIMEOUT_S", "BITS_PER_BYTE"]

log = logging.getLogger(__name__)

TAU_S = 0.030  # first-order tracking time constant
VELOCITY_MAX_TPS = 3400.0  # ticks/s: STS3215 no-load speed at 7.4 V (~5.2 rad/s)
CURRENT_PER_TICK = 0.6  # Present_Current units (6.5 mA) per tick of tracking error
CURRENT_MAX = 300  # ~2 A, the STS3215 stall current
LOAD_PER_TICK = 4.0  # Present_Load units (0.1 % PWM) per tick of tracking error
MOVING_ERROR_TICKS = 0.5  # Moving = 1 while |goal - present| exceeds this
TICKS_PER_TURN = 4096

# Addresses a bus write must not change: the table's read-only registers, plus the documented
# read-only bytes the table does not name (64 reg-write flag, 67..68 target position; servos.md §2).
_READ_ONLY = bytearray(256)
for _reg in T.STS_CONTROL_TABLE.values():
    if not _reg.writable:
        _READ_ONLY[_reg.address : _reg.address + _reg.size] = b"\x01" * _reg.size
for _addr in (64, 67, 68):
    _READ_ONLY[_addr] = 1
_READ_ONLY = bytes(_READ_ONLY)

_NAMES = {name.lower(): name for name in T.STS_CONTROL_TABLE}

# EEPROM bytes (persisted while Lock is 0); the rest of 0..79 is RAM, reset by a power cycle.
_EEPROM = bytearray(256)
for _reg in T.STS_CONTROL_TABLE.values():
    if _reg.eeprom:
        _EEPROM[_reg.address : _reg.address + _reg.size] = b"\x01" * _reg.size
_EEPROM = bytes(_EEPROM)
_RAM_START, _RAM_END = 40, 80

_A = {name: reg.address for name, reg in T.STS_CONTROL_TABLE.items()}
_ID = _A["ID"]
_BAUD = _A["Baud_Rate"]
_RETURN_DELAY = _A["Return_Delay_Time"]
_STATUS_LEVEL = _A["Response_Status_Level"]
_MIN_POS = _A["Min_Position_Limit"]
_MAX_POS = _A["Max_Position_Limit"]
_HOMING = _A["Homing_Offset"]
_MODE = _A["Operating_Mode"]
_TORQUE = _A["Torque_Enable"]
_GOAL_POS = _A["Goal_Position"]
_GOAL_VEL = _A["Goal_Velocity"]
_TORQUE_LIMIT = _A["Torque_Limit"]
_PRESENT_POS = _A["Present_Position"]
_PRESENT_VEL = _A["Present_Velocity"]
_PRESENT_LOAD = _A["Present_Load"]
_STATUS = _A["Status"]
_MOVING = _A["Moving"]
_PRESENT_CURRENT = _A["Present_Current"]
_REG_WRITE_FLAG = 64
_TARGET_POS = 67
_TORQUE_SET_MIDDLE = 128  # Torque_Enable value: "current position becomes 2048"


def _sm16(value: float) -> int:
    """Signed -> sign-magnitude bit 15, saturating (physics must never raise)."""
    v = int(round(value))
    if v < 0:
        return min(-v, 0x7FFF) | 0x8000
    return min(v, 0x7FFF)


def _from_sm(raw: int, sign_bit: int) -> int:
    if raw & (1 << sign_bit):
        return -(raw & ((1 << sign_bit) - 1))
    return raw & ((1 << sign_bit) - 1)


class SimServo(BusServo):
    """One simulated STS3215: its control table memory and its physical state.

    ``registers`` is the raw control table (little-endian, sign-magnitude where the table says);
    mutate it directly only if you mean to bypass every side effect. :meth:`read` and :meth:`write`
    are thread-safe and bring the physics up to date first.
    """

    def __init__(self, sim: FeetechSimulator, servo_id: int, position: int, model_number: int = 777,
                 baudrate: int | None = None, return_delay: int = 0):
        super().__init__(sim)
        self._pos = float(position)  # actual (un-offset) position, ticks
        r = self.registers
        r[0], r[1] = 3, 10  # firmware 3.10
        r[3], r[4] = model_number & 0xFF, model_number >> 8
        r[_ID] = servo_id
        r[_BAUD] = T.BAUD_CODES[baudrate or sim.baudrate]
        # the simulated arm's servos: 0, as LeRobot writes it (the real turnaround is unverified,
        # servos.md section 1); a factory-fresh one: 250 (x2 us)
        r[_RETURN_DELAY] = return_delay
        r[_STATUS_LEVEL] = 1
        self._put(_MIN_POS, 2, 0)
        self._put(_MAX_POS, 2, 4095)
        self._put(_A["Max_Temperature_Limit"], 1, 70)
        self._put(_A["Max_Voltage_Limit"], 1, 140)
        self._put(_A["Min_Voltage_Limit"], 1, 40)
        self._put(_A["Max_Torque_Limit"], 2, 1000)
        self._put(_A["P_Coefficient"], 1, 32)
        self._put(_A["D_Coefficient"], 1, 32)
        self._put(_A["Protection_Current"], 2, 511)
        self._put(_A["Angular_Resolution"], 1, 1)
        self._put(_A["Protective_Torque"], 1, 20)
        self._put(_A["Protection_Time"], 1, 200)
        self._put(_A["Overload_Torque"], 1, 80)
        self._put(_TORQUE_LIMIT, 2, 1000)
        self._put(_A["Lock"], 1, 1)
        self._put(_A["Present_Voltage"], 1, 74)
        self._put(_A["Present_Temperature"], 1, 30)
        self._put(_A["Maximum_Acceleration"], 1, 254)
        self._put(_GOAL_POS, 2, _sm16(position))
        self._flash = bytearray(self.registers)  # what a power cycle restores (EEPROM bytes)
        self._update(self._t)

    def _power_on(self) -> None:
        """EEPROM back from flash; RAM at power-on defaults (torque off, Lock 1, goal = present,
        Torque_Limit = Max_Torque_Limit, no error) (caller holds the simulator lock)."""
        r = self.registers
        for addr in range(256):
            if _EEPROM[addr]:
                r[addr] = self._flash[addr]
        r[_RAM_START:_RAM_END] = bytes(_RAM_END - _RAM_START)
        self._torque_on_at = None
        self._pending = None
        self._put(_TORQUE_LIMIT, 2, self._get("Max_Torque_Limit"))
        self._put(_A["Lock"], 1, 1)
        self._put(_A["Present_Voltage"], 1, 74)
        self._put(_A["Present_Temperature"], 1, 30)
        self._put(_GOAL_POS, 2, _sm16(round(self._pos) - self._offset()))
        self._update(self._t)

    def _persist(self, addr: int, end: int, force: bool = False) -> None:
        """Copy the EEPROM bytes of ``addr..end`` to flash when Lock is 0 (or ``force``)."""
        if force or self.registers[_A["Lock"]] == 0:
            for i in range(addr, end):
                if _EEPROM[i]:
                    self._flash[i] = self.registers[i]

    # --- internal (caller holds the simulator lock) ---
    def _put(self, addr: int, size: int, raw: int) -> None:
        self.registers[addr : addr + size] = raw.to_bytes(size, "little")

    def _get(self, name: str) -> int:
        reg = T.STS_CONTROL_TABLE[name]
        raw = int.from_bytes(self.registers[reg.address : reg.address + reg.size], "little")
        bit = T.SIGN_BITS.get(name)
        return _from_sm(raw, bit) if bit is not None else raw

    def _set(self, name: str, value: int) -> None:
        reg = T.STS_CONTROL_TABLE[name]
        value = int(value)
        bit = T.SIGN_BITS.get(name)
        if bit is not None:
            raw = T.encode_sign_magnitude(value, bit)
        else:
            if not 0 <= value < 1 << (8 * reg.size):
                raise ValueError(f"{name}: value {value} does not fit in {reg.size} byte(s)")
            raw = value
        self._put(reg.address, reg.size, raw)
        if reg.address == _PRESENT_POS:
            self._pos = float(value + self._offset())
        self._side_effects(reg.address, reg.address + reg.size)
        self._persist(reg.address, reg.address + reg.size, force=True)  # set up "earlier": persisted

    def _bus_write(self, addr: int, data: bytes | bytearray) -> None:
        """A WRITE/SYNC_WRITE/ACTION payload: read-only bytes keep their value."""
        data = self._delay_torque(addr, data)
        end = min(addr + len(data), 256)
        r = self.registers
        if any(_READ_ONLY[addr:end]):
            for i in range(addr, end):
                if not _READ_ONLY[i]:
                    r[i] = data[i - addr]
        else:
            r[addr:end] = data[: end - addr]
        self._side_effects(addr, end)
        self._persist(addr, end)

    def _side_effects(self, addr: int, end: int) -> None:
        r = self.registers
        if addr <= _TORQUE < end and r[_TORQUE] == _TORQUE_SET_MIDDLE:
            offset = max(-2047, min(2047, round(self._pos) - 2048))
            self._put(_HOMING, 2, T.encode_sign_magnitude(offset, 11))
            r[_TORQUE] = 0
            self._persist(_HOMING, _HOMING + 2)

    def _actual(self, present: int) -> float:
        return float(present + self._offset())  # Present = Actual - Homing_Offset

    def _present_exact(self) -> float:
        return self._pos - self._offset()

    def _offset(self) -> int:
        r = self.registers
        return _from_sm(r[_HOMING] | r[_HOMING + 1] << 8, 11)

    def _update(self, now: float) -> None:
        """Advance the physics to ``now`` and refresh the Present_* registers."""
        self._torque_due(now)
        dt = now - self._t
        if dt < 0:
            dt = 0.0
        self._t = now
        r = self.registers
        offset = _from_sm(r[_HOMING] | r[_HOMING + 1] << 8, 11)
        pos = self._pos
        vel = 0.0
        err = 0.0
        target = None
        if r[_TORQUE] == 1:
            mode = r[_MODE]
            gv = _from_sm(r[_GOAL_VEL] | r[_GOAL_VEL + 1] << 8, 15)
            if mode == 0:
                goal = _from_sm(r[_GOAL_POS] | r[_GOAL_POS + 1] << 8, 15)
                lo = r[_MIN_POS] | r[_MIN_POS + 1] << 8
                hi = r[_MAX_POS] | r[_MAX_POS + 1] << 8
                if (lo or hi) and lo <= hi:  # 0/0 = multi-turn, no limits
                    goal = lo if goal < lo else hi if goal > hi else goal
                target = goal
                err = goal + offset - pos
                a = abs(err)
                if not self.frozen and a > 0.0:
                    vmax = min(VELOCITY_MAX_TPS, abs(gv)) if gv else VELOCITY_MAX_TPS
                    if dt > 0.0:
                        a = approach(a, dt, vmax, TAU_S)
                        err = math.copysign(a, err)
                        pos = goal + offset - err
                    if a > MOVING_ERROR_TICKS:
                        vel = math.copysign(min(a / TAU_S, vmax), err)
            elif mode == 1 and not self.frozen:
                vel = max(-VELOCITY_MAX_TPS, min(VELOCITY_MAX_TPS, float(gv)))
                pos = (pos + vel * dt) % TICKS_PER_TURN
                err = vel * TAU_S  # the effort a real servo spends to hold that speed
        elif self._hand is not None:  # torque off: a hand turns the horn
            new = self._hand_step(pos, dt)
            vel = (new - pos) / dt if dt > 0.0 else 0.0
            pos = new
        self._pos = pos
        a = abs(err)
        present = round(pos) - offset
        raw = min(-present, 0x7FFF) | 0x8000 if present < 0 else min(present, 0x7FFF)
        r[_PRESENT_POS] = raw & 0xFF
        r[_PRESENT_POS + 1] = raw >> 8
        raw = _sm16(vel)
        r[_PRESENT_VEL] = raw & 0xFF
        r[_PRESENT_VEL + 1] = raw >> 8
        if r[_TORQUE] == 1:
            limit = r[_TORQUE_LIMIT] | r[_TORQUE_LIMIT + 1] << 8
            load = min(int(a * LOAD_PER_TICK), limit, 1000)
            if err < 0:
                load |= 0x400
            current = min(int(a * CURRENT_PER_TICK) + 2, CURRENT_MAX)  # +2: holding current
        else:
            load = current = 0
        r[_PRESENT_LOAD] = load & 0xFF
        r[_PRESENT_LOAD + 1] = load >> 8
        r[_PRESENT_CURRENT] = current & 0xFF
        r[_PRESENT_CURRENT + 1] = current >> 8
        r[_MOVING] = 1 if a > MOVING_ERROR_TICKS else 0
        if target is not None:
            raw = _sm16(target)
            r[_TARGET_POS] = raw & 0xFF
            r[_TARGET_POS + 1] = raw >> 8

    def _status(self, data: bytes | bytearray = b"") -> bytes:
        """This servo's status packet ``FF FF ID LEN ERR data CHK``."""
        sid = self.registers[_ID]
        err = self.registers[_STATUS] & 0x7F
        length = len(data) + 2
        chk = ~(sid + length + err + sum(data)) & 0xFF
        if self.corrupt:
            chk ^= 0xFF
        return self._deliver(b"\xff\xff" + bytes((sid, length, err)) + bytes(data) + bytes((chk,)))


class FeetechSimulator(BusSimulator):
    """A bus of simulated STS3215 servos on a pty; see the module docstring for the model.

    ``start()`` creates the pty (and ``link``, and the ``control`` socket) and the serving thread,
    and returns once clients may open :attr:`port`. ``stop()`` is idempotent. With
    ``emulate_baud`` each reply leaves no earlier than the request and reply would have taken on a
    real wire at ``baudrate`` (10 bits per byte, plus each servo's Return_Delay_Time).
    """

    vendor = "feetech"
    BAUD_CODES = T.BAUD_CODES
    FACTORY_BAUD = 1_000_000  # STS3215: Baud_Rate code 0 (servos.md section 2)
    DEFAULT_MODEL = "sts3215"
    ID_ADDRESS = _ID
    BAUD_ADDRESS = _BAUD
    RETURN_DELAY_ADDRESS = _RETURN_DELAY
    TORQUE_ADDRESS = _TORQUE
    MAX_ID = 253

    def __init__(
        self,
        servo_ids: Iterable[int] = (1,),
        baudrate: int = 1_000_000,
        link: str | os.PathLike | None = None,
        control: str | os.PathLike | None = None,
        emulate_baud: bool = False,
        initial_positions: dict[int, int] | None = None,
    ):
        ids = list(servo_ids)
        for sid in ids:
            if not 0 <= sid <= 253:
                raise SimulatorError(f"servo id {sid} is not a valid Feetech id (0..253)")
        if len(set(ids)) != len(ids):
            raise SimulatorError(f"duplicate servo ids in {ids}")
        super().__init__(baudrate, link, control, emulate_baud)
        positions = initial_positions or {}
        self._servos: dict[int, SimServo] = {
            sid: SimServo(self, sid, int(positions.get(sid, 2048))) for sid in ids
        }

    @classmethod
    def from_profile(
        cls,
        profile: Profile,
        link: str | os.PathLike | None = None,
        control: str | os.PathLike | None = None,
        emulate_baud: bool = False,
    ) -> FeetechSimulator:
        """One servo per joint with an ``id``, resting at its joint zero (calibration.offset)."""
        joints, baud = cls._profile_joints(profile)
        sim = cls(
            servo_ids=[j.id for j in joints],
            baudrate=baud,
            link=link,
            control=control,
            emulate_baud=emulate_baud,
            initial_positions={j.id: j.calibration.offset for j in joints},
        )
        for j in joints:
            model = T.MODEL_NUMBERS.get((j.model or "sts3215").lower(), 777)
            servo = sim._servos[j.id]
            servo.registers[3], servo.registers[4] = model & 0xFF, model >> 8
            servo._persist(3, 5, force=True)
        return sim

    # --- vendor hooks (see BusSimulator) ---
    def _register_name(self, servo: SimServo, register: object) -> str:
        name = _NAMES.get(str(register if register is not None else "").lower())
        if name is None:
            raise SimulatorError(f"servo {servo.id}: unknown register {register!r}")
        return name

    def _snapshot(self, servo: SimServo) -> dict:
        return {name.lower(): servo._get(name) for name in T.STS_CONTROL_TABLE}

    def _error_bits(self, servo: SimServo) -> int:
        return servo.registers[_STATUS]

    def _set_error_bits(self, servo: SimServo, bits: int) -> None:
        # Status (65) is what every status packet's ERR byte reports.
        if not 0 < bits <= 0x7F:
            raise SimulatorError(f"error_bits: bits {bits} must be in 1..127")
        servo.registers[_STATUS] |= bits

    def _clear_error_bits(self, servo: SimServo) -> None:
        servo.registers[_STATUS] = 0

    def _new_servo(self, servo_id: int, model: str, baudrate: int, position: int) -> SimServo:
        number = T.MODEL_NUMBERS.get(model.lower())
        if number is None:
            raise SimulatorError(f"unknown model {model!r} (known: {', '.join(T.MODEL_NUMBERS)})")
        return SimServo(self, servo_id, position, number, baudrate=baudrate, return_delay=250)

    def _power_cycle(self, servo: SimServo) -> None:
        servo._power_on()

    # --- the bus ---
    def _parse(self, buf: bytearray, now: float) -> list[Reply]:
        """Consume every complete packet in ``buf``; return (deadline, reply bytes) per packet
        that got an answer. Leaves an incomplete packet (or a trailing FF) in ``buf``."""
        sim_now = self.clock()
        replies: list[Reply] = []
        n = len(buf)
        i = 0
        while True:
            start = buf.find(b"\xff\xff", i)
            if start < 0:
                i = n - 1 if n and buf[-1] == 0xFF else n
                break
            if n - start < 4:
                i = start
                break
            sid = buf[start + 2]
            length = buf[start + 3]
            if sid == 0xFF:  # FF FF FF: the header starts one byte later
                i = start + 1
                continue
            if length < 2 or length > 250:
                i = start + 2
                continue
            end = start + length + 4
            if end > n:
                i = start
                break
            if (~sum(buf[start + 2 : end - 1])) & 0xFF != buf[end - 1]:
                log.debug("ignored packet with a bad checksum: %s", buf[start:end].hex(" "))
                i = start + 2
                continue
            reply = self._dispatch(sid, buf[start + 4], bytes(buf[start + 5 : end - 1]), end - start,
                                   now, sim_now)
            if reply is not None:
                replies.append(reply)
            i = end
        if i:
            del buf[:i]
        return replies

    def _dispatch(self, sid: int, inst: int, params: bytes, req_len: int, now: float, sim_now: float):
        """Execute one valid instruction packet. Returns (deadline, reply) or None.
        ``now``: wire clock (monotonic); ``sim_now``: physics clock (:attr:`clock`)."""
        out: list[bytes] = []
        with self._lock:
            if self.unplugged:
                return None
            servos = self._servos
            code = self._baud_code
            broadcast = sid == T.BROADCAST_ID
            if broadcast:
                targets = [s for s in servos.values() if code is None or s.registers[_BAUD] == code]
            else:
                s = servos.get(sid)
                if s is None or (code is not None and s.registers[_BAUD] != code):
                    return None  # not on this bus (or deaf at this baud): silence
                targets = [s]

            if inst == T.INST_READ:
                if not broadcast and len(params) == 2:
                    addr, ln = params
                    if ln and addr + ln <= 256:
                        s = targets[0]
                        s._update(sim_now)
                        out.append(s._status(s.registers[addr : addr + ln]))
            elif inst == T.INST_SYNC_READ:
                if len(params) >= 2:
                    addr, ln = params[0], params[1]
                    if ln and addr + ln <= 256:
                        targets = []
                        for tid in params[2:]:  # replies in request order
                            s = servos.get(tid)
                            if s is None or (code is not None and s.registers[_BAUD] != code):
                                continue
                            s._update(sim_now)
                            targets.append(s)
                            out.append(s._status(s.registers[addr : addr + ln]))
            elif inst == T.INST_SYNC_WRITE:
                if len(params) >= 2:
                    addr, ln = params[0], params[1]
                    step = ln + 1
                    for k in range(2, len(params) - ln, step):
                        s = servos.get(params[k])
                        if s is None or (code is not None and s.registers[_BAUD] != code):
                            continue
                        old = s.registers[_ID]
                        s._update(sim_now)
                        s._bus_write(addr, params[k + 1 : k + step])
                        self._rekey(s, old)
                return self._no_reply(req_len, now)
            elif inst == T.INST_PING:
                out = [s._status() for s in targets]  # a broadcast PING is answered by all
            elif inst in (T.INST_WRITE, T.INST_REG_WRITE, T.INST_ACTION):
                if inst == T.INST_ACTION:
                    for s in targets:
                        if s._pending is not None:
                            s._update(sim_now)
                            old = s.registers[_ID]
                            s._bus_write(*s._pending)
                            s._pending = None
                            s.registers[_REG_WRITE_FLAG] = 0
                            self._rekey(s, old)
                elif len(params) >= 2:
                    addr, data = params[0], params[1:]
                    for s in targets:
                        s._update(sim_now)
                        if inst == T.INST_WRITE:
                            old = s.registers[_ID]
                            s._bus_write(addr, data)
                            self._rekey(s, old)
                        else:
                            s._pending = (addr, data)
                            s.registers[_REG_WRITE_FLAG] = 1
                else:
                    return None
                if broadcast:
                    return self._no_reply(req_len, now)
                targets = [s for s in targets if s.registers[_STATUS_LEVEL]]
                out = [s._status() for s in targets]
            else:
                return None  # unknown instruction: a real servo stays silent
            if out and any(s.silent for s in targets):
                out = [p for p, s in zip(out, targets) if not s.silent]
                targets = [s for s in targets if not s.silent]
            delay_s = self._turnaround_s(targets)
        return self._reply(out, req_len, now, delay_s)

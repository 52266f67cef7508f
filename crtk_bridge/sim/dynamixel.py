"""Dynamixel X-series bus (Protocol 2.0) simulated at the wire level on a pseudo-terminal.

:class:`DynamixelSimulator` answers the real Protocol 2.0 packets ``dynamixel_sdk`` sends, byte
for byte (shared/reference/servos.md section 5): header ``FF FF FD 00``, CRC-16 (poly 0x8005),
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
- torque off: the joint stays where it is (no gravity). Present_Current (Present_Load on the
  XL430) grows with the tracking error; Moving is 1 while the servo moves.

Bus behaviour: broadcast id 0xFE (no reply, except PING and the sync/bulk reads), Status_Return_
Level (0 ping only, 1 + reads, 2 all), CRC errors ignored, garbage skipped, a half-received packet
dropped after ``FRAME_TIMEOUT_S`` of silence, unknown ids silent. Status ERR byte: bit 7 (Alert)
while Hardware_Error_Status (70) is nonzero; error 7 (access) for a write to a read-only address
or to EEPROM (< 64) with torque on, and nothing is written.

Faults (control socket or :meth:`DynamixelSimulator.set_fault`), the same kinds as the STS
simulator: ``silent`` (the servo receives but never replies; in a Fast Sync Read the reply stops
before its slot, as the following servos wait for it), ``corrupt`` (its replies carry a bad CRC),
``error_bits`` (OR bits into Hardware_Error_Status: a latched hardware error; if they are in the
Shutdown mask (63) torque goes off; only a REBOOT clears it, so ``clear_faults`` does not),
``freeze`` (the joint stops moving), and ``unplug`` of the whole bus. A REBOOT restores the RAM
defaults (torque off, goal = present position, error cleared) and leaves the servo deaf for
``REBOOT_S``.
"""

from __future__ import annotations

import enum
import logging
import math
import os
import select
import threading
import time
from collections.abc import Iterable
from pathlib import Path

from ..backends.dynamixel import tables as T
from ..profile import Profile
from . import SimulatorError
from .control import ControlServer
from .pty import PtyPort

log = logging.getLogger(__name__)

TAU_S = 0.030  # first-order tracking time constant
TICKS_PER_S_PER_RAW_VEL = 0.229 * 4096 / 60  # one Goal_Velocity unit in ticks/s
TICKS_PER_S_PER_MA = 12.0  # unloaded speed per mA in current mode (~0.02 rad/s per mA)
CURRENT_MA_PER_TICK = 0.8  # Present_Current (mA) per tick of tracking error in position modes
LOAD_PER_TICK = 4.0  # XL430 Present_Load (0.1 %) per tick of tracking error
HOLDING_MA = 5.0
FRAME_TIMEOUT_S = 0.010
REBOOT_S = 0.05  # deaf after a REBOOT
BITS_PER_BYTE = 10
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


class FaultKind(str, enum.Enum):
    SILENT = "silent"
    CORRUPT = "corrupt"
    ERROR_BITS = "error_bits"
    FREEZE = "freeze"


_A = {name: reg.address for name, reg in T.CONTROL_TABLES["xm430-w350"].items()}
_TORQUE = _A["Torque_Enable"]
_MODE = _A["Operating_Mode"]
_HW_ERROR = _A["Hardware_Error_Status"]
_STATUS_LEVEL = _A["Status_Return_Level"]
_RETURN_DELAY = _A["Return_Delay_Time"]
_BAUD = _A["Baud_Rate"]
_ID = _A["ID"]
_SHUTDOWN = _A["Shutdown"]


class SimServo:
    """One simulated X-series servo: control table memory and physical state.

    :meth:`read` / :meth:`write` (by register name) are thread-safe and update the physics first.
    """

    def __init__(self, sim: DynamixelSimulator, servo_id: int, model: str, position: int):
        self._sim = sim
        self.model = model
        self.table = T.CONTROL_TABLES[model]
        self._writable = bytearray(256)
        for reg in self.table.values():
            if reg.writable:
                self._writable[reg.address: reg.address + reg.size] = b"\x01" * reg.size
        self.registers = bytearray(256)
        self.silent = self.corrupt = self.frozen = False
        self.deaf_until = 0.0
        self._pending: tuple[int, bytes] | None = None
        self._pos = float(position)
        self._vel = 0.0
        self._err_ticks = 0.0  # tracking error (ticks), drives Present_Current / Present_Load
        self._t = sim.clock()
        self._eeprom_defaults(servo_id)
        self._ram_defaults()

    # --- defaults ---
    def _put(self, name: str, value: int) -> None:
        reg = self.table[name]
        raw = T.to_raw(value, reg.size) if reg.signed else int(value)
        self.registers[reg.address: reg.address + reg.size] = raw.to_bytes(reg.size, "little")

    def _get(self, name: str) -> int:
        reg = self.table[name]
        raw = int.from_bytes(self.registers[reg.address: reg.address + reg.size], "little")
        return T.to_signed(raw, reg.size) if reg.signed else raw

    def _eeprom_defaults(self, servo_id: int) -> None:
        m = self.model
        self._put("Model_Number", T.MODEL_NUMBERS[m])
        self._put("Firmware_Version", FIRMWARE)
        self._put("ID", servo_id)
        self._put("Baud_Rate", T.BAUD_CODES.get(self._sim.baudrate, 1))
        self._put("Return_Delay_Time", 250)
        self._put("Operating_Mode", int(T.OperatingMode.POSITION))
        self._put("Protocol_Type", 2)
        self._put("Moving_Threshold", 10)
        self._put("Temperature_Limit", 70 if m == "xl330-m288" else 80)
        self._put("Max_Voltage_Limit", 70 if m == "xl330-m288" else 140)
        self._put("Min_Voltage_Limit", 35 if m == "xl330-m288" else 60)
        self._put("PWM_Limit", 885)
        if "Current_Limit" in self.table:
            self._put("Current_Limit", T.CURRENT_LIMIT_DEFAULT[m])
        self._put("Velocity_Limit", T.VELOCITY_LIMIT_DEFAULT[m])
        self._put("Max_Position_Limit", 4095)
        self._put("Min_Position_Limit", 0)
        self._put("Shutdown", 53 if m == "xl330-m288" else 52)

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
        self._put("Present_Input_Voltage", 50 if self.model == "xl330-m288" else 120)
        self._put("Present_Temperature", 30)
        self._vel = 0.0
        self._put("Goal_Position", round(self._pos) + self._get("Homing_Offset"))
        self._refresh(0.0)

    # --- public, thread-safe ---
    @property
    def id(self) -> int:
        return self.registers[_ID]

    def read(self, name: str) -> int:
        """Decoded value of register ``name``. Raises KeyError."""
        with self._sim._lock:
            self._update(self._sim.clock())
            return self._get(name)

    def write(self, name: str, value: int) -> None:
        """Set register ``name`` by hand (read-only ones included; no access checks).
        Present_Position moves the joint. Raises KeyError / ValueError."""
        with self._sim._lock:
            now = self._sim.clock()
            self._update(now)
            old = self.id
            self._put(name, value)
            if name == "Present_Position":
                self._pos = float(value - self._get("Homing_Offset"))
            self._update(now)
            self._sim._rekey(self, old)

    # --- bus side (caller holds the lock) ---
    def _bus_write(self, addr: int, data: bytes) -> int:
        """A WRITE payload. Returns the status error number (0 = written)."""
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
        return pkt

    def _update(self, now: float) -> None:
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
            a = abs(err)
            knee = vmax * TAU_S
            if a > knee:
                t1 = (a - knee) / vmax
                a = a - vmax * dt if dt <= t1 else knee * math.exp(-(dt - t1) / TAU_S)
            else:
                a *= math.exp(-dt / TAU_S)
            if a < 1e-3:
                a = 0.0
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


class DynamixelSimulator:
    """A bus of simulated X-series servos on a pty; see the module docstring for the model.

    ``servos``: id -> model name ("xl330-m288", "xl430-w250", "xm430-w350"). ``start()`` creates
    the pty (``link``, ``control`` socket) and the serving thread; ``stop()`` is idempotent. With
    ``emulate_baud`` each reply leaves no earlier than request and reply would take on a real wire
    at ``baudrate`` (10 bits per byte) plus each replying servo's Return_Delay_Time.
    """

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
        if baudrate <= 0:
            raise SimulatorError(f"baudrate {baudrate} must be > 0")
        self.baudrate = int(baudrate)
        self.emulate_baud = bool(emulate_baud)
        self._byte_s = BITS_PER_BYTE / self.baudrate
        self._baud_code = T.BAUD_CODES.get(self.baudrate)
        self._lock = threading.Lock()
        self.clock = time.monotonic  # the physics clock; tests may swap in a fake one before start()
        positions = initial_positions or {}
        self._servos: dict[int, SimServo] = {
            sid: SimServo(self, sid, model, int(positions.get(sid, 2048))) for sid, model in servos.items()
        }
        self.unplugged = False
        self._pty = PtyPort(link)
        self._control = ControlServer(control, self.control) if control is not None else None
        self.control_path = Path(control) if control is not None else None
        self._thread: threading.Thread | None = None
        self._wake_r = self._wake_w = -1
        self._stopping = False
        self._bus_free_at = 0.0
        #: bytes received and sent on the wire since start (for bench/)
        self.rx_bytes = 0
        self.tx_bytes = 0

    @classmethod
    def from_profile(cls, profile: Profile, link=None, control=None, emulate_baud: bool = False
                     ) -> DynamixelSimulator:
        """One servo per joint with an ``id``, of the joint's ``model``, resting at its joint zero."""
        if profile.backend_type != "dynamixel":
            raise SimulatorError(f"profile {profile.name!r}: backend.type is "
                                 f"{profile.backend_type!r}, not 'dynamixel'")
        joints = [j for j in profile.joints if j.id is not None]
        if not joints:
            raise SimulatorError(f"profile {profile.name!r}: no joint has a bus id")
        baud = profile.backend.get("baudrate", 1_000_000)
        if not isinstance(baud, int) or isinstance(baud, bool):
            raise SimulatorError(f"profile {profile.name!r}: backend.baudrate must be an integer")
        servos = {}
        for j in joints:
            model = (j.model or "xm430-w350").lower()
            if model not in T.CONTROL_TABLES:
                raise SimulatorError(f"profile {profile.name!r}: joint {j.name!r}: unknown model "
                                     f"{j.model!r} (known: {', '.join(T.CONTROL_TABLES)})")
            servos[j.id] = model
        return cls(servos, baudrate=baud, link=link, control=control, emulate_baud=emulate_baud,
                   initial_positions={j.id: j.calibration.offset for j in joints})

    # --- lifecycle ---
    @property
    def port(self) -> str:
        return self._pty.path

    @property
    def pty_path(self) -> str | None:
        return self._pty.slave_path

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        if self._thread is not None:
            return
        self._pty.open()
        try:
            if self._control is not None:
                self._control.start()
        except BaseException:
            self._pty.close()
            raise
        self._wake_r, self._wake_w = os.pipe()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="sim-dynamixel", daemon=True)
        self._thread.start()
        log.info("dynamixel simulator: %d servo(s) %s on %s", len(self._servos), self.ids, self.port)

    def stop(self) -> None:
        if self._thread is None:
            return
        self._stopping = True
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass
        self._thread.join()
        self._thread = None
        os.close(self._wake_r)
        os.close(self._wake_w)
        self._wake_r = self._wake_w = -1
        if self._control is not None:
            self._control.stop()
        self._pty.close()

    def __enter__(self) -> DynamixelSimulator:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # --- state access ---
    @property
    def ids(self) -> list[int]:
        with self._lock:
            return sorted(self._servos)

    def servo(self, servo_id: int) -> SimServo:
        try:
            return self._servos[servo_id]
        except KeyError:
            raise SimulatorError(f"no simulated servo with id {servo_id} (ids: {sorted(self._servos)})") from None

    def set_fault(self, servo_id: int, kind: str | FaultKind, bits: int = 0) -> None:
        """Inject a fault into one servo (see the module docstring). Raises SimulatorError."""
        with self._lock:
            servo = self.servo(servo_id)
            try:
                kind = FaultKind(kind)
            except ValueError:
                raise SimulatorError(f"unknown fault kind {kind!r}; valid: "
                                     f"{', '.join(k.value for k in FaultKind)}") from None
            servo._update(self.clock())
            if kind is FaultKind.SILENT:
                servo.silent = True
            elif kind is FaultKind.CORRUPT:
                servo.corrupt = True
            elif kind is FaultKind.FREEZE:
                servo.frozen = True
            else:
                if not 0 < bits <= 0xFF:
                    raise SimulatorError(f"error_bits: bits {bits} must be in 1..255 "
                                         f"(Hardware_Error_Status bits)")
                servo.registers[_HW_ERROR] |= bits
                servo._update(self.clock())  # shutdown: torque off now

    def clear_faults(self, servo_id: int | None = None) -> None:
        """Clear injected communication faults and freeze (of one servo, or all) and the
        unplugged state. A latched hardware error (``error_bits``) stays until a REBOOT."""
        with self._lock:
            servos = [self.servo(servo_id)] if servo_id is not None else list(self._servos.values())
            now = self.clock()
            for s in servos:
                s._update(now)
                s.silent = s.corrupt = s.frozen = False
            if servo_id is None:
                self.unplugged = False

    def set_unplugged(self, on: bool) -> None:
        with self._lock:
            self.unplugged = bool(on)

    def _rekey(self, servo: SimServo, old_id: int) -> None:
        new_id = servo.registers[_ID]
        if new_id == old_id:
            return
        if new_id in self._servos or new_id > T.MAX_ID:
            log.warning("servo %d: refusing id change to %d (taken or invalid)", old_id, new_id)
            servo.registers[_ID] = old_id
            return
        del self._servos[old_id]
        self._servos[new_id] = servo

    # --- control socket ---
    def control(self, request: dict) -> dict:
        """Answer one control request (dict in, dict out): dump, read, write, fault,
        clear_faults, unplug -- as the STS simulator. Never raises for a bad request."""
        cmd = request.get("cmd")
        try:
            if cmd == "dump":
                return {"ok": True, **self._dump()}
            if cmd in ("read", "write"):
                servo = self._control_servo(request)
                names = {n.lower(): n for n in servo.table}
                name = names.get(str(request.get("register", "")).lower())
                if name is None:
                    return {"ok": False, "error": f"servo {servo.id}: unknown register "
                            f"{request.get('register')!r} on a {servo.model}"}
                if cmd == "read":
                    return {"ok": True, "value": servo.read(name)}
                value = request.get("value")
                if not isinstance(value, int) or isinstance(value, bool):
                    return {"ok": False, "error": f"{name}: value must be an integer, got {value!r}"}
                try:
                    servo.write(name, value)
                except ValueError as exc:
                    return {"ok": False, "error": f"servo {servo.id}: {name}: {exc}"}
                return {"ok": True}
            if cmd == "fault":
                servo = self._control_servo(request)
                bits = request.get("bits", 0)
                if not isinstance(bits, int) or isinstance(bits, bool):
                    return {"ok": False, "error": f"'bits' must be an integer, got {bits!r}"}
                self.set_fault(servo.id, str(request.get("kind")), bits)
                return {"ok": True}
            if cmd == "clear_faults":
                sid = request.get("id")
                self.clear_faults(None if sid is None else self._control_servo(request).id)
                return {"ok": True}
            if cmd == "unplug":
                self.set_unplugged(bool(request.get("on", True)))
                return {"ok": True}
        except SimulatorError as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": False, "error": f"unknown cmd {cmd!r}; valid: dump, read, write, fault, "
                "clear_faults, unplug"}

    def _control_servo(self, request: dict) -> SimServo:
        sid = request.get("id")
        if not isinstance(sid, int) or isinstance(sid, bool):
            raise SimulatorError(f"'id' must be an integer servo id, got {sid!r}")
        return self.servo(sid)

    def _dump(self) -> dict:
        with self._lock:
            now = self.clock()
            servos, faults = {}, {}
            for sid in sorted(self._servos):
                s = self._servos[sid]
                s._update(now)
                servos[str(sid)] = {"model": s.model, **{n.lower(): s._get(n) for n in s.table}}
                f = [k.value for k, on in ((FaultKind.SILENT, s.silent), (FaultKind.CORRUPT, s.corrupt),
                                           (FaultKind.FREEZE, s.frozen)) if on]
                if s.registers[_HW_ERROR]:
                    f.append(FaultKind.ERROR_BITS.value)
                if f:
                    faults[str(sid)] = f
            return {"servos": servos, "faults": faults, "unplugged": self.unplugged,
                    "baudrate": self.baudrate}

    # --- the bus ---
    def _run(self) -> None:
        master = self._pty.master_fd
        assert master is not None
        poller = select.poll()
        poller.register(master, select.POLLIN)
        poller.register(self._wake_r, select.POLLIN)
        buf = bytearray()
        last_rx = 0.0
        try:
            while True:
                poller.poll()
                if self._stopping:
                    return
                try:
                    data = os.read(master, 4096)
                except BlockingIOError:
                    continue
                now = time.monotonic()
                if buf and now - last_rx > FRAME_TIMEOUT_S:
                    buf.clear()
                last_rx = now
                self.rx_bytes += len(data)
                buf += data
                for deadline, reply in self._parse(buf, now):
                    if self.emulate_baud:
                        delay = deadline - time.monotonic()
                        if delay > 0:
                            time.sleep(delay)
                    self.tx_bytes += len(reply)
                    try:
                        os.write(master, reply)
                    except BlockingIOError:
                        log.debug("client not reading; dropped %d reply bytes", len(reply))
        except Exception:
            log.exception("dynamixel simulator thread died")
            raise

    def _parse(self, buf: bytearray, now: float) -> list[tuple[float, bytes]]:
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
            delay_s = sum(s.registers[_RETURN_DELAY] * 2e-6 for s in repliers) if self.emulate_baud else 0.0
        if not out:
            return self._no_reply(req_len, now)
        reply = b"".join(out)
        if not self.emulate_baud:
            return (0.0, reply)
        t0 = max(now, self._bus_free_at)
        deadline = t0 + (req_len + len(reply)) * self._byte_s + delay_s
        self._bus_free_at = deadline
        return (deadline, reply)

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

    def _no_reply(self, req_len: int, now: float) -> None:
        if self.emulate_baud:
            self._bus_free_at = max(now, self._bus_free_at) + req_len * self._byte_s
        return None

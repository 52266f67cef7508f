"""Robotiq 2F-85 / 2F-140 adaptive gripper over Modbus RTU: one gripper per bus, one joint.

The link: a USB-RS485 adapter at 115200 8N1 (``backend.port``: a device path, a
``/dev/serial/by-id`` link, ``{serial_number: ...}``), or the UR tool flange's RS-485 reachable as
a TCP socket carrying the raw RTU bytes (``backend.port: socket://HOST:54321``, the tool
communication URCap's port). Frames are pymodbus's (its RTU framer and the PDUs of function 4
and 16, CRC included); the transaction around them is this module's, because the control cycle
must never wait longer than one transaction: pymodbus's sync client polls the port with 1 ms
sleeps until the input stops growing, retries on its own and takes pyserial's ``socket://``
``in_waiting`` (0 or 1) for a byte count. Here a request goes out, the reply (its length known
from the function code) is awaited in ``select`` until the wire time of both frames plus
``timeout_ms``, and a missing reply is a transient ``bus_timeout`` Fault that core counts
(``safety.bus_errors_max`` in a row before FAULT), as on the serial servo buses.

The joint (``finger``): the finger opening in metres, 0 = closed (the fingers touch) to the
model's stroke (0.085 m on a 2F-85, 0.140 m on a 2F-140) = open; velocity is not measured. The
gripper's position is 0-255 (0 = open); ``opening = stroke * (closed - gPO) / (closed - open)``
with ``open`` and ``closed`` the gripper's OWN readings at its stroke ends, taken at activation
(the fingers run their whole stroke while activating: the smallest and largest gPO read during it)
unless the joint's ``calibration: {open: N, closed: M}`` gives them. A measured span below
``tables.CALIBRATION_MIN_SHARE`` of the nominal one fails the enable naming it (something blocked
the fingers; a scale from it would be wrong by far); a re-activation whose ends differ by more
than 2 counts from those in use is a ``device_warning`` saying both. A gripper found already
activated (the daemon restarted beside a powered gripper) is not activated again (below), so
nothing is measured: without a profile ``calibration`` the opening uses the nominal ends
``tables.NOMINAL_OPEN`` / ``NOMINAL_CLOSED`` (13 / 230, the simulator's; not the manual's), off
by a few tenths of a mm per count on another gripper, said once at enable in a
``device_warning`` naming the joint and ``joints[0].calibration``. A position request is the
same map inverted, rounded and clamped to 0-255 only (the profile's limits are core's).

One cycle is at most two transactions: ``read`` = ONE function 4 read of the three input words
(0x07D0: status, fault, position request echo, position, finger current); ``write`` = ONE
function 16 write of the three output words (0x03E8: action request, position request, speed,
force), and only when the request changed (the gripper keeps its last one). At 115200 baud the
pair is 42 bytes, ~3.6 ms of wire time: a loop up to ~200 Hz, ``loop.rate_hz`` 100 by default.

Lifecycle (steps, one transaction at most per cycle, waiting on the gripper across cycles):

* ENABLE = activation when the gripper is not activated (or after a fault): reset (rACT 0, wait
  for gACT 0), activate (rACT 1, then one status read per cycle until gSTA = 3, activation
  completed; the transition's time limit is ``activation_timeout_s``), then go (rGTO 1 with the
  position request = where the fingers are: they hold). An activated gripper without a fault is
  not re-activated (activation runs the fingers over their whole stroke: a held object would
  fall): ENABLE is then only the go.
* DISABLE = rGTO 0 (rACT stays 1), confirmed by gGTO 0: the gripper stops acting on its position
  request; the fingers stop where they are. The manual does not say the grip force is kept with
  rGTO 0: a held object is not promised held once DISABLED (the 2F's fingers are not back-driven
  easily, so in practice it usually stays), and the next ENABLE holds the fingers where they are
  then, without re-activating; on an object (gOBJ contact at the disable, the fingers still
  there) it sends the position request that held it, not their position (that would drop the
  grip force), and core's hold there writes nothing over it until a command goes elsewhere. During an activation (gSTA 1, or an activation started and not
  seen complete: an ENABLE abandoned by a disable, a pause, its time limit or a composite's
  rollback) rGTO 0 stops nothing: DISABLE is then rACT 0 (reset), confirmed by gACT 0 and the
  position unchanged across reads (the fingers stopped); the next ENABLE activates anew.
* FAULT_RESET (leaving FAULT) = rACT 0 (a reset clears the gripper's faults), then ENABLE
  activates again (rACT 0 -> 1, manual 4.4.3: major faults need it) -- only for the gripper's
  own reason: a major gFLT, or its activation lost (gSTA dropped) or abandoned. After a FAULT of
  the robot's (a UR's tracking error, an invalid command, the link dropped and back) an activated
  gripper without a major fault is not reset: ENABLE is only the go (a held object stays held).

Device status: ``gFLT`` (tables.FAULTS, from the manual): a major fault is a FAULT naming its
code and meaning (``gripper_fault``); minor ones (overheating, a 1 s gap in communication) are
warnings (``device_warning``) and priority ones (an action refused before activation) too. An
ENABLED gripper that leaves its activated state by itself (gSTA drops) is a FAULT. The link gone
(an OS error on the port, the TCP connection closed) is a non-transient ``port_lost`` FAULT naming
the port, and a background thread reopens it every 0.5 s; the next read after it did reports the
fault cleared, and ``enable`` decides from the status read then (activated, no major fault: only
the go; else reset and activation).

Commands: position (``servo_jp``, ``interpolate_jp``, ``move_jp``, ``hold``): each cycle's
position setpoint from core's trajectory goes out as the position request with the joint's
``speed`` and ``force`` settings (the gripper runs its own motion towards each request at that
speed, stopping on an object with that force). Effort commands (``servo_jf``) are not offered:
CRTK's effort setpoint is an effort held now in either direction, in free space; the 2F's force
setting is a limit on the grip force the fingers apply on contact while moving to a position,
not an effort it can hold, so the joint declares no effort capability and core refuses
``servo_jf`` naming it. ``free`` is not offered either (the fingers cannot be let go limp).
``measured_js``: position, and an effort ESTIMATE = finger current (about 10 mA per unit) x
``effort_per_amp`` N/A, negative while the fingers push towards closing (the joint's positive
direction is opening), when the joint gives ``effort_per_amp``.

Grasp state: gOBJ (fingers stopped on an object while closing or opening) is a ``device_status``
status event when it changes (``register`` gOBJ, ``value`` the code), naming the opening at which
the fingers stopped; an object on the fingers is not a FAULT (the opening stays within
``safety.tracking_error_max`` of a closed-gripper setpoint on a gripper's metre scale).
"""

from __future__ import annotations

import os
import select
import socket
import threading
import time
from typing import Annotated, Any, ClassVar

import msgspec
import numpy as np
import serial
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.register_message import ReadInputRegistersRequest, WriteMultipleRegistersRequest

from ...core.actuator import (
    Actuator,
    ActuatorInfo,
    Capabilities,
    DeviceStatus,
    Fault,
    JointCommand,
    JointFeedback,
    Lifecycle,
    SimWiring,
    Steps,
    Traits,
    background_thread,
)
from ...errors import BackendError, ProfileError
from ...profile import Profile, backend_config, joint_keys
from ..port_errors import open_error_reason
from ..ports import resolve_port
from ..servo_keys import PortMatch
from . import tables as T

Byte = Annotated[int, msgspec.Meta(ge=0, le=255)]


class Config(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """The ``backend:`` section of a profile with ``type: robotiq``."""

    #: a serial device (a USB-RS485 adapter), a /dev/serial/by-id link, {serial_number: ...}, or
    #: socket://HOST:PORT (the UR tool flange's RS-485 as a TCP socket, port 54321)
    port: str | PortMatch
    baudrate: Annotated[int, msgspec.Meta(gt=0)] = T.BAUDRATE
    #: ms a reply may take beyond the wire time of the request and the reply
    timeout_ms: Annotated[float, msgspec.Meta(gt=0, le=1000)] | None = None  # None: 15 ms
    #: the ENABLE transition's limit: reset + activation (a 2F activates in a few seconds)
    activation_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 10.0


class GripperCalibration(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """The gripper's position readings (0-255) at full opening and full closing."""

    open: Byte
    closed: Byte


class GripperJoint(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """The backend-owned keys of the gripper's one joint."""

    model: str  # "2f85" | "2f140"
    id: Byte = T.SLAVE_ID  # Modbus slave id
    speed: Annotated[float, msgspec.Meta(gt=0)] | None = None  # m/s the fingers move at; None: the model's fastest
    force: Annotated[float, msgspec.Meta(gt=0)] | None = None  # N grip force setting; None: the model's least
    effort_per_amp: Annotated[float, msgspec.Meta(gt=0)] | None = None  # N per A of finger current (an estimate)
    calibration: GripperCalibration | None = None  # None: taken at activation


DEFAULT_TIMEOUT_MS = 15.0
#: a profile's calibration: closed must exceed open by at least this many counts
CALIBRATION_MIN_SPAN = 100
#: acknowledged lifecycle writes: attempts (one per cycle) before the transition fails
WRITE_ATTEMPTS = 4
REOPEN_INTERVAL_S = 0.5
#: a stopped activation: the fingers' position the same in this many reads in a row after gACT 0
STEADY_READS = 3
_READ_REPLY = 5 + 2 * T.WORDS  # id, fc, byte count, 6 data bytes, crc 2
_WRITE_REPLY = 8  # id, fc, address 2, count 2, crc 2
_EXCEPTION_REPLY = 5


class _LinkLost(BackendError):
    """The port reported an OS error or the other end closed: the link is gone."""


class _Link:
    """A serial device through pyserial (its file descriptor read in ``select``), or a TCP socket
    for ``socket://HOST:PORT``. Raw bytes both ways; nothing here knows Modbus."""

    def __init__(self, where: str, baudrate: int):
        self.where = where
        self._ser: serial.Serial | None = None
        self._sock: socket.socket | None = None
        if where.startswith("socket://"):
            host, _, port = where[len("socket://"):].rpartition(":")
            try:
                sock = socket.create_connection((host.strip("[]"), int(port)), timeout=2.0)
            except (OSError, ValueError) as exc:
                raise OSError(getattr(exc, "errno", None), f"cannot connect to {host}:{port}: "
                              f"{getattr(exc, 'strerror', None) or exc}") from exc
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setblocking(False)
            self._sock = sock
            self.fd = sock.fileno()
        else:
            self._ser = serial.Serial(port=where, baudrate=baudrate, bytesize=T.BYTESIZE, parity=T.PARITY,
                                      stopbits=T.STOPBITS, timeout=0, exclusive=True)
            self.fd = self._ser.fileno()

    def drain(self) -> None:
        """Discard stale input (a late reply to a request that timed out)."""
        fd = self.fd
        while True:
            try:
                ready, _, _ = select.select((fd,), (), (), 0)
                if not ready:
                    return
                if not os.read(fd, 4096):
                    raise _LinkLost("end of file: the other end closed the link")
            except BlockingIOError:
                return
            except OSError as exc:
                raise _LinkLost(exc.strerror or str(exc)) from exc

    def send(self, data: bytes) -> None:
        fd, sent = self.fd, 0
        deadline = time.monotonic() + 0.1
        try:
            while sent < len(data):
                try:
                    sent += os.write(fd, data[sent:])
                except BlockingIOError:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise _LinkLost("the output does not drain") from None
                    select.select((), (fd,), (), left)
        except OSError as exc:
            raise _LinkLost(exc.strerror or str(exc)) from exc

    def receive(self, length: int, deadline: float) -> bytes:
        """Up to ``length`` bytes, waiting in ``select`` until ``deadline`` (monotonic); fewer
        when it passed. An exception reply (function code | 0x80) is 5 bytes long."""
        fd, buf = self.fd, b""
        while len(buf) < length:
            left = deadline - time.monotonic()
            if left <= 0:
                return buf
            try:
                ready, _, _ = select.select((fd,), (), (), left)
                if not ready:
                    return buf
                chunk = os.read(fd, length - len(buf))
            except BlockingIOError:
                continue
            except OSError as exc:
                raise _LinkLost(exc.strerror or str(exc)) from exc
            if not chunk:
                raise _LinkLost("end of file: the other end closed the link")
            buf += chunk
            if len(buf) >= 2 and buf[1] & 0x80:
                length = _EXCEPTION_REPLY
        return buf

    def close(self) -> None:
        for thing in (self._ser, self._sock):
            if thing is not None:
                try:
                    thing.close()
                except (OSError, serial.SerialException):
                    pass
        self._ser = self._sock = None


class RobotiqBackend(Actuator):
    """A Robotiq 2F-85 / 2F-140 on Modbus RTU (module docstring)."""

    simulator = SimWiring()  # backend.port takes the simulator's pty
    #: the simulator is a Python process on the same (possibly loaded) PC: wider reply margin
    SIM_DEFAULTS: ClassVar[dict[str, Any]] = {"timeout_ms": 30.0}

    def __init__(self, profile: Profile, *, source: str = "<profile>"):
        super().__init__(profile, source=source)
        self.source = source
        self.config = backend_config(
            profile, Config, source, owner="the robotiq backend",
            required={"port": "the serial device (/dev/serial/by-id/..., /dev/ttyUSB0), {serial_number: ...} "
                              "or socket://HOST:54321 (a UR tool flange)"})
        if self.n != 1:
            raise ProfileError(f"{source}: joints: a robotiq gripper is one joint (the finger opening), "
                               f"the profile has {self.n}; one gripper per bus")
        (keys,) = joint_keys(profile, GripperJoint, "robotiq", source)
        if profile.joints[0].unit != "m":
            raise ProfileError(f"{source}: joints[0] ({self.joint_names[0]}).unit: {profile.joints[0].unit!r}, but a "
                               f"Robotiq 2F's joint is its finger opening in metres: set unit: m")
        model = T.MODELS.get(keys.model)
        if model is None:
            raise ProfileError(f"{source}: joints[0] ({self.joint_names[0]}).model: {keys.model!r} is not a "
                               f"Robotiq 2F model; valid: {', '.join(T.MODELS)}")
        cal = keys.calibration
        if cal is not None and cal.closed - cal.open < CALIBRATION_MIN_SPAN:
            raise ProfileError(f"{source}: joints[0] ({self.joint_names[0]}).calibration: closed ({cal.closed}) "
                               f"must exceed open ({cal.open}) by at least {CALIBRATION_MIN_SPAN} counts")
        self.keys, self.model = keys, model
        self.slave = keys.id
        self._label = f"gripper {self.joint_names[0]!r} (slave {keys.id})"
        speed = model.speed_max if keys.speed is None else keys.speed
        force = model.force_min if keys.force is None else keys.force
        for key, value, lo, hi, unit in (("speed", speed, model.speed_min, model.speed_max, "m/s"),
                                         ("force", force, model.force_min, model.force_max, "N")):
            if not lo - 1e-9 <= value <= hi + 1e-9:
                raise ProfileError(f"{source}: joints[0] ({self.joint_names[0]}).{key}: {value:g} {unit} is outside "
                                   f"the {model.name}'s {lo:g}..{hi:g} {unit}")
        self._speed = _byte_of(speed, model.speed_min, model.speed_max)
        self._force = _byte_of(force, model.force_min, model.force_max)
        self._open_count, self._closed_count = (cal.open, cal.closed) if cal is not None else (None, None)
        self._effort_per_amp = keys.effort_per_amp
        cfg = self.config
        self._margin_s = (DEFAULT_TIMEOUT_MS if cfg.timeout_ms is None else cfg.timeout_ms) / 1000.0
        self._byte_s = 10.0 / cfg.baudrate  # 8N1: ten bits a byte
        self._framer = FramerRTU(DecodePDU(False))
        self._read_frame = self._framer.buildFrame(
            ReadInputRegistersRequest(address=T.INPUT_ADDRESS, count=T.WORDS, dev_id=self.slave))
        self._read_deadline_s = (len(self._read_frame) + _READ_REPLY) * self._byte_s + self._margin_s
        self._write_deadline_s = (7 + 2 * T.WORDS + 2 + _WRITE_REPLY) * self._byte_s + self._margin_s
        self._link: _Link | None = None
        self._where = str(cfg.port) if isinstance(cfg.port, str) else f"serial number {cfg.port.serial_number!r}"
        # what the gripper said last (raw), and what was last written
        self._status = self._fault = self._echo = self._gpo = self._gcu = 0
        self._have_status = False
        self._written: tuple[int, int, int, int] | None = None
        self._obj_reported = T.GOBJ_MOVING
        self._fault_reported = T.GFLT_NONE
        self._activating = False  # following gPO during an activation (calibration)
        self._seen = [255, 0]
        self._go = False  # rGTO is on (ENABLED): the gripper must stay activated
        self._must_reset = False
        self._grip: tuple[int, int] | None = None  # (request echo, gPO) at a disable with an object held
        self._grip_hold: int | None = None  # gPO at an enable that kept the grip request
        self._cal_warned = False  # the nominal ends said (or an activation measured them)
        self._activation_pending = False  # rACT 1 written for an activation not yet seen complete
        # the link lost: the Fault, and the link the reopen worker found
        self._lost: Fault | None = None
        self._reopened: _Link | None = None
        self._reopen_stop = threading.Event()
        self._reopen_thread: threading.Thread | None = None
        self._caps = Capabilities(position=True, velocity=False, effort=False, measures_velocity=False,
                                  measures_effort=self._effort_per_amp is not None, can_free=False)

    # ------------------------------------------------------------------ start-up
    def _open_hook(self) -> None:
        cfg = self.config
        path = cfg.port if isinstance(cfg.port, str) and "://" in cfg.port else \
            resolve_port(cfg.port, self.robot, self.source)
        self._where = path
        try:
            self._link = _Link(path, cfg.baudrate)
        except (OSError, serial.SerialException) as exc:
            raise BackendError(f"{self.robot}: backend.port: cannot open {path}: {open_error_reason(path, exc)}") from None
        error = None
        for _ in range(4):  # a gripper busy at power-up, or a loaded host: a few tries
            error = self._read_status()
            if error is None:
                break
        if error is not None:
            self._link.close()
            self._link = None
            raise BackendError(f"{self.robot}: {self._label} on {path} at {cfg.baudrate} baud: no answer to the status "
                               f"read (function 4, register 0x{T.INPUT_ADDRESS:04X}): {error}; check the gripper's "
                               f"24 V supply, its RS-485 wiring, backend.baudrate and the joint's id (slave id)")

    def _traits_hook(self) -> Traits:
        """One joint, position only, the loop's clock, written only while ENABLED / PAUSED; the
        activation's time limit is ``activation_timeout_s`` (reset + activation + go)."""
        limit = self.config.activation_timeout_s
        return Traits(joints=(self._caps,), min_period_s=self.wire_period_s(), transition_timeouts_s={
            Lifecycle.ENABLE: limit + 2.0, Lifecycle.FAULT_RESET: 5.0, Lifecycle.DISABLE: 2.0})

    def wire_period_s(self) -> float:
        """The shortest cycle the bus keeps (``Traits.min_period_s``): one read and one write on
        the wire, Modbus RTU's 11 bits a character and 3.5 characters of silence after each of the
        four frames. Beside a faster loop (a UR's 500 Hz) the composite serves the gripper at
        this rate, on its own thread (docs/architecture.md, "Several buses: the composite")."""
        frames = (len(self._read_frame), _READ_REPLY, 9 + 2 * T.WORDS, _WRITE_REPLY)
        return (sum(frames) + 3.5 * len(frames)) * 11.0 / self.config.baudrate

    def _close_hook(self) -> None:
        self._reopen_stop.set()
        thread = self._reopen_thread
        if thread is not None:
            thread.join(timeout=2.0)
        self._reopen_thread = None
        for link in (self._link, self._reopened):
            if link is not None:
                link.close()
        self._link = self._reopened = None

    def info(self) -> ActuatorInfo:
        return ActuatorInfo(list(self.joint_names), {
            "port": self._where, "model": self.model.name, "slave_id": self.slave,
            "calibration": {"open": self._open_count, "closed": self._closed_count}})

    # ------------------------------------------------------------------ transactions
    def _transact(self, frame: bytes, reply: int, deadline_s: float) -> tuple[Any, str | None]:
        """Send ``frame``, take its reply (``reply`` bytes). -> (the reply PDU, None) or (None,
        why not). Raises _LinkLost."""
        link = self._link
        if link is None:
            raise _LinkLost("the port is closed")
        link.drain()
        link.send(frame)
        data = link.receive(reply, time.monotonic() + deadline_s)
        if not data:
            return None, f"no reply within {deadline_s * 1000:.0f} ms"
        if len(data) < reply and not (len(data) >= 2 and data[1] & 0x80):
            return None, f"a reply of {len(data)} of {reply} bytes"
        try:
            _, pdu = self._framer.handleFrame(data, self.slave, 0)
        except Exception as exc:  # pymodbus: a frame it cannot decode
            return None, f"an undecodable reply ({exc})"
        if pdu is None:
            return None, f"a corrupt reply (CRC or slave id): {data.hex(' ')}"
        if pdu.isError():
            return None, f"exception response {pdu.exception_code}"
        return pdu, None

    def _read_status(self) -> str | None:
        """One function 4 read of the input words into the raw status fields. -> None, or why
        it failed. Raises _LinkLost."""
        pdu, error = self._transact(self._read_frame, _READ_REPLY, self._read_deadline_s)
        if error is not None:
            return error
        regs = pdu.registers
        if pdu.function_code != T.FC_READ_INPUT or len(regs) != T.WORDS:
            return f"a reply to another request (function {pdu.function_code}, {len(regs)} registers)"
        self._status, self._fault, self._echo, self._gpo, self._gcu = T.unpack_input(regs)
        self._have_status = True
        return None

    def _write_request(self, action: int, position: int) -> str | None:
        """One function 16 write of the output words. -> None, or why it failed. Raises _LinkLost."""
        words = T.pack_output(action, position, self._speed, self._force)
        frame = self._framer.buildFrame(
            WriteMultipleRegistersRequest(address=T.OUTPUT_ADDRESS, registers=words, dev_id=self.slave))
        pdu, error = self._transact(frame, _WRITE_REPLY, self._write_deadline_s)
        if error is not None:
            return error
        if pdu.function_code != T.FC_WRITE_MULTIPLE or pdu.address != T.OUTPUT_ADDRESS:
            return f"a reply to another request (function {pdu.function_code})"
        self._written = (action, position, self._speed, self._force)
        return None

    # ------------------------------------------------------------------ units
    def _calibrated(self) -> tuple[int, int]:
        if self._open_count is None:
            return T.NOMINAL_OPEN, T.NOMINAL_CLOSED  # nothing measured nor given: the nominal ends
        return self._open_count, self._closed_count

    def _calibrate(self) -> None:
        """The ends from the activation just completed (the smallest and largest gPO read
        during it), unless the profile gives them; a span far below the nominal one is refused
        (something blocked the fingers); a change of the ends in use is reported."""
        if self.keys.calibration is not None:
            return
        lo, hi = self._seen
        nominal = T.NOMINAL_CLOSED - T.NOMINAL_OPEN
        if hi - lo < T.CALIBRATION_MIN_SHARE * nominal:
            raise BackendError(
                f"{self.robot}: activation: {self._label} on {self._where}: the fingers ran only {max(hi - lo, 0)} "
                f"counts (gPO {lo}..{hi}), a 2F's stroke is about {nominal}: something blocked them; clear the "
                f"fingers and enable again (it activates anew), or give joints[0].calibration {{open: N, closed: M}}")
        before = self._open_count, self._closed_count
        self._open_count, self._closed_count = lo, hi
        if before[0] is not None and (abs(before[0] - lo) > 2 or abs(before[1] - hi) > 2):
            self._warn(f"calibration changed at this activation: open {before[0]} -> {lo}, closed {before[1]} -> "
                       f"{hi} (gPO at the stroke ends): the opening's scale moved", "gPO", hi - lo)
        self._cal_warned = True

    def _nominal_calibration(self) -> None:
        """Found activated (nothing to calibrate from) with no profile ``calibration``: the nominal
        ends, said once in a warning naming the joint and the profile key."""
        if self._cal_warned or self.keys.calibration is not None or self._open_count is not None:
            return
        self._cal_warned = True
        self._open_count, self._closed_count = T.NOMINAL_OPEN, T.NOMINAL_CLOSED
        self._warn(f"found activated: no activation to calibrate the opening from; it uses a 2F's nominal "
                   f"stroke ends (gPO {T.NOMINAL_OPEN} open, {T.NOMINAL_CLOSED} closed; a few tenths of a mm per "
                   f"count off on another gripper): give joints[0].calibration {{open: N, closed: M}} (its gPO "
                   f"fully open and fully closed) in the profile", "gPO", self._gpo)

    def opening(self, count: float) -> float:
        """m of finger opening at gripper position ``count``."""
        lo, hi = self._calibrated()
        return self.model.stroke_m * (hi - count) / (hi - lo)

    def count(self, opening: float) -> int:
        """The position request (0-255) for an opening in m (clamped to 0-255 only)."""
        lo, hi = self._calibrated()
        c = round(hi - opening / self.model.stroke_m * (hi - lo))
        return 0 if c < 0 else 255 if c > 255 else c

    # ------------------------------------------------------------------ real time
    def _read(self, feedback: JointFeedback) -> Fault | None:
        """ONE function 4 read of the status, decoded into ``feedback``; the device status from
        gFLT, gSTA and gOBJ. A missing reply is a transient ``bus_timeout`` naming the port."""
        if self._lost is not None and self._still_lost():
            return self._lost
        if self._link is None:
            return Fault("bus_timeout", f"{self.robot}: {self._label}: read on a closed port ({self._where})",
                         joint=self.joint_names[0], transient=False)
        stamp = time.time()
        try:
            error = self._read_status()
        except _LinkLost as exc:
            return self._lose_link(str(exc))
        if error is not None:
            return Fault("bus_timeout", f"{self.robot}: {self._label} on {self._where}: status read: {error}",
                         joint=self.joint_names[0], register="0x07D0", transient=True)
        gpo = self._gpo
        if self._activating:
            seen = self._seen
            if gpo < seen[0]:
                seen[0] = gpo
            if gpo > seen[1]:
                seen[1] = gpo
        feedback.position[0] = self.opening(gpo)
        if self._effort_per_amp is not None:
            amps = self._gcu * T.CURRENT_A_PER_UNIT * self._effort_per_amp
            feedback.effort[0] = -amps if self._echo > gpo else amps
        feedback.stamp = stamp
        self._gripper_news()
        return None

    def _gripper_news(self) -> None:
        """gFLT, gSTA and gOBJ changes as device status reports."""
        code = self._fault & T.GFLT_MASK
        if code != self._fault_reported:
            before, self._fault_reported = self._fault_reported, code
            fault = T.FAULTS.get(code)
            if code == T.GFLT_NONE:
                if before in T.FAULTS and T.FAULTS[before].major:
                    self.report_status(DeviceStatus.FAULT_CLEARED, Fault(
                        "fault_cleared", f"{self.robot}: {self._label}: gFLT 0x{before:02X} cleared"))
            elif fault is None or fault.major:
                self._must_reset = True
                self.report_status(DeviceStatus.FAULT, Fault(
                    "gripper_fault", f"{self.robot}: {self._label} on {self._where}: gFLT 0x{code:02X}: "
                    f"{T.fault_text(code)}; enable resets and re-activates it", joint=self.joint_names[0],
                    register="gFLT", value=code, transient=False))
            else:
                self._warn(f"gFLT 0x{code:02X} ({fault.severity} fault): {fault.meaning}", "gFLT", code)
        status = self._status
        # whatever a priority or minor code says (a major one is its own FAULT above): a gripper
        # that left its activated state while ENABLED is a FAULT (its next go would re-activate it)
        if self._go and not self._active(status) and self._lost is None and not self._major_fault():
            self._go = False
            self._must_reset = True
            self.report_status(DeviceStatus.FAULT, Fault(
                "gripper_fault", f"{self.robot}: {self._label} on {self._where}: no longer activated (gSTA "
                f"{T.gsta(status)}: {T.GSTA_TEXT[T.gsta(status)]}); enable re-activates it",
                joint=self.joint_names[0], register="gSTA", value=T.gsta(status), transient=False))
        obj = T.gobj(status) if status & T.GGTO else T.GOBJ_MOVING
        if obj != self._obj_reported:
            self._obj_reported = obj
            if obj in (T.GOBJ_CONTACT_CLOSING, T.GOBJ_CONTACT_OPENING):
                self._notice(f"gOBJ {obj}: {T.GOBJ_TEXT[obj]} at an opening of {self.opening(self._gpo):.4f} m",
                             "gOBJ", obj)
            elif obj == T.GOBJ_AT_REQUEST:
                self._notice(f"gOBJ {obj}: {T.GOBJ_TEXT[obj]}", "gOBJ", obj)

    @staticmethod
    def _active(status: int) -> bool:
        """gACT 1 and gSTA 3 (activation completed) in GRIPPER STATUS ``status``."""
        return bool(status & T.GACT) and T.gsta(status) == T.GSTA_ACTIVE

    def _warn(self, text: str, register: str, value: int) -> None:
        self.report_status(DeviceStatus.WARNING, Fault("device_warning", f"{self.robot}: {self._label}: {text}",
                                                       joint=self.joint_names[0], register=register, value=value))

    def _notice(self, text: str, register: str, value: int) -> None:
        self.report_status(DeviceStatus.NOTICE, Fault("device_status", f"{self.robot}: {self._label}: {text}",
                                                      joint=self.joint_names[0], register=register, value=value))

    def _write(self, command: JointCommand) -> Fault | None:
        """ONE function 16 write of the position request, only when it changed."""
        if not self._go or self._lost is not None or command.mode[0] != 1:  # 1: CommandMode.POSITION
            return None
        if not self._active(self._status):  # rACT|rGTO to a gripper in reset would be an activation
            return None
        request = (T.RACT | T.RGTO, self.count(float(command.position[0])), self._speed, self._force)
        if self._grip_hold is not None:  # enabled on an object, its grip request kept (_enable_steps)
            if abs(request[1] - self._grip_hold) <= 2:
                return None  # core holds where the fingers rest: the grip request stays
            self._grip_hold = None  # a command elsewhere: it goes out
        if request == self._written:
            return None
        try:
            error = self._write_request(request[0], request[1])
        except _LinkLost as exc:
            return self._lose_link(str(exc))
        if error is not None:
            return Fault("bus_timeout", f"{self.robot}: {self._label} on {self._where}: position request: {error}",
                         joint=self.joint_names[0], register="0x03E8", transient=True)
        return None

    # ------------------------------------------------------------------ lifecycle
    def _acknowledged(self, action: int, position: int, what: str) -> Steps:
        """Write the request, one attempt per cycle (WRITE_ATTEMPTS); raises BackendError."""
        error = "?"
        for attempt in range(WRITE_ATTEMPTS):
            if attempt:
                yield
            self._check_link(what)
            try:
                error = self._write_request(action, position)
            except _LinkLost as exc:
                self._lose_link(str(exc))
                self._check_link(what)
            if error is None:
                return
        raise BackendError(f"{self.robot}: {what}: {self._label} on {self._where}: {error}")

    def _check_link(self, what: str) -> None:
        if self._lost is not None:
            raise BackendError(f"{self.robot}: {what}: {self._lost.message}")

    def _fault_reset_steps(self) -> Steps:
        """rACT 0 only for the gripper's own reason (a major gFLT in the last read, its
        activation lost or abandoned: ``_must_reset``): the reset clears its faults and ENABLE
        then activates (rACT 0 -> 1). A FAULT of the robot's own (a UR's tracking error, an
        invalid command, the link dropped and back) leaves an activated gripper as it is: ENABLE
        is then only the go, the fingers stay where they are (activation runs the whole stroke)."""
        self._check_link("fault reset")
        if self._must_reset or self._major_fault():
            yield from self._reset()

    def _major_fault(self) -> bool:
        """The last read's gFLT is a major fault (or a code the manual does not list)."""
        code = self._fault & T.GFLT_MASK
        return code != T.GFLT_NONE and (code not in T.FAULTS or T.FAULTS[code].major)

    def _reset(self) -> Steps:
        self._go = False
        yield from self._acknowledged(0, 0, "reset (rACT 0)")
        while True:
            yield  # the cycle's read comes first
            if not self._status & T.GACT:
                self._must_reset = False
                return

    def _enable_steps(self, feedback: JointFeedback) -> Steps:
        """Activation when needed (reset, rACT 1, gSTA 3 across cycles), then rGTO 1 holding
        where the fingers are (module docstring)."""
        self._check_link("enable")
        yield  # decide on this cycle's read (the request may have arrived after it)
        self._check_link("enable")
        active = T.gsta(self._status) == T.GSTA_ACTIVE and self._status & T.GACT
        if self._must_reset or not active or self._major_fault():  # a minor fault (0x09 after a quiet second) is no reason
            if self._status & T.GACT:
                yield from self._reset()
            self._seen = [255, 0]
            self._activating = True
            # from the rACT 1 on, until gSTA 3: an activation abandoned now (a disable, a pause, the
            # time limit, a composite's rollback) is stopped by the DISABLE that follows
            # (_disable_steps), and the next ENABLE activates from the start
            self._activation_pending = self._must_reset = True
            try:
                yield from self._acknowledged(T.RACT, 0, "activation (rACT 1)")
                while True:
                    yield
                    code = self._fault & T.GFLT_MASK
                    if code in T.FAULTS and T.FAULTS[code].major:
                        raise BackendError(f"{self.robot}: activation: {self._label} on {self._where}: gFLT "
                                           f"0x{code:02X}: {T.fault_text(code)}")
                    if T.gsta(self._status) == T.GSTA_ACTIVE:
                        break
            finally:
                self._activating = False
            self._activation_pending = False
            self._calibrate()  # raises for a blocked stroke: _must_reset stays (the next enable activates anew)
            self._must_reset = False
            self._grip = None
        else:
            self._nominal_calibration()
        # the fingers resting on an object where a disable left them (or still squeezing it, gGTO
        # 1, after a daemon restart): the request that held it, not where they are (request ==
        # position drops the grip force); core's hold there is not written over it (_write)
        position, grip = self._gpo, self._grip
        status = self._status
        if status & T.GGTO and T.gobj(status) in (T.GOBJ_CONTACT_CLOSING, T.GOBJ_CONTACT_OPENING):
            position = self._echo
        elif grip is not None and abs(grip[1] - self._gpo) <= 2:
            position = grip[0]
        self._grip = None
        yield from self._acknowledged(T.RACT | T.RGTO, position, "go (rGTO 1)")
        self._grip_hold = self._gpo if position != self._gpo else None
        self._go = True
        self._obj_reported = T.GOBJ_MOVING

    def _disable_steps(self) -> Steps:
        """rGTO 0 (the gripper stays activated), confirmed by gGTO 0 in a later read. A gripper
        activating (gSTA 1 in the cycle's read, or an activation this backend started and did
        not see complete) is reset instead: rGTO 0 does not stop an activation, rACT 0 does."""
        self._go = False
        self._grip_hold = None
        if self._lost is not None:
            raise BackendError(f"{self.robot}: disable: {self._lost.message}")
        gsta = T.gsta(self._status)
        if gsta == T.GSTA_ACTIVATING or self._activation_pending and gsta != T.GSTA_ACTIVE:
            yield from self._stop_activation()
            return
        if not self._status & (T.GGTO | T.GACT) and self._written is None:
            return  # never activated nor told to go: nothing to stop
        position = self._written[1] if self._written is not None else self._gpo
        status = self._status
        grasp = status & T.GGTO and T.gobj(status) in (T.GOBJ_CONTACT_CLOSING, T.GOBJ_CONTACT_OPENING)
        self._grip = (self._echo, self._gpo) if grasp else None  # the request that holds an object, where
        yield from self._acknowledged(T.RACT if self._status & T.GACT else 0, position, "disable (rGTO 0)")
        for _ in range(50):
            yield
            if not self._status & T.GGTO:
                return
        raise BackendError(f"{self.robot}: disable: {self._label} on {self._where} still reports gGTO 1")

    def _stop_activation(self) -> Steps:
        """rACT 0, confirmed by gACT 0 and the fingers' position the same in STEADY_READS reads
        in a row (they stopped); the next ENABLE activates from the start (``_must_reset``)."""
        self._must_reset = True
        yield from self._acknowledged(0, 0, "disable: stop the activation (rACT 0)")
        last, steady = -1, 0
        for _ in range(100):
            yield  # the cycle's read comes first
            if self._status & T.GACT:
                last, steady = -1, 0
                continue
            steady = steady + 1 if self._gpo == last else 0
            last = self._gpo
            if steady >= STEADY_READS:
                self._activation_pending = False
                return
        raise BackendError(f"{self.robot}: disable: {self._label} on {self._where}: the activation did not stop "
                           f"(gACT {self._status & T.GACT}, gPO {self._gpo})")

    # ------------------------------------------------------------------ the link lost
    def _lose_link(self, reason: str) -> Fault:
        fault = Fault("port_lost", f"{self.robot}: {self._label}: port {self._where} is gone ({reason}); "
                      f"reopening it as soon as it is back", joint=self.joint_names[0], transient=False)
        if self._link is not None:
            self._link.close()
            self._link = None
        self._lost = fault
        self._go = False  # no _must_reset: enable decides from the status read once the link is back
        self.report_status(DeviceStatus.FAULT, fault)
        self._reopen_stop.clear()
        self._reopen_thread = background_thread(self._reopen_loop, f"reopen-{self.robot}")
        self._reopen_thread.start()
        return fault

    def _reopen_loop(self) -> None:
        while not self._reopen_stop.wait(REOPEN_INTERVAL_S):
            try:
                link = _Link(self._where, self.config.baudrate)
            except (OSError, serial.SerialException):
                continue
            self._reopened = link
            return

    def _still_lost(self) -> bool:
        link = self._reopened
        if link is None:
            return True
        self._reopened = None
        self._link = link
        self._lost = None
        self._written = None
        self.report_status(DeviceStatus.FAULT_CLEARED, Fault(
            "fault_cleared", f"{self.robot}: {self._label}: port {self._where} is back; enable re-activates the "
            f"gripper only if it lost its activation or reports a major fault"))
        return False


def _byte_of(value: float, lo: float, hi: float) -> int:
    """The 0-255 setting for ``value`` between the model's extremes (assumed linear)."""
    b = round((value - lo) / (hi - lo) * 255)
    return 0 if b < 0 else 255 if b > 255 else b


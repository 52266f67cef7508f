"""What the serial-servo bus simulators (Feetech STS, Dynamixel X) truly share.

:class:`BusSimulator` is the serving machinery of one simulated half-duplex servo bus on a
pseudo-terminal, as LeRobot's ``MotorsBus`` is for the real ones:

- lifecycle: the pty (and its optional stable link), the optional JSON-lines control socket, and
  one background thread blocked in poll() on the pty master and a wake pipe; ``start()`` returns
  once clients may open :attr:`~BusSimulator.port`, ``stop()`` is idempotent, context manager;
- state: the servos by id (an id change over the bus re-keys them), servos added factory-fresh,
  detached from the bus (keeping their EEPROM) and attached again, each known by a ``serial``
  handle; power cycles (EEPROM from flash, RAM defaults); the fault flags every servo
  carries (``silent``, ``corrupt``, ``frozen``, ``late_reply``: its previous status packet goes
  out again just ahead of its next one, once, as a reply the master gave up on arrives late,
  after the master flushed its input for the next request), the unplugged state of the whole bus, and a
  slow torque-on (``torque_delay_s``: a Torque_Enable = 1 written over the bus is acknowledged
  at once but takes effect -- and reads back 1 -- only that many seconds later, as a slow device
  would; how tests prove an enable never stalls the control loop);
- the control-socket protocol (``dump``, ``read``, ``write``, ``fault``, ``clear_faults``,
  ``unplug``, ``torque_delay``, ``hand``, ``usb_unplug``, ``usb_plug``, ``add_servo``, ``detach``,
  ``attach``, ``power_cycle``; see :mod:`crtk_bridge.sim.control` and :meth:`BusSimulator.control`):
  ``hand`` moves a servo whose torque is off as a hand would (at a
  bounded speed, so a reader sees it travel), ``usb_unplug`` / ``usb_plug`` pull the USB adapter
  out and plug it back in (the pty closes, and comes back under a new device name behind the same
  link; :class:`~crtk_bridge.sim.pty.PtyPort`), optionally with the servos' power lost meanwhile
  (torque off, as real servos come back);
- the wire rate: the rate the client set on the pty (:func:`~crtk_bridge.sim.pty.line_baud`;
  ``baudrate`` until a client sets one). A servo whose Baud_Rate register holds another rate's
  code is deaf and mute, as on a real bus: after a Baud_Rate write it answers only at the new rate;
- the wire: a half-received packet is dropped after ``FRAME_TIMEOUT_S`` of silence, and with
  ``emulate_baud`` each reply leaves no earlier than the request and the reply would have taken
  on a real wire (10 bits per byte, plus the replying servos' Return_Delay_Time, 2 us units),
  a request without a reply still occupying the wire.

Each vendor module fills the hooks: packet framing and parsing (:meth:`~BusSimulator._parse`,
which calls :meth:`~BusSimulator._reply` / :meth:`~BusSimulator._no_reply` per packet),
instruction dispatch, control tables, physics, register names, and what ``error_bits`` means on
that servo (:meth:`~BusSimulator._set_error_bits` and friends). Each vendor's servo is a
:class:`BusServo` (register memory, fault flags, ``read`` / ``write`` by name) filling
``_get`` / ``_set`` / ``_update`` with its encoding and physics.
"""

from __future__ import annotations

import ctypes
import enum
import logging
import math
import os
import select
import threading
import time
from pathlib import Path
from typing import ClassVar

from ..backends.servo_keys import ServoJoint
from ..profile import Profile, joint_keys
from . import SimulatorError
from .control import ControlServer
from .pty import PtyPort, line_baud

log = logging.getLogger(__name__)

FRAME_TIMEOUT_S = 0.010  # a partial packet older than this is dropped (servo inter-byte timeout)
BITS_PER_BYTE = 10  # 8N1 on the wire
RETURN_DELAY_UNIT_S = 2e-6  # Return_Delay_Time unit on both vendors

_PR_SET_TIMERSLACK = 29


def _tighten_timer_slack() -> None:
    """Ask Linux for 1 us timer slack on this thread (default 50 us): emulated wire times are
    ~0.1..2 ms, so the default slack alone would add several percent. Best effort."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_TIMERSLACK, 1000, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def approach(error: float, dt: float, vmax: float, tau_s: float) -> float:
    """Remaining |tracking error| after ``dt`` s of a position servo closing ``error`` (ticks) as
    a first-order lag with time constant ``tau_s``, its speed capped at ``vmax`` (ticks/s): at
    constant speed down to the knee ``vmax * tau_s``, exponentially below it; < 1e-3 is 0."""
    a = abs(error)
    knee = vmax * tau_s  # beyond this error the speed cap binds
    if a > knee:
        t1 = (a - knee) / vmax
        a = a - vmax * dt if dt <= t1 else knee * math.exp(-(dt - t1) / tau_s)
    else:
        a *= math.exp(-dt / tau_s)
    return 0.0 if a < 1e-3 else a


class FaultKind(str, enum.Enum):
    SILENT = "silent"
    CORRUPT = "corrupt"
    ERROR_BITS = "error_bits"
    FREEZE = "freeze"
    LATE_REPLY = "late_reply"


class BusServo:
    """Base of a vendor's simulated servo: 256 bytes of control table memory, the injected fault
    flags, and thread-safe access by register name. The vendor subclass fills :meth:`_get`,
    :meth:`_set` and :meth:`_update` (caller holds the simulator lock) and its defaults.

    ``registers`` is the raw control table; mutate it directly only if you mean to bypass every
    side effect. :meth:`read` and :meth:`write` bring the physics up to date first.
    """

    def __init__(self, sim: BusSimulator):
        self._sim = sim
        self.registers = bytearray(256)
        self.silent = self.corrupt = self.frozen = self.late_reply = False
        self._last_status = b""  # the status packet sent last (late_reply sends it again)
        self._pending: tuple[int, bytes] | None = None  # REG_WRITE awaiting ACTION
        self._torque_on_at: float | None = None  # a delayed torque-on takes effect then (sim clock)
        self._hand: tuple[float, float] | None = None  # (actual ticks, ticks/s): moved by hand
        self._t = sim.clock()  # physics time of the registers' Present_* values

    # --- public, thread-safe ---
    @property
    def id(self) -> int:
        return self.registers[self._sim.ID_ADDRESS]

    def read(self, name: str) -> int:
        """Decoded value of register ``name`` (signed where the table says). Raises KeyError."""
        with self._sim._lock:
            self._update(self._sim.clock())
            return self._get(name)

    def write(self, name: str, value: int) -> None:
        """Set register ``name`` from outside the bus ("by hand"): any register, read-only ones
        included, no access checks. Present_Position moves the joint; derived registers are
        recomputed. An ID change re-keys the servo. Raises KeyError / ValueError."""
        with self._sim._lock:
            now = self._sim.clock()
            self._update(now)
            old_id = self.id
            self._set(name, value)
            self._update(now)
            self._sim._rekey(self, old_id)

    # --- slow torque-on (caller holds the simulator lock) ---
    def _delay_torque(self, addr: int, data: bytes | bytearray) -> bytes | bytearray:
        """A bus write's payload with a torque-on held back by ``torque_delay_s`` (it takes
        effect in :meth:`_torque_due`); a torque-off cancels a pending one. Vendors call it first
        in their bus-write path."""
        t = self._sim.TORQUE_ADDRESS - addr
        if not 0 <= t < len(data):
            return data
        if data[t] != 1:
            self._torque_on_at = None
            return data
        delay = self._sim.torque_delay_s
        if delay <= 0 or self.registers[self._sim.TORQUE_ADDRESS] == 1:
            return data
        if self._torque_on_at is None:
            self._torque_on_at = self._sim.clock() + delay
        data = bytearray(data)
        data[t] = 0
        return data

    def _deliver(self, status: bytes) -> bytes:
        """What goes on the wire for this servo's status packet ``status``: with the
        ``late_reply`` fault (once), its previous status first. Vendors' ``_status`` returns it."""
        out = status
        if self.late_reply and self._last_status:
            self.late_reply = False
            out = self._last_status + status
        self._last_status = status
        return out

    def _torque_due(self, now: float) -> None:
        """Apply a delayed torque-on whose time has come. Vendors call it first in ``_update``."""
        if self._torque_on_at is not None and now >= self._torque_on_at:
            self._torque_on_at = None
            self.registers[self._sim.TORQUE_ADDRESS] = 1

    # --- moved by hand while torque is off (caller holds the simulator lock) ---
    def _hand_step(self, pos: float, dt: float) -> float:
        """The actual position ``pos`` (ticks) after ``dt`` s of a hand moving the horn toward
        its target at its speed. Vendors call it in ``_update`` while torque is off."""
        if self._hand is None:
            return pos
        target, speed = self._hand
        step = speed * dt
        if abs(target - pos) <= step:
            self._hand = None
            return target
        return pos + math.copysign(step, target - pos)

    def _actual(self, present: int) -> float:
        """Actual (encoder) ticks at which the servo reports Present_Position ``present``."""
        raise NotImplementedError

    def _present_exact(self) -> float | None:
        """Present_Position before its rounding to whole ticks: where the simulated horn is
        (None: the model has no such position)."""
        return None

    # --- vendor hooks (caller holds the simulator lock) ---
    def _get(self, name: str) -> int:
        raise NotImplementedError

    def _set(self, name: str, value: int) -> None:
        """Encode and store ``value``; ValueError (naming the register) if it does not fit."""
        raise NotImplementedError

    def _update(self, now: float) -> None:
        """Advance the physics to ``now`` (simulator clock) and refresh the Present_* registers."""
        raise NotImplementedError


Reply = tuple[float, bytes]  # (monotonic deadline, reply bytes); deadline 0.0 without emulate_baud


class BusSimulator:
    """A bus of simulated servos on a pty. Vendor subclasses fill the hooks below.

    Subclass ``__init__``: validate the servo ids, call ``super().__init__`` (validates
    ``baudrate``), then fill ``self._servos`` (servo objects may use :attr:`clock` and
    :attr:`baudrate`). Nothing is opened before :meth:`start`.
    """

    #: vendor name: thread name ``sim-<vendor>``, log lines, ``from_profile``'s backend.type
    vendor: ClassVar[str] = ""
    #: bus baud rate -> Baud_Rate register code (servos with another code are deaf and mute)
    BAUD_CODES: ClassVar[dict[int, int]] = {}
    #: control table address of ID, Baud_Rate, Return_Delay_Time and Torque_Enable (one byte each)
    ID_ADDRESS: ClassVar[int]
    BAUD_ADDRESS: ClassVar[int]
    RETURN_DELAY_ADDRESS: ClassVar[int]
    TORQUE_ADDRESS: ClassVar[int]
    #: highest id a servo may take over the bus
    MAX_ID: ClassVar[int] = 253
    #: a factory-fresh servo's id, baud rate and model (``add_servo``'s defaults)
    FACTORY_ID: ClassVar[int] = 1
    FACTORY_BAUD: ClassVar[int] = 1_000_000
    DEFAULT_MODEL: ClassVar[str] = ""

    def __init__(
        self,
        baudrate: int,
        link: str | os.PathLike | None,
        control: str | os.PathLike | None,
        emulate_baud: bool,
    ):
        if baudrate not in self.BAUD_CODES:
            raise SimulatorError(f"baudrate {baudrate} is not a {self.vendor} servo baud rate; valid: "
                                 f"{', '.join(map(str, sorted(self.BAUD_CODES)))}")
        self.baudrate = int(baudrate)
        self.emulate_baud = bool(emulate_baud)
        self._wire_baud = 0
        self._byte_s = BITS_PER_BYTE / self.baudrate
        self._baud_code = -1  # code of the wire rate; set with it (_set_wire_baud)
        self._set_wire_baud(self.baudrate)
        #: servos taken off the bus (``detach``), by serial handle; they keep their EEPROM
        self._detached: dict[int, BusServo] = {}
        self._next_serial = 1
        self._lock = threading.Lock()
        #: the physics clock (seconds); tests may swap in a fake one before start()
        self.clock = time.monotonic
        self._servos: dict[int, BusServo] = {}
        self.unplugged = False
        #: seconds a Torque_Enable = 1 written over the bus takes to take effect (0: at once)
        self.torque_delay_s = 0.0
        self._pty = PtyPort(link, self.baudrate)
        self._control = ControlServer(control, self.control) if control is not None else None
        self.control_path = Path(control) if control is not None else None
        self._thread: threading.Thread | None = None
        self._wake_r = self._wake_w = -1
        self._stopping = False
        self._port_jobs: list = []  # (fn, done event, result box): run on the wire thread
        self._bus_free_at = 0.0
        #: bytes received and sent on the wire since start (for bench/)
        self.rx_bytes = 0
        self.tx_bytes = 0
        #: bytes received whose packets the servos have acted on and answered (or ignored): a
        #: client that waits until it reaches what it sent knows the bus has caught up with it,
        #: whatever the host's load (a reply that will come is out, an unanswered write applied)
        self.handled_bytes = 0

    @staticmethod
    def _servo_keys(profile: Profile) -> list:
        """Every joint's servo keys (id, model, calibration), as the serial-servo backends read them."""
        return joint_keys(profile, ServoJoint, "servo simulator")

    @classmethod
    def _profile_joints(cls, profile: Profile) -> tuple[list, int]:
        """(servo keys of the joints with a bus id, baud rate) of a profile for this vendor.
        Raises SimulatorError, or ProfileError for a joint key the servos do not have."""
        if profile.backend_type != cls.vendor:
            raise SimulatorError(f"profile {profile.name!r}: backend.type is "
                                 f"{profile.backend_type!r}, not {cls.vendor!r}")
        joints = [j for j in cls._servo_keys(profile) if j.id is not None]
        if not joints:
            raise SimulatorError(f"profile {profile.name!r}: no joint has a bus id")
        baud = profile.backend.get("baudrate", 1_000_000)
        if not isinstance(baud, int) or isinstance(baud, bool):
            raise SimulatorError(f"profile {profile.name!r}: backend.baudrate must be an integer")
        return joints, baud

    # ------------------------------------------------------------------ vendor hooks
    def _parse(self, buf: bytearray, now: float) -> list[Reply]:
        """Consume every complete packet in ``buf`` (leave an incomplete one); return a reply per
        answered packet. ``now``: wire clock (monotonic) when the bytes arrived."""
        raise NotImplementedError

    def _register_name(self, servo: BusServo, register: object) -> str:
        """Canonical name of ``register`` (any case) on ``servo``. Raises SimulatorError."""
        raise NotImplementedError

    def _snapshot(self, servo: BusServo) -> dict:
        """Every register of ``servo`` by lower-case name, for ``dump`` (caller holds the lock)."""
        raise NotImplementedError

    def _error_bits(self, servo: BusServo) -> int:
        """The servo's error register (nonzero: the ``error_bits`` fault shows in ``dump``)."""
        raise NotImplementedError

    def _set_error_bits(self, servo: BusServo, bits: int) -> None:
        """OR ``bits`` into the servo's error register. Raises SimulatorError for bad bits."""
        raise NotImplementedError

    def _clear_error_bits(self, servo: BusServo) -> None:
        """What ``clear_faults`` does to the error register (nothing where errors latch)."""

    def _new_servo(self, servo_id: int, model: str, baudrate: int, position: int) -> BusServo:
        """A servo with factory EEPROM except ``servo_id`` and ``baudrate``, of ``model``, at
        ``position`` ticks (not yet on the bus). Raises SimulatorError for an unknown model."""
        raise NotImplementedError

    def _power_cycle(self, servo: BusServo) -> None:
        """Power off and on: EEPROM as last persisted, RAM at its power-on defaults."""
        raise NotImplementedError

    # ------------------------------------------------------------------ the wire rate
    def _set_wire_baud(self, baud: int) -> None:
        """The client now talks at ``baud``: only servos with that rate's code hear it."""
        self._wire_baud = baud
        self._byte_s = BITS_PER_BYTE / baud
        self._baud_code = self.BAUD_CODES.get(baud, -1)

    @property
    def wire_baud(self) -> int:
        """The baud rate the bus was last talked to at (the client's; ``baudrate`` before)."""
        return self._wire_baud

    # ------------------------------------------------------------------ lifecycle
    @property
    def port(self) -> str:
        """Path for pyserial / the vendor SDK: the link if given, else the pty slave."""
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
        with self._lock:
            for sid in sorted(self._servos):  # serial handles in id order
                self._serial_of(self._servos[sid])
        self._pty.open()
        try:
            if self._control is not None:
                self._control.start()
        except BaseException:
            self._pty.close()
            raise
        self._wake_r, self._wake_w = os.pipe()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name=f"sim-{self.vendor}", daemon=True)
        self._thread.start()
        log.info("%s simulator: %d servo(s) %s on %s", self.vendor, len(self._servos), self.ids,
                 self.port)

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

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ state access
    @property
    def ids(self) -> list[int]:
        with self._lock:
            return sorted(self._servos)

    def servo(self, servo_id: int):
        try:
            return self._servos[servo_id]
        except KeyError:
            raise SimulatorError(
                f"no simulated servo with id {servo_id} (ids: {sorted(self._servos)})") from None

    def set_fault(self, servo_id: int, kind: str | FaultKind, bits: int = 0) -> None:
        """Inject a fault into one servo (see the vendor module's docstring). Raises
        SimulatorError."""
        with self._lock:
            servo = self.servo(servo_id)
            try:
                kind = FaultKind(kind)
            except ValueError:
                raise SimulatorError(
                    f"unknown fault kind {kind!r}; valid: {', '.join(k.value for k in FaultKind)}"
                ) from None
            servo._update(self.clock())
            if kind is FaultKind.SILENT:
                servo.silent = True
            elif kind is FaultKind.CORRUPT:
                servo.corrupt = True
            elif kind is FaultKind.FREEZE:
                servo.frozen = True
            elif kind is FaultKind.LATE_REPLY:
                servo.late_reply = True
            else:
                self._set_error_bits(servo, bits)

    def clear_faults(self, servo_id: int | None = None) -> None:
        """Clear injected faults (of one servo, or all, and then the unplugged state too); the
        error register as the vendor's :meth:`_clear_error_bits` says."""
        with self._lock:
            servos = [self.servo(servo_id)] if servo_id is not None else list(self._servos.values())
            now = self.clock()
            for s in servos:
                s._update(now)
                s.silent = s.corrupt = s.frozen = s.late_reply = False
                self._clear_error_bits(s)
            if servo_id is None:
                self.unplugged = False

    def set_unplugged(self, on: bool) -> None:
        with self._lock:
            self.unplugged = bool(on)

    def hand(self, servo_id: int, position: int, speed: float = 2000.0) -> None:
        """Move servo ``servo_id`` by hand until it reports Present_Position ``position``, at
        ``speed`` ticks/s, as a hand turning a torque-off horn would (a servo with torque on
        holds: refused). Returns at once; the joint travels on the simulator's clock. Raises
        SimulatorError."""
        if not speed > 0:
            raise SimulatorError(f"hand: speed {speed} must be > 0 ticks/s")
        with self._lock:
            servo = self.servo(servo_id)
            servo._update(self.clock())
            if servo.registers[self.TORQUE_ADDRESS]:
                raise SimulatorError(f"servo {servo_id}: torque is on, it holds its position: "
                                     f"a hand cannot move it (disable the robot first)")
            servo._hand = (servo._actual(int(position)), float(speed))

    def usb_unplug(self, power_off: bool = False) -> None:
        """Pull the USB adapter out: the pty closes (a client's fd reads EIO) and its link goes
        away. ``power_off``: the servos lose power meanwhile (torque off when they come back, as
        on hardware). Raises SimulatorError."""
        self._on_wire_thread(self._pty.unplug)
        if power_off:
            with self._lock:
                now = self.clock()
                for s in self._servos.values():
                    s._update(now)
                    s._torque_on_at = None
                    s.registers[self.TORQUE_ADDRESS] = 0

    def usb_plug(self) -> None:
        """Plug the adapter back in: a new pty under another device name, the same link
        re-pointed at it. Raises SimulatorError."""
        self._on_wire_thread(self._pty.plug)

    @property
    def plugged(self) -> bool:
        return self._pty.master_fd is not None

    def _on_wire_thread(self, fn) -> None:
        """Run ``fn()`` on the serving thread (it owns the pty's fds: closing one under its
        poll() would race), waiting for it. Directly when the simulator is not running."""
        if self._thread is None or not self._thread.is_alive():
            fn()
            return
        done, box = threading.Event(), {}
        self._port_jobs.append((fn, done, box))
        os.write(self._wake_w, b"j")
        if not done.wait(2.0):
            raise SimulatorError(f"{self.vendor} simulator: the serving thread did not answer")
        if "exc" in box:
            raise box["exc"]

    def _run_port_jobs(self) -> None:
        while self._port_jobs:
            fn, done, box = self._port_jobs.pop(0)
            try:
                fn()
            except BaseException as exc:  # handed to the caller
                box["exc"] = exc
            done.set()

    def set_torque_delay(self, seconds: float) -> None:
        """From now on a torque-on written over the bus takes ``seconds`` to take effect."""
        if seconds < 0:
            raise SimulatorError(f"torque delay {seconds} s must be >= 0")
        with self._lock:
            self.torque_delay_s = float(seconds)

    def _faults(self, servo: BusServo) -> list[str]:
        out = [k.value for k, on in ((FaultKind.SILENT, servo.silent), (FaultKind.CORRUPT,
               servo.corrupt), (FaultKind.FREEZE, servo.frozen), (FaultKind.LATE_REPLY, servo.late_reply)) if on]
        if self._error_bits(servo):
            out.append(FaultKind.ERROR_BITS.value)
        return out

    # ------------------------------------------------------------------ servos on and off the bus
    def _serial_of(self, servo: BusServo) -> int:
        serial = getattr(servo, "serial", None)
        if serial is None:
            serial = servo.serial = self._next_serial
            self._next_serial += 1
        return serial

    def add_servo(self, servo_id: int | None = None, model: str | None = None,
                  baudrate: int | None = None, position: int = 2048) -> int:
        """Plug a factory-fresh servo onto the bus: id :attr:`FACTORY_ID` and baud rate
        :attr:`FACTORY_BAUD` unless given, factory EEPROM otherwise. Returns its serial handle.
        Raises SimulatorError (id taken on the bus, bad id, model or rate)."""
        servo_id = self.FACTORY_ID if servo_id is None else int(servo_id)
        baudrate = self.FACTORY_BAUD if baudrate is None else int(baudrate)
        if not 0 <= servo_id <= self.MAX_ID:
            raise SimulatorError(f"servo id {servo_id} is not a {self.vendor} id (0..{self.MAX_ID})")
        if baudrate not in self.BAUD_CODES:
            raise SimulatorError(f"baudrate {baudrate} is not a {self.vendor} servo baud rate; valid: "
                                 f"{', '.join(map(str, sorted(self.BAUD_CODES)))}")
        with self._lock:
            if servo_id in self._servos:
                raise SimulatorError(f"id {servo_id} is taken on the bus (ids: {sorted(self._servos)}); "
                                     f"detach that servo first")
            servo = self._new_servo(servo_id, model or self.DEFAULT_MODEL, baudrate, int(position))
            self._servos[servo_id] = servo
            return self._serial_of(servo)

    def remove_servo(self, servo_id: int) -> None:
        """Take the servo with this id off the bus for good. Raises SimulatorError."""
        with self._lock:
            self.servo(servo_id)
            del self._servos[servo_id]

    def replace_model(self, servo_id: int, model: str) -> None:
        """Swap the servo with this id for one of ``model`` (same id, baud rate and position;
        factory EEPROM otherwise): a servo of another model than the profile says."""
        with self._lock:
            old = self.servo(servo_id)
            baud = next(b for b, c in self.BAUD_CODES.items() if c == old.registers[self.BAUD_ADDRESS])
            self._servos[servo_id] = self._new_servo(servo_id, model, baud, round(old._pos))

    def detach(self, serial: int) -> None:
        """Take the servo with this serial handle off the bus (it keeps its EEPROM, as a servo
        unplugged by hand). Raises SimulatorError."""
        with self._lock:
            for sid, s in self._servos.items():
                if self._serial_of(s) == serial:
                    s._update(self.clock())
                    self._detached[serial] = self._servos.pop(sid)
                    return
        raise SimulatorError(f"no servo with serial {serial} on the bus")

    def attach(self, serial: int) -> None:
        """Plug a detached servo back (powered up again: :meth:`_power_cycle`). Raises
        SimulatorError when its id is taken on the bus."""
        with self._lock:
            s = self._detached.get(serial)
            if s is None:
                raise SimulatorError(f"no detached servo with serial {serial} "
                                     f"(detached: {sorted(self._detached)})")
            if s.id in self._servos:
                raise SimulatorError(f"servo serial {serial} has id {s.id}, taken on the bus")
            del self._detached[serial]
            s._t = self.clock()
            self._power_cycle(s)
            self._servos[s.id] = s

    def power_cycle(self, servo_id: int | None = None) -> None:
        """Power one servo (or all) off and on: EEPROM as persisted, RAM defaults (torque off).
        An id changed while the EEPROM was locked comes back as it was. Raises SimulatorError
        when a servo's persisted id is taken."""
        with self._lock:
            servos = [self.servo(servo_id)] if servo_id is not None else list(self._servos.values())
            now = self.clock()
            for s in servos:
                s._update(now)
                old = s.id
                self._power_cycle(s)
                self._rekey(s, old)

    def _rekey(self, servo: BusServo, old_id: int) -> None:
        """File ``servo`` under its new ID after a write changed it (caller holds the lock);
        an id that is taken or above :attr:`MAX_ID` is refused and the old one restored."""
        new_id = servo.registers[self.ID_ADDRESS]
        if new_id == old_id:
            return
        if new_id in self._servos or new_id > self.MAX_ID:
            log.warning("servo %d: refusing id change to %d (taken or invalid)", old_id, new_id)
            servo.registers[self.ID_ADDRESS] = old_id
            return
        del self._servos[old_id]
        self._servos[new_id] = servo

    # ------------------------------------------------------------------ control socket
    def control(self, request: dict) -> dict:
        """Answer one control request (dict in, dict out). Never raises for a bad request.

        ``dump``; ``read`` / ``write`` {id, register[, value]} (a register by hand: no access
        checks; an EEPROM register so written counts as persisted); ``fault`` {id, kind[, bits]};
        ``clear_faults`` [{id}]; ``unplug`` {on}; ``torque_delay`` {seconds}; ``add_servo``
        [{id, model, baudrate, position}] -> {serial} (a factory-fresh servo, id and baud rate
        the factory's unless given); ``detach`` {serial} / ``attach`` {serial} (take a servo off
        the bus and plug it back, keeping its EEPROM); ``power_cycle`` [{id}].
        """
        cmd = request.get("cmd")
        try:
            if cmd == "dump":
                return {"ok": True, **self._dump()}
            if cmd in ("read", "write"):
                servo = self._control_servo(request)
                name = self._register_name(servo, request.get("register"))
                if cmd == "read":
                    return {"ok": True, "value": servo.read(name)}
                value = request.get("value")
                if not isinstance(value, int) or isinstance(value, bool):
                    return {"ok": False, "error": f"{name}: value must be an integer, got {value!r}"}
                try:
                    servo.write(name, value)
                except ValueError as exc:
                    return {"ok": False, "error": f"servo {servo.id}: {exc}"}
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
            if cmd == "add_servo":
                args = {k: request.get(k) for k in ("id", "baudrate", "position") if request.get(k) is not None}
                for k, v in args.items():
                    if not isinstance(v, int) or isinstance(v, bool):
                        return {"ok": False, "error": f"{k!r} must be an integer, got {v!r}"}
                model = request.get("model")
                if model is not None and not isinstance(model, str):
                    return {"ok": False, "error": f"'model' must be a model name, got {model!r}"}
                serial = self.add_servo(args.get("id"), model, args.get("baudrate"), args.get("position", 2048))
                return {"ok": True, "serial": serial}
            if cmd in ("detach", "attach"):
                serial = request.get("serial")
                if not isinstance(serial, int) or isinstance(serial, bool):
                    return {"ok": False, "error": f"'serial' must be a servo's serial handle, got {serial!r}"}
                (self.detach if cmd == "detach" else self.attach)(serial)
                return {"ok": True}
            if cmd == "power_cycle":
                sid = request.get("id")
                self.power_cycle(None if sid is None else self._control_servo(request).id)
                return {"ok": True}
            if cmd == "hand":
                servo = self._control_servo(request)
                position, speed = request.get("position"), request.get("speed", 2000.0)
                if not isinstance(position, int) or isinstance(position, bool):
                    return {"ok": False, "error": f"'position' must be an integer (Present_Position ticks), got {position!r}"}
                if not isinstance(speed, (int, float)) or isinstance(speed, bool) or not speed > 0:
                    return {"ok": False, "error": f"'speed' must be a number > 0 (ticks/s), got {speed!r}"}
                self.hand(servo.id, position, float(speed))
                return {"ok": True}
            if cmd == "usb_unplug":
                self.usb_unplug(bool(request.get("power_off", False)))
                return {"ok": True}
            if cmd == "usb_plug":
                self.usb_plug()
                return {"ok": True, "pty": self.pty_path, "port": self.port}
            if cmd == "torque_delay":
                seconds = request.get("seconds")
                if not isinstance(seconds, (int, float)) or isinstance(seconds, bool) or not seconds >= 0:
                    return {"ok": False, "error": f"'seconds' must be a number >= 0, got {seconds!r}"}
                self.set_torque_delay(float(seconds))
                return {"ok": True}
        except SimulatorError as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": False, "error": f"unknown cmd {cmd!r}; valid: dump, read, write, fault, "
                "clear_faults, unplug, torque_delay, hand, usb_unplug, usb_plug, add_servo, detach, attach, "
                "power_cycle"}

    def _control_servo(self, request: dict):
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
                servos[str(sid)] = {**self._snapshot(s), "serial": self._serial_of(s)}
                exact = s._present_exact()
                if exact is not None:
                    servos[str(sid)]["present_position_exact"] = exact
                f = self._faults(s)
                if f:
                    faults[str(sid)] = f
            detached = {str(serial): {**self._snapshot(s), "serial": serial}
                        for serial, s in sorted(self._detached.items())}
            return {"clock": now, "servos": servos, "faults": faults, "unplugged": self.unplugged,
                    "baudrate": self.baudrate, "wire_baud": self._wire_baud,
                    "torque_delay_s": self.torque_delay_s, "detached": detached,
                    "usb_plugged": self.plugged, "pty": self.pty_path,
                    "by_hand": sorted(sid for sid, s in self._servos.items() if s._hand is not None)}

    # ------------------------------------------------------------------ the wire
    def _run(self) -> None:
        poller = select.poll()
        poller.register(self._wake_r, select.POLLIN)
        master = None  # the pty master polled; changes when the adapter is unplugged / plugged
        buf = bytearray()
        last_rx = 0.0
        if self.emulate_baud:
            _tighten_timer_slack()
        try:
            while True:
                if self._pty.master_fd != master:
                    if master is not None:
                        poller.unregister(master)
                    master = self._pty.master_fd
                    if master is not None:
                        poller.register(master, select.POLLIN)
                    buf.clear()
                events = poller.poll()
                if self._stopping:
                    return
                if any(fd == self._wake_r for fd, _ in events):
                    try:
                        os.read(self._wake_r, 64)
                    except BlockingIOError:
                        pass
                    self._run_port_jobs()
                    continue
                if master is None:
                    continue
                try:
                    data = os.read(master, 4096)
                except BlockingIOError:
                    continue
                now = time.monotonic()
                baud = line_baud(master) or self.baudrate
                if baud != self._wire_baud:
                    buf.clear()  # bytes at another rate are garbage to the servos
                    self._set_wire_baud(baud)
                if buf and now - last_rx > FRAME_TIMEOUT_S:
                    buf.clear()  # a servo forgets a half-received packet after a silence
                last_rx = now
                self.rx_bytes += len(data)
                buf += data
                replies = self._parse(buf, now)
                if replies:
                    self._send(master, replies)
                self.handled_bytes += len(data)
        except Exception:
            log.exception("%s simulator thread died", self.vendor)
            raise

    def _send(self, master: int, replies: list[Reply]) -> None:
        if self.emulate_baud:
            for deadline, pkt in replies:
                delay = deadline - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                self._write(master, pkt)
        else:
            self._write(master, b"".join(p for _, p in replies) if len(replies) > 1 else replies[0][1])

    def _write(self, master: int, data: bytes) -> None:
        self.tx_bytes += len(data)
        try:
            n = os.write(master, data)
        except BlockingIOError:
            log.debug("client not reading; dropped %d reply bytes", len(data))
            return
        if n < len(data):
            log.debug("client not reading; dropped %d reply bytes", len(data) - n)

    def _turnaround_s(self, repliers: list) -> float:
        """Summed Return_Delay_Time of the replying servos, in s (0 without emulate_baud).
        Caller holds the lock."""
        if not self.emulate_baud:
            return 0.0
        return sum(s.registers[self.RETURN_DELAY_ADDRESS] for s in repliers) * RETURN_DELAY_UNIT_S

    def _reply(self, out: list[bytes], req_len: int, now: float, delay_s: float) -> Reply | None:
        """Schedule the status packets ``out`` answering a ``req_len``-byte request that arrived
        at ``now``: with emulate_baud, after the request, the reply and ``delay_s`` of servo
        turnaround have passed on a wire that is free again only then."""
        if not out:
            return self._no_reply(req_len, now)
        reply = b"".join(out)
        if not self.emulate_baud:
            return (0.0, reply)
        t0 = max(now, self._bus_free_at)
        deadline = t0 + (req_len + len(reply)) * self._byte_s + delay_s
        self._bus_free_at = deadline
        return (deadline, reply)

    def _no_reply(self, req_len: int, now: float) -> None:
        # The request still occupied the wire: a reply to the next packet cannot start earlier.
        if self.emulate_baud:
            self._bus_free_at = max(now, self._bus_free_at) + req_len * self._byte_s
        return None

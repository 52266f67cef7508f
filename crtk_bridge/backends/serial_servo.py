"""What the serial-servo backends (Feetech STS, Dynamixel X) truly share, as LeRobot's MotorsBus does.

Both vendors' SDKs have the same shape: a ``PortHandler`` over pyserial, a ``PacketHandler``
with ``ping`` / ``readNByteTxRx`` / ``writeNByteTxRx`` returning ``(value, result, error)``,
``COMM_SUCCESS == 0``, and group sync reads/writes. What they share is here:

* :class:`SerialPortFixes` -- a mixin that fixes both SDKs' serial-port gaps (stale input, busy
  polling, 34 ms packet timeouts, wall-clock deadlines); each vendor's ``port.py`` mixes it into
  its SDK's ``PortHandler``.
* :class:`LastStatus` -- a mixin that keeps the status packet of a ``PacketHandler``'s last
  transaction, so a register read can check the reply's LENGTH field (the SDKs match a reply by
  id only).
* :class:`SerialServoBackend` -- profile validation (backend keys; the joints' servo keys,
  ``servo_keys.py``), the tick <-> rad calibration arrays, retried register reads/writes with errors
  naming robot, joint, id, register and port, opening (ping every servo, check its model number),
  the ENABLE transition as cross-cycle steps (rolled back on failure) and torque off, close,
  naming the first silent servo of a failed sync read, and the device status of its error bits.

The bus is one thread's at a time, and the loop's sync read must go on during an enable, so
ENABLE is steps the loop interleaves with its reads (never a worker holding the bus): one servo
per cycle (goal = its fresh present position, then torque on), then one check per cycle until
every servo reads Torque_Enable = 1 (a servo may take its time: the simulators' ``torque_delay``).
Torque off (DISABLE, the fault reaction) is stepped too, but a stop is not spread over cycles:
its first step is ONE sync write of Torque_Enable = 0 to every servo (no acknowledgement, the
whole arm unpowered by one packet), then one acknowledged Torque_Enable = 0 per servo per cycle
confirms it. No cycle carries more than one servo's acknowledged transactions beside its own
sync read and sync write (tests/test_stepped_bus.py counts them).

Hot replug. A failed sync read whose port reports an OS error (EIO: the USB adapter was pulled
out) or whose device path is gone loses the port: the read returns a non-transient ``port_lost``
Fault naming the port (FAULT when ENABLED, a ``device_fault`` warning when DISABLED), the dead
port is closed, and a worker thread (never the cycle) tries every ``REOPEN_INTERVAL_S`` to open
``backend.port`` again -- resolved again, so the same ``/dev/serial/by-id`` link or USB serial
number finds the adapter under a new ``ttyACM`` number --, pings every servo, reads back each
servo's Torque_Enable (a servo that lost power comes back with torque off; one that kept power
holds torque on) and writes the configuration again with torque off (a power loss reset the
servos' RAM). Meanwhile no bus transaction is made from the cycle and every lifecycle transition
(enable, and the fault reaction's torque off) is refused naming the port. The next read after the
worker succeeded installs the new port and reports the fault cleared (``fault_cleared`` event
naming the port and the torque read back); ``enable`` then works as after any fault.

Each vendor fills a few hooks: its tables (``MODEL_NUMBERS``, ``RESOLUTION``), its ``Config``
struct, how a register name maps to (address, size) for a joint and how values are encoded
(sign-magnitude on STS, two's complement on Dynamixel), how a status ERR byte is described, and
its ``_read`` / ``_write`` hot paths (the block layouts differ).
"""

from __future__ import annotations

import logging
import math
import os
import select
import termios
import threading
import time
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import serial

from ..core.actuator import (
    Actuator,
    ActuatorInfo,
    Capabilities,
    DeviceStatus,
    Fault,
    Lifecycle,
    Steps,
    Traits,
    background_thread,
)
from ..errors import BackendError, ProfileError
from ..profile import Profile, backend_config
from .calibration import RangeWatch, from_lerobot, lerobot_maps, sweep_calibration
from .optional import BusScanner, DeviceSetup
from .port_errors import open_error_reason, silent_bus_hint
from .ports import resolve_port
from .servo_keys import Calibration, ServoJoint, servo_joints

log = logging.getLogger(__name__)

DEFAULT_MARGIN_MS = 10.0
COMM_SUCCESS = 0  # the same value in scservo_sdk and dynamixel_sdk


class LastStatus:
    """Mixin for an SDK ``PacketHandler``: keeps the status packet of the last request /
    reply transaction (``txRxPacket``: ping, register reads and writes).

    Both SDKs' ``readTxRx`` take any status packet of the right id as the reply and slice its
    parameters to the length asked for, so a late reply to an earlier read (of another register)
    passes for this one. :meth:`status_params` is the parameter count the packet's own LENGTH
    field gives; the backend compares it with the length it asked for. The group sync read of
    the real-time path does not go through ``txRxPacket``, so it pays nothing for this."""

    last_status: list[int] = []

    def txRxPacket(self, port, txpacket):  # noqa: N802 (SDK name)
        rxpacket, result, error = super().txRxPacket(port, txpacket)  # type: ignore[misc]
        self.last_status = rxpacket or []
        return rxpacket, result, error

    def status_params(self) -> int:
        """Parameter bytes of the last status packet per its LENGTH field (-1 if too short)."""
        raise NotImplementedError


class SerialPortFixes:
    """Mixin for an SDK ``PortHandler`` (scservo_sdk or dynamixel_sdk): input flushing, sleeping
    reads, short packet timeouts on a monotonic clock, an exclusive open, OS errors as results.

    The pip SDKs' flaws that matter to a real-time loop (reference/servos.md sections 1 and 5):

    1. scservo's ``clearPort()`` only drains OUTPUT: a late reply from a failed transaction is
       taken as the answer to the next request. Here ``clearPort`` discards stale INPUT.
    2. Both open the port with ``timeout=0`` and busy-poll ``readPort`` until the packet deadline:
       a core spins while waiting. Here ``readPort(n)`` sleeps in ``select`` until ``n`` bytes
       arrived or the deadline passed; the SDKs' loops keep working unchanged.
    3. The packet timeout is wire time + 2 x 16 ms LATENCY_TIMER + 2 ms (~34 ms per attempt).
       Here it is the wire time of the expected bytes + ``margin_ms``.

    The deadline clock is monotonic (the SDKs use wall-clock time); the port is opened
    ``exclusive`` (an OS lock; the SDKs' ``is_using`` is an in-process flag); OS errors (adapter
    unplugged, pty closed) become the SDKs' TX_FAIL / RX_TIMEOUT results, kept in
    :attr:`last_os_error` for messages. Not thread-safe.
    """

    def __init__(self, port_name: str, margin_ms: float = DEFAULT_MARGIN_MS):
        super().__init__(port_name)  # type: ignore[call-arg]
        self.margin_ms = float(margin_ms)
        self.last_os_error: OSError | None = None
        self._fd = -1

    # ---- opening ----
    def setupPort(self, cflag_baud):  # noqa: N802 (SDK name)
        if self.is_open:
            self.closePort()
        # Raises serial.SerialException (an OSError subclass); the backend wraps it.
        self.ser = serial.Serial(port=self.port_name, baudrate=self.baudrate,
                                 bytesize=serial.EIGHTBITS, timeout=0, exclusive=True)
        self.is_open = True
        self._fd = self.ser.fileno()
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0  # ms per byte, 8N1
        self.last_os_error = None
        return True

    def closePort(self):  # noqa: N802
        if self.ser is not None:
            try:
                self.ser.close()
            except (OSError, serial.SerialException):
                pass
        self.is_open = False
        self._fd = -1

    # ---- gap 1: discard stale input ----
    def clearPort(self):  # noqa: N802
        try:
            termios.tcflush(self._fd, termios.TCIFLUSH)
        except (OSError, termios.error) as exc:
            self.last_os_error = exc if isinstance(exc, OSError) else OSError(str(exc))

    # ---- gap 2: sleep until the bytes arrive or the deadline passes ----
    def readPort(self, length):  # noqa: N802
        fd = self._fd
        try:
            data = os.read(fd, length)
        except BlockingIOError:
            data = b""
        except OSError as exc:
            return self._read_failed(exc)
        if len(data) >= length:
            return data
        deadline = self.packet_start_time + self.packet_timeout  # ms, monotonic
        while True:
            remaining = deadline - self.getCurrentTime()
            if remaining <= 0:
                return data
            try:
                ready, _, _ = select.select((fd,), (), (), remaining / 1000.0)
                if not ready:
                    return data
                chunk = os.read(fd, length - len(data))
            except BlockingIOError:
                continue
            except (OSError, ValueError) as exc:
                if not isinstance(exc, OSError):
                    exc = OSError(str(exc))
                return data if data else self._read_failed(exc)
            if not chunk:  # EOF: the other side is gone
                return data if data else self._read_failed(OSError("end of file on serial port"))
            data += chunk
            if len(data) >= length:
                return data

    def _read_failed(self, exc: OSError) -> bytes:
        # Expire the deadline so the SDK's loop gives up now instead of spinning on a dead fd.
        self.last_os_error = exc
        self.packet_timeout = -1.0
        return b""

    def writePort(self, packet):  # noqa: N802
        data = bytes(packet)
        sent = 0
        deadline = time.monotonic() + 0.1  # a full output queue drains in well under this
        try:
            while sent < len(data):
                try:
                    sent += os.write(self._fd, data[sent:])
                except BlockingIOError:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    select.select((), (self._fd,), (), remaining)
        except OSError as exc:
            self.last_os_error = exc
        return sent  # != len(packet) -> the SDK reports TX_FAIL and releases the port

    def getBytesAvailable(self):  # noqa: N802
        try:
            return self.ser.in_waiting
        except (OSError, serial.SerialException):
            return 0

    # ---- gap 3: short, byte-count-sized packet timeouts on a monotonic clock ----
    def setPacketTimeout(self, packet_length):  # noqa: N802
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.margin_ms

    def setPacketTimeoutMillis(self, msec):  # noqa: N802
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = msec

    def getCurrentTime(self):  # noqa: N802
        return time.monotonic() * 1000.0

    def getTimeSinceStart(self):  # noqa: N802
        return self.getCurrentTime() - self.packet_start_time


@dataclass(frozen=True)
class EepromDiff:
    """An EEPROM setting of a joint's servo that differs from what the profile and the backend
    expect (:meth:`SerialServoBackend.eeprom_diffs`)."""

    joint: str
    id: int
    register: str
    value: int
    expected: str  # e.g. "0", "<= 700"
    key: str  # the profile key that says so, e.g. "joints[2] (elbow_flex).calibration.homing_offset"
    wrong_positions: bool  # True: positions (or reachable positions) would be wrong: enable refused
    why: str  # what the difference does
    remedy: str  # what to do

    def message(self) -> str:
        return (f"joint {self.joint!r} (id {self.id}): {self.register} is {self.value}, expected "
                f"{self.expected} ({self.key}): {self.why}; {self.remedy}")


@dataclass(frozen=True)
class ScannedServo:
    """One servo that answered a bus scan (:meth:`SerialServoBackend.scan`)."""

    id: int
    model_number: int
    model: str | None  # the model's name, None when the backend does not know the number
    firmware: str | None  # None: it did not say
    torque: bool | None  # Torque_Enable; None: it did not say
    eeprom: tuple[EepromDiff, ...] = ()  # its joint's EEPROM differences (profile ids only)
    eeprom_error: str | None = None  # why its EEPROM could not be read


@dataclass(frozen=True)
class BusScan:
    """A :meth:`SerialServoBackend.scan`: the servos at the profile's rate, and (``all_bauds``)
    those answering at the other rates, by rate: [(id, model number)]."""

    servos: list[ScannedServo]
    elsewhere: dict[int, list[tuple[int, int]]]


class SerialServoBackend(Actuator, BusScanner, DeviceSetup):
    """Servos with one id each on one half-duplex serial bus. Subclasses fill the hooks below.
    Both optional capabilities (backends/optional.py): ``check --scan`` and ``setup-servos``.

    Constructing validates the profile (raises ProfileError naming ``backend.<key>`` or the joint
    key); nothing touches the bus before :meth:`open`.
    """

    #: vendor name as in the registry ("feetech", "dynamixel")
    vendor: ClassVar[str] = ""
    #: the backend's ``Config`` msgspec struct (must have ``port``, ``baudrate``, ``timeout_ms``,
    #: ``read_retries``)
    Config: ClassVar[type]
    #: model name -> model number (register read by ping)
    MODEL_NUMBERS: ClassVar[dict[str, int]] = {}
    #: model name -> encoder ticks per turn
    RESOLUTION: ClassVar[dict[str, int]] = {}
    MAX_ID: ClassVar[int] = 253
    SUPPORTED_BAUDS: ClassVar[list[int]] = []
    #: True when LeRobot applies a calibration's drive_mode in software (Feetech); False when the
    #: servo applies it itself (Dynamixel's Drive_Mode register) before its ticks are read
    SOFTWARE_DRIVE_MODE: ClassVar[bool] = True
    #: bus baud rate -> Baud_Rate register code
    BAUD_CODES: ClassVar[dict[int, int]] = {}
    #: a factory-fresh servo's baud rate (setup-servos looks there first after the profile's)
    FACTORY_BAUD: ClassVar[int] = 1_000_000
    #: largest |Homing_Offset| the servo takes (calibration.homing_offset is checked against it)
    HOMING_OFFSET_MAX: ClassVar[int] = 2047
    #: ``timeout_ms`` 30 under ``--sim`` unless the profile sets one: the simulated servos are a
    #: Python process on the same (possibly loaded) PC behind a pty, where a reply can take tens of
    #: ms; a real servo answers within ~1 ms of its wire time. A silent simulated servo still
    #: faults the robot within ``safety.bus_errors_max`` cycles, each costing up to
    #: ``(read_retries + 1) * (wire time + 30 ms)``.
    SIM_DEFAULTS: ClassVar[dict[str, Any]] = {"timeout_ms": 30.0}
    #: SDK result codes that mean "no reply" / "bad reply"
    RX_TIMEOUT: ClassVar[int] = -1
    RX_CORRUPT: ClassVar[int] = -2

    def __init__(self, profile: Profile, *, source: str = "<profile>"):
        super().__init__(profile, source=source)
        self.source = source
        self.config = backend_config(
            profile, self.Config, source, owner=f"the {self.vendor} backend",
            required={"port": "the serial device (e.g. /dev/serial/by-id/..., /dev/ttyACM0) or {serial_number: ...}"})
        cfg = self.config
        if cfg.baudrate not in self.SUPPORTED_BAUDS:
            raise ProfileError(f"{source}: backend.baudrate: {cfg.baudrate} is not supported; "
                               f"valid: {', '.join(map(str, self.SUPPORTED_BAUDS))}")
        self.joint_keys = servo_joints(profile, self.vendor, self.MODEL_NUMBERS, self.MAX_ID, source,
                                       self._check_joint)

        joints = self.joint_keys
        self._ids = [int(j.id) for j in joints]
        self._label = [f"joint {name!r} (id {j.id})" for name, j in zip(self.joint_names, joints)]
        res = np.array([self.RESOLUTION[j.model] for j in joints], dtype=float)
        self._direction = np.array([j.calibration.direction for j in joints], dtype=float)
        self._offset_ticks = np.array([j.calibration.offset for j in joints], dtype=float)
        self._resolution = res
        self._rad_per_tick = self._direction * 2.0 * math.pi / res  # signed: includes direction
        self._tick_per_rad = 1.0 / self._rad_per_tick
        self._attempts = 1 + cfg.read_retries
        # pre-allocated real-time buffers for the vendors' _read / _write hot paths
        n = self.n
        self._raw_pos = np.zeros(n)
        self._raw_vel = np.zeros(n)
        self._raw_cur = np.zeros(n)
        self._tmp = np.zeros(n)
        self._goal = np.zeros(n)  # goal ticks computed this cycle (float)
        self._free = [False] * n  # joints switched torque-off by a FREE command
        self._torque_param: list[int] = []  # the Torque_Enable sync write's parameters, reused
        self._port: Any = None
        self._port_path: str | None = None  # backend.port resolved at open (a serial_number)
        self._ph: Any = None
        self._details: dict = {}
        self._enable_refusal: str | None = None  # set at open (_startup_check)
        # hot replug (module docstring): set by the cycle when the port went away, cleared by the
        # cycle once the worker reopened it
        self._lost: Any = None  # the port_lost Fault while the port is gone
        #: (joint index, SDK result) of the deepest failure in the run of failed sync reads under
        #: way (None after a good read): what the run's FAULT names (:meth:`_sync_read_fault`)
        self._failed_run: tuple[int, int] | None = None
        self._reopened: str | None = None  # set by the reopen worker: what it found
        self._reopen_thread: threading.Thread | None = None
        self._reopen_stop = threading.Event()
        # calibration sweep (backends/calibration.py): followed in the vendors' _read
        self._cal: RangeWatch | None = None
        self._cal_homing: list[int | None] = [None] * self.n
        self._check_stop_deceleration(profile, source)

    #: the backend key of the servos' own acceleration limit (:meth:`deceleration_limit`)
    ACCELERATION_KEY: ClassVar[str] = ""

    def _check_stop_deceleration(self, profile: Profile, source: str) -> None:
        """A profile's ``stop_deceleration_max`` above what the servo follows as configured would
        be a longer stop than the profile says: refused, naming both keys."""
        for i, j in enumerate(profile.joints):
            want, most = j.limits.stop_deceleration_max, self.deceleration_limit(i)
            if want is not None and want > most:
                key = self.ACCELERATION_KEY
                raise ProfileError(
                    f"{source}: joints[{i}] ({j.name}).limits.stop_deceleration_max: {want:g} rad/s^2 is above "
                    f"what the servo follows with backend.{key} {getattr(self.config, key)} ({most:.2f} rad/s^2); "
                    f"lower it, or raise backend.{key} (0 = unlimited)")

    # ------------------------------------------------------------------ hooks
    def _check_joint(self, i: int, key: str, j: ServoJoint, problems: list[str]) -> None:
        """Vendor checks of joint ``i``'s servo keys ``j`` (known model); append 'key: message'
        to ``problems``. Called while constructing: ``self.config`` is set, nothing else."""
        res = self.RESOLUTION[j.model]
        r = j.calibration.range
        if r is not None and not (0 <= r[0] and r[1] <= res - 1):
            problems.append(f"{key}.calibration.range: {list(r)} is outside 0..{res - 1}")
        if not 0 <= j.calibration.offset <= res - 1:
            problems.append(f"{key}.calibration.offset: {j.calibration.offset} is outside 0..{res - 1}")
        self._check_homing_offset(key, j, problems)

    def _check_homing_offset(self, key: str, j: ServoJoint, problems: list[str]) -> None:
        h = self.HOMING_OFFSET_MAX
        if not -h <= j.calibration.homing_offset <= h:
            problems.append(f"{key}.calibration.homing_offset: {j.calibration.homing_offset} is outside "
                            f"-{h}..{h} (the servo's Homing_Offset register)")

    def _make_port(self, margin_ms: float) -> Any:
        """A :class:`SerialPortFixes` port handler of this vendor's SDK (not opened)."""
        raise NotImplementedError

    def _make_packet_handler(self) -> Any:
        raise NotImplementedError

    def _register(self, i: int, name: str) -> tuple[int, int]:
        """(address, size) of register ``name`` on joint ``i``'s model. Raises KeyError."""
        raise NotImplementedError

    def _encode(self, i: int, name: str, value: int) -> int:
        return int(value)

    def _decode(self, i: int, name: str, raw: int) -> int:
        return raw

    def _error_text(self, error: int) -> str | None:
        """Description of a status ERR byte if it means the servo is in error, else None."""
        return None

    def _after_open(self) -> None:
        """Set up sync groups etc. once the servos answered. Blocks; raises BackendError."""

    def _broadcast_ping(self) -> tuple[dict[int, int], bool]:
        """(id -> model number of every servo answering one broadcast PING at the port's current
        rate, whether some reply was garbled -- several servos answering at once, or noise).
        Blocks for the vendor's listening window. The port is open."""
        raise NotImplementedError

    def _vendor_eeprom_diffs(self, i: int, key: str, regs: dict[str, int]) -> list[EepromDiff]:
        """The vendor's own EEPROM expectations of joint ``i`` (operating mode, direction bits),
        from ``regs`` (:meth:`_read_eeprom`)."""
        return []

    def _unlock_eeprom(self, i: int, sid: int) -> None:
        """Make the EEPROM writes that follow persist on the servo with bus id ``sid`` (joint
        ``i``'s model; setup-servos). Default: nothing (the servo persists every EEPROM write).
        Blocks; raises BackendError."""

    def _lock_eeprom(self, i: int, sid: int) -> None:
        """Undo :meth:`_unlock_eeprom`. Blocks; raises BackendError."""

    def _limits_apply(self, i: int) -> bool:
        """Whether the servo's Min/Max_Position_Limit bound joint ``i``'s positions in the mode
        the backend drives it in."""
        return True

    # ------------------------------------------------------------------ helpers
    @property
    def _where(self) -> str:
        return self._port_path or str(self.config.port)

    port_name = _where  # the device path once opened (or scanned), else backend.port as given

    def info(self) -> ActuatorInfo:
        return ActuatorInfo(list(self.joint_names), dict(self._details))

    #: per joint, what it can do (set by the vendor's __init__ from the profile)
    _joint_caps: list[Capabilities]

    def _traits_hook(self) -> Traits:
        """Serial servos: the loop's clock; written only while ENABLED / PAUSED; core's braking
        ramp pauses them; no native homing, goal check or speed scaling; per joint what the
        profile gives (``_joint_caps``)."""
        return Traits(joints=tuple(self._joint_caps), transition_timeouts_s=self.TRANSITION_TIMEOUTS_S)

    def _result_text(self, result: int) -> str:
        text = self._ph.getTxRxResult(result) if self._ph else str(result)
        err = self._port.last_os_error if self._port else None
        if err is not None:
            text += f" (port error: {err})"
        return text

    #: attempts of one acknowledged lifecycle transaction (ping, register read/write). More
    #: patient than the real-time read: a servo busy at power-up, or a loaded host, must not fail
    #: `open` or `enable`; a truly missing servo costs this many packet timeouts, once.
    LIFECYCLE_ATTEMPTS = 4
    #: how long `open` keeps pinging a servo that does not answer (shared by all servos): a
    #: missing one costs this once, at start-up, and every servo gets at least LIFECYCLE_ATTEMPTS
    OPEN_PATIENCE_S = 0.5

    def _txrx(self, fn, *args, length: int | None = None):
        """Call an SDK ``...TxRx`` function, retrying comm failures. Returns its tuple.

        ``length``: a read's data length. The SDKs take any status packet of the right id as the
        reply, so a late status (of an earlier request that timed out, arriving after the input
        flush that precedes every request) would be decoded as this read's data; one of another
        length (the packet's LENGTH field, :class:`LastStatus`) is refused here as corrupt and
        the read retried."""
        if self._port is not None:
            self._port.last_os_error = None
            self._port.is_using = False  # we own the port alone; a stale flag = PORT_BUSY forever
        attempts = max(self._attempts, self.LIFECYCLE_ATTEMPTS)
        for _ in range(attempts):
            try:
                out = fn(self._port, *args)
            except IndexError:
                # the SDKs index a reply that came back short (scservo's ping reads the model
                # number of a stale or truncated status packet): a corrupt reply, retried
                self._port.is_using = False
                corrupt = (self.RX_CORRUPT, 0)
                out = corrupt if fn.__name__.startswith(("write", "reboot")) else (0, *corrupt)
                continue
            if out[-2] == COMM_SUCCESS:
                if length is None or len(out[0]) == length == self._ph.status_params():
                    break
                out = (out[0], self.RX_CORRUPT, out[2])  # not this read's reply: retried
        return out

    def _write_register(self, i: int, name: str, value: int, check_error: bool = False,
                        sid: int | None = None) -> None:
        """Write one register of joint ``i`` (of the servo with bus id ``sid`` if given: a servo
        being set up) and wait for its ack. Blocks. Raises BackendError."""
        address, size = self._register(i, name)
        raw = self._encode(i, name, value)
        fn = {1: self._ph.write1ByteTxRx, 2: self._ph.write2ByteTxRx, 4: self._ph.write4ByteTxRx}[size]
        result, error = self._txrx(fn, self._ids[i] if sid is None else sid, address, raw)
        if result != COMM_SUCCESS:
            raise BackendError(
                f"{self.robot}: {self._label[i]}: writing {name} = {value} on {self._where} "
                f"got no acknowledgement: {self._result_text(result)}")
        if check_error:
            text = self._error_text(error)
            if text:
                raise BackendError(f"{self.robot}: {self._label[i]} reports {text} "
                                   f"(status error 0x{error:02X}) when writing {name}")

    def _read_register(self, i: int, name: str, sid: int | None = None) -> int:
        """Read one register of joint ``i`` (of the servo with bus id ``sid`` if given), decoded
        (signed where the table says). The input is flushed before the request (the SDKs'
        ``txPacket`` calls :meth:`SerialPortFixes.clearPort`), and a reply of another length than
        the register's (a late reply to an earlier request) is refused and the read retried.
        Blocks. Raises BackendError."""
        address, size = self._register(i, name)
        data, result, _ = self._txrx(self._ph.readTxRx, self._ids[i] if sid is None else sid, address, size,
                                     length=size)
        if result != COMM_SUCCESS:
            raise BackendError(f"{self.robot}: {self._label[i]}: reading {name} on {self._where} "
                               f"failed: {self._result_text(result)}")
        return self._decode(i, name, int.from_bytes(bytes(data), "little"))

    def _write_unacknowledged(self, i: int, name: str, value: int, sid: int) -> bool:
        """Write one register of the servo with bus id ``sid`` (joint ``i``'s model) without
        waiting for a status: for ID and Baud_Rate, whose status may come back under the new id
        or at the new rate. True when the packet went out. Blocks briefly."""
        address, size = self._register(i, name)
        raw = self._encode(i, name, value)
        fn = {1: self._ph.write1ByteTxOnly, 2: self._ph.write2ByteTxOnly, 4: self._ph.write4ByteTxOnly}[size]
        port = self._port
        port.is_using = False
        result = fn(port, sid, address, raw)
        port.is_using = False
        # Its status (if the servo sends one) is read off the wire here, so that no later request
        # takes it for its own reply (the largest write status: Dynamixel's 11 bytes).
        port.setPacketTimeout(11)
        port.readPort(64)
        return result == COMM_SUCCESS

    # ------------------------------------------------------------------ EEPROM against the profile
    def eeprom_diffs(self, i: int) -> list[EepromDiff]:
        """Joint ``i``'s servo's EEPROM settings that differ from the profile and the backend:
        Homing_Offset (``calibration.homing_offset``), Min/Max_Position_Limit cutting into
        ``calibration.range`` (or the whole turn without one), Return_Delay_Time
        (``backend.return_delay``), and the vendor's (:meth:`_vendor_eeprom_diffs`). Reads the
        servo (the bus is open); writes nothing. Blocks. Raises BackendError."""
        name = self.joint_names[i]
        j = self.joint_keys[i]
        sid = self._ids[i]
        key = f"joints[{self.profile.joint_names.index(name)}] ({name})"
        never = "the daemon never rewrites EEPROM"
        out = []
        regs = self._read_eeprom(i)
        h = regs["Homing_Offset"]
        if h != j.calibration.homing_offset:
            out.append(EepromDiff(
                name, sid, "Homing_Offset", h, str(j.calibration.homing_offset),
                f"{key}.calibration.homing_offset", True,
                f"every position it reports is shifted by {h - j.calibration.homing_offset} ticks "
                f"from the calibration's",
                f"recalibrate (crtk-ctl calibrate), or set {key}.calibration.homing_offset: {h} if "
                f"the calibration was made with it ({never})"))
        if self._limits_apply(i):
            res = self.RESOLUTION[j.model]
            lo, hi = j.calibration.range or (0, res - 1)
            where = f"{key}.calibration.range" if j.calibration.range else f"{key}.model ({j.model}: 0..{res - 1})"
            low, high = regs["Min_Position_Limit"], regs["Max_Position_Limit"]
            if not self._no_limits(low, high):
                remedy = (f"widen the servo's limits (e.g. with the vendor's tool) or narrow "
                          f"{key}.calibration.range ({never})")
                if low > lo:
                    out.append(EepromDiff(name, sid, "Min_Position_Limit", low, f"<= {lo}", where, True,
                                          f"the servo refuses positions below {low} ticks", remedy))
                if high < hi:
                    out.append(EepromDiff(name, sid, "Max_Position_Limit", high, f">= {hi}", where, True,
                                          f"the servo refuses positions above {high} ticks", remedy))
        rd = regs["Return_Delay_Time"]
        if rd != self.config.return_delay:
            out.append(EepromDiff(
                name, sid, "Return_Delay_Time", rd, str(self.config.return_delay), "backend.return_delay",
                False, f"each reply waits {rd * 2} us",
                "the daemon sets it at start-up until the next power cycle; crtk-bridge setup-servos "
                "stores it"))
        return out + self._vendor_eeprom_diffs(i, key, regs)

    #: the registers :meth:`eeprom_diffs` reads (the vendor adds its own)
    EEPROM_REGISTERS: ClassVar[tuple[str, ...]] = ("Homing_Offset", "Min_Position_Limit",
                                                   "Max_Position_Limit", "Return_Delay_Time")

    def _read_eeprom(self, i: int) -> dict[str, int]:
        """:attr:`EEPROM_REGISTERS` of joint ``i``'s servo, decoded, from ONE read of the block
        spanning them. The reply must carry exactly the block's length: the SDKs take any status
        of the right id as the reply, so a late one (a smaller read that timed out before, on a
        loaded host) would otherwise be decoded as these registers. Blocks. Raises BackendError."""
        regs = {name: self._register(i, name) for name in self.EEPROM_REGISTERS}
        start = min(a for a, _ in regs.values())
        length = max(a + n for a, n in regs.values()) - start
        data, result, _ = self._txrx(self._ph.readTxRx, self._ids[i], start, length, length=length)
        if result != COMM_SUCCESS:
            raise BackendError(f"{self.robot}: {self._label[i]}: reading its EEPROM settings "
                               f"({', '.join(regs)}) on {self._where} failed: {self._result_text(result)}")
        return {name: self._decode(i, name, int.from_bytes(bytes(data[a - start:a - start + n]), "little"))
                for name, (a, n) in regs.items()}

    #: how long a joint's EEPROM is read again when a read fails (a loaded host, a servo still
    #: starting) before the failure counts
    EEPROM_PATIENCE_S = 2.0

    def _patient_eeprom_diffs(self, i: int) -> list[EepromDiff]:
        """:meth:`eeprom_diffs`, tried again on a failed read for up to EEPROM_PATIENCE_S."""
        deadline = time.monotonic() + self.EEPROM_PATIENCE_S
        while True:
            try:
                return self.eeprom_diffs(i)
            except BackendError:
                if time.monotonic() > deadline:
                    raise

    @staticmethod
    def _no_limits(low: int, high: int) -> bool:
        """Whether Min/Max_Position_Limit mean "no limit" (Feetech: both 0, multi-turn)."""
        return False

    def _startup_check(self) -> None:
        """At open: EEPROM settings that would make positions wrong (:meth:`eeprom_diffs`) make
        ENABLE refuse, naming robot, joint, register and the remedy. Blocks. Raises BackendError."""
        wrong = [d for i in range(self.n) for d in self._patient_eeprom_diffs(i) if d.wrong_positions]
        self._enable_refusal = None
        if wrong:
            self._enable_refusal = (f"{self.robot}: enable refused, the servos' EEPROM disagrees "
                                    f"with the profile {self.source}: "
                                    + "; ".join(d.message() for d in wrong))
            log.warning("%s", self._enable_refusal)

    def _require_open(self, what: str) -> None:
        self._check_not_lost(what)
        if self._port is None:
            raise BackendError(f"{self.robot}: {what} needs an open bus; call open() first")

    # ------------------------------------------------------------------ calibration
    def calibration_begin(self) -> Steps:
        """Read each servo's Homing_Offset (one per cycle: the ticks are measured with it), then
        follow every read's ticks from the middle pose, the latest read's (backends/calibration.py)."""
        self._require_open("calibrate")
        homing: list[int | None] = []
        for i in range(self.n):
            homing.append((yield from self._retrying(self._read_register, i, "Homing_Offset")))
            yield
        self._cal_homing = homing
        self._cal = RangeWatch(self._raw_pos, self._resolution)

    def _watch(self) -> RangeWatch:
        if self._cal is None:
            raise BackendError(f"{self.robot}: no calibration sweep under way (calibrate begin first)")
        return self._cal

    def calibration_seen(self) -> dict[str, list[float]]:
        w = self._watch()
        k = self._rad_per_tick
        return {name: sorted([float(w.lo[i] * k[i]), float(w.hi[i] * k[i])]) + [float(w.now[i] * k[i])]
                for i, name in enumerate(self.joint_names)}

    def calibration_result(self, grippers) -> dict[str, dict[str, Any]]:
        w = self._watch()
        result = sweep_calibration(self.robot, self.joint_names, w, [int(d) for d in self._direction],
                                   list(grippers), self._cal_homing)
        self._cal = None
        return _schema_keys(result)

    def calibration_cancel(self) -> None:
        self._cal = None

    def calibration_import(self, fmt: str, data: Any, grippers) -> dict[str, dict[str, Any]]:
        if fmt != "lerobot":
            return super().calibration_import(fmt, data, grippers)
        return _schema_keys(from_lerobot(self.robot, data, self.joint_names, self._ids,
                                         [int(r) for r in self._resolution], [int(d) for d in self._direction],
                                         list(grippers), self.SOFTWARE_DRIVE_MODE))

    def lerobot_maps(self) -> list[dict[str, list[float]] | None]:
        """Per joint, LeRobot's numbers as affine maps of its radians (backends/calibration.py,
        ``lerobot_maps``), from the joint's calibration keys; the ticks stay here."""
        return [lerobot_maps(j.calibration.offset, j.calibration.direction, j.calibration.range, int(r))
                for j, r in zip(self.joint_keys, self._resolution)]

    # ------------------------------------------------------------------ hot replug
    #: s between two attempts of the reopen worker (adapter unplugged, module docstring)
    REOPEN_INTERVAL_S = 0.2

    def _check_not_lost(self, what: str) -> None:
        """Raise BackendError while the port is gone (except on the reopen worker, which is the
        one bringing it back)."""
        if self._lost is not None and threading.current_thread() is not self._reopen_thread:
            raise BackendError(f"{self.robot}: {what} impossible: serial port {self._where} is gone "
                               f"(adapter unplugged?); waiting for it to come back")

    def _port_gone(self) -> bool:
        """After a failed read: did the port itself go away (OS error on its fd, or its device
        path no longer exists)? A silent servo on a live port is not that."""
        port = self._port
        err = port.last_os_error if port is not None else None
        if err is not None and not isinstance(err, (BlockingIOError, InterruptedError)):
            return True
        path = self._port_path
        return path is not None and not os.path.exists(path)

    def _lose_port(self) -> Any:
        """The cycle found the port gone: close it, report FAULT, start the reopen worker (once:
        a rare event, so starting a thread here is acceptable). Returns the port_lost Fault."""
        err = self._port.last_os_error if self._port is not None else None
        reason = f"{err.strerror or err}" if isinstance(err, OSError) and (err.strerror or str(err)) else "no such device"
        fault = Fault("port_lost", f"{self.robot}: serial port {self._where} is gone ({reason}): adapter "
                      f"unplugged? Reopening it as soon as it is back", transient=False)
        if self._port is not None:
            self._port.closePort()
        self._lost = fault
        self._reopened = None
        self.report_status(DeviceStatus.FAULT, fault)
        self._reopen_stop.clear()
        self._reopen_thread = background_thread(self._reopen_loop, f"reopen-{self.robot}")
        self._reopen_thread.start()
        return fault

    def _still_lost(self) -> bool:
        """Called by the cycle while the port is lost: False once the worker reopened it (the
        new port is installed and the fault reported cleared), else True (no bus I/O)."""
        found = self._reopened
        if found is None:
            return True
        self._lost = None
        self._reopened = None
        self.report_status(DeviceStatus.FAULT_CLEARED, Fault("fault_cleared", found))
        return False

    def _reopen_loop(self) -> None:
        """The reopen worker: retry until the port is back and every servo answers, or close."""
        while not self._reopen_stop.wait(self.REOPEN_INTERVAL_S):
            try:
                self._reopened = self._reopen_once()
                return
            except (BackendError, OSError):
                continue  # not back yet (no device, servos unpowered): try again

    def _reopen_once(self) -> str:
        """Open ``backend.port`` again (resolved again), check the servos, read back torque,
        configure again (torque off first). Runs on the worker. Returns what it found."""
        port, _ = self._open_port()
        try:
            self._check_servos()
            self._startup_check()  # the EEPROM may have changed (a servo swapped, recalibrated) meanwhile
            self._after_open()
            torque = [self._read_register(i, "Torque_Enable") for i in range(self.n)]
            self._configure_hook()
        except BaseException:
            port.closePort()
            raise
        on = [name for name, t in zip(self.joint_names, torque) if t]
        said = ("every servo had torque off (they lost power)" if not on else
                f"torque was on at {', '.join(on)} (kept power), switched off")
        return f"serial port {self._where} is back; {said}"

    def _first_missing(self, data: dict, length: int) -> int | None:
        """Index of the first joint whose sync-read entry is shorter than ``length``: the SDKs
        fill ids in request order and give up at the first silent or broken one."""
        for i, sid in enumerate(self._ids):
            if len(data.get(sid) or ()) < length:
                return i
        return None

    def _sync_read_fault(self, result: int, data: dict, length: int) -> Any:
        from ..core.actuator import Fault

        if self._port_gone():
            return self._lose_port()
        i = None
        if result in (self.RX_TIMEOUT, self.RX_CORRUPT):
            i = self._first_missing(data, length)
            # A run of failed reads ends in FAULT (safety.bus_errors_max) naming one joint: the
            # deepest any read of the run reached. The SDKs give up at the first servo without a
            # good reply, so every servo from it on went unanswered in that read too: a reply made
            # late by a loaded host shows an earlier servo missing in one read, while a silent
            # servo is the first missing in every read that gets as far as it.
            run = self._failed_run
            if run is not None and (i is None or run[0] > i):
                i, result = run
            self._failed_run = (i, result) if i is not None else None
        code = "bus_corrupt" if result == self.RX_CORRUPT else "bus_timeout"
        what = "bad reply" if code == "bus_corrupt" else "no reply"
        who = f" from {self._label[i]}" if i is not None else ""
        return Fault(code,
                     f"{self.robot}: {what}{who} to the sync read of ids "
                     f"{','.join(map(str, self._ids))} on {self._where} ({self._attempts} attempt"
                     f"{'s' if self._attempts > 1 else ''}): {self._result_text(result)}",
                     joint=self.joint_names[i] if i is not None else None, transient=True)

    # ------------------------------------------------------------------ lifecycle
    def _open_port(self) -> tuple[Any, float]:
        """Resolve ``backend.port``, open it at the profile's baud rate; set ``self._port`` and
        ``self._ph``. Returns (port, packet margin in ms). Blocks. Raises BackendError."""
        cfg = self.config
        self._port_path = resolve_port(cfg.port, self.robot, self.source)
        margin = DEFAULT_MARGIN_MS if cfg.timeout_ms is None else cfg.timeout_ms
        port = self._make_port(margin)
        port.baudrate = cfg.baudrate
        try:
            ok = port.openPort()
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
            raise BackendError(f"{self.robot}: cannot open port {self._where}: "
                               f"{open_error_reason(self._where, exc)}") from exc
        if not ok:
            raise BackendError(f"{self.robot}: cannot open port {self._where} at {cfg.baudrate} baud")
        self._port = port
        self._ph = self._make_packet_handler()
        return port, margin

    # ------------------------------------------------------------------ bus scan (check --scan)
    def scan_plan(self, all_bauds: bool) -> tuple[int | None, str]:
        return self.config.baudrate, (f"at {self.config.baudrate} baud{' (then every other rate)' if all_bauds else ''}, "
                                      f"ids 0-{self.MAX_ID}")

    def setup_devices(self, joints, emit, ask, timeout_s: float) -> int:
        """``crtk-bridge setup-servos`` (backends/servo_setup.py)."""
        from .servo_setup import ServoSetup

        return ServoSetup(self, emit, ask, timeout_s).run(joints)

    def scan(self, all_bauds: bool = False) -> BusScan:
        """Every servo answering on the bus at the profile's baud rate, by id: model number,
        firmware, torque state, and for a joint's servo of the right model its EEPROM
        differences (:meth:`eeprom_diffs`). Opens the port only for the scan (call it on a
        backend that is not open); writes nothing. Ids 0..MAX_ID are swept (:meth:`_discover`:
        the vendor's broadcast ping, else one ping per id); a profile id silent in the sweep is
        pinged again with the usual retries before it counts as missing. ``all_bauds``: also a
        broadcast ping at every other supported rate. Blocks (~1-3 s, more with all_bauds).
        Raises BackendError when the port does not open."""
        port, _ = self._open_port()
        try:
            servos = self._scan_servos()
            elsewhere = {}
            for baud in (b for b in self.SUPPORTED_BAUDS if all_bauds and b != self.config.baudrate):
                if not port.setBaudRate(baud):
                    continue
                found, _ = self._broadcast_ping()
                if found:
                    elsewhere[baud] = sorted(found.items())
            return BusScan(servos, elsewhere)
        finally:
            port.closePort()
            self._port = None

    def _scan_servos(self) -> list[ScannedServo]:
        """The servos answering at the port's rate (see :meth:`scan`). Blocks."""
        found = self._discover()
        for sid in self._ids:
            if sid not in found:
                model, result, _ = self._txrx(self._ph.ping, sid)
                if result == COMM_SUCCESS:
                    found[sid] = (model, None)
        names = {number: name for name, number in self.MODEL_NUMBERS.items()}
        out = []
        for sid, (number, firmware) in sorted(found.items()):
            model = names.get(number)
            firmware, torque = self._identify(sid, model, firmware)
            eeprom, error = (), None
            i = self._ids.index(sid) if sid in self._ids else None
            if i is not None and number == self.MODEL_NUMBERS[self.joint_keys[i].model]:
                try:
                    eeprom = tuple(self._patient_eeprom_diffs(i))
                except BackendError as exc:
                    error = str(exc).removeprefix(f"{self.robot}: ")
            out.append(ScannedServo(sid, number, model, firmware, torque, eeprom, error))
        return out

    def _discover(self) -> dict[int, tuple[int, int | None]]:
        """id -> (model number, firmware or None) of every servo answering a ping: one ping per
        id, a single attempt each (a missing id costs one packet timeout). Vendors with a
        broadcast ping override this."""
        found = {}
        for sid in range(self.MAX_ID + 1):
            self._port.is_using = False
            try:
                model, result, _ = self._ph.ping(self._port, sid)
            except IndexError:  # a truncated reply (see _txrx)
                continue
            if result == COMM_SUCCESS:
                found[sid] = (model, None)
        return found

    def _read_id(self, sid: int, address: int, size: int = 1) -> int | None:
        """One register of the servo with bus id ``sid`` (joint or not), or None without reply
        (a reply of another length is not one: see :meth:`_txrx`)."""
        data, result, _ = self._txrx(self._ph.readTxRx, sid, address, size, length=size)
        return int.from_bytes(bytes(data), "little") if result == COMM_SUCCESS else None

    def _identify(self, sid: int, model: str | None, firmware: int | None) -> tuple[str | None, bool | None]:
        """(firmware version text, torque on) of servo ``sid`` of ``model`` (None: unknown model),
        read from it; None where it did not say."""
        raise NotImplementedError

    def scan_report(self, scan: BusScan, hint: str = "") -> tuple[list[str], list[str], dict]:
        """(one line per servo, per missing joint, per EEPROM difference and per servo at another
        rate; the mismatches; the same findings as data) of a :meth:`scan` against the profile: a
        joint's id that did not answer, a servo of another model than the joint's, an id that
        answered but no joint has, an EEPROM setting that differs (naming the register), a servo
        at another baud rate (``hint``: the command that fixes it). The data (``crtk-bridge check
        --json``, docs/check.md): ``joints`` (one per profile joint: joint, id, expected_model,
        status ok / missing / wrong_model, model, model_number, firmware, torque, eeprom [register,
        value, expected, key, enable_refused, why, remedy], eeprom_error), ``extra`` (id, model,
        model_number, firmware, torque) and ``other_rates`` (id, baudrate, model, model_number)."""
        by_id = {s.id: s for s in scan.servos}
        lines, problems = [], []
        findings: dict[str, list] = {"joints": [], "extra": [], "other_rates": []}

        def servo(s: ScannedServo) -> dict:
            return {"model": s.model, "model_number": s.model_number, "firmware": s.firmware, "torque": s.torque}

        def describe(s: ScannedServo) -> str:
            torque = {True: "torque on", False: "torque off", None: "torque ?"}[s.torque]
            return (f"{s.model or 'unknown model'} (model number {s.model_number})  "
                    f"firmware {s.firmware or '?'}  {torque}")

        for i, (name, j) in enumerate(zip(self.joint_names, self.joint_keys)):
            s = by_id.pop(self._ids[i], None)
            joint = {"joint": name, "id": self._ids[i], "expected_model": j.model}
            findings["joints"].append(joint)
            if s is None:
                lines.append(f"id {self._ids[i]:3d}  {name:<16} MISSING: no reply")
                problems.append(f"{self._label[i]}: no reply at {self.config.baudrate} baud")
                joint.update(status="missing", model=None, model_number=None, firmware=None, torque=None,
                             eeprom=[], eeprom_error=None)
                continue
            expected = self.MODEL_NUMBERS[j.model]
            ok = s.model_number == expected
            joint.update(status="ok" if ok else "wrong_model", **servo(s), eeprom_error=s.eeprom_error,
                         eeprom=[{"register": d.register, "value": d.value, "expected": d.expected, "key": d.key,
                                  "enable_refused": d.wrong_positions, "why": d.why, "remedy": d.remedy}
                                 for d in s.eeprom])
            lines.append(f"id {s.id:3d}  {name:<16} {describe(s)}"
                         f"{'' if ok else f'  WRONG MODEL: the profile says {j.model}'}")
            if not ok:
                problems.append(f"{self._label[i]}: is model number {s.model_number} "
                                f"({s.model or 'unknown'}), the profile says {j.model} ({expected})")
            for d in s.eeprom:
                lines.append(f"         EEPROM {d.register} = {d.value}, expected {d.expected} ({d.key})"
                             f"{'  (enable refused)' if d.wrong_positions else ''}")
                problems.append(d.message())
            if s.eeprom_error:
                lines.append(f"         EEPROM not read: {s.eeprom_error}")
                problems.append(s.eeprom_error)
        for s in by_id.values():
            findings["extra"].append({"id": s.id, **servo(s)})
            lines.append(f"id {s.id:3d}  {'(no joint)':<16} {describe(s)}  EXTRA: not in the profile")
            problems.append(f"id {s.id} ({s.model or f'model number {s.model_number}'}) answered "
                            f"but no joint has this id")
        names = {number: name for name, number in self.MODEL_NUMBERS.items()}
        for baud, servos in sorted(scan.elsewhere.items()):
            for sid, number in servos:
                what = names.get(number) or f"model number {number}"
                findings["other_rates"].append({"id": sid, "baudrate": baud, "model": names.get(number),
                                                "model_number": number})
                lines.append(f"id {sid:3d}  at {baud} baud  {what}  OTHER RATE: the profile's is "
                             f"{self.config.baudrate}")
                problems.append(f"id {sid} ({what}) answers at {baud} baud, not the profile's "
                                f"{self.config.baudrate}{hint}")
        findings["servos_answered"] = len(scan.servos)
        return lines, problems, findings

    def _open_hook(self) -> None:
        """Open the port, ping every servo and check its model. Blocks. Raises BackendError."""
        cfg = self.config
        port, margin = self._open_port()
        try:
            self._check_servos()
            self._startup_check()
            self._after_open()
        except BaseException:
            port.closePort()
            self._port = None
            raise
        self._details = {
            "port": self._where, "baudrate": cfg.baudrate, "ids": list(self._ids),
            "models": {name: j.model for name, j in zip(self.joint_names, self.joint_keys)},
            "packet_margin_ms": margin, **self._details,
        }

    def _check_servos(self) -> None:
        problems = []
        answered = False
        deadline = time.monotonic() + self.OPEN_PATIENCE_S
        for i, j in enumerate(self.joint_keys):
            while True:  # a servo (or simulator) still starting, or a loaded host, gets a moment
                model, result, _ = self._txrx(self._ph.ping, self._ids[i])
                if result == COMM_SUCCESS or time.monotonic() > deadline:
                    break
            answered = answered or result == COMM_SUCCESS
            if result != COMM_SUCCESS:
                problems.append(f"{self._label[i]} did not answer ping on {self._where}: "
                                f"{self._result_text(result)}")
            elif model != self.MODEL_NUMBERS[j.model]:
                problems.append(f"{self._label[i]} on {self._where} is model number {model}, "
                                f"expected {self.MODEL_NUMBERS[j.model]} ({j.model})")
        if problems and len(problems) == self.n and not answered:
            problems.append(silent_bus_hint(self.config.baudrate, self._ids))
        if problems:
            raise BackendError(f"{self.robot}: " + "; ".join(problems))

    def _disable_steps(self) -> Steps:
        """DISABLE (also the fault reaction's torque off), stepped: in its first step ONE sync
        write of Torque_Enable = 0 to every servo (one transaction, no acknowledgement: every
        servo that hears it is unpowered at once, the whole arm safe in one packet), then one
        servo per step (per cycle): Torque_Enable = 0 written again, acknowledged -- the
        confirmation, and the torque off of a servo that missed the sync write.

        Tries every servo even if one fails, then raises BackendError naming those that did not
        confirm. Status error bits do not count as failure here (torque off is what we want).
        Raises at once while the port is gone (hot replug): torque off is not confirmed then.
        """
        self._check_not_lost("torque off")
        if self._port is None:
            return
        self._torque_sync_write(range(self.n), 0)  # a failed send is caught by the confirmations
        failed = []
        for i in range(self.n):
            if i:
                yield  # one servo's confirmation per cycle, between the cycle's reads
            try:
                self._write_register(i, "Torque_Enable", 0)
            except BackendError as exc:
                failed.append(str(exc).removeprefix(f"{self.robot}: "))
                if i == 0 and self._failed_run is not None:
                    # the cycle's sync read fails too: the bus itself does not answer (a pulled
                    # cable). Said now (the fault's own event carries it), not n cycles later;
                    # core retries the torque off once reads succeed again.
                    failed.append(f"the other servos' (sent in one sync write) neither: the sync read of "
                                  f"ids {','.join(map(str, self._ids))} gets no reply either")
                    break
        self._free = [False] * self.n
        if failed:
            raise BackendError(f"{self.robot}: torque off not confirmed: " + "; ".join(failed))

    def _disable_hook(self) -> None:
        """:meth:`_disable_steps` run to the end at once (start-up and reopen paths: configure
        switches torque off first). Blocks. Raises BackendError."""
        for _ in self._disable_steps():
            pass

    def _torque_sync_write(self, joints, value: int) -> int:
        """ONE sync write of Torque_Enable = ``value`` to the servos of ``joints`` (indices), no
        acknowledgement. Returns the SDK result. Never waits for a reply."""
        address, size = self._register(0, "Torque_Enable")
        param = self._torque_param
        del param[:]
        for i in joints:
            param.append(self._ids[i])
            param.append(value)
        port = self._port
        port.is_using = False
        result = self._ph.syncWriteTxOnly(port, address, size, param, len(param))
        port.is_using = False
        return result

    #: time limits (s) of the lifecycle transitions (a vendor's ``_traits_hook`` may grow ENABLE's)
    TRANSITION_TIMEOUTS_S = {Lifecycle.ENABLE: 5.0, Lifecycle.DISABLE: 2.0, Lifecycle.PAUSE: 1.0,
                             Lifecycle.RESUME: 1.0, Lifecycle.FAULT_RESET: 1.0}

    def _enable_steps(self, feedback) -> Steps:
        """ENABLE, one bus step per cycle (see the module docstring): the vendor's preparation
        (:meth:`_before_enable`), then per servo in joint order, in its own cycle: goal = a fresh
        read of its present position (:meth:`_hold_here`), then Torque_Enable = 1, each
        acknowledged and error-checked -- so enabling never moves the arm and no joint stays
        free; then one Torque_Enable read per cycle until every servo reports torque on. Raises
        BackendError naming joint and register; on failure the servos already on are switched
        off again (best effort)."""
        self._require_open("enable")
        if self._enable_refusal:
            raise BackendError(self._enable_refusal)
        yield from self._before_enable()
        self._free = [False] * self.n
        try:
            for i in range(self.n):
                yield from self._retrying(self._hold_and_torque, i)
                yield
            i = 0
            while i < self.n:  # the servos say torque is on, in joint order
                if (yield from self._retrying(self._read_register, i, "Torque_Enable")) == 1:
                    i += 1
                else:
                    yield
        except Exception:
            # roll back: every servo torque off, stepped like DISABLE (its first step is one sync
            # write to all of them), then the failure
            try:
                yield from self._disable_steps()
            except BackendError:
                pass
            raise

    #: cycles a transition step's transactions are tried (each with the lifecycle attempts)
    #: before the transition fails: a late reply on a loaded host must not fail a long enable
    STEP_CYCLES = 3

    def _retrying(self, fn, *args) -> Steps:
        """Steps running ``fn(*args)`` (idempotent bus transactions) and returning its value; a
        BackendError is retried in the next cycle, up to STEP_CYCLES cycles, then raised."""
        for cycle in range(self.STEP_CYCLES):
            try:
                return fn(*args)
            except BackendError:
                if cycle == self.STEP_CYCLES - 1:
                    raise
            yield

    def _hold_and_torque(self, i: int) -> None:
        self._hold_here(i)
        self._write_register(i, "Torque_Enable", 1, check_error=True)

    def _before_enable(self) -> Steps:
        """Vendor steps before any servo is held and torqued (Dynamixel: reboot servos in
        hardware error). Default: none."""
        yield from ()

    def _hold_here(self, i: int) -> None:
        """Goal of servo ``i`` = a fresh read of its present position, acknowledged (two
        transactions). Raises BackendError."""
        raise NotImplementedError

    def _error_status(self, fault: Any) -> None:
        """Report the device status from this read's servo error bits: FAULT with ``fault`` when
        they appear, FAULT_CLEARED once they are gone (:meth:`Actuator.report_status`)."""
        if fault is not None:
            self.report_status(DeviceStatus.FAULT, fault)
        elif self.device_status is DeviceStatus.FAULT:
            self.report_status(DeviceStatus.FAULT_CLEARED)

    def _close_hook(self) -> None:
        self._reopen_stop.set()
        worker = self._reopen_thread
        if worker is not None and worker is not threading.current_thread():
            worker.join(5.0)
        if self._port is not None:
            self._port.closePort()
        self._port = None


def _schema_keys(calibration: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Only the keys the profile's ``calibration`` schema has (servo_keys.Calibration): what a
    calibration measures beyond them is not written."""
    known = set(Calibration.__struct_fields__)
    return {name: {k: v for k, v in keys.items() if k in known} for name, keys in calibration.items()}

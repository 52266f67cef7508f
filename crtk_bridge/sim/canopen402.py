"""Simulated CiA 402 servo drives on a CAN bus (canopen ``LocalNode`` plus what it lacks).

canopen 2.4.1's :class:`canopen.LocalNode` serves SDO, NMT and heartbeat from an object
dictionary, but has no PDO behaviour and no device profile (canopen issue #558; docs/architecture.md,
"Sources": CANopen CiA 402). :class:`Drive402` adds, for one node id:

- the object dictionary built in code (:func:`make_object_dictionary`): CiA 301 communication
  objects (0x1000, 0x1001, 0x1005, 0x1014, 0x1016, 0x1017, 0x1018, RPDO 0x1400-0x1403 / 0x1600-0x1603,
  TPDO 0x1800-0x1803 / 0x1A00-0x1A03) and the CiA 402 objects the bridge uses (0x6007, 0x603F, 0x6040,
  0x6041, 0x605A, 0x6060, 0x6061, 0x6064, 0x6065, 0x6066, 0x606C, 0x6071, 0x6072, 0x6076, 0x6077,
  0x607A, 0x607C, 0x6085, 0x6098, 0x6099, 0x609A, 0x60C2, 0x60F4, 0x60FF, 0x6502); every
  variable has a default, so every SDO read answers;
- PDOs as CiA 301 says: the configuration the master writes over SDO is re-read when the node
  enters OPERATIONAL and on every write to 0x14xx-0x1Axx; mapping writes are checked (abort
  0x06040041 not mappable, 0x06040042 too long, 0x06010000 while the PDO is valid); received
  RPDOs are applied only in OPERATIONAL (SYNC-type ones at the next SYNC, event ones at once; a
  too-short RPDO is dropped with EMCY 0x8210); SYNC-type TPDOs (transmission type 1-240: every
  n-th SYNC; 0: at SYNC when changed) are sampled and sent on SYNC, event ones (254/255) on change
  (inhibit time) and on their event timer;
- the CiA 402 state machine (:class:`State`, :data:`STATUSWORD`; transitions numbered as in
  CiA 402-2 figure "State machine"): shutdown / switch on / enable operation / disable voltage /
  quick stop (stays in QUICK STOP ACTIVE after the ramp, 0x605A = 6; 1-2 go on to SWITCH ON
  DISABLED), fault reaction (quick-stop ramp, then FAULT), fault reset on a rising edge of
  controlword bit 7 (EMCY 0x0000 "error reset" on leaving FAULT);
- motion at a fixed internal rate (:data:`PHYSICS_DT_S`) advanced to the current time on every
  SYNC, SDO read and simulator tick: CSP (8) tracks 0x607A as a first-order lag capped at the
  drive's top speed, CSV (9) 0x60FF, CST (10) 0x6071 (speed proportional to torque, first order);
  homing (6) methods 35 / 37 (current position: at once) and 17 / 18 (search the negative /
  positive limit switch at 0x6099:1, taking time), statusword bits 10 / 12 / 13 as CiA 402 says;
- following error: in CSP, |0x607A - 0x6064| above 0x6065 for longer than 0x6066 ms faults
  the drive with EMCY 0x8611 and statusword bit 13;
- boot-up message, heartbeat producer (0x1017), EMCY producer (0x1001 / 0x603F kept in step:
  0x1001 holds the bits of the active fault and warning, and every EMCY carries it; EMCY 0x0000
  when an error ends: fault reset, a warning gone, a lost master heard again, NMT STOPPED left;
  no EMCY in NMT STOPPED, CiA 301),
  heartbeat consumer (0x1016: a monitored master gone silent -> EMCY 0x8130 and the reaction
  0x6007 names: fault by default, disable voltage or quick stop), so a drive left by a dead
  master stops as a real one does; NMT STOPPED entered while the power stage is on gets the same
  0x6007 reaction (error 0x8100, kept in 0x603F / 0x1001: no EMCY in STOPPED).

:class:`CanopenSimulator` is several drives on one bus in the shape of the serial simulators
(``from_profile``, ``start``, ``stop``, ``port``, fault injection, a control socket). Each drive
has its own :class:`canopen.Network` (a silenced node truly sends and hears nothing), and the
drives share one bus endpoint (python-can ``virtual`` channel in-process, or socketcan ``vcan0``
where the kernel has it) whose one notifier thread hands every frame to each drive in turn, the
drives' own frames too (they hear each other as on a real bus). One receive thread per drive
woke for every frame on the bus, each a thread switch and GIL hand-off: most of the simulator's
CPU at 250 Hz (issue 23: "the simulators count too"). Behind the simulated USB-CAN adapter
(``interface="slcan"``, what ``--sim`` runs) the drives and the adapter share the in-process bus
of :mod:`crtk_bridge.sim.canbus` instead of a ``virtual`` channel: the drives handle a frame in
the adapter's thread that parsed it, with no receive thread at all (a deepcopy and a thread
hand-off per frame and endpoint were ~half of the simulator's CPU per cycle).
:meth:`Drive402.connect` still gives a drive an endpoint and a notifier of its own.
"""

from __future__ import annotations

import enum
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import can
import canopen
from canopen import objectdictionary as odm
from canopen.sdo import SdoAbortedError

from ..profile import Profile
from . import SimulatorError, canbus

log = logging.getLogger(__name__)

#: internal motion step (s): the drive's own control rate, whatever the SYNC period is
PHYSICS_DT_S = 0.001
#: the simulator thread's period (s): event TPDOs, following error and homing between SYNCs
TICK_S = 0.005
#: how long a Network's notifier waits per iteration: bounds stop() (canopen's default is 1 s)
NOTIFIER_CYCLE_S = 0.02
_MAX_CATCH_UP_S = 1.0  # a stalled simulator jumps rather than replaying more than this

# --- CiA 301 ------------------------------------------------------------------------------
NMT_BOOTUP, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0, 4, 5, 127
PDO_INVALID = 1 << 31  # COB-ID bit 31: the PDO does not exist / is not valid
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_TOO_LONG = 0x06040042
ABORT_VALUE_RANGE = 0x06090030
EMCY_PDO_LENGTH = 0x8210  # PDO not processed due to length error
EMCY_PDO_TOO_LONG = 0x8220  # PDO length exceeded
EMCY_FOLLOWING_ERROR = 0x8611
EMCY_HEARTBEAT = 0x8130  # life guard / heartbeat error
EMCY_COMMUNICATION = 0x8100  # communication, generic: here "NMT STOPPED entered" (0x6007)
EMCY_RESET = 0x0000
#: NMT states in which the EMCY producer may send (CiA 301 "EMCY object": PRE-OPERATIONAL and
#: OPERATIONAL only; an error in STOPPED is kept in 0x1001 / 0x603F, not sent)
_EMCY_STATES = (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL)
#: error register 0x1001 bits (CiA 301 "Error register": 0 generic, 1 current, 2 voltage,
#: 3 temperature, 4 communication, 5 device profile specific, 7 manufacturer specific) by the
#: EMCY code's group (its high byte) or class (its high nibble) in CiA 301 table "Emergency
#: error codes" and CiA 402-2's codes: the drive monitoring groups 0x83-0x8A (torque, velocity,
#: position, positioning controller (0x8611 following error), sync, winding, process data,
#: control) are device profile specific, not communication (0x81 communication, 0x82 protocol)
_REGISTER_BY_GROUP = {0x81: 0x10, 0x82: 0x10, **{g: 0x20 for g in range(0x83, 0x8B)}, 0xFF: 0x80}
_REGISTER_BY_CLASS = {0x2: 0x02, 0x3: 0x04, 0x4: 0x08}


def error_register(code: int) -> int:
    """0x1001 for an active error with EMCY ``code``: bit 0 (generic) plus its class bit (none
    for a class without one: generic, hardware, software, modules, monitoring, external)."""
    if code == 0:
        return 0
    return 0x01 | _REGISTER_BY_GROUP.get(code >> 8, _REGISTER_BY_CLASS.get(code >> 12, 0))


# --- CiA 402 ------------------------------------------------------------------------------
class State(enum.Enum):
    """CiA 402 power drive system states; value: the statusword bits of the state (mask in
    :data:`STATE_MASK`), CiA 402-2 table "Statusword state bits"."""

    NOT_READY_TO_SWITCH_ON = 0x00
    SWITCH_ON_DISABLED = 0x40
    READY_TO_SWITCH_ON = 0x21
    SWITCHED_ON = 0x23
    OPERATION_ENABLED = 0x27
    QUICK_STOP_ACTIVE = 0x07
    FAULT_REACTION_ACTIVE = 0x0F
    FAULT = 0x08


STATE_MASK = {s: (0x4F if s in (State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED,
                                State.FAULT_REACTION_ACTIVE, State.FAULT) else 0x6F) for s in State}
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5  # 0: quick stop active
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_BIT12 = 1 << 12  # CSP/CSV/CST: drive follows the command value; HM: homing attained
SW_BIT13 = 1 << 13  # CSP: following error; HM: homing error
CW_SWITCH_ON, CW_ENABLE_VOLTAGE, CW_QUICK_STOP, CW_ENABLE_OPERATION = 1, 2, 4, 8
CW_HOMING_START = 1 << 4
CW_FAULT_RESET = 1 << 7
CW_HALT = 1 << 8


class Mode(enum.IntEnum):
    """Modes of operation (0x6060 / 0x6061) this drive supports."""

    HOMING = 6
    CSP = 8
    CSV = 9
    CST = 10


#: 0x6502 bit of each mode (CiA 402-2 "Supported drive modes")
MODE_BIT = {Mode.HOMING: 1 << 5, Mode.CSP: 1 << 7, Mode.CSV: 1 << 8, Mode.CST: 1 << 9}
HOMING_CURRENT_POSITION = (35, 37)
HOMING_LIMIT_SWITCH = {17: -1, 18: +1}  # method -> search direction


def command_transition(state: State, cw: int) -> State:
    """The state the controlword ``cw`` leads to from ``state`` (CiA 402-2 table "Command
    coding"; fault reset and the timed states are handled by the caller). Numbers: transitions."""
    voltage, quick, on, enable = cw & CW_ENABLE_VOLTAGE, cw & CW_QUICK_STOP, cw & CW_SWITCH_ON, cw & CW_ENABLE_OPERATION
    if state in (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE, State.FAULT):
        return state
    if not voltage:  # disable voltage: 7, 9, 10, 12
        return State.SWITCH_ON_DISABLED
    if not quick:  # quick stop: 7, 10 -> SWITCH ON DISABLED; 11 -> QUICK STOP ACTIVE
        if state is State.OPERATION_ENABLED:
            return State.QUICK_STOP_ACTIVE
        return State.QUICK_STOP_ACTIVE if state is State.QUICK_STOP_ACTIVE else State.SWITCH_ON_DISABLED
    if state is State.QUICK_STOP_ACTIVE:
        return State.OPERATION_ENABLED if on and enable else state  # 16 (0x605A 5..8)
    if not on:  # shutdown: 2, 6, 8
        return State.READY_TO_SWITCH_ON
    if state is State.SWITCH_ON_DISABLED:
        return state  # switch on needs READY TO SWITCH ON first
    if not enable:  # switch on: 3, disable operation: 5
        return State.SWITCHED_ON
    return State.OPERATION_ENABLED  # enable operation: 4 (3 + 4 from READY TO SWITCH ON)


# --- object dictionary ---------------------------------------------------------------------
U8, U16, U32 = odm.UNSIGNED8, odm.UNSIGNED16, odm.UNSIGNED32
I8, I16, I32 = odm.INTEGER8, odm.INTEGER16, odm.INTEGER32


def _var(name: str, index: int, sub: int, dtype: int, access: str, default, pdo: bool = False):
    v = odm.ODVariable(name, index, sub)
    v.data_type, v.access_type, v.default, v.pdo_mappable = dtype, access, default, pdo
    return v


def _record(od, cls, name: str, index: int, members: list[tuple[int, str, int, str, object]]):
    rec = cls(name, index)
    rec.add_member(_var("Highest sub-index supported", index, 0, U8, "ro", max(m[0] for m in members)))
    for sub, mname, dtype, access, default in members:
        rec.add_member(_var(mname, index, sub, dtype, access, default))
    od.add_object(rec)


@dataclass(frozen=True)
class DriveOptions:
    """What a simulated drive is like (raw device units: counts, counts/s, per mille)."""

    position: int = 0  #: position actual at power-on (counts)
    max_velocity: float = 200_000.0  #: top speed (counts/s)
    tau_s: float = 0.01  #: position / velocity tracking time constant (s)
    torque_velocity: float = 200.0  #: CST: steady speed per per-mille of torque (counts/s)
    following_window: int = 50_000  #: 0x6065 default (counts)
    following_timeout_ms: int = 10  #: 0x6066 default
    heartbeat_ms: int = 0  #: 0x1017 default (0: the master sets it)
    limit_switch: int = 20_000  #: homing 17/18: the switch is this far from power-on (counts)
    homing_speed: int = 100_000  #: 0x6099:1 default (counts/s)
    modes: tuple[int, ...] = (6, 8, 9, 10)  #: supported modes of operation (0x6502)
    rated_torque_mnm: int = 1000  #: 0x6076 motor rated torque (mN*m): what 1000 per mille is
    vendor_id: int = 0x00C2B51D  #: 0x1018:1 (not a registered vendor: a simulator)
    product_code: int = 0x402


def make_object_dictionary(node_id: int, opts: DriveOptions = DriveOptions()) -> odm.ObjectDictionary:
    """The drive's object dictionary, built in code; every variable has a default."""
    od = odm.ObjectDictionary()
    od.node_id = node_id
    add = od.add_object
    add(_var("Device type", 0x1000, 0, U32, "ro", 0x00020192))
    add(_var("Error register", 0x1001, 0, U8, "ro", 0, pdo=True))
    add(_var("COB-ID SYNC", 0x1005, 0, U32, "rw", 0x80))
    add(_var("Manufacturer device name", 0x1008, 0, odm.VISIBLE_STRING, "const", "crtk-bridge sim402"))
    add(_var("COB-ID EMCY", 0x1014, 0, U32, "ro", 0x80 + node_id))
    _record(od, odm.ODRecord, "Consumer heartbeat time", 0x1016, [
        (sub, f"Consumer heartbeat time {sub}", U32, "rw", 0) for sub in range(1, 5)])
    add(_var("Producer heartbeat time", 0x1017, 0, U16, "rw", opts.heartbeat_ms))
    _record(od, odm.ODRecord, "Identity object", 0x1018, [
        (1, "Vendor-ID", U32, "ro", opts.vendor_id), (2, "Product code", U32, "ro", opts.product_code),
        (3, "Revision number", U32, "ro", 0x00010000), (4, "Serial number", U32, "ro", node_id)])
    for n in range(4):
        # CiA 402 predefined connection: RPDO1 = controlword, TPDO1 = statusword, event driven
        rx_cob = (0x200 + 0x100 * n + node_id) | (0 if n == 0 else PDO_INVALID)
        tx_cob = (0x180 + 0x100 * n + node_id) | (0 if n == 0 else PDO_INVALID)
        _record(od, odm.ODRecord, f"RPDO {n + 1} communication parameter", 0x1400 + n, [
            (1, "COB-ID", U32, "rw", rx_cob), (2, "Transmission type", U8, "rw", 255),
            (3, "Inhibit time", U16, "rw", 0), (5, "Event timer", U16, "rw", 0)])
        _record(od, odm.ODRecord, f"TPDO {n + 1} communication parameter", 0x1800 + n, [
            (1, "COB-ID", U32, "rw", tx_cob), (2, "Transmission type", U8, "rw", 255),
            (3, "Inhibit time", U16, "rw", 0), (5, "Event timer", U16, "rw", 0)])
        for base, first in ((0x1600, 0x60400010), (0x1A00, 0x60410010)):
            # a RECORD, as CiA 301 declares it (canopen's PdoMap.save() writes a RECORD's entries
            # whatever sub0 says; an ARRAY's only up to sub0, which it has just set to 0)
            arr = odm.ODRecord(f"{'R' if base == 0x1600 else 'T'}PDO {n + 1} mapping parameter", base + n)
            arr.add_member(_var("Number of mapped objects", base + n, 0, U8, "rw", 1 if n == 0 else 0))
            for sub in range(1, 9):
                arr.add_member(_var(f"Mapped object {sub}", base + n, sub, U32, "rw",
                                    first if (n == 0 and sub == 1) else 0))
            add(arr)
    add(_var("Abort connection option code", 0x6007, 0, I16, "rw", 1))
    add(_var("Error code", 0x603F, 0, U16, "ro", 0, pdo=True))
    add(_var("Controlword", 0x6040, 0, U16, "rw", 0, pdo=True))
    add(_var("Statusword", 0x6041, 0, U16, "ro", 0, pdo=True))
    add(_var("Quick stop option code", 0x605A, 0, I16, "rw", 6))
    add(_var("Modes of operation", 0x6060, 0, I8, "rw", 0, pdo=True))
    add(_var("Modes of operation display", 0x6061, 0, I8, "ro", 0, pdo=True))
    add(_var("Position actual value", 0x6064, 0, I32, "ro", 0, pdo=True))
    add(_var("Following error window", 0x6065, 0, U32, "rw", opts.following_window))
    add(_var("Following error time out", 0x6066, 0, U16, "rw", opts.following_timeout_ms))
    add(_var("Velocity actual value", 0x606C, 0, I32, "ro", 0, pdo=True))
    add(_var("Target torque", 0x6071, 0, I16, "rw", 0, pdo=True))
    add(_var("Max torque", 0x6072, 0, U16, "rw", 3000))
    add(_var("Motor rated torque", 0x6076, 0, U32, "rw", opts.rated_torque_mnm))
    add(_var("Torque actual value", 0x6077, 0, I16, "ro", 0, pdo=True))
    add(_var("Target position", 0x607A, 0, I32, "rw", 0, pdo=True))
    add(_var("Home offset", 0x607C, 0, I32, "rw", 0))
    add(_var("Quick stop deceleration", 0x6085, 0, U32, "rw", int(opts.max_velocity * 20)))
    add(_var("Homing method", 0x6098, 0, I8, "rw", 37))
    # declared a RECORD: canopen's ODArray invents any sub-index 1..255, and a missing one must abort
    _record(od, odm.ODRecord, "Homing speeds", 0x6099, [
        (1, "Speed during search for switch", U32, "rw", opts.homing_speed),
        (2, "Speed during search for zero", U32, "rw", opts.homing_speed // 10)])
    add(_var("Homing acceleration", 0x609A, 0, U32, "rw", int(opts.max_velocity * 20)))
    _record(od, odm.ODRecord, "Interpolation time period", 0x60C2, [
        (1, "Interpolation time period value", U8, "rw", 1), (2, "Interpolation time index", I8, "rw", -3)])
    add(_var("Following error actual value", 0x60F4, 0, I32, "ro", 0, pdo=True))
    add(_var("Target velocity", 0x60FF, 0, I32, "rw", 0, pdo=True))
    add(_var("Supported drive modes", 0x6502, 0, U32, "ro",
             sum(MODE_BIT[Mode(m)] for m in opts.modes if m in MODE_BIT)))
    return od


# --- PDOs ----------------------------------------------------------------------------------
@dataclass
class _Pdo:
    """One PDO as the node's communication and mapping parameters say (re-read when changed)."""

    comm: int  # 0x14xx / 0x18xx
    cob: int = 0
    valid: bool = False
    trans: int = 255
    inhibit_s: float = 0.0
    event_s: float = 0.0
    entries: list[tuple[int, int, int]] = field(default_factory=list)  # (index, sub, bytes)
    objects: list[odm.ODVariable | None] = field(default_factory=list)  # each entry's variable
    size: int = 0
    syncs: int = 0  # SYNCs seen since the last transmission (TPDO)
    pending: bytes | None = None  # SYNC-type RPDO data awaiting the next SYNC
    last: bytes | None = None  # TPDO: data last sent
    sent_at: float = -math.inf


class _DriveNetwork(canopen.Network):
    """One drive's view of the bus: a muted drive (silent node, bus-off) sends and hears nothing,
    and a malformed frame never reaches (and kills) the notifier thread."""

    NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
    NOTIFIER_SHUTDOWN_TIMEOUT = 1.0

    def __init__(self, drive: Drive402):
        super().__init__()
        self.drive = drive
        self.muted = False
        self._reported: set[int] = set()

    def send_message(self, can_id: int, data, remote: bool = False) -> None:
        if not self.muted:
            super().send_message(can_id, data, remote)

    def notify(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.muted:
            return
        try:
            self.drive._on_frame(can_id, bytes(data), super().notify)
        except Exception as exc:  # a bad frame is dropped; the drive keeps serving
            if can_id not in self._reported:  # once per COB-ID: a flood must not flood the log
                self._reported.add(can_id)
                log.warning("drive %d: frame 0x%03X %s dropped: %r", self.drive.node_id, can_id,
                            bytes(data).hex(), exc)


class Drive402:
    """One simulated CiA 402 drive (node ``node_id``) on ``channel`` of python-can ``interface``.

    Thread-safe: the bus thread (SDO, NMT, SYNC, RPDOs), the simulator tick and the caller's
    inspection / fault injection all take :attr:`lock`. Units are the drive's: counts, counts/s,
    per mille of rated torque. ``clock``: monotonic seconds (a test may pass a fake one).
    """

    def __init__(self, node_id: int, options: DriveOptions = DriveOptions(), *,
                 clock: Callable[[], float] = time.monotonic):
        if not 1 <= node_id <= 127:
            raise SimulatorError(f"CANopen node id {node_id} must be 1..127")
        self.node_id = node_id
        self.options = options
        self.clock = clock
        self.lock = threading.RLock()
        self.od = make_object_dictionary(node_id, options)
        self.local = canopen.LocalNode(node_id, self.od)
        self.local.add_read_callback(self._on_read)
        self.local.add_write_callback(self._on_write)
        self.network = _DriveNetwork(self)
        self.network.add_node(self.local)
        # drive state (the object dictionary's dynamic values live here, not in data_store)
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.position = float(options.position)  # counts
        self.velocity = 0.0  # counts/s
        self.torque = 0.0  # per mille
        self.controlword = 0
        self.mode = 0  # display (0x6061)
        self.target_position = int(options.position)
        self.target_velocity = 0
        self.target_torque = 0
        self.error_code = 0  # the active fault's EMCY code (0x603F)
        self.warnings: set[int] = set()  # the active warnings' EMCY codes (statusword bit 7)
        self.following_error = False
        self.homing: tuple[str, int] = ("idle", 0)  # (phase, direction)
        self.homing_status = 0  # statusword bits 10/12/13 in HM
        self.homed = False
        self._switch_origin = float(options.position)  # homing 17/18: where the switches are
        self.jammed = False  # an external block: the shaft does not move (following error)
        self.heartbeat_stopped = False
        self.enable_delay_s = 0.0  # enable operation takes this long (brake release)
        self._enable_at: float | None = None
        self._ferr_since: float | None = None
        self._t = clock()
        self._rpdos = [_Pdo(0x1400 + n) for n in range(4)]
        self._tpdos = [_Pdo(0x1800 + n) for n in range(4)]
        self._pdo_dirty = True
        self._params: dict[tuple[int, int], int] = {}
        self._heartbeats: dict[int, float] = {}  # node id -> when its last heartbeat came
        self._lost: set[int] = set()  # monitored nodes whose heartbeat timed out, not heard since
        self._sync_cob = 0x80
        self.rx_frames = 0  # frames this drive received while not muted (bench / tests)
        self._shared_bus = False  # attach()ed to an endpoint it does not own
        self.sync_count = 0

    # ------------------------------------------------------------------ lifecycle
    def connect(self, interface: str, channel: str, **kwargs) -> None:
        """Join the bus and boot: boot-up message, PRE-OPERATIONAL, heartbeat if 0x1017 > 0."""
        self.network.connect(interface=interface, channel=channel, receive_own_messages=False, **kwargs)
        self.boot()

    def attach(self, bus: can.BusABC) -> None:
        """Join ``bus``, an endpoint shared with other drives whose owner hands this drive every
        frame (:meth:`hear`), and boot as :meth:`connect` does."""
        self._shared_bus = True
        self.network.bus = bus
        self.boot()

    def hear(self, msg: can.Message) -> None:
        """A frame from a shared endpoint (what canopen's listener does for its own network)."""
        if not (msg.is_error_frame or msg.is_remote_frame):
            self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)

    def disconnect(self) -> None:
        self.local.nmt.stop_heartbeat()
        if self.network.bus is not None:
            if self._shared_bus:  # the owner shuts it down
                self.network.bus = None
            else:
                self.network.disconnect()

    def boot(self) -> None:
        """Power-on / reset: INITIALISING -> boot-up message -> PRE-OPERATIONAL (CiA 301), and the
        402 state machine's automatic transitions 0 and 1 to SWITCH ON DISABLED."""
        with self.lock:
            self.state = State.SWITCH_ON_DISABLED
            self._pdo_dirty = True
            self.local.nmt.send_command(0x81)  # INITIALISING: sends the boot-up message
            self.local.nmt.send_command(0x80)  # PRE-OPERATIONAL: starts the heartbeat (0x1017)
            if self.heartbeat_stopped or self.network.muted:
                self.local.nmt.stop_heartbeat()

    # ------------------------------------------------------------------ bus side
    def _on_frame(self, can_id: int, data: bytes, dispatch) -> None:
        """Every frame this drive hears (bus thread). ``dispatch``: canopen's own handling
        (SDO server, NMT slave)."""
        with self.lock:
            self.rx_frames += 1
            if self._pdo_dirty:
                self._load_pdos()
            if can_id == 0:
                if len(data) == 2:  # CiA 301: an NMT frame of another length is not one
                    before = self.local.nmt._state
                    dispatch(can_id, data, 0.0)
                    self._after_nmt(data[0], data[1], before)
                return
            if can_id == self._sync_cob:
                if len(data) <= 1:
                    self._on_sync()
                return
            if 0x701 <= can_id <= 0x77F and len(data) == 1:
                node = can_id - 0x700
                self._heartbeats[node] = self.clock()  # another node's heartbeat
                if node in self._lost:  # a master heard again: its heartbeat error ends
                    self._lost.discard(node)
                    if not self._lost:
                        self._end_warning(EMCY_HEARTBEAT)
                return
            if can_id == 0x600 + self.node_id:
                # an SDO request is always 8 bytes; others are ignored. No SDO in STOPPED (CiA 301)
                if len(data) == 8 and self.local.nmt._state != NMT_STOPPED:
                    dispatch(can_id, data, 0.0)
                return
            if self.local.nmt._state != NMT_OPERATIONAL:
                return  # PDOs only in OPERATIONAL
            for pdo in self._rpdos:
                if pdo.valid and pdo.cob == can_id:
                    self._on_rpdo(pdo, data)

    def _after_nmt(self, cs: int, target: int, before: int) -> None:
        if target not in (0, self.node_id):
            return
        state = self.local.nmt._state
        if before == NMT_STOPPED and state in _EMCY_STATES:
            self._end_warning(EMCY_COMMUNICATION)  # the master took the node back: that error ends
        if cs in (0x81, 0x82):  # reset node / communication: defaults back, boot again
            keep = range(0x1000, 0x2000) if cs == 0x82 else range(0x1000, 0x10000)
            for index in [i for i in self.local.data_store if i in keep]:
                del self.local.data_store[index]
            self._params.clear()
            if cs == 0x81:
                self._reset_application()
            self.boot()
        elif state == NMT_OPERATIONAL and before != NMT_OPERATIONAL:
            self._pdo_dirty = True
            self._load_pdos()  # CiA 301: the PDO configuration takes effect on start
        elif state == NMT_STOPPED and before != NMT_STOPPED:
            self._advance(self.clock())
            if self.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
                self._abort_connection(EMCY_COMMUNICATION)  # CiA 402 0x6007: "NMT stopped entered"

    def _reset_application(self) -> None:
        now = self.clock()
        self._advance(now)
        self.controlword = self.mode = self.target_velocity = self.target_torque = 0
        self.target_position = round(self.position)
        self.error_code = 0
        self.warnings.clear()
        self._lost.clear()
        self.following_error = False
        self.homing, self.homing_status = ("idle", 0), 0

    def _on_sync(self) -> None:
        now = self.clock()
        self._advance(now)
        self.sync_count += 1
        if self.local.nmt._state != NMT_OPERATIONAL:
            return
        # CiA 301: RPDOs received since the previous SYNC take effect at this one; the TPDOs carry
        # the values sampled at it, after them (so a controlword's effect shows in the next reply)
        for pdo in self._rpdos:
            if pdo.pending is not None:
                data, pdo.pending = pdo.pending, None
                self._apply(pdo, data)
        for pdo in self._tpdos:
            if not pdo.valid or pdo.trans > 240:
                continue
            data = self._sample(pdo)
            if pdo.trans == 0:
                if data != pdo.last:
                    self._send_pdo(pdo, data, now)
                continue
            pdo.syncs += 1
            if pdo.syncs >= pdo.trans:
                pdo.syncs = 0
                self._send_pdo(pdo, data, now)

    def _on_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        if len(data) < pdo.size:
            self._emcy(EMCY_PDO_LENGTH, fault=False)
            return
        if len(data) > pdo.size:
            self._emcy(EMCY_PDO_TOO_LONG, fault=False)
            data = data[: pdo.size]
        if pdo.trans <= 240:
            pdo.pending = data
        else:
            self._advance(self.clock())
            self._apply(pdo, data)

    def _apply(self, pdo: _Pdo, data: bytes) -> None:
        # what LocalNode.set_data does for each mapped object -- its write callbacks (NMT's, then
        # ours) and its store -- with the object looked up and its length checked once per
        # mapping (_load_pdos; an object whose length does not match goes through set_data,
        # which refuses it): set_data's lookup per object per RPDO was a fifth of the
        # simulator's CPU
        local = self.local
        offset = 0
        for (index, sub, size), od in zip(pdo.entries, pdo.objects):
            chunk = data[offset:offset + size]
            offset += size
            try:
                if od is None:
                    local.set_data(index, sub, chunk)
                    continue
                for callback in local._write_callbacks:
                    callback(index=index, subindex=sub, od=od, data=chunk)
                local.data_store.setdefault(index, {})[sub] = bytes(chunk)
            except SdoAbortedError:
                pass  # e.g. an unsupported mode: the drive keeps its previous one

    def _sample(self, pdo: _Pdo) -> bytes:
        # what LocalNode.get_data does for each mapped object -- our read callback (the node's
        # only one) first, else its store -- with the objects looked up once per mapping
        # (_load_pdos): get_data's lookup per object per SYNC was a tenth of the simulator's CPU
        out = []
        for (index, sub, size), od in zip(pdo.entries, pdo.objects):
            value = self._on_read(index, sub, od) if od is not None else None
            out.append(od.encode_raw(value)[:size] if value is not None else self.local.get_data(index, sub)[:size])
        return b"".join(out)

    def _send_pdo(self, pdo: _Pdo, data: bytes, now: float) -> None:
        pdo.last, pdo.sent_at = data, now
        self.network.send_message(pdo.cob, data)

    def _load_pdos(self) -> None:
        """Re-read every PDO's communication and mapping parameters from the node's own store."""
        self._pdo_dirty = False
        raw = lambda index, sub: int.from_bytes(self.local.get_data(index, sub), "little")  # noqa: E731
        self._sync_cob = raw(0x1005, 0) & 0x7FF
        for pdos, tx in ((self._rpdos, False), (self._tpdos, True)):
            for n, pdo in enumerate(pdos):
                cob = raw(pdo.comm, 1)
                pdo.cob, pdo.valid = cob & 0x7FF, not cob & PDO_INVALID
                pdo.trans = raw(pdo.comm, 2)
                pdo.inhibit_s = raw(pdo.comm, 3) * 100e-6
                pdo.event_s = raw(pdo.comm, 5) / 1000.0
                mapping = pdo.comm + 0x200
                pdo.entries = []
                for sub in range(1, raw(mapping, 0) + 1):
                    entry = raw(mapping, sub)
                    pdo.entries.append((entry >> 16, (entry >> 8) & 0xFF, (entry & 0xFF) // 8))
                pdo.size = sum(e[2] for e in pdo.entries)
                pdo.objects = [self._object(*entry) for entry in pdo.entries]
                pdo.syncs, pdo.pending, pdo.last = 0, None, None

    def _object(self, index: int, sub: int, size: int) -> odm.ODVariable | None:
        """The object dictionary's variable ``index:sub`` if a number of ``size`` bytes, or None
        (get_data / set_data then answer as they do: an abort)."""
        try:
            od = self.local._find_object(index, sub)
        except SdoAbortedError:
            return None
        return od if od.data_type in odm.NUMBER_TYPES and len(od) == 8 * size else None

    # ------------------------------------------------------------------ object access
    def _param(self, index: int, sub: int = 0) -> int:
        """A configuration object's value, cached: the internal control reads several of them
        every millisecond. Writes (callback below) and NMT resets drop the cached value."""
        key = (index, sub)
        value = self._params.get(key)
        if value is None:
            value = self._params[key] = self.local._find_object(index, sub).decode_raw(
                self.local.get_data(index, sub))
        return value

    def _on_read(self, index: int, subindex: int, od) -> int | None:
        if index == 0x6041:
            self._advance(self.clock())
            return self.statusword()
        if index == 0x6064:
            self._advance(self.clock())
            return round(self.position)
        if index == 0x606C:
            return round(self.velocity)
        if index == 0x6077:
            return round(self.torque)
        if index == 0x6061:
            return self.mode
        if index == 0x603F:
            return self.error_code
        if index == 0x1001:
            return self.error_register()
        if index == 0x60F4:
            return self.target_position - round(self.position)
        if index == 0x6040:
            return self.controlword
        if index == 0x607A:
            return self.target_position
        if index == 0x60FF:
            return self.target_velocity
        if index == 0x6071:
            return self.target_torque
        return None

    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        value = od.decode_raw(data) if od.data_type in odm.NUMBER_TYPES else data
        self._params.pop((index, subindex), None)  # stored by LocalNode right after this callback
        if 0x1400 <= index <= 0x1403 or 0x1800 <= index <= 0x1803:
            self._check_comm_write(index, subindex, value)
        elif 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03:
            self._check_mapping_write(index, subindex, value)
        elif index == 0x1017 and (self.heartbeat_stopped or self.network.muted):
            # LocalNode's own callback (registered before this one) has just restarted the
            # producer: an injected stop holds
            self.local.nmt.stop_heartbeat()
        elif index == 0x1005:
            self._pdo_dirty = True
        now = self.clock()
        if index == 0x6040:
            self._advance(now)
            self._on_controlword(value, now)
        elif index == 0x6060:
            if value not in self.options.modes:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self._advance(now)
            self._set_mode(value)
        elif index == 0x607A:
            self.target_position = value
        elif index == 0x60FF:
            self.target_velocity = value
        elif index == 0x6071:
            self.target_torque = value

    def _check_comm_write(self, index: int, sub: int, value: int) -> None:
        if sub == 1:
            cob = value & 0x7FF
            if not value & PDO_INVALID and (value & (1 << 29) or not 0x180 <= cob <= 0x57F):
                raise SdoAbortedError(ABORT_VALUE_RANGE)  # no 29-bit ids; a PDO COB-ID range
        self._pdo_dirty = True

    def _check_mapping_write(self, index: int, sub: int, value: int) -> None:
        comm = index - 0x200
        if int.from_bytes(self.local.get_data(comm, 1), "little") & PDO_INVALID == 0:
            raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)  # CiA 301: disable the PDO first
        if sub == 0:
            if value > 8:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            size = 0
            for s in range(1, value + 1):
                size += int.from_bytes(self.local.get_data(index, s), "little") & 0xFF
            if size > 64:
                raise SdoAbortedError(ABORT_PDO_TOO_LONG)
        elif value != 0:
            obj_index, obj_sub, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
            try:
                obj = self.local._find_object(obj_index, obj_sub)
            except SdoAbortedError:
                raise SdoAbortedError(ABORT_NOT_MAPPABLE) from None
            readable_or_writable = obj.writable if index < 0x1A00 else obj.readable
            if not obj.pdo_mappable or not readable_or_writable or bits != len(obj):
                raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        self._pdo_dirty = True

    # ------------------------------------------------------------------ 402 behaviour
    def statusword(self) -> int:
        sw = self.state.value | SW_REMOTE
        if self.state is not State.NOT_READY_TO_SWITCH_ON:
            sw |= SW_VOLTAGE_ENABLED
        if self.state is not State.QUICK_STOP_ACTIVE:
            sw |= SW_QUICK_STOP
        if self.warnings:
            sw |= SW_WARNING
        enabled = self.state is State.OPERATION_ENABLED
        if self.mode == Mode.HOMING:
            sw |= self.homing_status
        elif self.mode in (Mode.CSP, Mode.CSV, Mode.CST):
            if enabled:
                sw |= SW_BIT12
            if self.mode == Mode.CSP and self.following_error:
                sw |= SW_BIT13
            if enabled and self.mode == Mode.CSP and abs(self.target_position - self.position) <= 10:
                sw |= SW_TARGET_REACHED
        return sw

    def _on_controlword(self, cw: int, now: float) -> None:
        rising = cw & CW_FAULT_RESET and not self.controlword & CW_FAULT_RESET
        homing_start = cw & CW_HOMING_START and not self.controlword & CW_HOMING_START
        self.controlword = cw
        if self.state is State.FAULT:
            if rising:  # 15: fault reset, which also acknowledges the warnings
                self.state = State.SWITCH_ON_DISABLED
                self.error_code = 0
                self.warnings.clear()
                self.following_error = False
                self._ferr_since = None
                self._send_emcy(EMCY_RESET)
            return
        new = command_transition(self.state, cw)
        if new is State.OPERATION_ENABLED and self.state is not State.OPERATION_ENABLED:
            if self.state is not State.QUICK_STOP_ACTIVE and self.enable_delay_s > 0:
                if self._enable_at is None:
                    self._enable_at = now + self.enable_delay_s
                new = State.SWITCHED_ON  # 3 happens now, 4 when the brake has released
            self._ferr_since = None
        else:
            self._enable_at = None
        self._set_state(new)
        if self.mode == Mode.HOMING and self.state is State.OPERATION_ENABLED:
            if homing_start:
                self._start_homing()
            elif not cw & CW_HOMING_START and self.homing[0] == "search":
                self._end_homing(0x0400)  # interrupted

    def _set_state(self, new: State) -> None:
        if new is not State.OPERATION_ENABLED and self.homing[0] == "search":
            self._end_homing(0x0400)
        self.state = new

    def _set_mode(self, mode: int) -> None:
        if mode == self.mode:
            return
        if self.homing[0] == "search":
            self._end_homing(0x0400)
        self.mode = mode
        if mode == Mode.HOMING:
            self.homing_status = SW_BIT12 | SW_TARGET_REACHED if self.homed else 0

    def _start_homing(self) -> None:
        method = self._param(0x6098, 0)
        self.homing_status = 0
        if method in HOMING_CURRENT_POSITION:
            self._home_here()
        elif method in HOMING_LIMIT_SWITCH:
            self.homing = ("search", HOMING_LIMIT_SWITCH[method])
        else:
            self.homing_status = 0x2400  # homing error, velocity zero
            self.homed = False

    def _home_here(self) -> None:
        offset = self._param(0x607C, 0)
        shift = offset - self.position
        self.position += shift
        self._switch_origin += shift  # the limit switch stays where it is on the machine
        self.target_position = round(self.position)
        self._end_homing(0x1400)
        self.homed = True

    def _end_homing(self, status: int) -> None:
        self.homing = ("idle", 0)
        self.homing_status = status
        if status != 0x1400:
            self.homed = False
        self.velocity = 0.0

    def error_register(self) -> int:
        """0x1001: the bits of the active fault and of every active warning."""
        register = error_register(self.error_code)
        for code in self.warnings:
            register |= error_register(code)
        return register

    def _emcy(self, code: int, fault: bool, data: bytes = b"") -> None:
        """Error ``code`` occurs: kept as the active fault (0x603F; the drive enters FAULT
        REACTION ACTIVE, 13/14) or, without ``fault``, an active warning (statusword bit 7);
        then the EMCY, carrying 0x1001 as it now is."""
        if fault:
            self.error_code = code
            if self.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                self._enable_at = None
                self._set_state(State.FAULT_REACTION_ACTIVE)
        else:
            self.warnings.add(code)
        self._send_emcy(code, data)

    def _send_emcy(self, code: int, data: bytes = b"") -> None:
        """The EMCY producer: ``code`` with 0x1001, only in PRE-OPERATIONAL and OPERATIONAL
        (CiA 301); ``EMCY_RESET`` says an error ended (a master clears its active list)."""
        if self.local.nmt._state in _EMCY_STATES:
            self.local.emcy.send(code, self.error_register(), data)

    def _end_warning(self, code: int) -> None:
        """Warning ``code``'s cause went away: EMCY 0x0000 with 0x1001 as it is then."""
        if code in self.warnings:
            self.warnings.discard(code)
            self._send_emcy(EMCY_RESET)

    def end_warnings(self) -> None:
        """The active warnings' causes went away: statusword bit 7 clears, EMCY 0x0000 (with
        0x1001 as it is then: an active fault's bits)."""
        with self.lock:
            if self.warnings:
                self.warnings.clear()
                self._send_emcy(EMCY_RESET)

    def _advance(self, now: float) -> None:
        """Run the drive's internal control at :data:`PHYSICS_DT_S` up to ``now``."""
        if now - self._t > _MAX_CATCH_UP_S:
            self._t = now - _MAX_CATCH_UP_S
        while self._t + PHYSICS_DT_S <= now:
            self._t += PHYSICS_DT_S
            self._step(PHYSICS_DT_S, self._t)

    def _step(self, dt: float, t: float) -> None:
        o = self.options
        if self._enable_at is not None and t >= self._enable_at:
            self._enable_at = None
            if self.state is State.SWITCHED_ON and command_transition(
                    State.SWITCHED_ON, self.controlword) is State.OPERATION_ENABLED:
                self.state = State.OPERATION_ENABLED
        state = self.state
        if state in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE) or (
                state is State.OPERATION_ENABLED and self.controlword & CW_HALT):
            decel = self._param(0x6085, 0) * dt
            self.velocity = 0.0 if abs(self.velocity) <= decel else self.velocity - math.copysign(decel, self.velocity)
            self.torque = 0.0 if self.velocity == 0 else -math.copysign(1000.0, self.velocity)
            if self.velocity == 0.0:
                if state is State.FAULT_REACTION_ACTIVE:
                    self.state = State.FAULT  # 14
                elif state is State.QUICK_STOP_ACTIVE:
                    qs = self._param(0x605A, 0)
                    if qs in (1, 2, 3, 4):
                        self.state = State.SWITCH_ON_DISABLED  # 12 after the ramp
        elif state is not State.OPERATION_ENABLED:
            self.velocity = self.torque = 0.0
        elif self.mode == Mode.CSP:
            err = self.target_position - self.position
            self.velocity = max(-o.max_velocity, min(o.max_velocity, err / o.tau_s))
            self.torque = max(-1000.0, min(1000.0, 1000.0 * err / max(1, o.following_window)))
        elif self.mode == Mode.CSV:
            target = max(-o.max_velocity, min(o.max_velocity, float(self.target_velocity)))
            err = target - self.velocity
            self.velocity += err * (1.0 - math.exp(-dt / o.tau_s))
            self.torque = max(-1000.0, min(1000.0, 1000.0 * err / o.max_velocity))
        elif self.mode == Mode.CST:
            limit = self._param(0x6072, 0)
            self.torque = float(max(-limit, min(limit, self.target_torque)))
            target = max(-o.max_velocity, min(o.max_velocity, self.torque * o.torque_velocity))
            self.velocity += (target - self.velocity) * (1.0 - math.exp(-dt / o.tau_s))
        elif self.mode == Mode.HOMING and self.homing[0] == "search":
            speed = self._param(0x6099, 1)
            direction = self.homing[1]
            self.velocity = direction * speed
            switch = self._switch_origin + direction * o.limit_switch
            if (self.position - switch) * direction >= 0:
                self.velocity = 0.0
                self._home_here()
        else:
            self.velocity = self.torque = 0.0
        if self.jammed:
            self.velocity = 0.0
        self.position += self.velocity * dt
        self._check_following_error(t)

    def _check_following_error(self, t: float) -> None:
        if self.state is not State.OPERATION_ENABLED or self.mode != Mode.CSP:
            self._ferr_since = None
            return
        window = self._param(0x6065, 0)
        if window == 0xFFFFFFFF or abs(self.target_position - self.position) <= window:
            self._ferr_since = None
            return
        if self._ferr_since is None:
            self._ferr_since = t
        timeout = self._param(0x6066, 0) / 1000.0
        if t - self._ferr_since >= timeout:
            self.trip_following_error()

    def trip_following_error(self) -> None:
        """The following-error monitor trips: bit 13, EMCY 0x8611, fault reaction."""
        with self.lock:
            self.following_error = True
            self._ferr_since = None
            self._emcy(EMCY_FOLLOWING_ERROR, fault=True)

    def tick(self) -> None:
        """Advance to now; send the event-driven TPDOs that are due (simulator thread)."""
        with self.lock:
            now = self.clock()
            self._advance(now)
            if self._pdo_dirty:
                self._load_pdos()
            if self.network.muted:
                return
            self._consume_heartbeats(now)
            if self.local.nmt._state != NMT_OPERATIONAL:
                return
            for pdo in self._tpdos:
                if not pdo.valid or pdo.trans < 254 or not pdo.entries:
                    continue
                if now - pdo.sent_at < pdo.inhibit_s:
                    continue
                data = self._sample(pdo)
                if data != pdo.last or (pdo.event_s > 0 and now - pdo.sent_at >= pdo.event_s):
                    self._send_pdo(pdo, data, now)

    def _consume_heartbeats(self, now: float) -> None:
        """Heartbeat consumer (0x1016, CiA 301): a monitored node (the master) silent past its
        time -> EMCY 0x8130 and the reaction 0x6007 says (CiA 402 "abort connection option
        code": 0 none, 1 fault, 2 disable voltage, 3 quick stop). Monitoring of a node starts
        at its first heartbeat and, after a timeout, again at the next one."""
        for sub in range(1, 5):
            entry = self._param(0x1016, sub)
            node, limit_s = (entry >> 16) & 0x7F, (entry & 0xFFFF) / 1000.0
            seen = self._heartbeats.get(node)
            if not node or not limit_s or seen is None or now - seen <= limit_s:
                continue
            del self._heartbeats[node]
            self._lost.add(node)
            self._abort_connection(EMCY_HEARTBEAT, bytes([node]))

    def _abort_connection(self, code: int, data: bytes = b"") -> None:
        """The connection to the master is lost (heartbeat, NMT STOPPED entered): error ``code``
        (its EMCY where NMT allows one), then the reaction 0x6007 says (CiA 402 "abort
        connection option code": 0 none, 1 fault, 2 disable voltage, 3 quick stop)."""
        option = self._param(0x6007, 0)
        self._emcy(code, fault=option == 1, data=data)
        if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE, State.NOT_READY_TO_SWITCH_ON):
            return  # a fault stays until the master resets it: neither command leaves it
        if option == 2:  # the disable voltage command (transitions 7, 9, 10, 12)
            self._set_state(State.SWITCH_ON_DISABLED)
        elif option == 3 and self.state is State.OPERATION_ENABLED:  # quick stop (11)
            self._set_state(State.QUICK_STOP_ACTIVE)

    # ------------------------------------------------------------------ inspection / injection
    def send_emcy(self, code: int, fault: bool = True, data: bytes = b"") -> None:
        """The drive reports EMCY ``code``; with ``fault`` (default) it also faults."""
        if not 0 <= code <= 0xFFFF:
            raise SimulatorError(f"node {self.node_id}: EMCY code {code} is not a 16-bit value")
        with self.lock:
            self._advance(self.clock())
            self._emcy(code, fault, data)

    def set_muted(self, on: bool) -> None:
        """A silent node: it sends nothing (no heartbeat, PDO, SDO answer, EMCY) and hears nothing."""
        with self.lock:
            self.network.muted = bool(on)
            if on:
                self.local.nmt.stop_heartbeat()
            else:
                self._restart_heartbeat()

    def set_heartbeat_stopped(self, on: bool) -> None:
        """The heartbeat producer stops (the node otherwise keeps working)."""
        with self.lock:
            self.heartbeat_stopped = bool(on)
            if on:
                self.local.nmt.stop_heartbeat()
            else:
                self._restart_heartbeat()

    def _restart_heartbeat(self) -> None:
        if self.network.muted or self.heartbeat_stopped or self.network.bus is None:
            return
        period = self._param(0x1017, 0)
        self.local.nmt.start_heartbeat(period)

    def set_position(self, counts: int) -> None:
        """Move the shaft by hand to ``counts`` (position actual)."""
        with self.lock:
            self._advance(self.clock())
            self.position = float(counts)

    def clear_faults(self) -> None:
        """Remove injected conditions (silence, heartbeat stop, jam, warning). A drive in FAULT
        stays there until the master's fault reset, as a real one does."""
        with self.lock:
            self.jammed = False
            self.set_muted(False)
            self.end_warnings()
            self.set_heartbeat_stopped(False)

    def snapshot(self) -> dict:
        """The drive's state, for the control socket's ``dump`` and tests."""
        with self.lock:
            self._advance(self.clock())
            return {
                "nmt": canopen.nmt.NMT_STATES.get(self.local.nmt._state, "?"),
                "state": self.state.name, "statusword": self.statusword(),
                "controlword": self.controlword, "mode": self.mode,
                "position": round(self.position), "velocity": round(self.velocity),
                "torque": round(self.torque), "target_position": self.target_position,
                "target_velocity": self.target_velocity, "target_torque": self.target_torque,
                "error_code": self.error_code, "warnings": sorted(self.warnings),
                "error_register": self.error_register(), "homed": self.homed, "muted": self.network.muted,
                "heartbeat_stopped": self.heartbeat_stopped, "jammed": self.jammed,
            }

    # the register names the serial simulators' servos answer to, so a suite written against
    # ``sim.servo(id).read("Present_Position")`` reaches a drive the same way (counts)
    _REGISTERS = {"present_position": "position", "goal_position": "target_position",
                  "position_actual": "position", "target_position": "target_position",
                  "target_velocity": "target_velocity", "target_torque": "target_torque",
                  "torque_enable": "enabled", "controlword": "controlword",
                  "statusword": "statusword", "mode": "mode", "error_code": "error_code"}

    def read(self, register: str) -> int:
        """A value by name (``Present_Position``, ``Goal_Position``, ``Torque_Enable``,
        ``Controlword``, ``Statusword``, ...), in the drive's units. Raises SimulatorError."""
        name = self._register(register)
        with self.lock:
            self._advance(self.clock())
            value = self.statusword() if name == "statusword" else getattr(self, name)
            return int(round(value)) if name != "enabled" else int(value)

    def write(self, register: str, value: int) -> None:
        """Set a value from outside the bus: ``Present_Position`` moves the shaft by hand, a
        target is as if the master had written it. Raises SimulatorError for the others."""
        name = self._register(register)
        if name == "position":
            self.set_position(value)
        elif name in ("target_position", "target_velocity", "target_torque"):
            with self.lock:
                setattr(self, name, int(value))
        else:
            raise SimulatorError(f"node {self.node_id}: {register!r} is read-only here")

    def _register(self, register: str) -> str:
        try:
            return self._REGISTERS[str(register).lower()]
        except KeyError:
            raise SimulatorError(f"node {self.node_id}: unknown register {register!r}; valid: "
                                 f"{', '.join(sorted(self._REGISTERS))}") from None

    @property
    def enabled(self) -> bool:
        """The power stage is on (torque applied): OPERATION ENABLED or stopping under power."""
        return self.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE)


# --- several drives on one bus ---------------------------------------------------------------
_channel_seq = iter(range(1, 1 << 30))


def _private_channel() -> str:
    """A python-can ``virtual`` channel name no other simulator in this process uses."""
    return f"crtk-sim-canopen-{os.getpid()}-{next(_channel_seq)}"


class FaultKind(str, enum.Enum):
    """What :meth:`CanopenSimulator.set_fault` injects into one drive."""

    SILENT = "silent"  # the node sends and hears nothing
    EMCY = "emcy"  # an EMCY with a code; the drive faults
    WARNING = "warning"  # an EMCY with a code; the drive keeps running (statusword bit 7)
    HEARTBEAT_STOP = "heartbeat_stop"  # the heartbeat producer stops, the rest works
    FOLLOWING_ERROR = "following_error"  # the following-error monitor trips (EMCY 0x8611)
    JAM = "jam"  # the shaft is blocked: a moving CSP target trips the monitor by itself


class CanopenSimulator:
    """Simulated CiA 402 drives (one per node id) on one CAN bus, in the serial simulators' shape.

    ``interface``: how a master reaches the drives, and :attr:`port` is its ``channel``:

    - ``"slcan"``: a simulated USB-CAN adapter on a pty (:mod:`crtk_bridge.sim.slcan`; ``link``:
      a stable symlink to it), the drives on a private virtual channel behind it. Any process
      can open it with python-can's ``slcan`` interface: what ``crtk-sim canopen`` and ``--sim`` use.
    - ``"virtual"``: a private python-can virtual channel (in-process clients only).
    - ``"socketcan"``: the kernel CAN interface ``channel`` (e.g. ``vcan0``).

    ``control``: serve the JSON-lines control socket (:mod:`crtk_bridge.sim.control`) there.
    Nothing is opened before :meth:`start`; :meth:`stop` is idempotent.
    """

    vendor = "canopen"

    def __init__(self, node_ids: list[int], options: dict[int, DriveOptions] | None = None, *,
                 interface: str = "virtual", channel: str | None = None, bitrate: int = 1_000_000,
                 control: str | os.PathLike | None = None, link: str | os.PathLike | None = None,
                 clock: Callable[[], float] = time.monotonic):
        if not node_ids:
            raise SimulatorError("a CANopen simulator needs at least one node id")
        if len(set(node_ids)) != len(node_ids):
            raise SimulatorError(f"node ids {node_ids} are not unique")
        if interface not in ("slcan", "virtual", "socketcan"):
            raise SimulatorError(f"interface {interface!r}: the simulator offers slcan, virtual, socketcan")
        if interface == "socketcan" and not channel:
            raise SimulatorError("interface 'socketcan' needs a channel (e.g. vcan0)")
        self.interface = interface
        self.bitrate = int(bitrate)
        self.adapter = None
        if interface == "slcan":
            from .slcan import SlcanAdapter

            # the adapter and the drives on one in-process bus: frames handed over in the
            # sending thread, no receive thread of the drives' own (canbus.py)
            self._bus = (canbus.INTERFACE, _private_channel())
            self.adapter = SlcanAdapter(*self._bus, self.bitrate, link=link)
        else:
            self._bus = (interface, channel or _private_channel())
        options = options or {}
        self.drives: dict[int, Drive402] = {
            n: Drive402(n, options.get(n, DriveOptions()), clock=clock) for n in node_ids}
        self.bus_off = False
        self.control_path = Path(control) if control is not None else None
        self._control = None
        if control is not None:
            from .control import ControlServer

            self._control = ControlServer(control, self.control)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._drive_bus: can.BusABC | None = None  # the drives' shared endpoint (start)
        self._notifier: can.Notifier | None = None

    @classmethod
    def from_profile(cls, profile: Profile, link: str | os.PathLike | None = None,
                     control: str | os.PathLike | None = None, *, interface: str = "slcan",
                     channel: str | None = None, **_ignored) -> CanopenSimulator:
        """One drive per joint with a ``node_id`` (backend-owned joint key). The bus's
        ``bitrate`` comes from the profile's backend section; ``interface`` defaults to the
        SLCAN adapter (the profile's ``interface`` / ``channel`` are the master's, written by
        the backend's ``sim_profile`` from :attr:`port`)."""
        node_ids, options = [], {}
        for i, j in enumerate(profile.joints):
            nid = j.backend.get("node_id")
            if nid is None:
                continue
            if not isinstance(nid, int) or isinstance(nid, bool) or not 1 <= nid <= 127:
                raise SimulatorError(f"profile {profile.name!r}: joints[{i}] ({j.name}).node_id "
                                     f"must be an integer 1..127, got {nid!r}")
            node_ids.append(nid)
            options[nid] = _joint_options(j)
        if not node_ids:
            raise SimulatorError(f"profile {profile.name!r}: no joint has a node_id")
        bitrate = (profile.backend or {}).get("bitrate", 1_000_000)
        if not isinstance(bitrate, int) or isinstance(bitrate, bool):
            raise SimulatorError(f"profile {profile.name!r}: backend.bitrate must be an integer")
        return cls(node_ids, options, interface=interface, channel=channel, bitrate=bitrate,
                   control=control, link=link)

    # ------------------------------------------------------------------ lifecycle
    @property
    def port(self) -> str:
        """The endpoint a master opens as its ``channel`` (with :attr:`interface`): the adapter's
        pty (or link) for slcan, else the CAN channel."""
        return self.adapter.port if self.adapter is not None else self._bus[1]

    channel = port

    @property
    def pty_path(self) -> str | None:
        return self.adapter.pty_path if self.adapter is not None else None

    @property
    def rx_bytes(self) -> int:
        """Bytes the master has sent to the adapter (slcan; 0 otherwise)."""
        return self.adapter.rx_bytes if self.adapter is not None else 0

    @property
    def ids(self) -> list[int]:
        return sorted(self.drives)

    @property
    def running(self) -> bool:
        alive = self._thread is not None and self._thread.is_alive()
        return alive and (self.adapter is None or self.adapter.running)

    def start(self) -> None:
        """Connect every drive (each boots: boot-up message, PRE-OPERATIONAL) and start the
        simulator thread. Raises SimulatorError if the bus cannot be opened."""
        if self._thread is not None:
            return
        started = []
        try:
            if self.adapter is not None:
                self.adapter.start()  # first: the drives' boot-up messages reach an open adapter
            # one endpoint for every drive (see the module docstring); its own frames come back
            # to it, so each drive hears the others. Behind the adapter, the in-process bus
            # hands each frame to the drives in the thread that sent it; on a python-can bus,
            # one receive thread does
            if self._bus[0] == canbus.INTERFACE:
                self._drive_bus = canbus.LocalBus(self._bus[1], receive_own_messages=True, on_message=self._hear)
            else:
                self._drive_bus = can.Bus(interface=self._bus[0], channel=self._bus[1], receive_own_messages=True)
                self._notifier = can.Notifier(self._drive_bus, [self._hear], timeout=NOTIFIER_CYCLE_S)
            for drive in self.drives.values():
                drive.attach(self._drive_bus)
                started.append(drive)
            if self._control is not None:
                self._control.start()
        except Exception as exc:
            for drive in started:
                drive.disconnect()
            self._close_drive_bus()
            if self.adapter is not None:
                self.adapter.stop()
            if isinstance(exc, SimulatorError):
                raise
            raise SimulatorError(f"CANopen simulator: cannot open {self._bus[0]} channel "
                                 f"{self._bus[1]!r}: {exc}") from exc
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="sim-canopen", daemon=True)
        self._thread.start()
        log.info("canopen simulator: node(s) %s on %s %s", self.ids, self.interface, self.port)

    def stop(self) -> None:
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        self._thread = None
        if self._control is not None:
            self._control.stop()
        for drive in self.drives.values():
            drive.disconnect()
        self._close_drive_bus()
        if self.adapter is not None:
            self.adapter.stop()

    def _hear(self, msg: can.Message) -> None:
        """Every frame on the drives' endpoint, to each drive (the receive thread). A drive that
        raises is logged and the others still hear it, as canopen's own listener does: the
        thread must not die."""
        for drive in self.drives.values():
            try:
                drive.hear(msg)
            except Exception:
                log.exception("drive %d: frame 0x%03X dropped", drive.node_id, msg.arbitration_id)

    def _close_drive_bus(self) -> None:
        if self._notifier is not None:
            self._notifier.stop(_DriveNetwork.NOTIFIER_SHUTDOWN_TIMEOUT)
            self._notifier = None
        if self._drive_bus is not None:
            self._drive_bus.shutdown()
            self._drive_bus = None

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _run(self) -> None:
        try:
            while not self._stop.wait(TICK_S):
                for drive in self.drives.values():
                    drive.tick()
        except Exception:
            log.exception("canopen simulator thread died")
            raise

    # ------------------------------------------------------------------ conformance-row hooks
    def drive(self, node_id: int) -> Drive402:
        try:
            return self.drives[node_id]
        except KeyError:
            raise SimulatorError(f"no simulated drive with node id {node_id} (ids: {self.ids})") from None

    #: the serial simulators' name, so conformance rows reach a drive as they reach a servo
    servo = drive

    def set_fault(self, node_id: int, kind: str | FaultKind, code: int = 0) -> None:
        """Inject a fault into one drive (see :class:`FaultKind`); ``code``: the EMCY code of
        ``emcy`` / ``warning`` (default 0x5000 device hardware / 0x4210 temperature warning)."""
        drive = self.drive(node_id)
        try:
            kind = FaultKind(kind)
        except ValueError:
            raise SimulatorError(f"unknown fault kind {kind!r}; valid: "
                                 f"{', '.join(k.value for k in FaultKind)}") from None
        if kind is FaultKind.SILENT:
            drive.set_muted(True)
        elif kind is FaultKind.EMCY:
            drive.send_emcy(code or 0x5000, fault=True)
        elif kind is FaultKind.WARNING:
            drive.send_emcy(code or 0x4210, fault=False)
        elif kind is FaultKind.HEARTBEAT_STOP:
            drive.set_heartbeat_stopped(True)
        elif kind is FaultKind.FOLLOWING_ERROR:
            drive.trip_following_error()
        else:
            with drive.lock:
                drive._advance(drive.clock())
                drive.jammed = True

    def clear_faults(self, node_id: int | None = None) -> None:
        """Remove injected conditions (of one drive, or all and bus-off too). Drives in FAULT
        stay there until the master resets them (controlword bit 7)."""
        for drive in ([self.drive(node_id)] if node_id is not None else self.drives.values()):
            drive.clear_faults()
        if node_id is None:
            self.set_bus_off(False)

    def set_bus_off(self, on: bool) -> None:
        """The master's side of the bus is unusable (adapter bus-off, cable cut): nothing passes
        either way; the drives run on (with slcan the adapter's status flags say so)."""
        self.bus_off = bool(on)
        if self.adapter is not None:
            self.adapter.bus_off = self.bus_off
            return
        for drive in self.drives.values():
            drive.set_muted(on)

    # the serial simulators' name for "the bus is gone"
    set_unplugged = set_bus_off

    def set_torque_delay(self, seconds: float) -> None:
        """Enable operation takes ``seconds`` (a brake releasing): the drive stays SWITCHED ON
        that long before OPERATION ENABLED. How tests prove an enable never stalls the loop."""
        if seconds < 0:
            raise SimulatorError(f"enable delay {seconds} s must be >= 0")
        for drive in self.drives.values():
            with drive.lock:
                drive.enable_delay_s = float(seconds)

    @property
    def rx_frames(self) -> int:
        """Frames the drives have heard (each frame counted once per drive)."""
        return sum(d.rx_frames for d in self.drives.values())

    # ------------------------------------------------------------------ control socket
    def control(self, request: dict) -> dict:
        """Answer one control request: dump, read / write {node, register[, value]} (register
        names as :meth:`Drive402.read`), fault, clear_faults, bus_off (alias unplug), position,
        enable_delay (alias torque_delay). ``id`` / ``bits`` are accepted for ``node`` / ``code``,
        so a client written for the serial simulators' control socket reaches a drive the same
        way. Never raises for a bad request."""
        cmd = request.get("cmd")
        try:
            if cmd == "dump":
                return {"ok": True, "drives": {str(n): d.snapshot() for n, d in sorted(self.drives.items())},
                        "bus_off": self.bus_off, "interface": self.interface, "channel": self.port,
                        "bitrate": self.bitrate}
            if cmd in ("read", "write"):  # a value by the serial simulators' register names
                drive = self.drive(self._node(request))
                if cmd == "read":
                    return {"ok": True, "value": drive.read(str(request.get("register")))}
                value = request.get("value")
                if not isinstance(value, int) or isinstance(value, bool):
                    return {"ok": False, "error": f"'value' must be an integer, got {value!r}"}
                drive.write(str(request.get("register")), value)
                return {"ok": True}
            if cmd == "fault":
                code = request.get("code", request.get("bits", 0))
                if isinstance(code, str):
                    code = int(code, 0)
                if not isinstance(code, int) or isinstance(code, bool):
                    return {"ok": False, "error": f"'code' must be an integer, got {code!r}"}
                self.set_fault(self._node(request), str(request.get("kind")), code)
                return {"ok": True}
            if cmd == "clear_faults":
                self.clear_faults(None if request.get("node") is None else self._node(request))
                return {"ok": True}
            if cmd in ("bus_off", "unplug"):
                self.set_bus_off(bool(request.get("on", True)))
                return {"ok": True}
            if cmd == "position":
                value = request.get("value")
                if not isinstance(value, int) or isinstance(value, bool):
                    return {"ok": False, "error": f"'value' must be an integer count, got {value!r}"}
                self.drive(self._node(request)).set_position(value)
                return {"ok": True}
            if cmd in ("enable_delay", "torque_delay"):
                seconds = request.get("seconds")
                if not isinstance(seconds, (int, float)) or isinstance(seconds, bool) or not seconds >= 0:
                    return {"ok": False, "error": f"'seconds' must be a number >= 0, got {seconds!r}"}
                self.set_torque_delay(float(seconds))
                return {"ok": True}
        except (SimulatorError, ValueError) as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": False, "error": f"unknown cmd {cmd!r}; valid: dump, read, write, fault, "
                "clear_faults, bus_off, unplug, position, enable_delay, torque_delay"}

    def _node(self, request: dict) -> int:
        nid = request.get("node", request.get("id"))  # ``id``: the serial simulators' name
        if not isinstance(nid, int) or isinstance(nid, bool):
            raise SimulatorError(f"'node' must be an integer node id, got {nid!r}")
        return self.drive(nid).node_id


def _joint_options(joint) -> DriveOptions:
    """A joint's drive: at power-on at its ``offset`` counts if the backend keys give one; its
    top speed 1.5 x the joint's velocity limit when the keys give counts per revolution."""
    keys = joint.backend
    opts = DriveOptions()
    offset = keys.get("offset")
    if isinstance(offset, int) and not isinstance(offset, bool):
        opts = replace(opts, position=offset)
    cpr = keys.get("counts_per_revolution", keys.get("counts_per_rev"))
    gear = keys.get("gear_ratio", 1.0)
    if isinstance(cpr, (int, float)) and isinstance(gear, (int, float)) and cpr > 0 and gear > 0:
        vmax = 1.5 * joint.limits.velocity_max * cpr * gear / (2 * math.pi)
        opts = replace(opts, max_velocity=max(vmax, 1.0), torque_velocity=max(vmax, 1.0) / 1000.0,
                       following_window=max(int(cpr * gear / 8), 100),
                       limit_switch=max(int(cpr * gear / 20), 10), homing_speed=max(int(vmax / 4), 1))
    return opts

"""CANopen CiA 402 drives on one CAN bus: one drive (node id) per joint, CSP / CSV / CST.

Built on ``canopen`` (object dictionaries, SDO client, NMT, EMCY consumer, PDO maps) over
``python-can`` (any interface it speaks: socketcan, slcan, pcan, kvaser, socketcand, virtual...).
What the library does not do, or does in a way a real-time loop cannot use, is done here
(docs/architecture.md, "Sources": CANopen CiA 402):

* **The loop paces the bus.** The cycle runs on the loop's clock (core/cycle.py): at the tick of
  its absolute schedule :meth:`Canopen402Backend.wait_cycle` sends ONE SYNC
  (``SyncProducer.transmit()``), the first thing of the cycle, so the SYNC period jitters by the
  wake-up alone. At that SYNC the drives apply the RPDOs the previous cycle's ``write`` sent
  (CiA 301: SYNC-type RPDOs take effect at the next SYNC) and answer with their SYNC-type TPDOs
  (statusword, position, mode display; velocity, torque). ``read`` takes the TPDOs that answered
  the previous SYNC (in already: no waiting in the cycle); ``write`` sets each drive's RPDOs
  (controlword, target position, mode; target velocity and torque where the drive has CSV / CST)
  and transmits them with ``PdoMap.transmit()`` (on an slcan adapter the cycle's frames -- SYNC
  and the master's heartbeat in one write, the RPDOs in another -- are formatted here into
  python-can's slcan lines, slcan.py ``send_lines``: a ``Message``, a lock and a format per
  frame were a fifth of the control process's CPU). Every cycle, in every operating state. No library
  thread sends anything periodic (its ``start()`` threads are not locked to the loop, and its
  setters do not send SYNC-type RPDOs at all). Start-up, shutdown and tests run the same cycle
  (core/cycle.py), so there is one way the bus is driven. TPDOs are counted, not tagged: a TPDO that has not
  arrived ``tpdo_timeout_ms`` after its SYNC is missing, a transient ``tpdo_missing`` fault naming
  the node (core faults after ``safety.bus_errors_max`` in a row); a late one is not.
* **Heartbeat consumer** (the library has none): each node's heartbeat is timed here; a node
  silent beyond ``heartbeat_timeout_ms`` is a ``heartbeat_lost`` fault naming it, a node whose
  heartbeat leaves OPERATIONAL (a reboot) a ``nmt_state`` fault.
* **The master's own heartbeat**, the other way: ``configure`` writes each drive's heartbeat
  consumer (0x1016:1 = ``master_node_id`` << 16 | ``master_heartbeat_timeout_ms``) and its abort
  connection option (0x6007, ``abort_connection_option``), and the loop's SYNC sends the master's
  heartbeat (COB 0x700 + ``master_node_id``, every ``master_heartbeat_ms``) from the cycle's own
  ``wait_cycle`` on -- no library thread, nothing that outlives the loop. A drive starts watching
  at the first heartbeat (CiA 301), so the start-up before the loop runs cannot trip it; once the
  loop is gone (the control process killed, the loop stalled) the drive stops by itself within
  the consumer time (EMCY 0x8130 and the 0x6007 reaction). A clean ``close`` clears 0x1016:1 of
  the drives it left disabled, so a normal shutdown does not leave them in FAULT.
* **EMCY** -> device status FAULT naming the node, the code and its meaning (tables.py), unless
  the drive's statusword after it says a warning (bit 7 set, not in FAULT: CiA 402-2, the drive
  goes on): then a device WARNING, once per EMCY, and the robot keeps running. The drive's own
  FAULT state faults whatever its EMCY said.
* **The CiA 402 state machine** is walked across cycles from ``tables.WALK`` (never the library's
  blocking ``state`` setter): each step sets the controlword the next SYNC carries and looks at
  the statusword the SYNC after brings back. Fault reset is a rising edge of bit 7 (bit 7 low
  for one cycle first; canopen's ``reset_from_fault`` is broken, canopen issue #261).
* **Bus errors** (a failed send, the interface's receive error, a bus-off error frame) fault the
  robot; the bus is reopened on a worker thread and the reads resume once it is back.

Blocking SDO traffic happens only at ``open`` / ``configure`` and inside lifecycle transitions
(``on_worker``), never in ``read`` / ``write``. Transitions are stepped by the cycle (the loop's,
or the runner's at start-up and shutdown): the cycle's ``write`` carries their controlwords and
a later cycle's ``read`` brings the statusword that answers them.

Units (raw counts never leave this module), per joint, ``k = 2*pi / (counts_per_revolution *
gear_ratio)`` for ``unit: rad`` (``1 / (...)`` for ``unit: m``):

* position  = direction * (counts - offset) * k
* velocity  = direction * (velocity units / velocity_factor) * k
* effort    = direction * per mille / 1000 * rated torque (N*m) * gear_ratio  (x 2*pi for m: N)
"""

from __future__ import annotations

import errno
import logging
import math
import struct
import threading
import time
from binascii import hexlify
from pathlib import Path
from typing import Annotated, Any, Literal

import can
import canopen
import msgspec
import numpy as np
from canopen.sdo.exceptions import SdoError

from ...core.actuator import (
    Actuator,
    ActuatorInfo,
    Capabilities,
    Clock,
    CommandMode,
    DeviceStatus,
    Fault,
    JointCommand,
    JointFeedback,
    Lifecycle,
    SimWiring,
    Steps,
    Traits,
    background_thread,
    on_worker,
)
from ...errors import BackendError, ProfileError
from ...profile import Profile, backend_config, joint_keys
from . import tables as t
from .od import standard_402
from .slcan import SlcanBus
from .tables import Command, Goal, Mode, State402

PDO_NOT_VALID = 1 << 31
I32 = (-(2**31), 2**31 - 1)
#: target torque (0x6071) of a joint without limits.effort_max: at most the rated torque
RATED_PER_MILLE = 1000
I16 = (-(2**15), 2**15 - 1)
_RING = 64  # SYNC send times kept (stamps of late answers, TPDO deadlines)
CAN_ERR_BUSOFF = 0x00000040  # SocketCAN error class in an error frame's id (linux/can/error.h)

_POSITION, _VELOCITY, _EFFORT, _FREE = (int(CommandMode.POSITION), int(CommandMode.VELOCITY),
                                        int(CommandMode.EFFORT), int(CommandMode.FREE))
_CSP, _CSV, _CST, _HM = (int(Mode.CYCLIC_SYNC_POSITION), int(Mode.CYCLIC_SYNC_VELOCITY),
                         int(Mode.CYCLIC_SYNC_TORQUE), int(Mode.HOMING))


def _open_hint(exc: BaseException) -> str:
    """What to do about a CAN interface that would not open, from its errno (the OSError, or the
    one python-can wrapped), or ""."""
    while exc is not None and not isinstance(exc, OSError):
        exc = exc.__cause__ or exc.__context__
    code = getattr(exc, "errno", None)
    if code == errno.EAFNOSUPPORT:
        return ("; this kernel has no SocketCAN (AF_CAN): use a USB-CAN adapter over slcan "
                "(backend.interface: slcan, backend.channel: /dev/ttyACM0) or run with --sim")
    if code == errno.ENODEV:
        return ("; no such network interface: see `ip link` (a CAN interface is brought up with "
                "`ip link set can0 up type can bitrate 1000000`), or run with --sim")
    return ""


# ---------------------------------------------------------------- profile keys

class Homing(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """A joint's CiA 402 homing (mode 6), run by ``home``; absent = absolute encoder."""

    method: Annotated[int, msgspec.Meta(ge=-128, le=127)]  # 0x6098, e.g. 35 / 37 = current position
    speed_switch: Annotated[float, msgspec.Meta(gt=0)] = 0.2  # rad/s (m/s): 0x6099:1
    speed_zero: Annotated[float, msgspec.Meta(gt=0)] = 0.05  # rad/s (m/s): 0x6099:2
    acceleration: Annotated[float, msgspec.Meta(gt=0)] = 1.0  # rad/s^2 (m/s^2): 0x609A


class DriveJoint(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """A joint's CANopen keys (beside its generic ones in the profile)."""

    node_id: Annotated[int, msgspec.Meta(ge=1, le=127)]
    counts_per_revolution: Annotated[int, msgspec.Meta(gt=0)]  # encoder counts per motor turn
    gear_ratio: Annotated[float, msgspec.Meta(gt=0)] = 1.0  # motor turns per joint turn (per metre: unit m)
    direction: Literal[1, -1] = 1
    offset: int = 0  # counts at joint zero
    velocity_factor: Annotated[float, msgspec.Meta(gt=0)] = 1.0  # drive velocity units per count/s
    rated_torque: Annotated[float, msgspec.Meta(gt=0)] | None = None  # motor N*m at 1000 per mille; None: 0x6076
    eds: str | None = None  # the drive's EDS file (relative to the profile); None: standard 402 objects
    homing: Homing | None = None


class Config(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """The ``backend:`` section of a profile with ``type: canopen402``."""

    interface: str = "socketcan"  # python-can interface name
    channel: str  # python-can channel: can0, /dev/ttyACM0 (slcan), a pty (--sim)...
    bitrate: Annotated[int, msgspec.Meta(gt=0, le=1_000_000)] = 1_000_000
    options: dict[str, Any] = {}  # further python-can Bus arguments (host/port for socketcand...)
    boot_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=120)] = 5.0  # per node
    heartbeat_ms: Annotated[int, msgspec.Meta(ge=1, le=65535)] = 100  # producer time written to 0x1017
    heartbeat_timeout_ms: Annotated[float, msgspec.Meta(gt=0, le=60000)] = 350.0  # consumer
    tpdo_timeout_ms: Annotated[float, msgspec.Meta(gt=0, le=1000)] | None = None  # None: three loop periods
    sdo_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=10)] = 0.3
    # the master's (this backend's) heartbeat, which each drive watches (0x1016) so it stops by
    # itself when the control process dies; it cannot be switched off (0 is refused)
    master_node_id: Annotated[int, msgspec.Meta(ge=1, le=127)] = 127  # heartbeat COB 0x700 + id
    master_heartbeat_ms: Annotated[int, msgspec.Meta(ge=0, le=65535)] = 100  # producer period
    master_heartbeat_timeout_ms: Annotated[int, msgspec.Meta(ge=1, le=65535)] | None = None  # None: 3 x period
    abort_connection_option: Literal["fault", "disable_voltage", "quick_stop"] | None = "fault"  # 0x6007


# ---------------------------------------------------------------- one drive
class _Drive:
    """One node: its canopen objects, the last TPDO values (raw) and the next RPDO values."""

    def __init__(self, i: int, name: str, keys: DriveJoint, limits: Any, unit: str):
        self.i = i
        self.unit = unit  # the joint's generic ``unit``: rad (revolute) or m (prismatic)
        self.name = name
        self.keys = keys
        self.id = keys.node_id
        self.label = f"joint {name!r} (node {keys.node_id})"
        k = 1.0 / (keys.counts_per_revolution * keys.gear_ratio)
        if unit == "rad":
            k *= 2.0 * math.pi
        self.k_pos = keys.direction * k  # SI per count (signed)
        self.k_vel = keys.direction * k / keys.velocity_factor  # SI/s per velocity unit
        self.k_eff: float | None = None  # N*m (N) per per mille; set at open
        self.eff_max = limits.effort_max  # None: targets capped at the rated torque
        self.node: canopen.RemoteNode | None = None
        self.supported = 0  # 0x6502
        self.csv = self.cst = False
        self.tpdos: list[Any] = []
        self.on_tpdo: list[Any] = []  # per TPDO: the notifier's handler of its frames (_add_node)
        self.rpdo1: Any = None
        self.rpdo2: Any = None
        self.v: dict[int, Any] = {}  # object index -> PdoVariable (RPDO and TPDO entries)
        #: PDO map -> the struct of its payload, from the mapped objects' types (_map_pdos)
        self.layout: dict[Any, struct.Struct] = {}
        #: RPDO map -> the head of its slcan line (``t`` COB-ID DLC), for the cycle's frames
        self.head: dict[Any, bytes] = {}
        # last TPDO values (raw) and the SYNC count they answered
        self.sw = 0
        self.state: State402 | None = None
        self.pos = 0
        self.vel = 0
        self.torque = 0
        self.mode_display = 0
        # per TPDO: frames arrived, and the offset that makes "arrived - base == SYNCs sent" when
        # every SYNC was answered (a TPDO answering an older SYNC late must not pass for fresh)
        self.arrived = [0, 0]
        self.base = [0, 0]
        self.missed = 0  # consecutive reads with a TPDO missing
        self.heard = 0  # sum(arrived) at the previous read: the node has sent TPDOs since if it grew
        self.heard_t = 0.0  # monotonic time of the last read that found new TPDOs from it
        # next RPDO values
        self.cw = int(Command.DISABLE_VOLTAGE)
        self.mode = _CSP
        self.target_pos = 0
        self.target_vel = 0
        self.target_torque = 0
        self.homing = False
        # heartbeat consumer and EMCY (written by the notifier thread)
        self.hb_t = 0.0  # monotonic time of the last heartbeat
        self.nmt = t.NMT_OPERATIONAL
        self.started_t = 0.0  # monotonic time of our NMT start
        self.rebooted = False
        self.emcy: tuple[int, int] | None = None  # (code, error register) not yet reset
        self.emcy_at = 0  # arrived[0] (statuswords) when that EMCY came
        # read thread: the EMCY last reported as a warning (once each)
        self.emcy_warned: tuple[int, int] | None = None

    def counts(self, si: float) -> int:
        """Counts of position ``si`` (finite, within the profile's limits: core's output), clamped
        to the I32 range of 0x607A."""
        c = round(self.keys.offset + si / self.k_pos)
        return min(max(c, I32[0]), I32[1])


def _payload_struct(d: _Drive, pdo: Any) -> struct.Struct:
    """The struct of ``pdo``'s payload: its mapped objects in order, each packed as its object
    dictionary type (canopen's own struct for that type), little-endian as CANopen is."""
    fmt = "<"
    for var in pdo.map:
        od_struct = var.od.STRUCT_TYPES.get(var.od.data_type)
        if od_struct is None or var.length != od_struct.size * 8:
            raise BackendError(f"{d.label}: object 0x{var.index:04X} ({var.name}) has data type "
                               f"0x{var.od.data_type:X}, not a number a PDO of this backend carries; "
                               "check the joint's eds file")
        fmt += od_struct.format.lstrip("<>=!@")
    layout = struct.Struct(fmt)
    assert layout.size * 8 == pdo.length, (fmt, pdo.length)
    return layout


class _BusWatch(can.Listener):
    """Sees what canopen's listener drops: the interface's receive errors and error frames."""

    def __init__(self, backend: "Canopen402Backend"):
        self.backend = backend

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.backend._error_frames += 1
            if msg.arbitration_id & CAN_ERR_BUSOFF:
                self.backend._bus_down = "bus-off (error frame)"

    def on_error(self, exc: Exception) -> None:
        # the notifier calls this on every failing recv; a dead interface would spin it
        self.backend._bus_down = f"{type(exc).__name__}: {exc}"
        time.sleep(0.05)


# ---------------------------------------------------------------- the backend
class Canopen402Backend(Actuator):
    """CiA 402 drives on one CAN bus. See the module docstring.

    Constructing validates the profile (ProfileError naming the key); nothing touches the bus
    before :meth:`open`.
    """

    simulator = SimWiring(endpoint_key="channel")  # crtk-sim canopen's SLCAN pty
    #: the interface ``--sim`` uses to reach the simulated USB-CAN adapter
    SIM_INTERFACE = "slcan"
    #: ``tpdo_timeout_ms`` on the simulator unless the profile sets one: the simulated adapter
    #: and drives are Python threads in another process, on a loaded host their answers can take
    #: tens of ms (a real drive answers within a millisecond)
    SIM_DEFAULTS = {"tpdo_timeout_ms": 50.0}
    TRANSITION_TIMEOUTS_S = {Lifecycle.ENABLE: 5.0, Lifecycle.DISABLE: 2.0, Lifecycle.PAUSE: 3.0,
                             Lifecycle.RESUME: 3.0, Lifecycle.FAULT_RESET: 2.0, Lifecycle.HOME: 60.0}
    #: cycles a drive's statusword may stay missing inside a transition before it fails
    TRANSITION_MISSED_MAX = 25

    def __init__(self, profile: Profile, *, source: str = "<profile>"):
        super().__init__(profile, source=source)
        self.source = source
        self.config: Config = backend_config(
            profile, Config, source, owner="the canopen402 backend",
            required={"channel": "the python-can channel (e.g. can0 for socketcan, /dev/ttyACM0 for slcan)"})
        cfg = self.config
        if cfg.heartbeat_timeout_ms <= cfg.heartbeat_ms:
            raise ProfileError(f"{source}: backend.heartbeat_timeout_ms: {cfg.heartbeat_timeout_ms} must be "
                               f"longer than backend.heartbeat_ms ({cfg.heartbeat_ms})")
        keys = joint_keys(profile, DriveJoint, "canopen402", source)
        self._consumer_ms = self._check_master_heartbeat(cfg, profile, keys, source)
        seen: dict[int, str] = {}
        for i, (j, k) in enumerate(zip(profile.joints, keys)):
            if k.node_id in seen:
                raise ProfileError(f"{source}: joints[{i}] ({j.name}).node_id: {k.node_id} is also "
                                   f"joint {seen[k.node_id]!r}'s")
            seen[k.node_id] = j.name
            h = k.homing
            for key in ("speed_switch", "speed_zero"):  # the drive homes at these: bounded too
                if h is not None and getattr(h, key) > j.limits.velocity_max:
                    raise ProfileError(f"{source}: joints[{i}] ({j.name}).homing.{key}: {getattr(h, key)} is "
                                       f"above limits.velocity_max ({j.limits.velocity_max})")
            if h is not None and h.acceleration > j.limits.acceleration_max:
                raise ProfileError(f"{source}: joints[{i}] ({j.name}).homing.acceleration: {h.acceleration} is "
                                   f"above limits.acceleration_max ({j.limits.acceleration_max})")
        self.drives = [_Drive(i, j.name, k, j.limits, j.unit) for i, (j, k) in enumerate(zip(profile.joints, keys))]
        self._period_s = 1.0 / profile.loop.rate_hz
        self._tpdo_timeout_s = (cfg.tpdo_timeout_ms / 1000.0 if cfg.tpdo_timeout_ms is not None
                                else 3 * self._period_s)
        self._hb_timeout_s = cfg.heartbeat_timeout_ms / 1000.0
        # the master's heartbeat: sent by _sync_out once the loop's wait_cycle has run
        self._master_hb_cob = t.HEARTBEAT_COB_BASE + cfg.master_node_id
        self._master_hb_data = bytes([t.NMT_OPERATIONAL])
        self._master_hb_line = SlcanBus.line(self._master_hb_cob, self._master_hb_data)
        self._master_hb_period_s = cfg.master_heartbeat_ms / 1000.0
        self._master_hb_due: float | None = None  # monotonic time the next one is due; None: not yet
        # after an outage (TPDOs missing, bus down), a fault reset waits until the drives' consumer
        # time has run out (bounded well inside the ENABLE time limit)
        self._settle_s = min((self._consumer_ms + cfg.master_heartbeat_ms) / 1000.0, 2.0)
        self._settle_until = 0.0
        #: per drive, what its supported modes allow (known at open: _identify)
        self._joint_caps: list[Capabilities | None] = [None] * self.n
        self._network: canopen.Network | None = None
        self._rx_event = threading.Event()
        self._waiting = False  # a read waits for TPDOs: the notifier sets _rx_event (_wait_tpdos)
        self._sync_seq = 0  # SYNCs sent
        self._sync_t = 0.0  # monotonic time of the last SYNC
        self._sync_mono = [0.0] * _RING  # monotonic time of SYNC n at [n % _RING]
        self._sync_wall = [0.0] * _RING  # its wall-clock time: the stamp of the samples answering it
        self._bus_down: str | None = None  # why the bus failed; None: up
        self._reopening: threading.Thread | None = None
        self._error_frames = 0
        self._error_frames_seen = 0
        self._paused_by_us = False
        self._details: dict[str, Any] = {}
        #: statistics for bench/ (counted in read / write)
        self.stats = {"syncs": 0, "rpdos": 0, "tpdos_missed": 0, "reads": 0, "heartbeats": 0}

    @staticmethod
    def _check_master_heartbeat(cfg: Config, profile: Profile, keys: list[DriveJoint], source: str) -> int:
        """The drives' consumer time (ms) for the master's heartbeat, after checking its keys.
        Raises ProfileError naming the key."""
        if cfg.master_heartbeat_ms == 0:
            raise ProfileError(
                f"{source}: backend.master_heartbeat_ms: 0 would switch the master's heartbeat off, and "
                f"a drive would then stay enabled when the control process dies; not offered (give a "
                f"period in ms, default 100)")
        for i, (j, k) in enumerate(zip(profile.joints, keys)):
            if k.node_id == cfg.master_node_id:
                raise ProfileError(f"{source}: backend.master_node_id: {cfg.master_node_id} is also joints[{i}] "
                                   f"({j.name}).node_id; the master needs a node id of its own")
        consumer = cfg.master_heartbeat_timeout_ms
        if consumer is None:
            consumer = min(3 * cfg.master_heartbeat_ms, 65535)
        # the heartbeat goes with the cycle's SYNC: at most a loop period late
        period_ms = 1000.0 / profile.loop.rate_hz
        if consumer <= cfg.master_heartbeat_ms + period_ms:
            raise ProfileError(
                f"{source}: backend.master_heartbeat_timeout_ms: {consumer} must be longer than "
                f"backend.master_heartbeat_ms ({cfg.master_heartbeat_ms}) plus one loop period "
                f"({period_ms:.3g} ms), or a drive would fault on a heartbeat that is merely on time")
        return consumer

    # ------------------------------------------------------------------ sim wiring
    @classmethod
    def sim_profile(cls, profile: Profile, endpoint: str) -> Profile:
        """The profile wired to the simulated USB-CAN adapter at ``endpoint`` (its channel), on
        the adapter's interface."""
        wired = super().sim_profile(profile, endpoint)
        options = {**wired.backend.get("options", {}), **cls.sim_options()}
        backend = {**wired.backend, "interface": cls.SIM_INTERFACE, "options": options}
        return msgspec.structs.replace(wired, backend=backend)

    @classmethod
    def sim_options(cls) -> dict[str, Any]:
        """python-can arguments for the simulated adapter (no 2 s settle after opening a pty)."""
        return {"sleep_after_open": 0} if cls.SIM_INTERFACE == "slcan" else {}

    # ------------------------------------------------------------------ info
    def info(self) -> ActuatorInfo:
        return ActuatorInfo(list(self.joint_names), dict(self._details))

    def _traits_hook(self) -> Traits:
        """Per drive, what its supported modes (0x6502) and rated torque allow (read at open);
        the loop's clock, whose tick sends the SYNC (wait_cycle); RPDOs every cycle in
        every state; pause is the drives' own quick stop; the drives home themselves (CiA 402
        homing mode) where a joint has ``homing``."""
        return Traits(joints=tuple(self._joint_caps), clock=Clock.LOOP, cyclic_write=True,
                      stops_itself_on_pause=True,
                      native_homing=any(d.keys.homing is not None for d in self.drives),
                      transition_timeouts_s=self.TRANSITION_TIMEOUTS_S)

    @property
    def _where(self) -> str:
        return f"{self.config.interface} {self.config.channel}"

    # ------------------------------------------------------------------ start-up
    def _connect(self) -> canopen.Network:
        cfg = self.config
        network = canopen.Network()
        network.NOTIFIER_CYCLE = 0.05  # disconnect() waits up to this (default 1 s)
        try:
            self._open_bus(network)
        except (can.CanError, OSError, ValueError, TypeError, ImportError) as exc:
            raise BackendError(f"{self.robot}: cannot open CAN interface {self._where} "
                               f"(backend.interface / backend.channel): {exc}{_open_hint(exc)}") from exc
        network.notifier.add_listener(_BusWatch(self))
        return network

    def _open_bus(self, network: canopen.Network) -> None:
        """Open the CAN interface and canopen's notifier on it. The ``slcan`` interface is
        python-can's with a receive that reads what the adapter sent in one go (slcan.py: byte by
        byte, it took a quarter of a core at 250 Hz); every other interface is ``can.Bus``'s."""
        cfg = self.config
        if cfg.interface == "slcan":
            network.bus = SlcanBus(channel=cfg.channel, bitrate=cfg.bitrate, **cfg.options)
        network.connect(interface=cfg.interface, channel=cfg.channel, bitrate=cfg.bitrate, **cfg.options)

    def _open_hook(self) -> None:
        """Open the bus, wait for every node to boot (boot-up, heartbeat or an SDO answer, within
        ``boot_timeout_s`` each), check it is a CiA 402 drive, read its supported modes and rated
        torque. Blocks. Raises BackendError naming the node."""
        quiet = logging.getLogger("canopen")
        if quiet.level == logging.NOTSET:  # its INFO lines narrate every SDO of the PDO set-up
            quiet.setLevel(logging.WARNING)
        network = self._connect()
        self._network = network
        try:
            for d in self.drives:
                self._add_node(d)
            for d in self.drives:
                self._boot(d)
                self._identify(d)
        except BaseException:
            self._disconnect()
            raise
        self._details = {
            "interface": self.config.interface, "channel": self.config.channel, "bitrate": self.config.bitrate,
            "nodes": {d.name: d.id for d in self.drives},
            "supported_modes": {d.name: f"0x{d.supported:08X}" for d in self.drives},
        }

    def _add_node(self, d: _Drive) -> None:
        eds = d.keys.eds
        if eds is not None:
            path = Path(eds)
            if not path.is_absolute() and Path(self.source).is_file():
                path = Path(self.source).parent / path
            try:
                od = canopen.import_od(str(path), d.id)
            except Exception as exc:  # the parser raises whatever the file trips
                raise BackendError(f"{self.robot}: {d.label}: cannot read EDS {path} "
                                   f"(joints[{d.i}].eds): {exc}") from exc
        else:
            od = standard_402()
        node = canopen.RemoteNode(d.id, od)
        self._network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = self.config.sdo_timeout_s
        d.node = node

        def heartbeat(state: int, d: _Drive = d) -> None:  # notifier thread
            d.hb_t = time.monotonic()
            d.nmt = state
            if state == t.NMT_BOOTUP:
                d.rebooted = True
            if self._waiting:
                self._rx_event.set()

        def emcy(err: Any, d: _Drive = d) -> None:  # notifier thread
            if err.code & 0xFF00 == 0:
                d.emcy = None
            else:
                d.emcy_at = d.arrived[0]  # before d.emcy: the read thread judges it by the TPDOs after
                d.emcy = (err.code, err.register)

        node.nmt.add_heartbeat_callback(heartbeat)
        node.emcy.add_callback(emcy)
        d.tpdos = [node.tpdo[1], node.tpdo[2]]
        d.on_tpdo = []
        for m, pdo in enumerate(d.tpdos):
            def got(can_id: int, data: bytearray, timestamp: float, d: _Drive = d, m: int = m,
                    pdo: Any = pdo) -> None:  # notifier thread
                pdo.data, pdo.timestamp = data, timestamp  # what PdoMap.on_message keeps (_decode reads it)
                d.arrived[m] += 1
                if self._waiting:  # after the count (see _wait_tpdos)
                    self._rx_event.set()

            d.on_tpdo.append(got)
        d.rpdo1, d.rpdo2 = node.rpdo[1], node.rpdo[2]

    def _boot(self, d: _Drive) -> None:
        """Wait until node ``d`` is up: a boot-up or heartbeat seen, or an SDO answer."""
        deadline = time.monotonic() + self.config.boot_timeout_s
        last: Exception | None = None
        while True:
            if d.hb_t:
                return
            try:
                d.node.sdo.upload(t.DEVICE_TYPE, 0)
                return
            except (SdoError, can.CanError) as exc:
                last = exc
            if time.monotonic() > deadline:
                raise BackendError(
                    f"{self.robot}: {d.label} did not boot within {self.config.boot_timeout_s:g} s "
                    f"(backend.boot_timeout_s) on {self._where}: no boot-up, heartbeat or SDO answer"
                    f"{f' ({last})' if last else ''}")
            time.sleep(0.02)

    def _sdo_read(self, d: _Drive, index: int, sub: int = 0) -> int:
        try:
            return d.node.sdo[index].raw if sub == 0 else d.node.sdo[index][sub].raw
        except (SdoError, can.CanError, KeyError) as exc:
            raise BackendError(f"{self.robot}: {d.label}: reading 0x{index:04X}:{sub} on {self._where} "
                               f"failed: {exc}") from exc

    def _sdo_write(self, d: _Drive, index: int, value: int, sub: int = 0, key: str = "") -> None:
        """Write one object over SDO; ``key``: the profile key the value comes from (named in
        the error). Blocks. Raises BackendError naming the node and the object."""
        try:
            if sub == 0:
                d.node.sdo[index].raw = value
            else:
                d.node.sdo[index][sub].raw = value
        except (SdoError, can.CanError, KeyError, ValueError) as exc:
            raise BackendError(f"{self.robot}: {d.label}: writing 0x{index:04X}:{sub} = {value} on "
                               f"{self._where} failed{f' ({key})' if key else ''}: {exc}") from exc

    def _identify(self, d: _Drive) -> None:
        device_type = self._sdo_read(d, t.DEVICE_TYPE)
        if device_type & 0xFFFF != t.DEVICE_PROFILE_402:
            raise BackendError(f"{self.robot}: {d.label} is not a CiA 402 drive (device type 0x1000 = "
                               f"0x{device_type:08X}, profile {device_type & 0xFFFF})")
        d.supported = self._sdo_read(d, t.SUPPORTED_MODES)
        if not t.supports(d.supported, Mode.CYCLIC_SYNC_POSITION):
            raise BackendError(f"{self.robot}: {d.label} does not support cyclic synchronous position "
                               f"(0x6502 = 0x{d.supported:08X}), which holding a joint needs")
        d.csv = t.supports(d.supported, Mode.CYCLIC_SYNC_VELOCITY)
        d.cst = t.supports(d.supported, Mode.CYCLIC_SYNC_TORQUE)
        if d.keys.homing is not None and not t.supports(d.supported, Mode.HOMING):
            raise BackendError(f"{self.robot}: {d.label} does not support homing mode (0x6502 = "
                               f"0x{d.supported:08X}) but joints[{d.i}].homing is set")
        rated = d.keys.rated_torque
        if rated is None:
            try:
                mnm = d.node.sdo[t.RATED_TORQUE].raw
                rated = mnm / 1000.0 if mnm else None
            except (SdoError, can.CanError, KeyError):
                rated = None  # no torque scale: effort neither measured nor commanded
        if rated is not None:
            lever = d.keys.gear_ratio * (2.0 * math.pi if d.unit == "m" else 1.0)
            d.k_eff = d.keys.direction * rated / 1000.0 * lever
        caps = Capabilities(position=True, velocity=d.csv, effort=d.cst and d.k_eff is not None,
                            measures_velocity=True, measures_effort=d.k_eff is not None,
                            needs_homing=d.keys.homing is not None, can_free=d.cst)
        self._joint_caps[d.i] = caps

    def _configure_hook(self) -> None:
        """Per node: NMT PRE-OPERATIONAL, heartbeat producer, the PDO mapping (SDO, CiA 301
        remap procedure via ``PdoMap.save``), homing parameters; NMT OPERATIONAL; then one SYNC
        whose TPDOs every node must answer. The drives are left in SWITCH ON DISABLED (controlword
        disable voltage): the robot starts DISABLED. Blocks. Raises BackendError naming the node."""
        self._require_open()
        for d in self.drives:
            self._configure_node(d)
        self._prime()

    def _require_open(self) -> None:
        if self._network is None:
            raise BackendError(f"{self.robot}: the CAN bus is not open; call open() first")

    def _configure_node(self, d: _Drive) -> None:
        node = d.node
        node.nmt.state = "PRE-OPERATIONAL"
        self._sdo_write(d, t.HEARTBEAT_PRODUCER, self.config.heartbeat_ms)
        self._watch_master(d)
        try:
            self._map_pdos(d)
        except (SdoError, can.CanError, KeyError, ValueError) as exc:
            raise BackendError(f"{self.robot}: {d.label}: configuring its PDOs on {self._where} failed: "
                               f"{exc}") from exc
        h = d.keys.homing
        if h is not None:
            per_si = 1.0 / abs(d.k_pos)
            self._sdo_write(d, t.HOMING_METHOD, h.method)
            self._sdo_write(d, t.HOMING_SPEEDS, round(h.speed_switch * per_si * d.keys.velocity_factor), 1)
            self._sdo_write(d, t.HOMING_SPEEDS, round(h.speed_zero * per_si * d.keys.velocity_factor), 2)
            self._sdo_write(d, t.HOMING_ACCELERATION, round(h.acceleration * per_si * d.keys.velocity_factor))
        # first RPDO values: hold where it is, disabled
        d.pos = self._sdo_read(d, t.POSITION_ACTUAL)
        d.cw, d.mode, d.target_pos, d.target_vel, d.target_torque = int(Command.DISABLE_VOLTAGE), _CSP, d.pos, 0, 0
        d.homing = False
        node.nmt.state = "OPERATIONAL"
        d.started_t = d.hb_t = time.monotonic()
        d.nmt = t.NMT_OPERATIONAL
        d.rebooted = False

    def _watch_master(self, d: _Drive) -> None:
        """The drive watches the master's heartbeat (0x1016:1) and reacts to its loss as
        ``abort_connection_option`` says (0x6007); both read back, since a drive may clamp or
        ignore a value. Blocks (SDO). Raises BackendError naming the node, object and key."""
        cfg = self.config
        entry = t.heartbeat_consumer_entry(cfg.master_node_id, self._consumer_ms)
        key = "backend.master_node_id / master_heartbeat_timeout_ms: the drive's heartbeat consumer"
        self._sdo_write(d, t.HEARTBEAT_CONSUMER, entry, 1, key)
        checks = [(t.HEARTBEAT_CONSUMER, 1, entry, key)]
        if cfg.abort_connection_option is not None:
            option = t.ABORT_CONNECTION_OPTIONS[cfg.abort_connection_option]
            key = f"backend.abort_connection_option: {cfg.abort_connection_option}"
            self._sdo_write(d, t.ABORT_CONNECTION_OPTION, option, 0, key)
            checks.append((t.ABORT_CONNECTION_OPTION, 0, option, key))
        for index, sub, want, key in checks:
            got = self._sdo_read(d, index, sub)
            if got != want:
                raise BackendError(f"{self.robot}: {d.label}: 0x{index:04X}:{sub} reads back 0x{got:X} after "
                                   f"writing 0x{want:X} ({key}); the drive would not stop by itself when "
                                   f"the master is gone")

    def _unwatch_master(self) -> None:
        """Clean close: drives left disabled stop watching the master's heartbeat (0x1016:1 = 0),
        so a daemon that shut down properly leaves no EMCY 0x8130 FAULT behind; a drive still
        enabled (or unknown) keeps watching and stops itself. Best effort, blocks (SDO)."""
        if self._network is None or self._bus_down is not None:
            return
        for d in self.drives:
            if d.node is None or not d.v or d.state in (None, State402.OPERATION_ENABLED,
                                                        State402.QUICK_STOP_ACTIVE):
                continue
            try:
                d.node.sdo[t.HEARTBEAT_CONSUMER][1].raw = 0
            except (SdoError, can.CanError, KeyError, ValueError):
                pass

    def _map_pdos(self, d: _Drive) -> None:
        """RPDO1 = controlword + target position + mode; RPDO2 = target velocity + target torque
        (CSV / CST drives only); TPDO1 = statusword + position + mode display; TPDO2 = velocity +
        torque. All SYNC-type (transmission type 1: every SYNC). PDOs 3 and 4 switched off."""
        node = d.node
        layout = (
            (d.rpdo1, 0x200, (t.CONTROLWORD, t.TARGET_POSITION, t.MODES_OF_OPERATION), True),
            (node.rpdo[2], 0x300, (t.TARGET_VELOCITY, t.TARGET_TORQUE), d.csv or d.cst),
            (d.tpdos[0], 0x180, (t.STATUSWORD, t.POSITION_ACTUAL, t.MODES_DISPLAY), True),
            (d.tpdos[1], 0x280, (t.VELOCITY_ACTUAL, t.TORQUE_ACTUAL), True),
        )
        d.v = {}
        d.layout = {}
        for pdo, base, objects, used in layout:
            pdo.clear()
            pdo.cob_id = base + d.id
            pdo.trans_type = 1
            pdo.enabled = used
            if used:
                for index in objects:
                    d.v[index] = pdo.add_variable(index)
                d.layout[pdo] = _payload_struct(d, pdo)
                d.head[pdo] = SlcanBus.head(pdo.cob_id, d.layout[pdo].size)
            pdo.save()
        # Each TPDO frame straight to the backend's own handler (got, _add_node) rather than
        # through PdoMap.on_message, which save() subscribed: its Condition, notify_all and
        # callback loop per frame were a seventh of the notifier thread's CPU (4 frames a
        # 2-drive cycle; issue 23), and nothing here waits on the map's reception
        network = self._network
        for pdo, got in zip(d.tpdos, d.on_tpdo):
            if pdo.on_message in network.subscribers.get(pdo.cob_id, ()):
                network.unsubscribe(pdo.cob_id, pdo.on_message)
            network.subscribe(pdo.cob_id, got)
        d.rpdo2 = node.rpdo[2] if d.csv or d.cst else None
        for n in (2, 3):  # PDOs 3 and 4: off, so no event-driven frames share the cycle
            for com, base in ((0x1400, 0x200), (0x1800, 0x180)):
                if com + n in node.object_dictionary:
                    node.sdo[com + n][1].raw = (base + 0x100 * n + d.id) | PDO_NOT_VALID

    def _prime(self) -> None:
        """One exchange right after start-up, so the first read has data: every node's TPDOs must
        answer a SYNC within ``boot_timeout_s``."""
        deadline = time.monotonic() + self.config.boot_timeout_s
        while True:
            self._send(None)
            self._sync_out()
            missing = self._wait_tpdos(time.monotonic() + min(0.1, self.config.boot_timeout_s))
            self._resync(self._sync_seq)
            if missing is None:
                self._decode()
                return
            if time.monotonic() > deadline:
                raise BackendError(f"{self.robot}: {missing.label} sent no TPDO answering SYNC within "
                                   f"{self.config.boot_timeout_s:g} s of NMT start on {self._where}")

    # ------------------------------------------------------------------ the cycle
    # TPDO accounting: each drive answers every SYNC with one frame per TPDO, so "frames arrived
    # - base" is the number of the last SYNC it answered. Counting (not tagging frames with the
    # SYNC sent last) keeps a late answer to an older SYNC from passing for a fresh one.
    def _answered(self, d: _Drive) -> int:
        return min(d.arrived[0] - d.base[0], d.arrived[1] - d.base[1])

    def _resync(self, upto: int) -> None:
        """Count from SYNC ``upto`` on: a drive behind it is taken as having answered it (each
        missed SYNC is counted once), one ahead of the SYNCs sent is brought back."""
        seq = self._sync_seq
        for d in self.drives:
            for m in (0, 1):
                answered = d.arrived[m] - d.base[m]
                if answered < upto:
                    d.base[m] = d.arrived[m] - upto
                elif answered > seq:
                    d.base[m] = d.arrived[m] - seq

    def _wait_tpdos(self, deadline: float, drives: list[_Drive] | None = None,
                    seq: int | None = None) -> _Drive | None:
        """Wait (at most until ``deadline``, monotonic) until every node's (of ``drives``) TPDOs
        answered SYNC ``seq`` (default: the last). Returns the first drive that did not, or None."""
        seq = self._sync_seq if seq is None else seq
        ev = self._rx_event
        drives = self.drives if drives is None else drives
        # The notifier signals only while a read waits: a TPDO's Event.set (a Condition and a
        # notify_all) for each of the cycle's frames was a tenth of the notifier's CPU, and the
        # cycle's read rarely waits (its TPDOs answered the previous SYNC). No wake-up is lost:
        # the notifier counts a frame before it looks at _waiting, and this looks at the counts
        # after setting it.
        if all(self._answered(d) >= seq for d in drives):
            return None  # the usual case: in already, the event untouched
        try:
            while True:
                ev.clear()
                self._waiting = True
                missing = next((d for d in drives if self._answered(d) < seq), None)
                remaining = deadline - time.monotonic()
                if missing is None or remaining <= 0:
                    return missing
                ev.wait(remaining)
        finally:
            self._waiting = False

    def _overdue(self, now: float) -> _Drive | None:
        """The first drive that has not answered a SYNC sent more than ``tpdo_timeout_ms`` ago
        (missing TPDOs; a late drive within the time limit is not missing), or None. Counts each
        missed SYNC once."""
        seq = self._sync_seq
        due = seq
        while due > 0 and seq - due < _RING - 1 and self._sync_mono[due % _RING] + self._tpdo_timeout_s > now:
            due -= 1
        missing = next((d for d in self.drives if self._answered(d) < due), None)
        self._resync(due)
        return missing

    def _decode(self) -> None:
        # each TPDO's payload in one unpack (its layout: _map_pdos), not five canopen Variable.raw
        # reads per drive (each one logs and shifts bits: a quarter of the cycle's CPU, issue 23);
        # a payload shorter than the map (a broken drive) leaves the previous values
        for d in self.drives:
            tpdo1, tpdo2 = d.tpdos
            data, layout = tpdo1.data, d.layout[tpdo1]
            if len(data) >= layout.size:
                d.sw, d.pos, d.mode_display = layout.unpack_from(data)
            data, layout = tpdo2.data, d.layout[tpdo2]
            if len(data) >= layout.size:
                d.vel, d.torque = layout.unpack_from(data)
            d.state = t.decode_state(d.sw)

    def _read(self, feedback: JointFeedback) -> Fault | None:
        """Take the TPDOs that answered the previous SYNC (the one before this cycle's: in
        already, no waiting in the cycle), waiting for a late drive at most until ``tpdo_timeout_ms`` after that
        SYNC; convert them into ``feedback`` (stamp: the SYNC the oldest sample answered), check
        heartbeats and EMCYs, report the device status. Returns a transient ``tpdo_missing``
        fault, a ``heartbeat_lost`` / ``nmt_state`` / ``bus_error`` fault, or None."""
        fault = self._unusable("read")
        if fault is not None:
            self._settle_until = time.monotonic() + self._settle_s
            return fault
        self.stats["reads"] += 1
        want = self._sync_seq - 1  # this cycle's SYNC went out in wait_cycle: the one before it
        # A late drive is waited for until tpdo_timeout_ms after that SYNC; one that missed the
        # previous read is not, so a silent node does not stretch every cycle: its data is then
        # that of the last SYNC it answered, and it is missing once that is overdue.
        if want > 0:
            self._wait_tpdos(self._sync_mono[want % _RING] + self._tpdo_timeout_s,
                             [d for d in self.drives if not d.missed], want)
        now = time.monotonic()
        missing = self._overdue(now)
        if missing is not None:
            self.stats["tpdos_missed"] += 1
        else:  # a drive that missed and has sent nothing for tpdo_timeout_ms stays missing in
            # every read, not only in those that bring a new SYNC due (after a late cycle,
            # several bring none)
            missing = next((d for d in self.drives if d.missed and sum(d.arrived) == d.heard
                            and now - d.heard_t > self._tpdo_timeout_s), None)
        self._decode()
        fault = None
        if missing is not None:
            self._settle_until = now + self._settle_s  # the drives may not hear us either
            missing.missed += 1
            fault = Fault("tpdo_missing",
                          f"{self.robot}: {missing.label} sent no TPDO answering a SYNC within "
                          f"{self._tpdo_timeout_s * 1000:.3g} ms on {self._where} ({missing.missed} in a row)",
                          joint=missing.name, transient=True)
        for d in self.drives:
            heard, d.heard = sum(d.arrived) != d.heard, sum(d.arrived)
            if heard:
                d.heard_t = now
            if d is not missing and heard:  # it sent TPDOs: waited for again (a silent one stays
                d.missed = 0  # missed, not waited for every other cycle while none is overdue)
            silent = now - d.hb_t
            if silent > self._hb_timeout_s:
                fault = Fault("heartbeat_lost",
                              f"{self.robot}: {d.label}: no heartbeat for {silent:.2f} s "
                              f"(backend.heartbeat_timeout_ms = {self.config.heartbeat_timeout_ms:g})",
                              joint=d.name, transient=False)
                break
            if (d.nmt != t.NMT_OPERATIONAL or d.rebooted) and d.hb_t > d.started_t + 0.05:
                what = "restarted (boot-up)" if d.rebooted else \
                    f"left OPERATIONAL (heartbeat: {t.NMT_STATE_NAMES.get(d.nmt, hex(d.nmt))})"
                fault = Fault("nmt_state", f"{self.robot}: {d.label} {what}", joint=d.name, transient=False)
                break
        if self._error_frames != self._error_frames_seen and fault is None:
            self._error_frames_seen = self._error_frames
            fault = Fault("bus_error", f"{self.robot}: error frame on {self._where} "
                          f"({self._error_frames} so far)", transient=True)
        pos, vel, eff = feedback.position, feedback.velocity, feedback.effort
        for d in self.drives:
            i = d.i
            pos[i] = (d.pos - d.keys.offset) * d.k_pos
            vel[i] = d.vel * d.k_vel
            eff[i] = d.torque * d.k_eff if d.k_eff is not None else 0.0
        oldest = min(min(self._answered(d) for d in self.drives), self._sync_seq)
        feedback.stamp = self._sync_wall[oldest % _RING]  # when the oldest sample was taken
        self._device_status()
        return fault

    def _device_status(self) -> None:
        """Report what the drives say about themselves (core maps it, state.DEVICE_STATUS)."""
        cause = None
        paused = powered_off = False
        for d in self.drives:
            s = d.state
            emcy = d.emcy
            if emcy is None:
                d.emcy_warned = None  # its EMCY 0x0000 came (or a fault reset): a new one is news again
            if s in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
                cause = self._drive_fault(d)
                break
            if emcy is not None:
                seen = d.arrived[0] - d.emcy_at  # statuswords since the EMCY
                if seen > 0 and d.sw & t.SW_WARNING:  # the drive goes on: a warning
                    if d.emcy_warned != emcy:
                        d.emcy_warned = emcy
                        self.report_status(DeviceStatus.WARNING, self._drive_warning(d, emcy))
                elif seen >= t.EMCY_DECIDE_TPDOS:  # neither its FAULT state nor a warning: a fault
                    cause = self._drive_fault(d)
                    break
            if self._enabled and d.cw == Command.ENABLE_OPERATION and not d.homing:
                if s is State402.QUICK_STOP_ACTIVE and not self._paused_by_us:
                    paused = True
                elif s not in (State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE, None):
                    powered_off = True
        if cause is not None:
            self.report_status(DeviceStatus.FAULT, cause)
        elif self.device_status is DeviceStatus.FAULT:
            self.report_status(DeviceStatus.FAULT_CLEARED)
        elif powered_off:
            self.report_status(DeviceStatus.POWERED_OFF)
        elif paused:
            self.report_status(DeviceStatus.PAUSED)
        elif self.device_status is not DeviceStatus.OK:
            self.report_status(DeviceStatus.OK)

    def _drive_warning(self, d: _Drive, emcy: tuple[int, int]) -> Fault:
        code, register = emcy
        return Fault("device_warning", f"{self.robot}: {d.label}: EMCY 0x{code:04X} {t.emcy_meaning(code)} "
                     f"(error register 0x{register:02X}), a warning (statusword 0x{d.sw:04X}, bit 7): "
                     "the drive goes on; see to its cause", joint=d.name, register="EMCY", value=code,
                     transient=True)

    def _drive_fault(self, d: _Drive) -> Fault:
        state = d.state.value if d.state is not None else f"statusword 0x{d.sw:04X}"
        if d.emcy is not None:
            code, register = d.emcy
            return Fault("drive_fault", f"{self.robot}: {d.label}: EMCY 0x{code:04X} {t.emcy_meaning(code)} "
                         f"(error register 0x{register:02X}); drive state {state}",
                         joint=d.name, register="EMCY", value=code, transient=False)
        return Fault("drive_fault", f"{self.robot}: {d.label}: drive state {state} (statusword 0x{d.sw:04X})",
                     joint=d.name, register="statusword", value=d.sw, transient=False)

    def _write(self, command: JointCommand) -> Fault | None:
        """Set every drive's RPDOs from ``command`` and send them (applied at the next SYNC).
        Never blocks.

        A drive that is OPERATION ENABLED (and not homing) follows its joint's mode: POSITION ->
        CSP, VELOCITY -> CSV, EFFORT -> CST, FREE -> CST with zero torque, NONE -> as before.
        Every other drive holds its measured position as target in CSP. Setpoints arrive finite
        and within the profile's limits (``Actuator.write``, core's motion output); targets are
        clamped to their objects' ranges only (I32, I16; the rated torque without effort_max)."""
        return self._send(command)

    def _unusable(self, what: str) -> Fault | None:
        """Why the bus cannot be used for ``what`` (read / write) now, or None."""
        if self._network is None:
            return Fault("bus_error", f"{self.robot}: {what} on a closed CAN bus", transient=False)
        if self._bus_down is not None:
            return self._bus_fault()
        if not self.drives[0].v:
            return Fault("bus_error", f"{self.robot}: {what} before configure(): no PDO mapped yet", transient=False)
        return None

    def _send(self, command: JointCommand | None) -> Fault | None:
        fault = self._unusable("write")
        if fault is not None:
            return fault
        for d in self.drives:
            enabled = self._enabled and d.state is State402.OPERATION_ENABLED and command is not None
            if d.homing:
                d.mode, d.target_pos, d.target_vel, d.target_torque = _HM, d.pos, 0, 0
            elif not enabled:
                d.mode, d.target_pos, d.target_vel, d.target_torque = _CSP, d.pos, 0, 0
            else:
                self._follow(d, command)
                if d.mode != _CSP:
                    d.target_pos = d.pos  # a switch back to CSP starts from here
            # each RPDO's payload in one pack (see _decode)
            d.rpdo1.data = bytearray(d.layout[d.rpdo1].pack(d.cw, d.target_pos, d.mode))
            if d.rpdo2 is not None:
                d.rpdo2.data = bytearray(d.layout[d.rpdo2].pack(d.target_vel, d.target_torque))
        try:
            bus = self._network.bus
            if isinstance(bus, SlcanBus):
                # the cycle's RPDOs as ONE write of lines formatted here (slcan.py: send_lines,
                # python-can's bytes without a Message, a lock and a format per frame)
                lines = []
                for d in self.drives:
                    lines.append(d.head[d.rpdo1] + hexlify(d.rpdo1.data).upper() + b"\r")
                    if d.rpdo2 is not None:
                        lines.append(d.head[d.rpdo2] + hexlify(d.rpdo2.data).upper() + b"\r")
                bus.send_lines(b"".join(lines))
                self._network.check()  # what canopen's send_message checks: the notifier's error
                self.stats["rpdos"] += len(lines)
            else:
                for d in self.drives:
                    d.rpdo1.transmit()
                    if d.rpdo2 is not None:
                        d.rpdo2.transmit()
                        self.stats["rpdos"] += 1
                    self.stats["rpdos"] += 1
        except (can.CanError, OSError) as exc:
            self._bus_down = f"send failed: {exc}"
            return self._bus_fault()
        return fault

    def _sync_out(self) -> None:
        """Transmit one SYNC: the drives apply the RPDOs received since the previous one and
        answer with their TPDOs. Never blocks (a failed send marks the bus down for read)."""
        if self._network is None or self._bus_down is not None:
            return
        try:
            self._sync_seq += 1  # first: the answers to this SYNC count against it
            self._sync_t = self._sync_mono[self._sync_seq % _RING] = time.monotonic()
            self._sync_wall[self._sync_seq % _RING] = time.time()
            due = self._master_hb_due
            heartbeat = due is not None and self._sync_t >= due  # the master's heartbeat rides the SYNC
            network = self._network
            bus = network.bus
            if isinstance(bus, SlcanBus):  # both in one write, formatted here (slcan.py: send_lines)
                sync = network.sync
                bus.send_lines(bus.line(sync.cob_id, b"") + (self._master_hb_line if heartbeat else b""))
                network.check()
            else:
                network.sync.transmit()
                if heartbeat:
                    network.send_message(self._master_hb_cob, self._master_hb_data)
            self.stats["syncs"] += 1
            if heartbeat:
                self.stats["heartbeats"] += 1
                due += self._master_hb_period_s  # on its own grid, unless a stall put it behind
                self._master_hb_due = due if due > self._sync_t else self._sync_t + self._master_hb_period_s
        except (can.CanError, OSError) as exc:
            self._bus_down = f"send failed: {exc}"

    # ------------------------------------------------------------------ pacing
    def wait_cycle(self, deadline: float) -> bool:
        """The cycle starts (the runner slept to its tick, ``deadline``, on its absolute
        schedule): the SYNC at once -- the first thing of the cycle, so its jitter is the
        wake-up's alone (and the master's heartbeat with it when due: the first call starts it).
        Always True."""
        if self._master_hb_due is None:
            self._master_hb_due = 0.0
        self._sync_out()
        return True

    def _follow(self, d: _Drive, command: JointCommand) -> None:
        i = d.i
        mode = command.mode[i]
        if mode == _POSITION:
            d.mode, d.target_pos = _CSP, d.counts(command.position[i])
            d.target_vel = d.target_torque = 0
        elif mode == _VELOCITY and d.csv:
            x = command.velocity[i] / d.k_vel
            d.mode, d.target_vel, d.target_torque = _CSV, round(min(max(x, I32[0]), I32[1])), 0
        elif mode == _EFFORT and d.cst and d.k_eff is not None:
            x = command.effort[i] / d.k_eff
            # no limits.effort_max: never above the rated torque (1000 per mille), not the I16 range
            cap = I16[1] if d.eff_max is not None else RATED_PER_MILLE
            d.mode, d.target_torque, d.target_vel = _CST, round(min(max(x, -cap), cap)), 0
        elif mode == _FREE and d.cst:
            d.mode, d.target_torque, d.target_vel = _CST, 0, 0
        return None

    # ------------------------------------------------------------------ bus errors
    def _bus_fault(self) -> Fault:
        if self._reopening is None or not self._reopening.is_alive():
            self._reopening = background_thread(self._reopen, "can-reopen")
            self._reopening.start()
        return Fault("bus_error", f"{self.robot}: CAN bus {self._where} failed ({self._bus_down}); "
                     f"reopening it", transient=False)

    def _reopen(self) -> None:
        """Worker: close the failed bus and open it again, retrying each second until it opens
        (or the backend closes)."""
        while self._network is not None and self._bus_down is not None:
            network = self._network
            try:
                network.disconnect()
            except Exception:
                pass
            try:
                self._open_bus(network)
                network.notifier.add_listener(_BusWatch(self))
                for d in self.drives:  # the heartbeat clock restarts with the bus
                    d.hb_t = time.monotonic()
                self._bus_down = None
                return
            except Exception:
                time.sleep(1.0)

    # ------------------------------------------------------------------ transitions
    def _walk(self, goal: Goal, drives: list[_Drive] | None = None) -> Steps:
        """Every cycle, each drive's controlword from ``tables.WALK`` for its state and ``goal``,
        until every drive is there. Raises BackendError naming a drive that is in FAULT (when
        enabling), or whose statusword stays missing."""
        drives = self.drives if drives is None else drives
        missed = 0
        while True:
            pending = None
            for d in drives:
                if d.state is None:
                    pending = d
                    continue
                step = t.WALK[(d.state, goal)]
                if step.command is None:
                    raise BackendError(f"{self.robot}: {d.label} is in {d.state.value} "
                                       f"(statusword 0x{d.sw:04X}); cannot {goal.value}")
                d.cw = int(step.command)
                if not step.done or d.missed:  # a stale statusword (TPDOs missing) confirms nothing
                    pending = d
            if pending is None:
                return
            yield
            missed = missed + 1 if pending.missed else 0
            if missed > self.TRANSITION_MISSED_MAX:
                raise BackendError(f"{self.robot}: {pending.label}: no statusword for {missed} cycles; "
                                   f"cannot confirm {goal.value} ({pending.state.value if pending.state else '?'})")

    def _reset_faults(self) -> Steps:
        """Fault reset of every drive in FAULT: bit 7 low for a cycle, then high (the rising edge,
        transition 15), until the drive leaves FAULT; its EMCY is acknowledged. Nodes that
        rebooted, or whose heartbeat says they left OPERATIONAL (put in NMT STOPPED by something
        on the bus), are configured again and started (SDO, on a worker thread)."""
        rebooted = [d for d in self.drives if d.rebooted or d.nmt != t.NMT_OPERATIONAL]
        if rebooted:
            yield from on_worker(lambda: [self._configure_node(d) for d in rebooted], "canopen-reconfigure")
        # After a bus outage a drive may still be about to trip on the master's heartbeat it
        # missed (its consumer time after the last one it heard): let that happen first, so the
        # reset below sees it, rather than the walk meeting a fresh FAULT
        settle = min(self._settle_until, time.monotonic() + self._settle_s)  # a silent node keeps
        while time.monotonic() < settle:  # pushing _settle_until: bounded from here
            yield
        # a node whose heartbeat was lost gets a moment to be heard again (it may just be back)
        deadline = time.monotonic() + 2 * self._hb_timeout_s
        while True:
            now = time.monotonic()
            silent = next((d for d in self.drives if now - d.hb_t > self._hb_timeout_s), None)
            if silent is None:
                break
            if now > deadline:
                raise BackendError(f"{self.robot}: {silent.label}: no heartbeat for {now - silent.hb_t:.2f} s; "
                                   f"cannot enable")
            yield
        faulted = [d for d in self.drives if d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)]
        for d in self.drives:
            d.emcy = None
        if not faulted:
            return
        for d in faulted:
            d.cw = int(Command.DISABLE_VOLTAGE)  # bit 7 low first: the reset acts on a rising edge
        yield
        cycles = 0
        while True:
            for d in faulted:
                d.cw = int(Command.FAULT_RESET)
            yield
            still = [d for d in faulted if d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)]
            for d in faulted:
                d.emcy = None
            if not still:
                break
            cycles += 1
            if cycles > self.TRANSITION_MISSED_MAX:
                d = still[0]
                raise BackendError(f"{self.robot}: {d.label} stays in FAULT after a fault reset "
                                   f"(statusword 0x{d.sw:04X}); the cause may persist")
        for d in faulted:
            d.cw = int(Command.DISABLE_VOLTAGE)

    def _fault_reset_steps(self) -> Steps:
        yield from self._reset_faults()

    def _enable_steps(self, feedback: JointFeedback) -> Steps:
        """Fault reset where needed, then SWITCH ON DISABLED -> READY TO SWITCH ON -> SWITCHED ON
        -> OPERATION ENABLED, one controlword per cycle, each drive holding its measured position
        as target in CSP. On failure every drive gets disable voltage."""
        self._require_open()
        self._paused_by_us = False
        try:
            yield from self._reset_faults()
            yield from self._walk(Goal.OPERATION_ENABLED)
        except BaseException:
            for d in self.drives:
                d.cw = int(Command.DISABLE_VOLTAGE)
            raise

    def _disable_steps(self) -> Steps:
        """Disable voltage on every drive (transitions 7, 9, 10, 12) until each confirms."""
        if self._network is None:
            return
        self._paused_by_us = False
        for d in self.drives:
            d.homing = False
        yield from self._walk(Goal.SWITCH_ON_DISABLED)

    def _pause_steps(self) -> Steps:
        """Quick stop (transition 11) until every drive is QUICK STOP ACTIVE (or stopped)."""
        self._paused_by_us = True
        yield from self._walk(Goal.QUICK_STOP_ACTIVE)

    def _resume_steps(self) -> Steps:
        """Enable operation (transition 16) from QUICK STOP ACTIVE, holding the measured position
        (a drive whose quick stop ended in SWITCH ON DISABLED walks the whole way)."""
        try:
            yield from self._walk(Goal.OPERATION_ENABLED)
        finally:
            self._paused_by_us = False

    def _home_steps(self) -> Steps:
        """CiA 402 homing (mode 6) of every joint with ``homing``, all at once: mode 6, a rising
        edge of controlword bit 4, then statusword bits 10 / 12 / 13 until homing is completed
        (``is_homed`` = bit 12), an error (BackendError naming the joint) or the time limit.
        Joints without ``homing`` (absolute encoders) hold."""
        drives = [d for d in self.drives if d.keys.homing is not None]
        try:
            for d in drives:
                d.homing = True
                d.cw = int(Command.ENABLE_OPERATION)  # bit 4 low while the mode switches
            while any(d.mode_display != _HM for d in drives):
                yield
            for d in drives:
                d.cw = int(Command.ENABLE_OPERATION) | t.CW_HOMING_START
            yield
            pending = list(drives)
            while pending:
                yield
                for d in list(pending):
                    meaning, finished, failed = t.HOMING_STATUS[d.sw & t.HOMING_STATUS_MASK]
                    if failed:
                        raise BackendError(f"{self.robot}: {d.label}: {meaning} (statusword 0x{d.sw:04X}, "
                                           f"method {d.keys.homing.method})")
                    if finished and d.state is State402.OPERATION_ENABLED:
                        pending.remove(d)
        finally:  # back to CSP in the cycle this ends: core holds the homed position from it on
            for d in drives:
                d.homing = False
                d.cw = int(Command.ENABLE_OPERATION)

    # ------------------------------------------------------------------ close
    def _disconnect(self) -> None:
        network, self._network = self._network, None
        if network is not None:
            try:
                network.disconnect()
            except Exception:
                pass

    def _close_hook(self) -> None:
        self._unwatch_master()
        self._master_hb_due = None
        self._disconnect()

"""CiA 402 and CiA 301 as data: the drive state machine, modes, homing status, EMCY codes.

Sources (the numbers below are the standards', docs/architecture.md, "Sources": CANopen CiA 402):

* CiA 402-2 (IEC 61800-7-201) section 6.2 "Device control": the power drive system state
  machine, the statusword 0x6041 state coding (its table "State coding") and the controlword
  0x6040 commands (its table "Command coding"), transitions numbered 0..16 as in its figure
  "State machine".
* CiA 402-2 section 6.2.3 / 0x6502 "Supported drive modes": one bit per mode.
* CiA 402-2 section 8 "Homing mode": statusword bits 10, 12, 13 while in homing mode.
* CiA 301 section 7.2.7 "Emergency object" (error code classes, table "Emergency error codes")
  and CiA 402-2 annex "Error codes" for the drive-specific codes.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

# ---------------------------------------------------------------- objects (CiA 301 / CiA 402)
DEVICE_TYPE = 0x1000  # U32; low 16 bits = device profile number (402)
ERROR_REGISTER = 0x1001
HEARTBEAT_CONSUMER = 0x1016  # sub 1..n U32: monitored node id << 16 | consumer time in ms (CiA 301 7.5.2.33)
HEARTBEAT_PRODUCER = 0x1017  # U16 ms
HEARTBEAT_COB_BASE = 0x700  # a node's heartbeat (NMT error control) COB-ID: 0x700 + node id
IDENTITY = 0x1018
CONTROLWORD = 0x6040  # U16
STATUSWORD = 0x6041  # U16
MODES_OF_OPERATION = 0x6060  # I8
MODES_DISPLAY = 0x6061  # I8
POSITION_ACTUAL = 0x6064  # I32 counts
VELOCITY_ACTUAL = 0x606C  # I32 velocity units
TORQUE_ACTUAL = 0x6077  # I16 per mille of rated torque
TARGET_POSITION = 0x607A  # I32 counts
TARGET_VELOCITY = 0x60FF  # I32 velocity units
TARGET_TORQUE = 0x6071  # I16 per mille of rated torque
RATED_TORQUE = 0x6076  # U32 mN*m (motor)
SUPPORTED_MODES = 0x6502  # U32, one bit per mode
HOMING_METHOD = 0x6098  # I8
HOMING_SPEEDS = 0x6099  # sub1 search for switch, sub2 search for zero (U32 velocity units)
HOMING_ACCELERATION = 0x609A  # U32
HOME_OFFSET = 0x607C  # I32 counts
ERROR_CODE = 0x603F  # U16
FOLLOWING_ERROR_WINDOW = 0x6065  # U32 counts
ABORT_CONNECTION_OPTION = 0x6007  # I16: the drive's reaction to a lost connection (heartbeat), below

DEVICE_PROFILE_402 = 402

#: CiA 301 heartbeat payload (the NMT state of the producer), byte 0 without the toggle bit
NMT_STATE_NAMES = {0x00: "BOOT-UP", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
NMT_OPERATIONAL = 0x05
NMT_BOOTUP = 0x00

#: 0x6007 "abort connection option code" (CiA 402-2 6.4.1): what a drive does when it loses the
#: master (its heartbeat consumer times out; it also sends EMCY 0x8130). 0 "no action" is not
#: offered: a drive left by a dead control process must stop.
ABORT_CONNECTION_OPTIONS = {"fault": 1, "disable_voltage": 2, "quick_stop": 3}


def heartbeat_consumer_entry(node_id: int, time_ms: int) -> int:
    """A 0x1016 entry: watch node ``node_id``'s heartbeat, ``time_ms`` at most between two."""
    return (node_id & 0x7F) << 16 | (time_ms & 0xFFFF)


# ---------------------------------------------------------------- the state machine (CiA 402-2 6.2)
class State402(enum.Enum):
    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


S = State402

#: statusword 0x6041 state coding, CiA 402-2 table "State coding": (mask, value) per state.
#: Bits: 0 ready to switch on, 1 switched on, 2 operation enabled, 3 fault, 5 quick stop
#: (0 = active), 6 switch on disabled. Checked in this order; exactly one matches a valid word.
STATUSWORD_STATES: tuple[tuple[State402, int, int], ...] = (
    (S.NOT_READY_TO_SWITCH_ON, 0x4F, 0x00),  # xxxx xxxx x0xx 0000
    (S.SWITCH_ON_DISABLED, 0x4F, 0x40),  # xxxx xxxx x1xx 0000
    (S.READY_TO_SWITCH_ON, 0x6F, 0x21),  # xxxx xxxx x01x 0001
    (S.SWITCHED_ON, 0x6F, 0x23),  # xxxx xxxx x01x 0011
    (S.OPERATION_ENABLED, 0x6F, 0x27),  # xxxx xxxx x01x 0111
    (S.QUICK_STOP_ACTIVE, 0x6F, 0x07),  # xxxx xxxx x00x 0111
    (S.FAULT_REACTION_ACTIVE, 0x4F, 0x0F),  # xxxx xxxx x0xx 1111
    (S.FAULT, 0x4F, 0x08),  # xxxx xxxx x0xx 1000
)

SW_TARGET_REACHED = 1 << 10
SW_BIT12 = 1 << 12  # CSP/CSV/CST: drive follows the command value; HM: homing attained
SW_BIT13 = 1 << 13  # CSP: following error; HM: homing error


def decode_state(statusword: int) -> State402 | None:
    """The 402 state a statusword codes, or None for a word no state matches."""
    for state, mask, value in STATUSWORD_STATES:
        if statusword & mask == value:
            return state
    return None


class Command(enum.IntEnum):
    """Controlword 0x6040 commands, CiA 402-2 table "Command coding" (bits 7, 3, 2, 1, 0)."""

    SHUTDOWN = 0x0006  # 0 x 1 1 0: transitions 2, 6, 8 -> READY TO SWITCH ON
    SWITCH_ON = 0x0007  # 0 0 1 1 1: transition 3 -> SWITCHED ON (also 5: disable operation)
    ENABLE_OPERATION = 0x000F  # 0 1 1 1 1: transitions 4, 16 -> OPERATION ENABLED
    DISABLE_VOLTAGE = 0x0000  # 0 x x 0 x: transitions 7, 9, 10, 12 -> SWITCH ON DISABLED
    QUICK_STOP = 0x0002  # 0 x 0 1 x: transition 11 -> QUICK STOP ACTIVE (7, 10 elsewhere)
    FAULT_RESET = 0x0080  # rising edge of bit 7: transition 15 FAULT -> SWITCH ON DISABLED


CW_FAULT_RESET_BIT = 0x0080
#: statusword bit 7 "warning" (CiA 402-2): the drive reports a condition and keeps running; its
#: bit 3 "fault" (the FAULT / FAULT REACTION ACTIVE states) is what stops it
SW_WARNING = 0x0080
#: TPDOs after an EMCY within which the drive's statusword says what it is: its FAULT state (a
#: fault) or its warning bit (a warning); an EMCY still explained by neither then is a fault
EMCY_DECIDE_TPDOS = 3
CW_HOMING_START = 0x0010  # bit 4 in homing mode: a rising edge starts homing (CiA 402-2 8.1)


class Goal(enum.Enum):
    """Where a lifecycle transition walks a drive."""

    OPERATION_ENABLED = "enable"
    SWITCH_ON_DISABLED = "disable"
    QUICK_STOP_ACTIVE = "quick stop"


class Step(NamedTuple):
    command: Command | None  # controlword to send; None: the drive must get there alone (wait)
    transitions: str  # CiA 402-2 transition number(s) this command takes
    done: bool = False  # the drive is where the goal wants it


_W = Step(Command.DISABLE_VOLTAGE, "automatic")  # wait: the drive moves on by itself

#: (drive state, goal) -> the controlword to send this cycle. A walk sends one command per
#: cycle and looks at the statusword the next SYNC brings back. FAULT is left only by a fault
#: reset (transition 15, a rising edge of bit 7), which the backend runs before ENABLE.
WALK: dict[tuple[State402, Goal], Step] = {
    # enable: 2 -> 3 -> 4 (and 16 from QUICK STOP ACTIVE)
    (S.NOT_READY_TO_SWITCH_ON, Goal.OPERATION_ENABLED): _W._replace(transitions="1 (automatic)"),
    (S.SWITCH_ON_DISABLED, Goal.OPERATION_ENABLED): Step(Command.SHUTDOWN, "2"),
    (S.READY_TO_SWITCH_ON, Goal.OPERATION_ENABLED): Step(Command.SWITCH_ON, "3"),
    (S.SWITCHED_ON, Goal.OPERATION_ENABLED): Step(Command.ENABLE_OPERATION, "4"),
    (S.OPERATION_ENABLED, Goal.OPERATION_ENABLED): Step(Command.ENABLE_OPERATION, "-", done=True),
    (S.QUICK_STOP_ACTIVE, Goal.OPERATION_ENABLED): Step(Command.ENABLE_OPERATION, "16"),
    (S.FAULT_REACTION_ACTIVE, Goal.OPERATION_ENABLED): _W._replace(transitions="14 (automatic)"),
    (S.FAULT, Goal.OPERATION_ENABLED): Step(None, "15 (fault reset first)"),
    # disable: disable voltage from every state (7, 9, 10, 12); FAULT already has no torque
    (S.NOT_READY_TO_SWITCH_ON, Goal.SWITCH_ON_DISABLED): _W._replace(transitions="1 (automatic)"),
    (S.SWITCH_ON_DISABLED, Goal.SWITCH_ON_DISABLED): Step(Command.DISABLE_VOLTAGE, "-", done=True),
    (S.READY_TO_SWITCH_ON, Goal.SWITCH_ON_DISABLED): Step(Command.DISABLE_VOLTAGE, "7"),
    (S.SWITCHED_ON, Goal.SWITCH_ON_DISABLED): Step(Command.DISABLE_VOLTAGE, "10"),
    (S.OPERATION_ENABLED, Goal.SWITCH_ON_DISABLED): Step(Command.DISABLE_VOLTAGE, "9"),
    (S.QUICK_STOP_ACTIVE, Goal.SWITCH_ON_DISABLED): Step(Command.DISABLE_VOLTAGE, "12"),
    (S.FAULT_REACTION_ACTIVE, Goal.SWITCH_ON_DISABLED): _W._replace(transitions="14 (automatic)"),
    (S.FAULT, Goal.SWITCH_ON_DISABLED): Step(Command.DISABLE_VOLTAGE, "-", done=True),
    # quick stop (pause): 11 from OPERATION ENABLED; a drive whose quick stop option code
    # (0x605A 0..4) ends in SWITCH ON DISABLED is stopped too
    (S.NOT_READY_TO_SWITCH_ON, Goal.QUICK_STOP_ACTIVE): Step(Command.QUICK_STOP, "-", done=True),
    (S.SWITCH_ON_DISABLED, Goal.QUICK_STOP_ACTIVE): Step(Command.QUICK_STOP, "-", done=True),
    (S.READY_TO_SWITCH_ON, Goal.QUICK_STOP_ACTIVE): Step(Command.QUICK_STOP, "7", done=True),
    (S.SWITCHED_ON, Goal.QUICK_STOP_ACTIVE): Step(Command.QUICK_STOP, "10", done=True),
    (S.OPERATION_ENABLED, Goal.QUICK_STOP_ACTIVE): Step(Command.QUICK_STOP, "11"),
    (S.QUICK_STOP_ACTIVE, Goal.QUICK_STOP_ACTIVE): Step(Command.QUICK_STOP, "-", done=True),
    (S.FAULT_REACTION_ACTIVE, Goal.QUICK_STOP_ACTIVE): _W._replace(transitions="14 (automatic)"),
    (S.FAULT, Goal.QUICK_STOP_ACTIVE): Step(Command.DISABLE_VOLTAGE, "-", done=True),
}

#: states in which the power stage drives the motor (torque on)
TORQUE_ON = frozenset({S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE})
del S


# ---------------------------------------------------------------- modes of operation (0x6060)
class Mode(enum.IntEnum):
    PROFILE_POSITION = 1
    VELOCITY = 2
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CYCLIC_SYNC_POSITION = 8  # CSP
    CYCLIC_SYNC_VELOCITY = 9  # CSV
    CYCLIC_SYNC_TORQUE = 10  # CST


#: 0x6502 supported drive modes: bit per mode (CiA 402-2 6.2.3)
SUPPORTED_MODE_BIT: dict[Mode, int] = {
    Mode.PROFILE_POSITION: 0, Mode.VELOCITY: 1, Mode.PROFILE_VELOCITY: 2, Mode.PROFILE_TORQUE: 3,
    Mode.HOMING: 5, Mode.INTERPOLATED_POSITION: 6, Mode.CYCLIC_SYNC_POSITION: 7,
    Mode.CYCLIC_SYNC_VELOCITY: 8, Mode.CYCLIC_SYNC_TORQUE: 9,
}


def supports(supported_modes: int, mode: Mode) -> bool:
    return bool(supported_modes >> SUPPORTED_MODE_BIT[mode] & 1)


# ---------------------------------------------------------------- homing status (CiA 402-2 8.1)
HOMING_STATUS_MASK = 0x3400  # bits 13, 12, 10

#: statusword & HOMING_STATUS_MASK -> (meaning, finished, failed)
HOMING_STATUS: dict[int, tuple[str, bool, bool]] = {
    0x0000: ("homing in progress", False, False),
    0x0400: ("homing interrupted or not started", False, False),
    0x1000: ("homing attained, target not reached", False, False),
    0x1400: ("homing completed", True, False),
    0x2000: ("homing error, velocity not zero", False, True),
    0x2400: ("homing error, velocity zero", False, True),
    0x3000: ("reserved", False, True),
    0x3400: ("reserved", False, True),
}


# ---------------------------------------------------------------- EMCY (CiA 301 7.2.7, CiA 402-2 annex)
#: the specific codes a drive sends most; anything else is named by its class (CiA 301)
EMCY_CODES: dict[int, str] = {
    0x1000: "generic error",
    0x2220: "continuous over-current (device internal)",
    0x2310: "continuous over-current (motor side)",
    0x2320: "short circuit / earth leakage (motor side)",
    0x3110: "mains over-voltage",
    0x3120: "mains under-voltage",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "excess temperature (device)",
    0x4310: "excess temperature (drive)",
    0x4410: "excess temperature (supply)",
    0x5112: "supply low voltage",
    0x5530: "data storage (non-volatile memory)",
    0x6010: "software reset (watchdog)",
    0x6320: "parameter error",
    0x7121: "motor blocked",
    0x7300: "sensor (encoder) error",
    0x7305: "incremental sensor 1 fault",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8250: "RPDO timeout",
    0x8400: "velocity speed controller (deviation)",
    0x8611: "following error",
    0x8612: "reference limit",
    0xFF00: "device specific",
}

#: CiA 301 table "Emergency error codes": (mask, value, class), most specific first
EMCY_CLASSES: tuple[tuple[int, int, str], ...] = (
    (0xFF00, 0x0000, "error reset or no error"),
    (0xFF00, 0x1000, "generic error"),
    (0xFF00, 0x2100, "current, device input side"),
    (0xFF00, 0x2200, "current inside the device"),
    (0xFF00, 0x2300, "current, device output side"),
    (0xF000, 0x2000, "current"),
    (0xFF00, 0x3100, "mains voltage"),
    (0xFF00, 0x3200, "voltage inside the device"),
    (0xFF00, 0x3300, "output voltage"),
    (0xF000, 0x3000, "voltage"),
    (0xFF00, 0x4100, "ambient temperature"),
    (0xFF00, 0x4200, "device temperature"),
    (0xF000, 0x4000, "temperature"),
    (0xFF00, 0x5000, "device hardware"),
    (0xF000, 0x5000, "device hardware"),
    (0xF000, 0x6000, "device software"),
    (0xFF00, 0x7000, "additional modules"),
    (0xF000, 0x7000, "additional modules"),
    (0xFF00, 0x8100, "communication"),
    (0xFF00, 0x8200, "protocol error"),
    (0xFF00, 0x8600, "positioning controller"),
    (0xF000, 0x8000, "monitoring"),
    (0xFF00, 0x9000, "external error"),
    (0xFF00, 0xF000, "additional functions"),
    (0xFF00, 0xFF00, "device specific"),
)


def emcy_meaning(code: int) -> str:
    """'following error (positioning controller)' for 0x8611: the code's name where the table
    has it, and its CiA 301 class."""
    cls = next((text for mask, value, text in EMCY_CLASSES if code & mask == value), "unknown class")
    name = EMCY_CODES.get(code)
    return f"{name} ({cls})" if name and name != cls else cls

"""Robotiq 2F-85 / 2F-140 register map, bit fields and fault codes: plain data, read by the
backend (``backend.py``) and the simulator (``crtk_bridge/sim/robotiq.py``).

Source for every fact here: Robotiq, "2F-85 & 2F-140 Instruction Manual", section 4 "Control"
(4.1 overview, 4.2 "Gripper Register Mapping" table 4-1, 4.3 "Robot Output Registers &
Functionalities", 4.4 "Robot Input Registers & Status", 4.5 "Picking Features", 4.7 "Modbus RTU
communication" with its example frames), and section 6 "Specifications" for the stroke, speed and
grip force of each model (docs/architecture.md, Sources: Robotiq 2F-85 / 2F-140). What is NOT
from the manual is marked so.

Registers are 16-bit Modbus words made of two of the gripper's byte registers, the lower byte
number in the high half (manual 4.7: "each register (word - 16 bits) of the Modbus RTU protocol
is composed of 2 registers (bytes - 8 bits) from the Gripper"; the example response ``B9 00 00 FF
BD 00`` is GRIPPER STATUS 0xB9, FAULT STATUS 0x00, POSITION REQUEST ECHO 0xFF, POSITION 0xBD).
"""

from __future__ import annotations

from dataclasses import dataclass

# ---------------------------------------------------------------- the link (manual 4.7.1)
#: default Modbus slave id of a 2F gripper
SLAVE_ID = 9
#: 115200 bit/s, 8 data bits, no parity, 1 stop bit
BAUDRATE = 115200
BYTESIZE, PARITY, STOPBITS = 8, "N", 1
#: function codes the gripper answers: 3 read holding, 4 read input registers, 6 preset single,
#: 16 preset multiple, 23 read/write multiple registers. No exception responses (manual 4.7.1:
#: "Exception Responses: Not supported"): a request it refuses gets no answer.
FC_READ_INPUT = 4
FC_WRITE_MULTIPLE = 16

# ---------------------------------------------------------------- the register map (4.2, table 4-1)
#: first robot output register (robot -> gripper): ACTION REQUEST, RESERVED, RESERVED, POSITION
#: REQUEST, SPEED, FORCE (bytes 0-5), written with function 16
OUTPUT_ADDRESS = 0x03E8
#: first robot input register (gripper -> robot): GRIPPER STATUS, RESERVED, FAULT STATUS, POSITION
#: REQUEST ECHO, POSITION, CURRENT (bytes 0-5), read with function 4
INPUT_ADDRESS = 0x07D0
#: words the backend reads and writes each: bytes 0-5
WORDS = 3

# ---------------------------------------------------------------- ACTION REQUEST, output byte 0 (4.3.1)
RACT = 1 << 0  # activation: 0 reset (clears every fault), 1 activate; a rising edge re-activates
RGTO = 1 << 3  # go to the position request (0: stop)
RATR = 1 << 4  # automatic release (emergency release; the fingers open or close slowly, rARD)
RARD = 1 << 5  # automatic release direction: 0 closing, 1 opening

# ---------------------------------------------------------------- GRIPPER STATUS, input byte 0 (4.4.1)
GACT = 1 << 0  # echo of rACT
GGTO = 1 << 3  # echo of rGTO
GSTA_SHIFT, GSTA_MASK = 4, 0x3  # bits 4-5
GOBJ_SHIFT, GOBJ_MASK = 6, 0x3  # bits 6-7

#: gSTA: the gripper's activation state
GSTA_RESET = 0  # in reset (or automatic release): see the fault status if activated
GSTA_ACTIVATING = 1  # activation in progress
GSTA_ACTIVE = 3  # activation completed (2: not used)
GSTA_TEXT = {0: "in reset (or automatic release)", 1: "activation in progress", 2: "not used",
             3: "activation completed"}

#: gOBJ: object detection (ignore when gGTO is 0)
GOBJ_MOVING = 0  # fingers in motion towards the requested position, no object detected
GOBJ_CONTACT_OPENING = 1  # stopped by a contact while opening: object detected
GOBJ_CONTACT_CLOSING = 2  # stopped by a contact while closing: object detected
GOBJ_AT_REQUEST = 3  # at the requested position: no object, or it was lost / dropped
GOBJ_TEXT = {0: "fingers moving, no object detected",
             1: "fingers stopped on an object while opening",
             2: "fingers stopped on an object while closing",
             3: "fingers at the requested position, no object (or object lost)"}

# ---------------------------------------------------------------- FAULT STATUS, input byte 2 (4.4.3)
GFLT_MASK = 0x0F  # gFLT: the gripper's fault (low nibble)
KFLT_SHIFT = 4  # kFLT: the controller's own fault (high nibble), codes in the controller's manual


@dataclass(frozen=True)
class GripperFault:
    code: int
    severity: str  # "priority" | "minor" | "major"
    meaning: str

    @property
    def major(self) -> bool:
        """A major fault: the LED blinks red / blue and the gripper needs a reset (rACT 0 -> 1)."""
        return self.severity == "major"


#: gFLT codes (manual 4.4.3). Priority faults (solid blue LED) say an action was refused; minor
#: faults (solid red LED) clear by themselves; major faults (blinking red / blue LED) stop the
#: gripper until a reset (rACT cleared, then set).
FAULTS: dict[int, GripperFault] = {f.code: f for f in (
    GripperFault(0x05, "priority", "action delayed: the activation (re-activation) must complete before the action"),
    GripperFault(0x07, "priority", "the activation bit must be set before an action"),
    GripperFault(0x08, "minor", "maximum operating temperature exceeded (85 C inside); let it cool below 80 C"),
    GripperFault(0x09, "minor", "no communication during at least 1 second"),
    GripperFault(0x0A, "major", "under minimum operating voltage"),
    GripperFault(0x0B, "major", "automatic release in progress"),
    GripperFault(0x0C, "major", "internal fault; contact Robotiq support"),
    GripperFault(0x0D, "major", "activation fault: verify that no interference or other error occurred"),
    GripperFault(0x0E, "major", "overcurrent triggered"),
    GripperFault(0x0F, "major", "automatic release completed"),
)}
GFLT_NONE = 0x00
GFLT_NO_COMMUNICATION = 0x09
GFLT_UNDER_VOLTAGE = 0x0A
GFLT_ACTIVATION = 0x0D
GFLT_OVERCURRENT = 0x0E


def fault_text(code: int) -> str:
    """gFLT ``code``'s meaning (an unknown code said as such)."""
    fault = FAULTS.get(code)
    return fault.meaning if fault is not None else f"unknown fault 0x{code:02X}"


# ---------------------------------------------------------------- position, speed, force, current (4.3-4.4)
#: position request / position: 0x00 full opening, 0xFF full closing
POSITION_OPEN, POSITION_CLOSED = 0x00, 0xFF
#: NOT from the manual (which gives only 0x00 = full opening, 0xFF = full closing): the position
#: readings of a 2F at its stroke ends used when none was measured (a gripper found activated)
#: and the profile gives no ``calibration``: a real 2F reads about 3-13 fully open and about 230
#: fully closed (each gripper its own, a few counts apart: a few tenths of a mm each); the
#: simulator's ends are these
NOMINAL_OPEN, NOMINAL_CLOSED = 13, 230
#: an activation's measured span must be at least this share of the nominal one (a shorter one:
#: something blocked the fingers, and a scale from it would be wrong by far)
CALIBRATION_MIN_SHARE = 0.8
#: speed 0x00 = the model's minimum speed, 0xFF its maximum; force 0x00 minimum, 0xFF maximum
BYTE_MAX = 0xFF
#: finger current: the motor current read instantaneously, about 10 mA per unit (4.4.6)
CURRENT_A_PER_UNIT = 0.010


@dataclass(frozen=True)
class Model:
    """One gripper model's mechanics (manual section 6, "Specifications"). The manual gives
    speed and force only at the settings' ends (0x00, 0xFF); in between the backend assumes them
    linear in the setting (not from the manual)."""

    name: str
    stroke_m: float  # finger opening at full opening (the fingers touch at full closing)
    speed_min: float  # m/s closing speed at rSP 0x00
    speed_max: float  # m/s at rSP 0xFF
    force_min: float  # N grip force at rFR 0x00
    force_max: float  # N at rFR 0xFF


MODELS: dict[str, Model] = {m.name: m for m in (
    Model("2f85", stroke_m=0.085, speed_min=0.020, speed_max=0.150, force_min=20.0, force_max=235.0),
    Model("2f140", stroke_m=0.140, speed_min=0.030, speed_max=0.250, force_min=10.0, force_max=125.0),
)}


# ---------------------------------------------------------------- packing (4.2: byte n of a pair in the high half)
def pack_output(action: int, position: int, speed: int, force: int) -> list[int]:
    """The three output words: ACTION REQUEST | RESERVED, RESERVED | POSITION REQUEST, SPEED | FORCE."""
    return [(action & 0xFF) << 8, position & 0xFF, ((speed & 0xFF) << 8) | (force & 0xFF)]


def unpack_output(words) -> tuple[int, int, int, int]:
    """(action, position request, speed, force) from the three output words."""
    return (words[0] >> 8) & 0xFF, words[1] & 0xFF, (words[2] >> 8) & 0xFF, words[2] & 0xFF


def pack_input(status: int, fault: int, position_echo: int, position: int, current: int) -> list[int]:
    """The three input words: GRIPPER STATUS | RESERVED, FAULT STATUS | POSITION REQUEST ECHO,
    POSITION | CURRENT."""
    return [(status & 0xFF) << 8, ((fault & 0xFF) << 8) | (position_echo & 0xFF),
            ((position & 0xFF) << 8) | (current & 0xFF)]


def unpack_input(words) -> tuple[int, int, int, int, int]:
    """(status, fault, position request echo, position, current) from the three input words."""
    return ((words[0] >> 8) & 0xFF, (words[1] >> 8) & 0xFF, words[1] & 0xFF,
            (words[2] >> 8) & 0xFF, words[2] & 0xFF)


def status_byte(gact: bool, ggto: bool, gsta: int, gobj: int) -> int:
    return (GACT if gact else 0) | (GGTO if ggto else 0) | ((gsta & GSTA_MASK) << GSTA_SHIFT) | (
        (gobj & GOBJ_MASK) << GOBJ_SHIFT)


def gsta(status: int) -> int:
    return (status >> GSTA_SHIFT) & GSTA_MASK


def gobj(status: int) -> int:
    return (status >> GOBJ_SHIFT) & GOBJ_MASK

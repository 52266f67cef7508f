"""Dynamixel Protocol 2.0 constants and the X-series control table, as data.

Sources: ROBOTIS e-Manual, Protocol 2.0 (https://emanual.robotis.com/docs/en/dxl/protocol2/) and
the X-series pages (https://emanual.robotis.com/docs/en/dxl/x/xl330-m288/, .../xl330-m077/,
.../xl430-w250/, .../xm430-w350/); dynamixel-sdk 4.1.0; docs/architecture.md, "Sources": Dynamixel.
Multi-byte values are little-endian; signed registers are two's complement of their size.

Plain data shared by the backend and the simulator (a device table is a fact, not logic).
"""

from __future__ import annotations

import enum
import math

from typing import NamedTuple


class Register(NamedTuple):
    address: int
    size: int
    eeprom: bool = False
    writable: bool = True
    signed: bool = False  # two's complement of its size

# ---- instructions (Protocol 2.0) ----
INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REG_WRITE = 0x04
INST_ACTION = 0x05
INST_FACTORY_RESET = 0x06
INST_REBOOT = 0x08
INST_CLEAR = 0x10
INST_STATUS = 0x55
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83
INST_FAST_SYNC_READ = 0x8A
INST_BULK_READ = 0x92
INST_BULK_WRITE = 0x93
INST_FAST_BULK_READ = 0x9A
BROADCAST_ID = 0xFE
MAX_ID = 252

# ---- status packet ERR byte: bit 7 = Alert (see Hardware_Error_Status), bits 0-6 = error number ----
ERR_ALERT = 0x80
ERRNUM_RESULT_FAIL = 1
ERRNUM_INSTRUCTION = 2
ERRNUM_CRC = 3
ERRNUM_DATA_RANGE = 4
ERRNUM_DATA_LENGTH = 5
ERRNUM_DATA_LIMIT = 6
ERRNUM_ACCESS = 7  # e.g. EEPROM write with torque on, or a read-only address

# ---- Hardware_Error_Status (70) / Shutdown (63) bits ----
HW_INPUT_VOLTAGE = 0x01
HW_OVERHEATING = 0x04
HW_MOTOR_ENCODER = 0x08  # not on XL330
HW_ELECTRICAL_SHOCK = 0x10
HW_OVERLOAD = 0x20
HARDWARE_ERROR_BITS: dict[int, str] = {
    HW_INPUT_VOLTAGE: "input voltage error",
    HW_OVERHEATING: "overheating error",
    HW_MOTOR_ENCODER: "motor encoder error",
    HW_ELECTRICAL_SHOCK: "electrical shock error",
    HW_OVERLOAD: "overload error",
}


class OperatingMode(enum.IntEnum):
    """Operating_Mode (11) values."""

    CURRENT = 0
    VELOCITY = 1
    POSITION = 3  # 0..4095, one turn
    EXTENDED_POSITION = 4  # multi-turn, +-256 rev
    CURRENT_BASED_POSITION = 5  # multi-turn position with a current limit (Goal_Current)
    PWM = 16


POSITION_MODES = (OperatingMode.POSITION, OperatingMode.EXTENDED_POSITION,
                  OperatingMode.CURRENT_BASED_POSITION)

# ---- X-series control table (XL330-M288 / XL430-W250 / XM430-W350 share these addresses) ----
# Register(address, size, eeprom, writable, signed)
_X_COMMON: dict[str, Register] = {
    # EEPROM (writable only with Torque_Enable = 0)
    "Model_Number": Register(0, 2, True, False),
    "Model_Information": Register(2, 4, True, False),
    "Firmware_Version": Register(6, 1, True, False),
    "ID": Register(7, 1, True),
    "Baud_Rate": Register(8, 1, True),
    "Return_Delay_Time": Register(9, 1, True),
    "Drive_Mode": Register(10, 1, True),
    "Operating_Mode": Register(11, 1, True),
    "Secondary_ID": Register(12, 1, True),
    "Protocol_Type": Register(13, 1, True),
    "Homing_Offset": Register(20, 4, True, True, True),
    "Moving_Threshold": Register(24, 4, True),
    "Temperature_Limit": Register(31, 1, True),
    "Max_Voltage_Limit": Register(32, 2, True),
    "Min_Voltage_Limit": Register(34, 2, True),
    "PWM_Limit": Register(36, 2, True),
    "Velocity_Limit": Register(44, 4, True),
    "Max_Position_Limit": Register(48, 4, True),
    "Min_Position_Limit": Register(52, 4, True),
    "Shutdown": Register(63, 1, True),
    # RAM
    "Torque_Enable": Register(64, 1),
    "LED": Register(65, 1),
    "Status_Return_Level": Register(68, 1),
    "Registered_Instruction": Register(69, 1, False, False),
    "Hardware_Error_Status": Register(70, 1, False, False),
    "Velocity_I_Gain": Register(76, 2),
    "Velocity_P_Gain": Register(78, 2),
    "Position_D_Gain": Register(80, 2),
    "Position_I_Gain": Register(82, 2),
    "Position_P_Gain": Register(84, 2),
    "Feedforward_2nd_Gain": Register(88, 2),
    "Feedforward_1st_Gain": Register(90, 2),
    "Bus_Watchdog": Register(98, 1),
    "Goal_PWM": Register(100, 2, False, True, True),
    "Goal_Velocity": Register(104, 4, False, True, True),
    "Profile_Acceleration": Register(108, 4),
    "Profile_Velocity": Register(112, 4),
    "Goal_Position": Register(116, 4, False, True, True),
    "Realtime_Tick": Register(120, 2, False, False),
    "Moving": Register(122, 1, False, False),
    "Moving_Status": Register(123, 1, False, False),
    "Present_PWM": Register(124, 2, False, False, True),
    "Present_Velocity": Register(128, 4, False, False, True),
    "Present_Position": Register(132, 4, False, False, True),
    "Velocity_Trajectory": Register(136, 4, False, False, True),
    "Position_Trajectory": Register(140, 4, False, False, True),
    "Present_Input_Voltage": Register(144, 2, False, False),
    "Present_Temperature": Register(146, 1, False, False),
}
_CURRENT_REGS: dict[str, Register] = {
    "Current_Limit": Register(38, 2, True),
    "Goal_Current": Register(102, 2, False, True, True),
    "Present_Current": Register(126, 2, False, False, True),
}

# per model: name -> Register
CONTROL_TABLES: dict[str, dict[str, Register]] = {
    "xl330-m288": {**_X_COMMON, **_CURRENT_REGS},
    "xl330-m077": {**_X_COMMON, **_CURRENT_REGS},  # the Koch leader's: the M288's table, 77.5:1 gears
    "xm430-w350": {**_X_COMMON, **_CURRENT_REGS, "Acceleration_Limit": Register(40, 4, True)},
    # XL430: no current sensing; 126 is Present_Load (0.1 % of max torque, signed)
    "xl430-w250": {**_X_COMMON, "Present_Load": Register(126, 2, False, False, True)},
}
MODEL_NUMBERS: dict[str, int] = {"xl330-m288": 1200, "xl330-m077": 1190, "xl430-w250": 1060, "xm430-w350": 1020}
MODEL_NAMES: dict[int, str] = {v: k for k, v in MODEL_NUMBERS.items()}
RESOLUTION: dict[str, int] = {m: 4096 for m in MODEL_NUMBERS}  # pulses per turn, 0.088 deg
OPERATING_MODES: dict[str, tuple[OperatingMode, ...]] = {
    "xl330-m288": tuple(OperatingMode),
    "xl330-m077": tuple(OperatingMode),
    "xm430-w350": tuple(OperatingMode),
    "xl430-w250": (OperatingMode.VELOCITY, OperatingMode.POSITION, OperatingMode.EXTENDED_POSITION,
                   OperatingMode.PWM),
}
# Present_Current / Goal_Current LSB in A (None: the model has no current sensing)
CURRENT_UNIT_A: dict[str, float | None] = {"xl330-m288": 0.001, "xl330-m077": 0.001, "xm430-w350": 0.00269, "xl430-w250": None}
# factory Current_Limit (raw) where the model has one
CURRENT_LIMIT_DEFAULT: dict[str, int] = {"xl330-m288": 1750, "xl330-m077": 1750, "xm430-w350": 1193}
LOAD_UNIT = 0.001  # XL430 Present_Load LSB: 0.1 % of maximum torque
VELOCITY_UNIT_RAD_S = 0.229 * 2.0 * math.pi / 60.0  # Goal/Present_Velocity LSB: 0.229 rev/min
#: Profile_Acceleration LSB in the velocity-based profile (Drive_Mode bit 2 clear): 214.577 rev/min^2
PROFILE_ACCELERATION_RAD_S2 = 214.577 * 2.0 * math.pi / 3600.0
VELOCITY_LIMIT_DEFAULT: dict[str, int] = {"xl330-m288": 445, "xl330-m077": 1620, "xm430-w350": 128, "xl430-w250": 265}
# Fast Sync Read (0x8A) needs this firmware (Firmware_Version, register 6) or newer
FAST_SYNC_READ_FIRMWARE: dict[str, int] = {"xl330-m288": 46, "xl330-m077": 46, "xl430-w250": 45, "xm430-w350": 45}
# factory position P gains (Position_P_Gain, 84)
POSITION_P_DEFAULT: dict[str, int] = {"xl330-m288": 400, "xl330-m077": 400, "xl430-w250": 640, "xm430-w350": 800}
POSITION_EXTENDED_LIMIT = 1_048_575  # extended position mode goal range (+-256 rev)

# The present-state block read once per cycle: Present_Current (or Present_Load on XL430) 126,
# Present_Velocity 128, Present_Position 132: 10 bytes per servo, the same on every X model.
PRESENT_BLOCK_START = 126
PRESENT_BLOCK_LEN = 10

# Baud_Rate (8) codes
BAUD_CODES: dict[int, int] = {
    9600: 0, 57_600: 1, 115_200: 2, 1_000_000: 3, 2_000_000: 4, 3_000_000: 5, 4_000_000: 6, 4_500_000: 7,
}


def describe_hardware_error(bits: int) -> str:
    names = [name for bit, name in HARDWARE_ERROR_BITS.items() if bits & bit]
    return ", ".join(names) if names else f"unknown hardware error bits 0x{bits:02X}"


def to_signed(raw: int, size: int) -> int:
    """Two's complement of a ``size``-byte register value."""
    bits = 8 * size
    return raw - (1 << bits) if raw & (1 << (bits - 1)) else raw


def to_raw(value: int, size: int) -> int:
    """Signed int -> unsigned register value of ``size`` bytes. Raises ValueError if it does not fit."""
    bits = 8 * size
    value = int(value)
    if not -(1 << (bits - 1)) <= value < (1 << bits):
        raise ValueError(f"value {value} does not fit in {size} byte(s)")
    return value & ((1 << bits) - 1)

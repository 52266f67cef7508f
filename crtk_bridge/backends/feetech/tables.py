"""Feetech STS/SMS series (STS3215) protocol constants and control table, as data.

Sources: Feetech SMS/STS memory table (STS3215, firmware 3.x) as transcribed in the
feetech-servo-sdk (scservo_sdk) and LeRobot's ``motors/feetech/tables.py``; docs/architecture.md,
"Sources": Feetech. Multi-byte values are little-endian on STS/SMS.
Signed registers use sign-magnitude with the sign in the bit given by ``SIGN_BITS``.

This module is plain data shared by the backend and the simulator (a device table is a fact,
not logic, so both sides read the same one).
"""

from __future__ import annotations

from typing import NamedTuple


class Register(NamedTuple):
    address: int
    size: int
    eeprom: bool = False
    writable: bool = True


# ---- instructions (FT-SCS protocol, Dynamixel-1.0-like framing) ----
INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REG_WRITE = 0x04
INST_ACTION = 0x05
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83
BROADCAST_ID = 0xFE

# ---- status packet error bits (also the Status register 65 bits) ----
ERR_VOLTAGE = 0x01
ERR_ANGLE_SENSOR = 0x02
ERR_OVERHEAT = 0x04
ERR_OVERCURRENT = 0x08
ERR_OVERLOAD = 0x20
ERROR_BITS: dict[int, str] = {
    ERR_VOLTAGE: "input voltage",
    ERR_ANGLE_SENSOR: "angle sensor (encoder)",
    ERR_OVERHEAT: "overheating",
    ERR_OVERCURRENT: "over-current",
    ERR_OVERLOAD: "overload",
}

# ---- STS3215 control table: name -> (address, size) ----
STS_CONTROL_TABLE: dict[str, Register] = {
    # EEPROM
    "Firmware_Major_Version": Register(0, 1, True, False),
    "Firmware_Minor_Version": Register(1, 1, True, False),
    "Model_Number": Register(3, 2, True, False),
    "ID": Register(5, 1, True),
    "Baud_Rate": Register(6, 1, True),
    "Return_Delay_Time": Register(7, 1, True),
    "Response_Status_Level": Register(8, 1, True),
    "Min_Position_Limit": Register(9, 2, True),
    "Max_Position_Limit": Register(11, 2, True),
    "Max_Temperature_Limit": Register(13, 1, True),
    "Max_Voltage_Limit": Register(14, 1, True),
    "Min_Voltage_Limit": Register(15, 1, True),
    "Max_Torque_Limit": Register(16, 2, True),
    "Phase": Register(18, 1, True),
    "Unloading_Condition": Register(19, 1, True),
    "LED_Alarm_Condition": Register(20, 1, True),
    "P_Coefficient": Register(21, 1, True),
    "D_Coefficient": Register(22, 1, True),
    "I_Coefficient": Register(23, 1, True),
    "Minimum_Startup_Force": Register(24, 2, True),
    "CW_Dead_Zone": Register(26, 1, True),
    "CCW_Dead_Zone": Register(27, 1, True),
    "Protection_Current": Register(28, 2, True),
    "Angular_Resolution": Register(30, 1, True),
    "Homing_Offset": Register(31, 2, True),
    "Operating_Mode": Register(33, 1, True),
    "Protective_Torque": Register(34, 1, True),
    "Protection_Time": Register(35, 1, True),
    "Overload_Torque": Register(36, 1, True),
    "Velocity_closed_loop_P_proportional_coefficient": Register(37, 1, True),
    "Over_Current_Protection_Time": Register(38, 1, True),
    "Velocity_closed_loop_I_integral_coefficient": Register(39, 1, True),
    # SRAM
    "Torque_Enable": Register(40, 1),
    "Acceleration": Register(41, 1),
    "Goal_Position": Register(42, 2),
    "Goal_Time": Register(44, 2),
    "Goal_Velocity": Register(46, 2),
    "Torque_Limit": Register(48, 2),
    "Lock": Register(55, 1),
    "Present_Position": Register(56, 2, False, False),
    "Present_Velocity": Register(58, 2, False, False),
    "Present_Load": Register(60, 2, False, False),
    "Present_Voltage": Register(62, 1, False, False),
    "Present_Temperature": Register(63, 1, False, False),
    "Status": Register(65, 1, False, False),
    "Moving": Register(66, 1, False, False),
    "Present_Current": Register(69, 2, False, False),
    "Maximum_Acceleration": Register(85, 1, True),
}

# sign-magnitude encodings: register name -> index of the sign bit
SIGN_BITS: dict[str, int] = {
    "Homing_Offset": 11,
    "Goal_Position": 15,
    "Goal_Velocity": 15,
    "Present_Position": 15,
    "Present_Velocity": 15,
    "Present_Load": 10,
}

# The present-state block read once per cycle by one sync read: Present_Position (56) through
# Present_Current (69..70), 15 bytes per servo.
PRESENT_BLOCK_START = 56
PRESENT_BLOCK_LEN = 15

# Model numbers (register 3) and per-model facts.
MODEL_NUMBERS: dict[str, int] = {"sts3215": 777, "sts3250": 2825, "sm8512bl": 11272}
RESOLUTION: dict[str, int] = {"sts3215": 4096, "sts3250": 4096, "sm8512bl": 4096}
CURRENT_UNIT_A = 0.0065  # Present_Current LSB, A
VOLTAGE_UNIT_V = 0.1

# Baud rate register codes (Feetech documentation values).
BAUD_CODES: dict[int, int] = {
    1_000_000: 0, 500_000: 1, 250_000: 2, 128_000: 3, 115_200: 4, 76_800: 5, 57_600: 6, 38_400: 7,
}


def decode_sign_magnitude(value: int, sign_bit: int) -> int:
    """Raw register value -> signed int (sign-magnitude, sign in ``sign_bit``)."""
    if value & (1 << sign_bit):
        return -(value & ((1 << sign_bit) - 1))
    return value & ((1 << sign_bit) - 1)


def encode_sign_magnitude(value: int, sign_bit: int) -> int:
    """Signed int -> raw register value. Raises ValueError if |value| does not fit."""
    magnitude = abs(int(value))
    if magnitude >= (1 << sign_bit):
        raise ValueError(f"magnitude {magnitude} exceeds {(1 << sign_bit) - 1} (sign bit {sign_bit})")
    return magnitude | (1 << sign_bit) if value < 0 else magnitude

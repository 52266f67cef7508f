"""The RTDE wire protocol (port 30004) as data: message types, variable types, recipe codecs.

Source: Universal Robots, "Real-Time Data Exchange (RTDE) Guide" (protocol version 2), and what
ur_rtde 1.6.5 sends, observed from a fake controller (docs/architecture.md, "Sources": Universal
Robots). Everything is big-endian. A message is ``uint16 size`` (header included),
``uint8 type``, payload. ur_rtde decodes data packages with its own static type table, so every
variable here has the standard size of its type.
"""

from __future__ import annotations

import enum
import re
import struct

HEADER = struct.Struct(">HB")
PROTOCOL_VERSION = 2


class Msg(enum.IntEnum):
    """RTDE message types (the ASCII letter of each)."""

    REQUEST_PROTOCOL_VERSION = 86  # V: uint16 version -> uint8 accepted
    GET_URCONTROL_VERSION = 118  # v: -> 4 x uint32 major, minor, bugfix, build
    TEXT_MESSAGE = 77  # M: v2 layout uint8 len, text, uint8 srclen, source, uint8 level
    DATA_PACKAGE = 85  # U: uint8 recipe id + the recipe's fields
    CONTROL_PACKAGE_SETUP_OUTPUTS = 79  # O: double frequency + "name,name" -> uint8 id + "TYPE,TYPE"
    CONTROL_PACKAGE_SETUP_INPUTS = 73  # I: "name,name" -> uint8 id + "TYPE,TYPE"
    CONTROL_PACKAGE_START = 83  # S: -> uint8 accepted
    CONTROL_PACKAGE_PAUSE = 80  # P: -> uint8 accepted


#: RTDE type name -> struct format of one value (the standard sizes ur_rtde assumes)
FORMATS: dict[str, str] = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}
#: number of values a type carries (vectors are flattened into the struct)
WIDTHS = {t: int(f[:-1]) if len(f) > 1 else 1 for t, f in FORMATS.items()}

#: controller outputs (RTDE guide, "Field names and associated types", outputs), name -> type
OUTPUTS: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D", "target_qd": "VECTOR6D", "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D", "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D", "actual_qd": "VECTOR6D", "actual_current": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D", "actual_TCP_speed": "VECTOR6D", "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D", "target_TCP_speed": "VECTOR6D",
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32", "joint_mode": "VECTOR6INT32", "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE", "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE", "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32", "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE", "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE", "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "euromap67_input_bits": "UINT32", "euromap67_output_bits": "UINT32",
    "tool_mode": "UINT32", "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE", "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32", "tool_output_current": "DOUBLE", "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "ft_raw_wrench": "VECTOR6D",
    "payload": "DOUBLE", "payload_cog": "VECTOR3D", "payload_inertia": "VECTOR6D",
    "script_control_line": "UINT32",
}
for _i in range(48):
    OUTPUTS[f"output_int_register_{_i}"] = "INT32"
    OUTPUTS[f"output_double_register_{_i}"] = "DOUBLE"
    OUTPUTS[f"input_int_register_{_i}"] = "INT32"  # inputs may be read back as outputs
    OUTPUTS[f"input_double_register_{_i}"] = "DOUBLE"

#: controller inputs (RTDE guide, inputs), name -> type
INPUTS: dict[str, str] = {
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}
for _i in range(48):
    INPUTS[f"input_int_register_{_i}"] = "INT32"
    INPUTS[f"input_double_register_{_i}"] = "DOUBLE"
for _i in range(64, 128):
    INPUTS[f"input_bit_register_{_i}"] = "BOOL"

NOT_FOUND = "NOT_FOUND"  # an unknown variable name in a recipe (ur_rtde throws)
IN_USE = "IN_USE"  # an input already owned by another client (ur_rtde throws)

_REGISTER = re.compile(r"input_(int|double)_register_(\d+)$")


def frame(msg: int, payload: bytes = b"") -> bytes:
    """One RTDE message: header + payload."""
    return HEADER.pack(HEADER.size + len(payload), msg) + payload


def split_names(payload: bytes) -> list[str]:
    """The variable names of a setup request (ur_rtde adds a trailing comma)."""
    return [n.strip() for n in payload.decode("ascii", "replace").split(",") if n.strip()]


class Recipe:
    """One output or input recipe: its names, types and one precompiled struct.

    ``types`` holds ``NOT_FOUND`` (or ``IN_USE``) for a name the controller refuses; such a
    recipe is answered but never used (:attr:`valid` false), as the controller does.
    """

    __slots__ = ("id", "names", "types", "valid", "_struct", "_widths")

    def __init__(self, recipe_id: int, names: list[str], types: list[str]):
        self.id = recipe_id
        self.names = names
        self.types = types
        self.valid = all(t in FORMATS for t in types)
        self._widths = [WIDTHS.get(t, 1) for t in types]
        self._struct = struct.Struct(">B" + "".join(FORMATS[t] for t in types)) if self.valid else None

    def setup_reply(self) -> bytes:
        return bytes([self.id]) + ",".join(self.types).encode("ascii")

    @property
    def size(self) -> int:
        return self._struct.size - 1 if self._struct is not None else 0

    def pack(self, values: dict) -> bytes:
        """A data package payload from ``values`` (name -> scalar or sequence)."""
        flat: list = [self.id]
        for name, width in zip(self.names, self._widths):
            v = values[name]
            if width == 1:
                flat.append(v)
            else:
                flat.extend(v)
        return self._struct.pack(*flat)

    def unpack(self, payload: bytes) -> dict:
        """name -> value of a data package payload (recipe id byte included). Raises
        ValueError when the size is not the recipe's."""
        if len(payload) != self._struct.size:
            raise ValueError(f"recipe {self.id}: data package of {len(payload) - 1} bytes, expected {self.size}")
        flat = self._struct.unpack(payload)
        out = {}
        i = 1
        for name, width in zip(self.names, self._widths):
            out[name] = flat[i] if width == 1 else list(flat[i:i + width])
            i += width
        return out


def input_register(name: str) -> tuple[str, int] | None:
    """("int" | "double", index) for an input register name, else None."""
    m = _REGISTER.match(name)
    return (m.group(1), int(m.group(2))) if m else None

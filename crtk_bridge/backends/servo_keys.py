"""The joint keys the serial-servo backends own (Feetech STS, Dynamixel X), and their checks.

A joint on a serial servo bus is one servo: its bus ``id``, its ``model`` (control table, ticks
per turn), the tick ``calibration`` that maps ticks to radians, and optionally ``effort_per_amp``
(current to torque). Core's profile schema knows none of these (a CiA 402 drive or a UR arm
describes its joints its own way); the backends validate them with :func:`servo_joints`, which
the simulators use too (this module imports nothing of core).
"""

from __future__ import annotations

from typing import Callable

import msgspec

from ..errors import ProfileError
from ..profile import Profile, joint_keys


class PortMatch(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """``backend.port`` given by the USB adapter's serial number instead of a device path:
    resolved when the bus opens (backends/ports.py), so two arms on two adapters never swap."""

    serial_number: str  # as `crtk-bridge find-port` shows it


class Calibration(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Tick calibration of one servo: ``joint = direction * (ticks - offset) * 2*pi / ticks_per_turn``."""

    offset: int = 0  # ticks at joint zero (e.g. 2048 = middle of a 4096-tick turn)
    direction: int = 1  # +1 or -1
    range: tuple[int, int] | None = None  # valid tick range [min, max]; commands are clamped to it
    # the servo's Homing_Offset register (EEPROM) this calibration was measured with: the servo
    # reports ticks already shifted by it, so another value would shift every joint position.
    # 0 = a factory servo's. The daemon reads it at open and refuses to enable when it differs.
    homing_offset: int = 0


class ServoJoint(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """The backend-owned keys of one joint on a serial servo bus."""

    id: int | None = None  # servo id on the bus; required (checked with a clearer message)
    model: str | None = None  # e.g. "sts3215", "xl330-m288"; required
    calibration: Calibration = Calibration()
    effort_per_amp: float | None = None  # N*m per A, effort from current; None = no effort


def servo_joints(profile: Profile, vendor: str, models: dict[str, int], max_id: int,
                 source: str = "<profile>",
                 check: Callable[[int, str, ServoJoint, list[str]], None] | None = None) -> list[ServoJoint]:
    """Every joint's servo keys, checked: id and model present and known, ids unique on the bus,
    direction +-1, range ordered; then ``check(i, key, joint, problems)`` for each joint of a
    known model (the vendor's own checks). Raises one ProfileError naming every problem by key
    path."""
    joints = joint_keys(profile, ServoJoint, f"{vendor} backend", source)
    problems: list[str] = []
    ids: dict[int, str] = {}
    names = ", ".join(models)
    for i, (j, s) in enumerate(zip(profile.joints, joints)):
        key = f"joints[{i}] ({j.name})"
        if s.id is None:
            problems.append(f"{key}.id: required by the {vendor} backend (servo id 0-{max_id})")
        elif not 0 <= s.id <= max_id:
            problems.append(f"{key}.id: {s.id} is not a servo id (0-{max_id})")
        elif s.id in ids:
            problems.append(f"{key}.id: bus id {s.id} is also used by joint {ids[s.id]!r}")
        else:
            ids[s.id] = j.name
        if s.model is None:
            problems.append(f"{key}.model: required by the {vendor} backend (one of {names})")
        elif s.model not in models:
            problems.append(f"{key}.model: unknown model {s.model!r} for the {vendor} backend (known: {names})")
        elif check is not None:
            check(i, key, s, problems)
        if s.calibration.direction not in (1, -1):
            problems.append(f"{key}.calibration.direction: must be 1 or -1")
        r = s.calibration.range
        if r is not None and not r[0] < r[1]:
            problems.append(f"{key}.calibration.range: min must be < max")
    if problems:
        raise ProfileError(f"{source}: " + "; ".join(problems))
    return joints

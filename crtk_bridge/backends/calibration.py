"""Calibration of serial-servo joints: a sweep by hand, or a LeRobot calibration file, turned into
the joints' ``calibration`` keys (``offset``, ``direction``, ``range``, ``homing_offset``; see
``servo_keys.py`` and docs/calibration.md).

Raw ticks never leave the backend layer: while a sweep runs, :class:`RangeWatch` follows each
joint's ticks in the backend's own read (unwrapped across the encoder's 4095 -> 0 step, relative to
the middle pose) and the backend reports the range seen in radians; at the end the result is the
joints' calibration keys, which are the backend's own profile keys (opaque to core and clients,
written into the profile as they are).

The arithmetic here is pure (no bus, no clock), so it is tested directly.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from ..errors import BackendError

#: a joint whose range seen is narrower than this (ticks, ~3.5 degrees) did not move: refused
MIN_TRAVEL_TICKS = 40
#: a sweep this close to a whole turn is a continuous joint (wrist roll): its range is the turn
FULL_TURN_FRACTION = 0.95


class RangeWatch:
    """Per joint, the ticks travelled since the middle pose: now, lowest, highest (unwrapped).

    :meth:`track` runs in the real-time read: in place on pre-allocated arrays, no allocation."""

    def __init__(self, middle: np.ndarray, resolution: np.ndarray):
        n = len(middle)
        self.middle = np.array(middle, dtype=float)
        self.resolution = np.array(resolution, dtype=float)
        self._half = self.resolution / 2.0
        self._prev = self.middle.copy()
        self._d = np.zeros(n)
        self.now = np.zeros(n)
        self.lo = np.zeros(n)
        self.hi = np.zeros(n)

    def track(self, raw: np.ndarray) -> None:
        """One read's raw ticks: a step larger than half a turn is taken the short way round
        (a hand moves a joint far less than that in one cycle)."""
        d = self._d
        np.subtract(raw, self._prev, out=d)
        np.add(d, self._half, out=d)
        np.mod(d, self.resolution, out=d)
        np.subtract(d, self._half, out=d)
        np.add(self.now, d, out=self.now)
        np.minimum(self.lo, self.now, out=self.lo)
        np.maximum(self.hi, self.now, out=self.hi)
        self._prev[:] = raw


def sweep_calibration(robot: str, names: Sequence[str], watch: RangeWatch, directions: Sequence[int],
                      grippers: Sequence[str], homing: Sequence[int | None]) -> dict[str, dict[str, Any]]:
    """The calibration keys of every joint from a finished sweep.

    An arm joint: ``range`` = the lowest and highest ticks seen, ``offset`` = their middle (joint
    zero in the middle of its travel, as LeRobot's degrees and the SO-101 URDF have it),
    ``direction`` kept (a sweep cannot tell which way the robot's model counts). A gripper (named
    in ``grippers``; the user closed it last): ``offset`` = the end of its range it is now nearer
    to (closed = 0 rad), ``direction`` = +1 when opening raises the ticks, else -1. A continuous
    joint swept over (nearly) a whole turn gets the whole turn, zero at the middle pose.
    ``homing[i]``: the servo's Homing_Offset register the ticks were read with (None: unknown).

    Raises BackendError naming every joint that did not move, or whose travel crosses the
    encoder's wrap point (its servo's middle is then not near the middle of its ticks)."""
    problems, out = [], {}
    res = watch.resolution
    for i, name in enumerate(names):
        turn = int(res[i])
        lo = int(math.floor(watch.middle[i] + watch.lo[i] + 0.5))
        hi = int(math.floor(watch.middle[i] + watch.hi[i] + 0.5))
        travel = hi - lo
        if travel < MIN_TRAVEL_TICKS:
            problems.append(f"joint {name!r} did not move ({travel} ticks seen): sweep it through its whole range")
            continue
        if travel >= FULL_TURN_FRACTION * turn:
            keys: dict[str, Any] = {"offset": int(round(watch.middle[i])) % turn, "direction": int(directions[i]),
                                    "range": [0, turn - 1]}
        elif lo < 0 or hi > turn - 1:
            problems.append(f"joint {name!r} travels across its servo's encoder wrap point (ticks {lo}..{hi} "
                            f"of 0..{turn - 1}): set the servo's Homing_Offset so that the middle pose reads "
                            f"{turn // 2} (as lerobot-calibrate does), then calibrate again")
            continue
        elif name in grippers:
            here = watch.middle[i] + watch.now[i]
            closed, opened = (lo, hi) if abs(here - lo) <= abs(here - hi) else (hi, lo)
            keys = {"offset": closed, "direction": 1 if opened > closed else -1, "range": [lo, hi]}
        else:
            keys = {"offset": (lo + hi) // 2, "direction": int(directions[i]), "range": [lo, hi]}
        if homing[i] is not None:
            keys["homing_offset"] = int(homing[i])
        out[name] = keys
    if problems:
        raise BackendError(f"{robot}: calibration refused: " + "; ".join(problems))
    return out


def from_lerobot(robot: str, data: Any, names: Sequence[str], ids: Sequence[int], resolution: Sequence[int],
                 directions: Sequence[int], grippers: Sequence[str], software_drive_mode: bool,
                 source: str = "lerobot calibration") -> dict[str, dict[str, Any]]:
    """The calibration keys of every joint from a LeRobot calibration file of the same arm
    (``{motor: {id, drive_mode, homing_offset, range_min, range_max}}``, motors named as the
    joints; docs/calibration.md says how each field maps and what is lost).

    LeRobot reads Present_Position with ``homing_offset`` in the servo's EEPROM, and its ranges
    are in those ticks: ``homing_offset`` is kept (the servo must still hold it), ``range`` =
    [range_min, range_max]. A joint in degrees (or -100..100) has its zero in the middle of the
    range: ``offset`` = (range_min + range_max) // 2 (the half tick LeRobot keeps is lost), and
    its ``direction`` is kept (LeRobot's degrees ignore drive_mode). A gripper (0..100): ``offset``
    = the end LeRobot calls 0, ``direction`` toward its 100 end; that end is range_max when
    ``drive_mode`` flips it in software (Feetech: ``software_drive_mode``; a Dynamixel applies
    drive_mode itself, in its Drive_Mode register, before the ticks are read).

    Raises BackendError naming ``source``, the motor and the field of every problem."""
    if not isinstance(data, dict):
        raise BackendError(f"{robot}: {source}: expected a JSON object of motors by name, got {type(data).__name__}")
    problems, out = [], {}
    for i, name in enumerate(names):
        m = data.get(name)
        if not isinstance(m, dict):
            problems.append(f"{name}: missing (the file has {', '.join(map(str, data)) or 'no motor'})")
            continue
        vals = {}
        for field in ("id", "drive_mode", "homing_offset", "range_min", "range_max"):
            v = m.get(field)
            if not isinstance(v, int) or isinstance(v, bool):
                problems.append(f"{name}.{field}: expected an integer, got {v!r}")
            vals[field] = v
        extra = sorted(set(m) - set(vals))
        if extra:
            problems.append(f"{name}: unknown field{'s' if len(extra) > 1 else ''} {', '.join(extra)}")
        if any(not isinstance(v, int) or isinstance(v, bool) for v in vals.values()) or extra:
            continue
        lo, hi, turn = vals["range_min"], vals["range_max"], int(resolution[i])
        if vals["id"] != ids[i]:
            problems.append(f"{name}.id: {vals['id']}, but the profile's joint {name!r} is servo id {ids[i]}: "
                            f"not the same arm?")
        elif not 0 <= lo < hi <= turn - 1:
            problems.append(f"{name}: range_min {lo} .. range_max {hi} is not an ordered range within 0..{turn - 1}")
        elif vals["drive_mode"] not in (0, 1):
            problems.append(f"{name}.drive_mode: {vals['drive_mode']} is not 0 or 1")
        elif name in grippers:
            flipped = software_drive_mode and vals["drive_mode"] == 1
            out[name] = {"offset": hi if flipped else lo, "direction": -1 if flipped else 1, "range": [lo, hi],
                         "homing_offset": vals["homing_offset"]}
        else:
            out[name] = {"offset": (lo + hi) // 2, "direction": int(directions[i]), "range": [lo, hi],
                         "homing_offset": vals["homing_offset"]}
    unknown = sorted(set(data) - set(names))
    if unknown:
        problems.append(f"motor{'s' if len(unknown) > 1 else ''} {', '.join(map(str, unknown))}: no joint of "
                        f"that name in the profile (joints: {', '.join(names)})")
    if problems:
        raise BackendError(f"{robot}: {source}: " + "; ".join(problems))
    return out


#: LeRobot's norm modes (lerobot/motors/motors_bus.py ``MotorNormMode``), as ``list`` names them,
#: and the interval RANGE modes clamp to (LeRobot clamps the ticks to the calibrated range first)
LEROBOT_MODES = {"degrees": None, "range_m100_100": (-100.0, 100.0), "range_0_100": (0.0, 100.0)}


def lerobot_maps(offset: int, direction: int, range_: Sequence[int] | None, resolution: int) -> dict[str, list[float]] | None:
    """Per LeRobot norm mode, the affine map ``[scale, bias]`` from a serial-servo joint's value
    (rad: ``direction * (ticks - offset) * 2*pi / resolution``) to the number LeRobot's motors bus
    reports for the same ticks with the same calibration (range_min, range_max = ``range_``):
    ``lerobot = scale * rad + bias`` (docs/protocol.md, "LeRobot units"). Raw ticks never leave:
    only these coefficients do. None without a range (LeRobot's numbers need one).

    - ``degrees``: ``(ticks - (min + max) / 2) * 360 / (resolution - 1)`` (not clamped).
    - ``range_m100_100``: ``(ticks - min) / (max - min) * 200 - 100``, clamped to [-100, 100]; an
      arm joint's ``drive_mode`` is 0 in every SO / Koch calibration LeRobot writes on Feetech, and a
      Dynamixel applies its own in the servo (LeRobot's ``apply_drive_mode`` is False there).
    - ``range_0_100``: ``(ticks - min) / (max - min) * 100``, clamped to [0, 100]; ``100 - that``
      when the calibration's zero is ``max`` with direction -1, which is how a LeRobot gripper with
      ``drive_mode`` 1 imports (:func:`from_lerobot`) and how a sweep calibrates a gripper that
      closes toward ``max``."""
    if range_ is None:
        return None
    lo, hi = float(range_[0]), float(range_[1])
    res = float(resolution)
    ticks_per_rad = direction * res / (2.0 * math.pi)  # ticks = offset + ticks_per_rad * rad
    deg = 360.0 / (res - 1.0)
    m100 = 200.0 / (hi - lo)
    p100 = 100.0 / (hi - lo)
    flipped = direction == -1 and offset == int(hi)
    return {
        "degrees": [ticks_per_rad * deg, (offset - (lo + hi) / 2.0) * deg],
        "range_m100_100": [ticks_per_rad * m100, (offset - lo) * m100 - 100.0],
        "range_0_100": ([-ticks_per_rad * p100, (hi - offset) * p100] if flipped
                        else [ticks_per_rad * p100, (offset - lo) * p100]),
    }

"""Vectors, poses and quaternions as crtk-bridge reads them: ONE implementation for the client, the
front (server) and core (docs/architecture.md, "Limits").

A leaf module: it imports numpy, the standard library and :mod:`crtk_client.errors` only, so the
client library carries it without the daemon. Everything a command carries (a joint vector, a
pose, a twist, a wrench) is read here into float64 numpy arrays of the right shape with every
entry finite, or refused with :class:`InvalidVector` (a ``bad_request``
:class:`~crtk_client.errors.CommandError` that is also a ``ValueError``), its one-line message
naming what was given (``"arm: servo_jp position"``), the entry and, where known, the joint.

Conventions (docs/protocol.md): a pose is ``position`` [x, y, z] (m) and ``orientation``, the unit
quaternion [x, y, z, w] (ROS order); a quaternion given with a norm in (0.5, 1.5) is normalised,
anything farther from unit is refused (a typo, not rounding). ``quaternion_from_matrix`` returns
``w >= 0``.

These are early, friendly refusals: the one guarantee of profile limits and finiteness is core's
motion output, and :meth:`~crtk_bridge.core.actuator.Actuator.write` refuses a non-finite setpoint
for every backend whatever came before it.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from .errors import CommandError

#: a quaternion's norm must lie strictly between these to be taken as a rotation (then normalised)
QUATERNION_NORM_MIN, QUATERNION_NORM_MAX = 0.5, 1.5


class InvalidVector(CommandError, ValueError):
    """A vector, pose or quaternion that is no such thing: a ``bad_request`` refusal (and a
    ``ValueError``, for callers that are not about commands)."""

    def __init__(self, message: str):
        super().__init__("bad_request", message)


def _fits_float(v: int) -> bool:
    try:
        float(v)
    except OverflowError:
        return False
    return True


def floats(values: Any, what: str, n: int | None = None, names: Sequence[str] | None = None) -> np.ndarray:
    """``values`` (a list, tuple or numpy array of numbers) as a new float64 array of ``n`` finite
    entries (any length when ``n`` is None). ``what`` says whose vector it is
    (``"arm: servo_jp position"``); ``names`` (one per entry, e.g. the joints) go into the message.
    Raises :class:`InvalidVector`."""
    if isinstance(values, np.ndarray):
        flat: Any = values.ravel()
    elif isinstance(values, (list, tuple)):
        flat = values
    else:
        raise InvalidVector(f"{what}: expected a list of numbers, got {type(values).__name__}")
    if n is not None and len(flat) != n:
        which = f" ({', '.join(names)})" if names else ""
        raise InvalidVector(f"{what} needs {n} values{which}, got {len(flat)}")
    try:
        vec = np.array(flat)  # numbers only (a request's list, nearly always): no per-entry look
        if vec.dtype.kind not in "biuf":  # text, None, ...: each entry looked at (numpy reads "1.5")
            vec = None if _has_text(flat) else np.array(flat, dtype=float)
        elif vec.dtype.char != "d":  # ints, bools, float32: float64
            vec = vec.astype(float)
    except OverflowError:  # an int beyond a float's range (10**400): no motor position
        bad = next(i for i, v in enumerate(flat) if isinstance(v, int) and not _fits_float(v))
        raise InvalidVector(f"{what}: entry {bad}{_name(names, bad)} is out of range: {_short(flat[bad])}") from None
    except (TypeError, ValueError):
        vec = None
    if vec is None or vec.ndim != 1:
        bad = next((i for i, v in enumerate(flat) if not _number(v)), 0)
        raise InvalidVector(f"{what}: entry {bad}{_name(names, bad)} is not a number: {_short(flat[bad])}")
    # a finite sum has finite terms only (inf, nan propagate); an overflowing one is looked at
    # closely. Python floats: an overflow is inf, never a warning; a third of numpy's cost
    if not math.isfinite(sum(vec.tolist())) and not np.isfinite(vec).all():
        i = int(np.flatnonzero(~np.isfinite(vec))[0])
        raise InvalidVector(f"{what}: entry {i}{_name(names, i)} is non-finite ({vec[i]})")
    return vec


def field(data: Any, key: str, n: int, what: str, names: Sequence[str] | None = None) -> np.ndarray:
    """``data[key]`` read by :func:`floats` (``what`` names the command: ``"arm: servo_cv"``)."""
    if not isinstance(data, dict):
        raise InvalidVector(f"{what} needs data with {key!r} ({n} numbers)")
    if key not in data:
        raise InvalidVector(f"{what} needs {key!r} with {n} numbers")
    return floats(data[key], f"{what} {key}", n, names)


def unit_quaternion(values: Any, what: str) -> np.ndarray:
    """4 finite numbers [x, y, z, w] with a norm in (0.5, 1.5), normalised. Raises InvalidVector."""
    q = floats(values, what, 4)
    norm = math.hypot(*q.tolist())  # 1e308 entries: a huge norm (refused), never an overflow
    if not QUATERNION_NORM_MIN < norm < QUATERNION_NORM_MAX:
        raise InvalidVector(f"{what} must be a unit quaternion [x, y, z, w] (norm {norm:.3g})")
    return q / norm


def pose(data: Any, what: str) -> tuple[np.ndarray, np.ndarray]:
    """``{"position": [3], "orientation": [4]}`` -> (position [3] m, unit quaternion [4] xyzw).
    Raises InvalidVector naming the field."""
    p = field(data, "position", 3, what)
    return p, unit_quaternion(field(data, "orientation", 4, what), f"{what} orientation")


def six(data: Any, a: str, b: str, what: str) -> np.ndarray:
    """A twist (``a, b = "linear", "angular"``) or wrench (``"force", "torque"``) given as two
    3-vectors of ``data`` -> one 6-vector ``[a; b]``. Raises InvalidVector naming the field."""
    return np.concatenate([field(data, a, 3, what), field(data, b, 3, what)])


def any_pose(value: Any, what: str = "pose") -> tuple[np.ndarray, np.ndarray]:
    """A pose as a client gives it: a 4x4 homogeneous matrix (the rotation block a rotation
    within 1e-3), a ``(position[3], quaternion[4] xyzw)`` pair, or a dict with ``position`` and
    ``orientation`` -> (position [3], unit quaternion [4] with w >= 0 for a matrix). Raises
    InvalidVector."""
    if isinstance(value, dict):
        if "position" not in value or "orientation" not in value:
            raise InvalidVector(f"{what}: a pose dict needs 'position' and 'orientation'")
        position, quaternion = value["position"], value["orientation"]
    elif isinstance(value, (tuple, list)) and len(value) == 2:
        position, quaternion = value
    else:
        try:
            T = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise InvalidVector(f"{what}: not a 4x4 matrix or a (position, quaternion) pair: "
                                f"{_short(value)}") from None
        if T.shape != (4, 4):
            raise InvalidVector(f"{what}: expected a 4x4 homogeneous matrix or a (position, quaternion) "
                                f"pair, got shape {T.shape}")
        if not np.isfinite(T).all():
            raise InvalidVector(f"{what}: the matrix has a non-finite entry")
        R = T[:3, :3]
        if (not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9)
                or not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0):
            raise InvalidVector(f"{what}: not a homogeneous transform (rotation block not orthonormal, "
                                "or last row not [0, 0, 0, 1])")
        return T[:3, 3].copy(), quaternion_from_matrix(R)
    p = _coerced(position, f"{what} position")
    q = _coerced(quaternion, f"{what} orientation")
    if len(p) != 3 or len(q) != 4:
        raise InvalidVector(f"{what}: position needs 3 numbers (m) and the quaternion 4 [x, y, z, w], "
                            f"got {len(p)} and {len(q)}")
    return floats(p, f"{what} position", 3), unit_quaternion(q, f"{what} orientation")


def matrix_from_quaternion(quaternion: Any) -> np.ndarray:
    """3x3 rotation matrix of a quaternion ``[x, y, z, w]`` (ROS order), normalised first.
    Raises InvalidVector (a ValueError) on a zero or non-finite quaternion."""
    x, y, z, w = (float(v) for v in np.asarray(quaternion, dtype=float).ravel())
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not (n > 1e-9 and math.isfinite(n)):
        raise InvalidVector(f"quaternion [x, y, z, w] = {[x, y, z, w]} has no direction")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quaternion_from_matrix(rotation: Any) -> np.ndarray:
    """Unit quaternion ``[x, y, z, w]`` (``w >= 0``) of a 3x3 rotation matrix (or the rotation
    block of a 4x4 pose); Shepperd's method, stable for every rotation."""
    if not (isinstance(rotation, np.ndarray) and rotation.shape == (3, 3)):
        rotation = np.asarray(rotation, dtype=float)[:3, :3]
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rotation.tolist()
    t = r00 + r11 + r22
    if t > 0.0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = [(r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s, s / 4]
    elif r00 >= r11 and r00 >= r22:
        s = 2.0 * math.sqrt(max(0.0, 1.0 + r00 - r11 - r22))
        q = [s / 4, (r01 + r10) / s, (r02 + r20) / s, (r21 - r12) / s]
    elif r11 >= r22:
        s = 2.0 * math.sqrt(max(0.0, 1.0 + r11 - r00 - r22))
        q = [(r01 + r10) / s, s / 4, (r12 + r21) / s, (r02 - r20) / s]
    else:
        s = 2.0 * math.sqrt(max(0.0, 1.0 + r22 - r00 - r11))
        q = [(r02 + r20) / s, (r12 + r21) / s, s / 4, (r10 - r01) / s]
    k = (-1.0 if q[3] < 0 else 1.0) / math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return np.array([q[0] * k, q[1] * k, q[2] * k, q[3] * k])


def pose_matrix(position: Any, quaternion: Any) -> np.ndarray:
    """The 4x4 homogeneous matrix of ``position`` [x, y, z] (m) and ``quaternion`` [x, y, z, w]."""
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion(quaternion)
    T[:3, 3] = np.asarray(position, dtype=float).ravel()[:3]
    return T


def pose_pq(matrix: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(position [3] in m, quaternion [4] x, y, z, w with w >= 0)`` of a 4x4 homogeneous matrix."""
    T = np.asarray(matrix, dtype=float)
    return T[:3, 3].copy(), quaternion_from_matrix(T[:3, :3])


def distance(a: Any, b: Any) -> float:
    """Euclidean distance of two 3-vectors, without overflow (1e308 apart: a huge number)."""
    (ax, ay, az), (bx, by, bz) = a, b
    return math.hypot(float(ax) / 2 - float(bx) / 2, float(ay) / 2 - float(by) / 2, float(az) / 2 - float(bz) / 2) * 2


def norm(v: Any) -> float:
    """Euclidean norm of a vector, without overflow."""
    return math.hypot(*(float(x) for x in v))


def rotation_angle(q: np.ndarray, base: np.ndarray) -> float:
    """rad between the rotations of quaternions ``q`` (unit) and ``base`` (any norm)."""
    cos = abs(float(np.dot(q, base))) / max(float(np.linalg.norm(base)), 1e-12)
    return 2.0 * math.acos(min(1.0, cos))


def _coerced(values: Any, what: str) -> list:
    """A client's vector (a list, tuple, numpy array or any iterable of numbers) as a list."""
    if isinstance(values, np.ndarray):
        return list(values.ravel())
    if isinstance(values, (str, bytes, dict)) or not hasattr(values, "__iter__"):
        raise InvalidVector(f"{what}: expected a list of numbers, got {type(values).__name__}")
    return list(values)


def client_floats(values: Any, what: str = "vector") -> list[float]:
    """A client's vector (any iterable of numbers, a numpy array) as a list of plain finite floats
    (the wire wants JSON numbers). Raises InvalidVector before anything is sent."""
    return floats(_coerced(values, what), what).tolist()


def _has_text(flat: Any) -> bool:
    """Whether ``flat`` holds strings or None (numpy would read "1.5" as a number and None as NaN:
    neither may pass for a number)."""
    if isinstance(flat, np.ndarray) and flat.dtype.kind not in "USO":
        return False
    return any(v is None or isinstance(v, (str, bytes)) for v in flat)


def _number(v: Any) -> bool:
    if v is None or isinstance(v, (str, bytes)):
        return False
    try:
        float(v)
    except (TypeError, ValueError):
        return False
    except OverflowError:  # a number, beyond a float's range (floats names it so)
        return True
    return True


def _name(names: Sequence[str] | None, i: int) -> str:
    return f" ({names[i]!r})" if names is not None and i < len(names) else ""


def _short(value: Any, limit: int = 60) -> str:
    try:
        text = repr(value)
    except ValueError:  # an int past Python's digit limit for str()
        return f"an integer of {value.bit_length()} bits"
    return text if len(text) <= limit else text[:limit - 3] + "..."

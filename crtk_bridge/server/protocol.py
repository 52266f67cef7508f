"""Wire protocol of the socket API (docs/protocol.md): version, request schema, codec.

A request line is decoded in two typed stages, both by msgspec:

1. the envelope (:class:`Request`): an object with an integer ``id``, a string ``cmd``, an
   optional string ``ns``; ``data`` is kept raw. A line that is not such an object gets a
   ``bad_request`` reply carrying the line's ``id`` when an integer one can be read from it (a
   JSON object with an integer ``id``, as JSON-RPC), else ``"id": null``.
2. the payload, by the command's Struct in :data:`PAYLOADS` (strict: a number field takes a JSON
   number only, never a boolean, a string, null or a nested array; unknown fields are refused).
   The reply carries the request's id; the message names the field (``data.position[0]``).

Nesting deeper than :data:`MAX_DEPTH` is refused before decoding (no decoder recursion; the
reply's id is read from the line with its nested values flattened). A line that is not valid
UTF-8 is refused naming the field whose string is not (``cmd``, ``data.position[0]``, a key of
``data``), never with the decoder's own text.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal

import msgspec
import numpy as np

from ..errors import CommandError, one_line
from ..vocabulary import (  # noqa: F401 - the protocol's words, re-exported for the server
    JOINT_TOPICS as JOINT_QUERIES, PROTOCOL_VERSION, ROBOT_TOPICS as ROBOT_QUERIES, STOP_COMMANDS, ErrorCode,
    MaintenanceCommand, RecordingCommand, SessionCommand, StateCommand, Topic,
)

STATE_COMMANDS = tuple(StateCommand)
TOPICS = tuple(Topic)
SESSION_COMMANDS = tuple(SessionCommand)
RECORDING_COMMANDS = tuple(RecordingCommand)

MAX_LINE = 1 << 16  #: bytes per request line (a motion command is a few hundred)
MAX_DEPTH = 32  #: nesting of arrays and objects in a request line (a real request uses 3)


class Request(msgspec.Struct, kw_only=True):
    id: int
    cmd: str
    ns: str | None = None
    data: msgspec.Raw = msgspec.Raw(b"null")


# ------------------------------------------------------------------ payloads, one Struct per shape
class _Payload(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True):
    pass


class NoData(_Payload):
    """Commands without a payload: ``data`` absent, null or ``{}``."""


class JointPosition(_Payload):
    position: list[float]


class JointServo(_Payload):
    position: list[float]
    velocity: list[float] | msgspec.UnsetType = msgspec.UNSET  # optional feed-forward


class JointVelocity(_Payload):
    velocity: list[float]


class JointEffort(_Payload):
    effort: list[float]


Vec3 = Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)]
Quaternion = Annotated[list[float], msgspec.Meta(min_length=4, max_length=4)]


class Pose(_Payload):
    position: Vec3
    orientation: Quaternion


class Twist(_Payload):
    linear: Vec3
    angular: Vec3


class Wrench(_Payload):
    force: Vec3
    torque: Vec3


class Joints(_Payload):
    jp: list[float]


class IkRequest(_Payload):
    position: Vec3
    orientation: Quaternion
    jp: list[float] | msgspec.UnsetType = msgspec.UNSET  # seed; default the measured joints


class Subscribe(_Payload):
    topic: str
    rate_hz: Annotated[float, msgspec.Meta(gt=0)] = 10.0


class Unsubscribe(_Payload):
    sub: int


class Calibrate(_Payload):
    """``calibrate`` (docs/calibration.md): a sweep by hand, or an import."""
    action: Literal["begin", "status", "end", "cancel", "import"]
    grippers: list[str] = []  # joints with closed / open ends (end, import)
    format: Literal["lerobot"] = "lerobot"  # import: the file's format
    file: dict[str, Any] = {}  # import: the file's content


class Record(_Payload):
    """``record`` (docs/recording.md): the bag's path on the daemon's machine."""
    path: Annotated[str, msgspec.Meta(min_length=1)]
    duration_s: Annotated[float, msgspec.Meta(gt=0)] | None = None  # default: until record_stop
    namespaces: list[str] | None = None  # default: every namespace


class RecordStop(_Payload):
    recording: int | None = None  # default: the session's latest recording
    wait: bool = False  # a recording with a duration: wait for its end instead of cutting it short


class Blackbox(_Payload):
    path: Annotated[str, msgspec.Meta(min_length=1)]


#: command -> payload Struct; commands not listed take no data (:class:`NoData`)
PAYLOADS: dict[str, type[_Payload]] = {
    "servo_jp": JointServo, "servo_jr": JointPosition,
    "interpolate_jp": JointPosition, "interpolate_jr": JointPosition,
    "move_jp": JointPosition, "move_jr": JointPosition,
    "servo_jv": JointVelocity, "interpolate_jv": JointVelocity,
    "servo_jf": JointEffort, "interpolate_jf": JointEffort,
    **{c: Pose for c in ("servo_cp", "interpolate_cp", "move_cp", "servo_cr", "interpolate_cr", "move_cr")},
    "servo_cv": Twist, "interpolate_cv": Twist, "servo_cf": Wrench, "interpolate_cf": Wrench,
    "forward_kinematics": Joints, "inverse_kinematics": IkRequest,
    "subscribe": Subscribe, "unsubscribe": Unsubscribe,
    "calibrate": Calibrate,
    "record": Record, "record_stop": RecordStop, "blackbox": Blackbox,
}
#: joint commands whose vectors have one entry per joint of the namespace
JOINT_VECTORS = {c: t for c, t in PAYLOADS.items() if t in (JointServo, JointPosition, JointVelocity, JointEffort)}


class ProtocolError(CommandError):
    """A request refused by the front process; ``rid`` is the id its reply carries."""

    def __init__(self, code: str, message: str, rid: Any = None):
        super().__init__(code, message)
        self.rid = rid


_envelope = msgspec.json.Decoder(Request)
_payload_decoders = {t: msgspec.json.Decoder(t) for t in set(PAYLOADS.values()) | {NoData}}
_encoder = msgspec.json.Encoder()
_STRINGS = re.compile(rb'"(?:[^"\\]|\\.)*"')
_OPEN = np.zeros(256, np.int8)
_OPEN[[ord("["), ord("{")]] = 1
_OPEN[[ord("]"), ord("}")]] = -1


def nesting_depth(line: bytes) -> int:
    """The deepest nesting of arrays and objects in a JSON text (brackets inside strings do not
    count). Vectorised: no recursion, linear in the line length."""
    if line.count(b"[") + line.count(b"{") <= MAX_DEPTH:  # cannot be deeper: the common case
        return 0
    text = _STRINGS.sub(b'""', line)
    steps = _OPEN[np.frombuffer(text, np.uint8)]
    return int(np.cumsum(steps, dtype=np.int64).max(initial=0))


class _IdOnly(msgspec.Struct):
    """A request line read for its ``id`` alone (other fields skipped, their strings not decoded)."""
    id: int


_id_only = msgspec.json.Decoder(_IdOnly)
_as_object = msgspec.json.Decoder(dict[str, msgspec.Raw])
_as_array = msgspec.json.Decoder(list[msgspec.Raw])


def _flatten(line: bytes) -> bytes:
    """``line`` with every array or object inside the top-level value replaced by ``""`` (never
    an integer): the top-level keys and scalars kept verbatim, so a too-deep line's ``id`` can be
    read without recursion."""
    blank = _STRINGS.sub(lambda m: b'"' + b" " * (len(m[0]) - 2) + b'"', line)  # same length
    steps = _OPEN[np.frombuffer(blank, np.uint8)]
    before = np.cumsum(steps, dtype=np.int64) - steps  # depth before each byte
    ends = ((steps == 1) & (before == 1)) | ((steps == -1) & (before == 2))  # of a nested value
    out = np.frombuffer(line, np.uint8).copy()
    out[ends] = ord('"')
    return out[(before <= 1) | ends].tobytes()


def read_id(line: bytes) -> int | None:
    """The integer ``id`` of a request line that is a JSON object, however wrong its other fields
    are; None when none can be read (not JSON, not an object, no id, an id of another type)."""
    if nesting_depth(line) > MAX_DEPTH:
        line = _flatten(line)
    try:
        return _id_only.decode(line).id
    except (msgspec.ValidationError, msgspec.DecodeError, UnicodeDecodeError, RecursionError):
        return None


def _path(base: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{base}[{key}]"
    return f"{base}.{key}" if base else key


def _utf8(raw: bytes) -> bool:
    try:
        raw.decode()
        return True
    except UnicodeDecodeError:
        return False


def not_utf8_at(raw: bytes, path: str = "") -> str:
    """Which field of JSON text ``raw`` (found at ``path``: "" for a whole request line) holds a
    string that is not valid UTF-8, said for a reply: "`data.position[0]` is not valid UTF-8",
    "a key of `data` is not ...", or "the line is not ..." when it cannot be attributed (the
    bytes are outside any string: not JSON). Descends at most :data:`MAX_DEPTH` levels."""
    for _ in range(MAX_DEPTH + 1):
        try:
            items = list(_as_object.decode(raw).items())
        except UnicodeDecodeError:
            return f"a key of `{path}` is not valid UTF-8" if path else "a key of the request is not valid UTF-8"
        except msgspec.ValidationError:
            try:
                items = list(enumerate(_as_array.decode(raw)))
            except msgspec.ValidationError:
                break  # a scalar: the string at path
            except msgspec.DecodeError:
                break
        except msgspec.DecodeError:
            break
        bad = next(((k, bytes(v)) for k, v in items if not _utf8(bytes(v))), None)
        if bad is None:
            break
        path, raw = _path(path, bad[0]), bad[1]
    return f"`{path}` is not valid UTF-8" if path else "the line is not valid UTF-8"


def decode_request(line: bytes) -> Request:
    """Parse one request line's envelope. Raises ProtocolError("bad_request") carrying the id
    :func:`read_id` finds (None when there is none), its message naming the field at fault."""
    if nesting_depth(line) > MAX_DEPTH:
        raise ProtocolError("bad_request", f"invalid request: nested deeper than {MAX_DEPTH} levels",
                            read_id(line))
    if not _utf8(line):  # any string, also of a field the envelope ignores (the framing is UTF-8)
        raise ProtocolError("bad_request", f"invalid request: {not_utf8_at(line)}", read_id(line))
    try:
        return _envelope.decode(line)
    except msgspec.ValidationError as exc:
        text = str(exc).replace("`$.", "`")
        raise ProtocolError("bad_request", f"invalid request: {text}", read_id(line)) from None
    except (msgspec.DecodeError, RecursionError) as exc:
        raise ProtocolError("bad_request", f"invalid JSON: {exc}") from None


def decode_payload(req: Request, who: str) -> dict:
    """The request's ``data`` typed by its command's Struct, as a plain dict (absent optional
    fields left out). Raises ProtocolError("bad_request") naming the field, with the request's id.
    An unknown command's data is not looked at (the command is refused on its own)."""
    kind = PAYLOADS.get(req.cmd, NoData)
    raw = bytes(req.data)
    if kind is NoData and raw == b"null":
        return {}
    try:
        payload = _payload_decoders[kind].decode(raw)
    except UnicodeDecodeError:  # (a line from decode_request was checked whole)
        raise ProtocolError("bad_request", f"{who}: {req.cmd} refused: {not_utf8_at(raw, 'data')}",
                            req.id) from None
    except (msgspec.ValidationError, msgspec.DecodeError, RecursionError) as exc:
        text = str(exc).replace("`$", "`data")
        if " - at " not in text:
            text += " - at `data`"
        raise ProtocolError("bad_request", f"{who}: {req.cmd} refused: {text}", req.id) from None
    return msgspec.to_builtins(payload)  # a dict; unset optional fields left out


def encode(msg: Any) -> bytes:
    """One message as a JSON line (with the trailing newline)."""
    return _encoder.encode(msg) + b"\n"


def frame_head(topic: str, ns: str | None, sub: int) -> bytes:
    """A stream frame up to its data: ``frame_head(t, ns, k) + encode_body(data) + b"}\\n"`` is
    ``encode({"topic": t, "ns": ns, "sub": k, "data": data})`` (server/streams.py encodes the
    data once for every subscriber of a topic)."""
    return _encoder.encode({"topic": topic, "ns": ns, "sub": sub, "data": None})[:-len(b"null}")]


def encode_body(data: Any) -> bytes:
    """A stream frame's data, encoded once per tick whatever the number of subscribers."""
    return _encoder.encode(data)


def ok(rid: Any, data: Any = None) -> dict:
    return {"id": rid, "ok": True, "data": data}


def error(rid: Any, code: str, message: str) -> dict:
    """An error reply; its message one line (control characters a client sent escaped)."""
    return {"id": rid, "ok": False, "error": {"code": code, "message": one_line(message)}}

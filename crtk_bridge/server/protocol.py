"""Wire protocol of the socket API (docs/protocol.md): version, request schema, codec."""

from __future__ import annotations

from typing import Any

import msgspec

PROTOCOL_VERSION = 1

STATE_COMMANDS = ("enable", "disable", "pause", "resume", "home", "unhome")
JOINT_QUERIES = ("measured_js", "setpoint_js", "goal_js")
ROBOT_QUERIES = ("operating_state", "period_statistics")
TOPICS = JOINT_QUERIES + ROBOT_QUERIES
SESSION_COMMANDS = ("list", "subscribe", "unsubscribe", "acquire", "release")


class Request(msgspec.Struct, kw_only=True):
    id: int
    cmd: str
    ns: str | None = None
    data: Any = None


class ProtocolError(Exception):
    def __init__(self, code: str, message: str, rid: Any = None):
        super().__init__(message)
        self.code = code
        self.rid = rid


_decoder = msgspec.json.Decoder(Request)
_encoder = msgspec.json.Encoder()


def decode_request(line: bytes) -> Request:
    """Parse one request line. Raises ProtocolError("bad_request") with the reason."""
    try:
        return _decoder.decode(line)
    except msgspec.ValidationError as exc:
        rid = None
        try:
            obj = msgspec.json.decode(line)
            if isinstance(obj, dict) and isinstance(obj.get("id"), int):
                rid = obj["id"]
        except msgspec.DecodeError:
            pass
        raise ProtocolError("bad_request", f"invalid request: {exc}", rid) from None
    except msgspec.DecodeError as exc:
        raise ProtocolError("bad_request", f"invalid JSON: {exc}") from None


def encode(msg: Any) -> bytes:
    """One message as a JSON line (with the trailing newline)."""
    return _encoder.encode(msg) + b"\n"


def ok(rid: Any, data: Any = None) -> dict:
    return {"id": rid, "ok": True, "data": data}


def error(rid: Any, code: str, message: str) -> dict:
    return {"id": rid, "ok": False, "error": {"code": code, "message": message}}

"""What every part of the controller shares: the refusal, the command tables, the deferred reply."""

from __future__ import annotations

from ...errors import CommandError
from ..state import StateCommand

STATE_COMMANDS = tuple(c.value for c in StateCommand)
#: joint motion commands -> (payload field, capability needed: "position" / "velocity" / "effort" / "free")
MOTION_COMMANDS: dict[str, tuple[str | None, str]] = {
    "servo_jp": ("position", "position"),
    "servo_jr": ("position", "position"),
    "servo_jv": ("velocity", "velocity"),
    "servo_jf": ("effort", "effort"),
    "interpolate_jp": ("position", "position"),
    "interpolate_jr": ("position", "position"),
    "interpolate_jv": ("velocity", "velocity"),
    "interpolate_jf": ("effort", "effort"),
    "move_jp": ("position", "position"),
    "move_jr": ("position", "position"),
    "hold": (None, "position"),
    "free": (None, "free"),
}

DEFERRED = object()  # a request's reply comes when the transition it started ends


class Refused(CommandError):
    """A request refused; becomes an error reply with ``code``."""

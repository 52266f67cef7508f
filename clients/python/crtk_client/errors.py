"""One error tree for the whole project, rooted at :class:`CrtkBridgeError`.

Messages name the robot, joint, register or profile key involved. Foreign exceptions (serial,
SDK, OS) are re-raised as one of these, chained with ``raise ... from exc``.
"""

import math
import re

#: what would break a message's one line or act on a terminal: C0 and C1 controls, DEL, and the
#: Unicode line and paragraph separators
_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def one_line(text: str) -> str:
    """``text`` with its control characters escaped as Python writes them (``\\n``, ``\\x1b``,
    ``\\u2028``): an error message stays one line whatever strings a client sent."""
    return _CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


class CrtkBridgeError(Exception):
    """Root of every error crtk-bridge raises on purpose."""


class ProfileError(CrtkBridgeError):
    """A robot profile is missing, unreadable or invalid (message names file and key path)."""


class BackendError(CrtkBridgeError):
    """A backend failed on its lifecycle path (open, configure, enable, disable, close)."""


class BackendUnavailableError(BackendError):
    """A backend's vendor SDK is not installed; the message names the pip extra to install."""


class CommandError(CrtkBridgeError):
    """The daemon refused a command. ``code`` is one of the protocol's error codes."""

    def __init__(self, code: str, message: str):
        message = one_line(message)  # it may quote a client's strings (a field name, a command)
        super().__init__(message)
        self.code = code
        self.message = message


def fmt_number(value: float, decimals: int = 4, sign: bool = False) -> str:
    """A number as a message shows it: ``decimals`` fixed decimals while that stays short, else
    scientific notation, so a hostile ``1e308`` prints as ``1e+308``, not as 309 digits."""
    x = float(value)
    plus = "+" if sign else ""
    if not math.isfinite(x) or abs(x) < 1e6:
        return f"{x:{plus}.{decimals}f}"
    return f"{x:{plus}.{decimals}g}"

"""CRTK operating states and the transition table, as data (crtk-spec section 3.3).

The table is the spec's, cell for cell. ``home`` and ``unhome`` follow cisst's
``prmOperatingState::ValidCommand`` (the dVRK's implementation): ``home`` only in ENABLED,
``unhome`` in every state.
"""

from __future__ import annotations

import enum
from typing import NamedTuple


class OperatingState(str, enum.Enum):
    DISABLED = "DISABLED"
    ENABLED = "ENABLED"
    PAUSED = "PAUSED"
    FAULT = "FAULT"


class StateCommand(str, enum.Enum):
    ENABLE = "enable"
    DISABLE = "disable"
    PAUSE = "pause"
    RESUME = "resume"
    HOME = "home"
    UNHOME = "unhome"


class Transition(NamedTuple):
    target: OperatingState | None  # None: the command is invalid in this state
    retry: bool = False  # FAULT rows: the transition is attempted again (may fail, stays FAULT)


S, C = OperatingState, StateCommand
_INVALID = Transition(None)

#: crtk-spec 3.3 "State Transitions", one entry per cell; rows = current state.
TRANSITIONS: dict[tuple[OperatingState, StateCommand], Transition] = {
    # DISABLED row: enable -> ENABLED, disable -> DISABLED, pause/resume invalid
    (S.DISABLED, C.ENABLE): Transition(S.ENABLED),
    (S.DISABLED, C.DISABLE): Transition(S.DISABLED),
    (S.DISABLED, C.PAUSE): _INVALID,
    (S.DISABLED, C.RESUME): _INVALID,
    # ENABLED row: enable -> ENABLED, disable -> DISABLED, pause -> PAUSED, resume invalid
    (S.ENABLED, C.ENABLE): Transition(S.ENABLED),
    (S.ENABLED, C.DISABLE): Transition(S.DISABLED),
    (S.ENABLED, C.PAUSE): Transition(S.PAUSED),
    (S.ENABLED, C.RESUME): _INVALID,
    # PAUSED row: enable invalid, disable -> DISABLED, pause -> PAUSED, resume -> ENABLED
    (S.PAUSED, C.ENABLE): _INVALID,
    (S.PAUSED, C.DISABLE): Transition(S.DISABLED),
    (S.PAUSED, C.PAUSE): Transition(S.PAUSED),
    (S.PAUSED, C.RESUME): Transition(S.ENABLED),
    # FAULT row: enable -> ENABLED (retry), disable -> DISABLED (retry), pause/resume invalid
    (S.FAULT, C.ENABLE): Transition(S.ENABLED, retry=True),
    (S.FAULT, C.DISABLE): Transition(S.DISABLED, retry=True),
    (S.FAULT, C.PAUSE): _INVALID,
    (S.FAULT, C.RESUME): _INVALID,
    # home / unhome (cisst prmOperatingState): home only while ENABLED, unhome anywhere
    (S.DISABLED, C.HOME): _INVALID,
    (S.ENABLED, C.HOME): Transition(S.ENABLED),
    (S.PAUSED, C.HOME): _INVALID,
    (S.FAULT, C.HOME): _INVALID,
    (S.DISABLED, C.UNHOME): Transition(S.DISABLED),
    (S.ENABLED, C.UNHOME): Transition(S.ENABLED),
    (S.PAUSED, C.UNHOME): Transition(S.PAUSED),
    (S.FAULT, C.UNHOME): Transition(S.FAULT),
}
del S, C


def transition(state: OperatingState, command: StateCommand) -> Transition:
    return TRANSITIONS[(state, command)]

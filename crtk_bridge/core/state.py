"""CRTK operating states and the transition table, as data (crtk-spec section 3.3).

The table is the spec's, cell for cell. ``home`` and ``unhome`` follow cisst's
``prmOperatingState::ValidCommand`` (the dVRK's implementation): ``home`` only in ENABLED,
``unhome`` in every state.

``DEVICE_STATUS`` is the ONE place where what a device reports about itself
(:class:`~crtk_bridge.core.actuator.DeviceStatus`) becomes a CRTK state and an event.
"""

from __future__ import annotations

from typing import NamedTuple

from ..vocabulary import OperatingState, StateCommand  # noqa: F401 - defined in the vocabulary, used here
from .actuator import DeviceStatus


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


class StatusReaction(NamedTuple):
    target: OperatingState | None  # None: the state stays
    event: str | None  # event stream ("error", "warning", "status"); None: no event
    code: str | None  # event code (docs/protocol.md)


D = DeviceStatus
S = OperatingState
_STAY = StatusReaction(None, None, None)
_OK = StatusReaction(None, "status", "device_ok")
_CLEARED = StatusReaction(None, "status", "fault_cleared")
_FAULT = StatusReaction(S.FAULT, "error", None)  # the event carries the fault's own code

#: (state, what the device reports) -> reaction. Core never enables itself: a device that is ok
#: again, or whose fault cleared, leaves the robot where it is (the user resumes / enables).
DEVICE_STATUS: dict[tuple[OperatingState, DeviceStatus], StatusReaction] = {
    (S.DISABLED, D.OK): _OK,
    (S.DISABLED, D.PAUSED): StatusReaction(None, "warning", "device_paused"),
    (S.DISABLED, D.POWERED_OFF): StatusReaction(None, "warning", "device_powered_off"),
    (S.DISABLED, D.FAULT): StatusReaction(None, "warning", "device_fault"),  # enable will fail or reset it
    (S.DISABLED, D.FAULT_CLEARED): _CLEARED,
    (S.ENABLED, D.OK): _OK,
    (S.ENABLED, D.PAUSED): StatusReaction(S.PAUSED, "warning", "device_paused"),  # UR safeguard stop
    (S.ENABLED, D.POWERED_OFF): StatusReaction(S.DISABLED, "error", "device_powered_off"),  # e-stop
    (S.ENABLED, D.FAULT): _FAULT,
    (S.ENABLED, D.FAULT_CLEARED): _CLEARED,
    (S.PAUSED, D.OK): _OK,  # stays PAUSED: resume is the user's
    (S.PAUSED, D.PAUSED): StatusReaction(None, "warning", "device_paused"),
    (S.PAUSED, D.POWERED_OFF): StatusReaction(S.DISABLED, "error", "device_powered_off"),
    (S.PAUSED, D.FAULT): _FAULT,
    (S.PAUSED, D.FAULT_CLEARED): _CLEARED,
    (S.FAULT, D.OK): _OK,
    (S.FAULT, D.PAUSED): StatusReaction(None, "warning", "device_paused"),
    (S.FAULT, D.POWERED_OFF): StatusReaction(None, "warning", "device_powered_off"),
    (S.FAULT, D.FAULT): _STAY,  # already in FAULT with its cause
    (S.FAULT, D.FAULT_CLEARED): _CLEARED,  # stays FAULT: enable (retry) or disable to leave it
    # news from the device, in every state: an event, the state stays
    **{(s, D.WARNING): StatusReaction(None, "warning", "device_warning") for s in S},
    **{(s, D.NOTICE): StatusReaction(None, "status", "device_status") for s in S},
}
del D, S


def transition(state: OperatingState, command: StateCommand) -> Transition:
    return TRANSITIONS[(state, command)]

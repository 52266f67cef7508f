"""The ONE table that turns what a UR controller reports into a device status.

:func:`device_state` maps (link, robot mode, safety mode, runtime state, enabled) onto a
:class:`~crtk_bridge.core.actuator.DeviceStatus` and a cause; core then maps that onto the CRTK
state with its own one table (``core/state.py``, ``DEVICE_STATUS``). Evaluated top to bottom,
first match wins (reference/canopen-ur.md section 6; mode values in :mod:`.tables`):

| # | condition | device status | cause code | CRTK state (from ENABLED) |
|---|---|---|---|---|
| 1 | RTDE link down (closed, or no packet for ``backend.link_timeout_s``) | FAULT | ``link_lost`` | FAULT |
| 2 | robot mode NO_CONTROLLER / DISCONNECTED | FAULT | ``controller_disconnected`` | FAULT |
| 3 | safety PROTECTIVE_STOP | FAULT | ``protective_stop`` | FAULT |
| 4 | safety SYSTEM / ROBOT_EMERGENCY_STOP | FAULT | ``emergency_stop`` | FAULT |
| 5 | safety VIOLATION / FAULT | FAULT | ``safety_fault`` | FAULT |
| 6 | safety RECOVERY | FAULT | ``safety_recovery`` | FAULT |
| 7 | safety VALIDATE_JOINT_ID / UNDEFINED | FAULT | ``safety_undefined`` | FAULT |
| 8 | safety SAFEGUARD_STOP / AUTOMATIC_MODE_SAFEGUARD_STOP / 3-POSITION_ENABLING_STOP | PAUSED | ``safeguard_stop`` | PAUSED |
| 9 | enabled, runtime PAUSING / PAUSED | PAUSED | ``program_paused`` | PAUSED |
| 10 | enabled, robot mode not RUNNING (power button, controller power off) | POWERED_OFF | ``powered_off`` | DISABLED |
| 11 | enabled, control script not PLAYING | FAULT | ``script_stopped`` | FAULT |
| 12 | otherwise | OK | | |

Rows 9-11 apply only while the backend is enabled: a robot powered off, idle or with no script
is simply DISABLED, which is not news. A protective stop needs ``unlock protective stop``, a
violation or safety fault ``restart safety``, an e-stop its button released: ``enable`` does what
can be done from the PC (``UrBackend._fault_reset_steps``) and says what it cannot.
"""

from __future__ import annotations

from typing import NamedTuple

from ...core.actuator import DeviceStatus
from .tables import RobotMode, RuntimeState, SafetyMode


class DeviceState(NamedTuple):
    status: DeviceStatus
    code: str | None  # the cause's stable code (docs/protocol.md); None with OK
    text: str | None  # what happened, for the message


_SAFETY: dict[int, DeviceState] = {
    SafetyMode.PROTECTIVE_STOP: DeviceState(DeviceStatus.FAULT, "protective_stop", "protective stop (a collision or "
                                            "a limit; enable unlocks it)"),
    SafetyMode.SYSTEM_EMERGENCY_STOP: DeviceState(DeviceStatus.FAULT, "emergency_stop", "system emergency stop "
                                                  "(release it, then enable)"),
    SafetyMode.ROBOT_EMERGENCY_STOP: DeviceState(DeviceStatus.FAULT, "emergency_stop", "robot emergency stop "
                                                 "(release the button, then enable)"),
    SafetyMode.VIOLATION: DeviceState(DeviceStatus.FAULT, "safety_fault", "safety violation (enable restarts safety)"),
    SafetyMode.FAULT: DeviceState(DeviceStatus.FAULT, "safety_fault", "safety system fault (enable restarts safety)"),
    SafetyMode.RECOVERY: DeviceState(DeviceStatus.FAULT, "safety_recovery", "safety recovery mode: a joint is "
                                     "outside its safety limits (move it back by hand in teach mode on the pendant)"),
    SafetyMode.VALIDATE_JOINT_ID: DeviceState(DeviceStatus.FAULT, "safety_undefined", "safety mode VALIDATE_JOINT_ID"),
    SafetyMode.UNDEFINED_SAFETY_MODE: DeviceState(DeviceStatus.FAULT, "safety_undefined", "safety mode undefined"),
    SafetyMode.SAFEGUARD_STOP: DeviceState(DeviceStatus.PAUSED, "safeguard_stop", "safeguard stop"),
    SafetyMode.AUTOMATIC_MODE_SAFEGUARD_STOP: DeviceState(DeviceStatus.PAUSED, "safeguard_stop",
                                                          "automatic mode safeguard stop"),
    SafetyMode.SYSTEM_THREE_POSITION_ENABLING_STOP: DeviceState(DeviceStatus.PAUSED, "safeguard_stop",
                                                                "three-position enabling stop"),
}
_OK = DeviceState(DeviceStatus.OK, None, None)
_LINK = DeviceState(DeviceStatus.FAULT, "link_lost", "RTDE link lost")
_NO_CONTROLLER = DeviceState(DeviceStatus.FAULT, "controller_disconnected", "the controller reports no robot "
                             "connected (robot mode NO_CONTROLLER / DISCONNECTED)")
_PROGRAM_PAUSED = DeviceState(DeviceStatus.PAUSED, "program_paused", "the control script was paused")
_POWERED_OFF = DeviceState(DeviceStatus.POWERED_OFF, "powered_off", "the arm was powered off or its brakes engaged")
_SCRIPT_STOPPED = DeviceState(DeviceStatus.FAULT, "script_stopped", "the control script stopped running")


def device_state(link: bool, robot_mode: int, safety_mode: int, runtime_state: int, enabled: bool) -> DeviceState:
    """The table in the module docstring. Pure; allocation-free (returns shared tuples)."""
    if not link:
        return _LINK
    if robot_mode <= RobotMode.DISCONNECTED:
        return _NO_CONTROLLER
    hit = _SAFETY.get(safety_mode)
    if hit is not None:
        return hit
    if enabled:
        if runtime_state in (RuntimeState.PAUSING, RuntimeState.PAUSED):
            return _PROGRAM_PAUSED
        if robot_mode != RobotMode.RUNNING:
            return _POWERED_OFF
        if runtime_state != RuntimeState.PLAYING:
            return _SCRIPT_STOPPED
    return _OK

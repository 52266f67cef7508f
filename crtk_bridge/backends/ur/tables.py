"""Universal Robots controller modes (robot mode, safety mode, runtime state), as data.

Mode values: the RTDE output variables ``robot_mode``, ``safety_mode`` and ``runtime_state``
(UR "Real-Time Data Exchange (RTDE) Guide", e-Series / PolyScope 5; the same values on CB3 from
3.x; ur_rtde 1.6.5 exposes them as ``getRobotMode()`` / ``getSafetyMode()`` / ``getRuntimeState()``).

Data only (the simulated controller, sim/ur_robot.py, uses these too). What they mean for the
CRTK state is :mod:`.state`.
"""

from __future__ import annotations

import enum


class RobotMode(enum.IntEnum):
    """RTDE ``robot_mode``."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5  # powered, brakes engaged
    BACKDRIVE = 6
    RUNNING = 7  # powered, brakes released
    UPDATING_FIRMWARE = 8


class SafetyMode(enum.IntEnum):
    """RTDE ``safety_mode``."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    VALIDATE_JOINT_ID = 10
    UNDEFINED_SAFETY_MODE = 11
    AUTOMATIC_MODE_SAFEGUARD_STOP = 12
    SYSTEM_THREE_POSITION_ENABLING_STOP = 13


class RuntimeState(enum.IntEnum):
    """RTDE ``runtime_state`` (of the program the controller runs: ur_rtde's control script)."""

    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


#: safety modes in which the arm may move on our commands
MOVABLE = frozenset({SafetyMode.NORMAL, SafetyMode.REDUCED})

"""The protocol's vocabulary, in one neutral module: operating states, commands, topics, reply
error codes and event codes (docs/protocol.md), as string enums.

It imports nothing of the project, so every layer may use it: ``core`` (the state machine),
``server`` (the socket protocol) and ``client`` (the library and ``crtk-ctl``) speak the same
words. Members are ``str``: they compare equal to, and encode (JSON, msgpack) as, their value, so
``OperatingState.ENABLED == "ENABLED"``. tests/test_vocabulary.py checks that the error and event
codes here are exactly those docs/protocol.md lists, and that the code uses no other.
"""

from __future__ import annotations

import enum

try:
    from enum import StrEnum
except ImportError:  # Python 3.10
    class StrEnum(str, enum.Enum):  # type: ignore[no-redef]
        def __str__(self) -> str:
            return str(self.value)

#: version of docs/protocol.md; a client refuses a daemon that speaks another
PROTOCOL_VERSION = 2


class OperatingState(StrEnum):
    """CRTK operating states (crtk-spec 3.3)."""
    DISABLED = "DISABLED"
    ENABLED = "ENABLED"
    PAUSED = "PAUSED"
    FAULT = "FAULT"


class StateCommand(StrEnum):
    """Commands of the operating-state machine (crtk-spec 3.3, cisst for home / unhome)."""
    ENABLE = "enable"
    DISABLE = "disable"
    PAUSE = "pause"
    RESUME = "resume"
    HOME = "home"
    UNHOME = "unhome"


class JointCommand(StrEnum):
    """Joint-space motion commands (crtk-spec 4.3)."""
    SERVO_JP = "servo_jp"
    SERVO_JR = "servo_jr"
    SERVO_JV = "servo_jv"
    SERVO_JF = "servo_jf"
    INTERPOLATE_JP = "interpolate_jp"
    INTERPOLATE_JR = "interpolate_jr"
    INTERPOLATE_JV = "interpolate_jv"
    INTERPOLATE_JF = "interpolate_jf"
    MOVE_JP = "move_jp"
    MOVE_JR = "move_jr"
    HOLD = "hold"
    FREE = "free"


class CartesianCommand(StrEnum):
    """Cartesian motion commands (docs/cartesian.md)."""
    SERVO_CP = "servo_cp"
    SERVO_CR = "servo_cr"
    SERVO_CV = "servo_cv"
    SERVO_CF = "servo_cf"
    INTERPOLATE_CP = "interpolate_cp"
    INTERPOLATE_CR = "interpolate_cr"
    INTERPOLATE_CV = "interpolate_cv"
    INTERPOLATE_CF = "interpolate_cf"
    MOVE_CP = "move_cp"
    MOVE_CR = "move_cr"


class SessionCommand(StrEnum):
    """Commands about the session itself, not the robot."""
    LIST = "list"
    SUBSCRIBE = "subscribe"
    UNSUBSCRIBE = "unsubscribe"
    ACQUIRE = "acquire"
    RELEASE = "release"


class MaintenanceCommand(StrEnum):
    """crtk-bridge's own robot-wide commands, not CRTK's (docs/protocol.md, Calibration)."""
    CALIBRATE = "calibrate"


class RecordingCommand(StrEnum):
    """Recording and the black box, served by the front process (docs/recording.md)."""
    RECORD = "record"
    RECORD_STOP = "record_stop"
    BLACKBOX = "blackbox"


class Topic(StrEnum):
    """Queries that can also be streamed (``subscribe``); cartesian ones in :class:`CartesianTopic`."""
    MEASURED_JS = "measured_js"
    SETPOINT_JS = "setpoint_js"
    GOAL_JS = "goal_js"
    OPERATING_STATE = "operating_state"
    PERIOD_STATISTICS = "period_statistics"


class CartesianTopic(StrEnum):
    MEASURED_CP = "measured_cp"
    SETPOINT_CP = "setpoint_cp"
    GOAL_CP = "goal_cp"
    MEASURED_CV = "measured_cv"
    SETPOINT_CV = "setpoint_cv"
    GOAL_CV = "goal_cv"
    MEASURED_CF = "measured_cf"
    SETPOINT_CF = "setpoint_cf"


class ErrorCode(StrEnum):
    """The ``error.code`` of a refused request (docs/protocol.md, Error codes)."""
    BAD_REQUEST = "bad_request"
    UNKNOWN_COMMAND = "unknown_command"
    UNKNOWN_NAMESPACE = "unknown_namespace"
    UNSUPPORTED = "unsupported"
    INVALID_STATE = "invalid_state"
    NOT_HOMED = "not_homed"
    OUT_OF_LIMITS = "out_of_limits"
    STEP_TOO_LARGE = "step_too_large"
    READ_ONLY = "read_only"
    IK_FAILED = "ik_failed"
    FAULT = "fault"
    ABORTED = "aborted"
    INTERNAL = "internal"


class EventKind(StrEnum):
    """The ``event`` of a pushed message."""
    OPERATING_STATE = "operating_state"
    STATUS = "status"
    WARNING = "warning"
    ERROR = "error"


class EventCode(StrEnum):
    """The ``data.code`` of a status, warning or error event (docs/protocol.md, Event codes)."""
    BUS_TIMEOUT = "bus_timeout"
    BUS_CORRUPT = "bus_corrupt"
    PORT_LOST = "port_lost"
    SERVO_ERROR = "servo_error"
    TPDO_MISSING = "tpdo_missing"  # CANopen
    HEARTBEAT_LOST = "heartbeat_lost"  # CANopen
    NMT_STATE = "nmt_state"  # CANopen
    DRIVE_FAULT = "drive_fault"  # CANopen
    BUS_ERROR = "bus_error"  # CANopen
    TRACKING_ERROR = "tracking_error"
    TRAJECTORY_FAILED = "trajectory_failed"
    INVALID_COMMAND = "invalid_command"
    BACKEND_EXCEPTION = "backend_exception"
    INTERNAL = "internal"
    ENABLE_FAILED = "enable_failed"
    PAUSE_FAILED = "pause_failed"
    RESUME_FAILED = "resume_failed"
    HOME_FAILED = "home_failed"
    MODE_SWITCH_FAILED = "mode_switch_failed"  # a Dynamixel operating-mode switch
    DEVICE_POWERED_OFF = "device_powered_off"
    TORQUE_OFF_UNCONFIRMED = "torque_off_unconfirmed"
    DISABLE_FAILED = "disable_failed"
    CONTROL_PROCESS_DIED = "control_process_died"
    REALTIME_UNAVAILABLE = "realtime_unavailable"
    SERVO_TIMEOUT = "servo_timeout"
    CONTROL_RELEASED = "control_released"
    LIMIT_CLIPPED = "limit_clipped"
    DEVICE_PAUSED = "device_paused"
    DEVICE_FAULT = "device_fault"
    STATE_CHANGED = "state_changed"
    TORQUE_OFF_CONFIRMED = "torque_off_confirmed"
    FAULT_CLEARED = "fault_cleared"
    DEVICE_OK = "device_ok"
    DEVICE_WARNING = "device_warning"  # a device's warning it works on through (a gripper's minor fault)
    DEVICE_STATUS = "device_status"  # a device's news of its work (a gripper's grasp)
    SHUTDOWN_PARK = "shutdown_park"
    SHUTDOWN_PARKED = "shutdown_parked"
    SHUTDOWN_TORQUE_OFF = "shutdown_torque_off"
    SHUTDOWN_PARK_TIMEOUT = "shutdown_park_timeout"
    SHUTDOWN_PARK_ABORTED = "shutdown_park_aborted"
    # Universal Robots (backends/ur/tables.py): what the controller reports, as FAULT causes
    LINK_LOST = "link_lost"
    CONTROLLER_DISCONNECTED = "controller_disconnected"
    PROTECTIVE_STOP = "protective_stop"
    EMERGENCY_STOP = "emergency_stop"
    SAFETY_FAULT = "safety_fault"
    SAFETY_RECOVERY = "safety_recovery"
    SAFETY_UNDEFINED = "safety_undefined"
    SCRIPT_STOPPED = "script_stopped"
    MOVE_TIMEOUT = "move_timeout"
    COMMAND_REFUSED = "command_refused"
    COMMAND_FAILED = "command_failed"
    WORKER_DIED = "worker_died"  # the UR backend's ur_rtde worker process died (backends/ur/worker.py)
    WORKER_STALLED = "worker_stalled"  # ...or took no command for a channel's worth
    # Robotiq 2F grippers (backends/robotiq/tables.py)
    GRIPPER_FAULT = "gripper_fault"
    # recording and the black box (recording/recorder.py, docs/recording.md)
    SAMPLES_LOST = "samples_lost"
    RECORDING_FAILED = "recording_failed"
    BLACKBOX_WRITTEN = "blackbox_written"
    BLACKBOX_FAILED = "blackbox_failed"


#: accepted from any session, whoever holds control: a stop is never refused (as on the dVRK)
STOP_COMMANDS = (StateCommand.DISABLE, StateCommand.PAUSE, JointCommand.HOLD)
#: per-namespace joint-state queries and topics
JOINT_TOPICS = (Topic.MEASURED_JS, Topic.SETPOINT_JS, Topic.GOAL_JS)
#: robot-wide queries and topics (sent without ``ns``)
ROBOT_TOPICS = (Topic.OPERATING_STATE, Topic.PERIOD_STATISTICS)
#: a joint's ``unit`` (``list``'s ``units``) -> the units of its position, velocity and effort
JOINT_UNITS = {"rad": ("rad", "rad/s", "N·m"), "m": ("m", "m/s", "N")}

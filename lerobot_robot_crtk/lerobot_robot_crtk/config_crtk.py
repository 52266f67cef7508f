"""The plugin's LeRobot configurations: ``--robot.type=crtk`` and ``--teleop.type=crtk``
(docs/lerobot.md). Registered with draccus when this package is imported, which LeRobot's
plugin discovery does for every installed distribution named ``lerobot_robot_*``."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.cameras import CameraConfig
from lerobot.robots.config import RobotConfig
from lerobot.teleoperators.config import TeleoperatorConfig

from .arm import check_settings


@dataclass
class CrtkDaemonConfig:
    """Which daemon, which of its namespaces, in which units (shared by robot and teleoperator)."""

    # the daemon's Unix socket path; else `robot`'s default socket; else the only daemon running
    socket: str | None = None
    # a robot name: its default socket path, or which robot on the Zenoh network of `zenoh_connect`
    robot: str | None = None
    # a Zenoh endpoint (tcp/127.0.0.1:7447) to reach a daemon on another PC (crtk-client[zenoh])
    zenoh_connect: str | None = None
    # the namespaces whose joints LeRobot sees; empty: all of them (so101: the arm and so101/gripper)
    namespaces: list[str] = field(default_factory=list)
    # "lerobot": LeRobot's own numbers for the same calibration (degrees about the middle of the
    # range or -100..100, the gripper 0..100); "si": radians / metres (any robot)
    units: str = "lerobot"
    # with units=lerobot: body joints in degrees (LeRobot's SO default since 0.4.4); False: -100..100
    # (Koch's default, and SO datasets recorded before 0.4.4)
    use_degrees: bool = True
    # s: connecting, enabling
    timeout_s: float = 5.0


@RobotConfig.register_subclass("crtk")
@dataclass
class CrtkRobotConfig(RobotConfig, CrtkDaemonConfig):
    """A robot served by a crtk-bridge daemon."""

    # "interpolate": each action is a goal the daemon moves to smoothly over one action period at
    # its loop rate (30 Hz actions); "servo": a setpoint followed at once (callers at the loop rate)
    command: str = "interpolate"
    # LeRobot's safety cap: each joint's target stays within this of its measured position (action
    # units); a number for every joint or {joint: cap} (joint names without .pos); None: off
    max_relative_target: float | dict[str, float] | None = None
    # cameras stay in the LeRobot process, as for LeRobot's own robots
    cameras: dict[str, CameraConfig] = field(default_factory=dict)
    # "hold": the arm holds its position, stays ENABLED and control is released (never drops);
    # "disable": torque off (an arm without brakes falls)
    on_disconnect: str = "hold"

    def __post_init__(self):
        super().__post_init__()
        check_settings(self.units, self.command, self.on_disconnect, self.max_relative_target)


@TeleoperatorConfig.register_subclass("crtk")
@dataclass
class CrtkTeleoperatorConfig(TeleoperatorConfig, CrtkDaemonConfig):
    """A leader arm served by its own crtk-bridge daemon, read with torque off (never enabled)."""

    def __post_init__(self):
        check_settings(self.units)

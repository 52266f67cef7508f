"""LeRobot plugin for crtk-bridge (docs/lerobot.md): ``--robot.type=crtk`` (a robot served by a
daemon) and ``--teleop.type=crtk`` (a leader arm served by its own daemon). LeRobot imports this
package by its distribution's name (``lerobot_robot_crtk``) and the import registers both."""

from .arm import ConfigError, CrtkFaultError
from .config_crtk import CrtkRobotConfig, CrtkTeleoperatorConfig
from .crtk import CrtkRobot, CrtkTeleoperator

__all__ = ["ConfigError", "CrtkFaultError", "CrtkRobot", "CrtkRobotConfig", "CrtkTeleoperator",
           "CrtkTeleoperatorConfig"]

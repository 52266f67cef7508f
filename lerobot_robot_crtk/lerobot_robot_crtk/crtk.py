"""``CrtkRobot`` and ``CrtkTeleoperator``: LeRobot's ``Robot`` and ``Teleoperator`` on a
crtk-bridge daemon (docs/lerobot.md). The joints and their units come from the daemon
(:mod:`.arm`); cameras are LeRobot's own, in this process."""

from __future__ import annotations

import logging
from functools import cached_property
from typing import Any

from lerobot.cameras.utils import make_cameras_from_configs
from lerobot.robots.robot import Robot
from lerobot.teleoperators.teleoperator import Teleoperator
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError

from .arm import DaemonArm
from .config_crtk import CrtkRobotConfig, CrtkTeleoperatorConfig

log = logging.getLogger(__name__)


class _OnDaemon:
    """What the robot and the teleoperator share: their arm on the daemon (``self.arm``), its
    joints as the action's features, calibration left to the daemon's profile, and the
    connection guards LeRobot's devices raise."""

    arm: DaemonArm

    def _attach(self, config, role: str) -> None:
        self.config = config
        self.arm = DaemonArm(socket=config.socket, robot=config.robot, zenoh_connect=config.zenoh_connect,
                             namespaces=config.namespaces, units=config.units, use_degrees=config.use_degrees,
                             timeout_s=config.timeout_s,
                             who=f"crtk {role} {config.id or config.robot or ''}".rstrip())

    @cached_property
    def action_features(self) -> dict[str, type]:
        return dict.fromkeys(self.arm.keys(), float)

    @property
    def is_calibrated(self) -> bool:
        return True  # the daemon's profile holds the calibration (crtk-ctl calibrate)

    def configure(self) -> None:
        pass

    def _open(self) -> None:
        if self.arm.is_open:
            raise DeviceAlreadyConnectedError(f"{self} already connected")
        self.arm.open()

    def _connected(self) -> DaemonArm:
        if not self.arm.is_open:
            raise DeviceNotConnectedError(f"{self} is not connected")
        return self.arm


class CrtkRobot(_OnDaemon, Robot):
    """A robot served by a crtk-bridge daemon. ``connect()`` enables it (the user's command);
    ``send_action`` sends goals the daemon interpolates and returns what it sent;
    ``disconnect()`` holds and releases control (``on_disconnect``)."""

    config_class = CrtkRobotConfig
    name = "crtk"

    def __init__(self, config: CrtkRobotConfig):
        super().__init__(config)
        self._attach(config, "robot")
        self.cameras = make_cameras_from_configs(config.cameras)

    @cached_property
    def observation_features(self) -> dict[str, Any]:
        """Known before connect(): the joints from the daemon's ``list`` (one short query)."""
        cams = {name: (cfg.height, cfg.width, 3) for name, cfg in self.config.cameras.items()}
        return {**dict.fromkeys(self.arm.keys(), float), **cams}

    @property
    def is_connected(self) -> bool:
        return self.arm.is_open and all(cam.is_connected for cam in self.cameras.values())

    def calibrate(self) -> None:
        log.info("%s: calibration is the daemon's: crtk-ctl calibrate --profile ... (docs/calibration.md)", self)

    def connect(self, calibrate: bool = True) -> None:
        self._open()
        try:
            self.arm.enable()
            for cam in self.cameras.values():
                cam.connect()
        except BaseException:
            self.arm.release(self.config.on_disconnect)
            self.arm.close()
            raise

    def get_observation(self) -> dict[str, Any]:
        obs: dict[str, Any] = self._connected().read()
        for key, cam in self.cameras.items():
            obs[key] = cam.read_latest() if hasattr(cam, "read_latest") else cam.async_read()
        return obs

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        return self._connected().send(action, self.config.command, self.config.max_relative_target)

    def disconnect(self) -> None:
        self._connected()
        try:
            self.arm.release(self.config.on_disconnect)
        finally:
            self.arm.close()
            for cam in self.cameras.values():
                if cam.is_connected:
                    cam.disconnect()


class CrtkTeleoperator(_OnDaemon, Teleoperator):
    """A leader arm served by its own daemon: ``get_action`` is its measured position, read with
    the robot as it is (DISABLED: torque off, moved by hand). Never enables it."""

    config_class = CrtkTeleoperatorConfig
    name = "crtk"

    def __init__(self, config: CrtkTeleoperatorConfig):
        super().__init__(config)
        self._attach(config, "teleoperator")

    @cached_property
    def feedback_features(self) -> dict[str, type]:
        return {}

    @property
    def is_connected(self) -> bool:
        return self.arm.is_open

    def calibrate(self) -> None:
        pass

    def connect(self, calibrate: bool = True) -> None:
        self._open()

    def get_action(self) -> dict[str, float]:
        return self._connected().read()

    def send_feedback(self, feedback: dict[str, Any]) -> None:
        pass

    def disconnect(self) -> None:
        self._connected()
        self.arm.close()

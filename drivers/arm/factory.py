"""Build the configured arm; the one place that maps a config kind to a driver class."""

from __future__ import annotations

from drivers.arm.base import Arm
from drivers.arm.config import ArmConfig, RobotServerConfig
from drivers.arm.dynamixel import DynamixelArm, ExclusivePortHandler
from drivers.arm.mock import MockArm
from drivers.arm.robot_server import RobotServerArm
from drivers.arm.serial_gcode import SerialGcodeArm
from drivers.arm.serial_line import SerialLine
from drivers.errors import ConfigError


def with_overrides(cfg: ArmConfig, kind: str | None = None, port: str | None = None) -> ArmConfig:
    """The arm config with command-line --arm / --port applied."""
    update = {k: v for k, v in (("kind", kind), ("port", port)) if v is not None}
    return cfg.model_validate({**cfg.model_dump(), **update}) if update else cfg


def make_arm(cfg: ArmConfig, robot_server: RobotServerConfig | None = None) -> Arm:
    """An unconnected arm for the config; use it as `with make_arm(cfg) as arm:`. A robot server
    (kind 'robot-server', set up by `robot_server`) must also be listening: `with arm.serving():`."""
    if cfg.kind == "mock":
        return MockArm(cfg)
    if cfg.kind == "robot-server":
        return RobotServerArm(robot_server or RobotServerConfig())
    if cfg.kind == "sim":
        raise ConfigError(
            "arm.kind 'sim' is the simulated cell's arm: it needs camera.source 'sim'",
            hint="use arm.kind 'mock' to check commands without moving, or 'serial'/'dynamixel'",
        )
    if not cfg.port:
        raise ConfigError(
            f"arm.port is empty but arm.kind is {cfg.kind!r}",
            hint="set arm.port in the config or pass --port; `run-cell ports` lists the serial ports",
        )
    if cfg.kind == "serial":
        return SerialGcodeArm(SerialLine(cfg.port, cfg.serial.baud), cfg.serial)
    return DynamixelArm(ExclusivePortHandler(cfg.port, cfg.dynamixel.latency_timer_ms), cfg.dynamixel)

"""Typed arm errors: each carries the port, the command sent and the device's own reply,
so the one-line message the operator sees says what failed, where, and what to do."""

from __future__ import annotations

from drivers.errors import DeviceError


class ArmError(DeviceError):
    """Base of every arm failure."""


class NoResponse(ArmError):
    """The device did not answer within its timeout (or answered with garbage)."""

    default_hint = "check the arm is powered, the port and baud rate are right (`run-cell ports`)"


class ErrorResponse(ArmError):
    """The device refused a command with its own error code."""

    def __init__(self, message: str, *, code: int | None = None, **kw: str | None) -> None:
        super().__init__(message, **kw)
        self.code = code


class AlarmResponse(ArmError):
    """The device is in alarm: motion stopped and locked until the operator acts."""

    default_hint = "clear the cause, then re-home the arm (`run-cell home`); the driver never unlocks an alarm itself"

    def __init__(self, message: str, *, code: int | None = None, **kw: str | None) -> None:
        super().__init__(message, **kw)
        self.code = code


class HardwareFault(ArmError):
    """A servo reported a hardware error (overload, overheating, ...); torque has been released."""

    default_hint = "remove the load or obstruction, let the servo cool, then power-cycle the arm"


class OutOfReach(ArmError):
    """A target outside the workspace or the joint limits; refused before anything was sent."""

    default_hint = "choose a point inside the arm's workspace (see the arm section of the config)"


class ConnectionLost(ArmError):
    """The port vanished or could not be opened (cable pulled, wrong path, device busy)."""

    default_hint = "check the USB cable and the port path (`run-cell ports`); re-home after reconnecting"


class NotConnected(ArmError):
    """A command was issued before connect() or after disconnect()."""

    default_hint = "call connect() first"


class PositionLost(ArmError):
    """The controller restarted (GRBL's banner mid-run or its position reset across a reconnect,
    a Dynamixel servo's torque found off while the driver had it on): the position the driver
    relied on is void. Every motion is refused until the arm is homed or an operator unlocks it;
    `reply` carries the evidence the restart was detected by."""

    MESSAGE = "controller restarted: position lost; home before moving"
    default_hint = (
        "home the arm (`run-cell home`); only an operator who has checked the arm is where its "
        "controller says may unlock it instead (Arm.unlock)"
    )

    def __init__(self, message: str = MESSAGE, **kw: str | None) -> None:
        super().__init__(message, **kw)


class PickWithdrawn(ArmError):
    """A pick offered to a robot was withdrawn before the robot took it (a stop came first):
    nothing moved."""

    default_hint = "nothing to do: the robot never took the pick"


class RobotSilent(NoResponse):
    """A robot took a pick and reported nothing (PICKED, MISSED, PLACED) within its timeout: where
    the part went is unknown, and the cell faults."""

    default_hint = (
        "check the robot (its program, its gripper) and the table, take away a part it may hold, then Reset; "
        "robot_server.pick_timeout_s sets the wait"
    )


class PickUnknown(ArmError):
    """A command about a pick whose outcome is unknown (its robot went silent): refused."""

    default_hint = "check the robot and the table; where the part went is unknown"

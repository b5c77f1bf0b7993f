"""An arm that moves nothing: it validates every command exactly as the real driver it stands
in for would (same planning code), records it, and tracks where the arm would be."""

from __future__ import annotations

import collections
import logging
import math
from dataclasses import dataclass

from drivers.arm import dynamixel, serial_gcode
from drivers.arm.base import Arm, ArmState, ArmStatus
from drivers.arm.config import ArmConfig
from drivers.arm.errors import NotConnected
from drivers.arm.kinematics import FourAxisKinematics, Pose

COMMANDS_KEPT = 1000  # the commands a stand-in arm remembers, newest last

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MockCommand:
    """One accepted command and what the real driver would have sent for it."""

    name: str
    args: tuple[float | None, ...] = ()  # move_to's x_mm, y_mm, z_mm, angle_deg
    wire: tuple[int | str, ...] = ()  # goal ticks (Dynamixel) or G-code lines


class MockArm(Arm):
    """Stands in for the arm of kind `cfg.mock_of` (for `run-cell --dry-run`)."""

    def __init__(self, cfg: ArmConfig):
        self.cfg = cfg
        self.port = cfg.port or "mock"
        # the last commands accepted, in order (bounded: a dry run may run for days)
        self.commands: collections.deque[MockCommand] = collections.deque(maxlen=COMMANDS_KEPT)
        self._connected = False
        self._gripper_closed: bool | None = None
        self._kin: FourAxisKinematics | None = None
        if cfg.mock_of == "dynamixel":
            self._kin = FourAxisKinematics(cfg.dynamixel)
            q1, q2, q3, q4 = (math.radians(v) for v in cfg.dynamixel.home_joints_deg)
            self._home = self._kin.forward((q1, q2, q3, q4))
        else:
            self._home = Pose(*cfg.serial.home_position_mm, 0.0)
        self._pose = self._home

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self) -> None:
        self._connected = True
        self.commands.append(MockCommand("connect"))

    def disconnect(self) -> None:
        if self._connected:
            self.commands.append(MockCommand("disconnect"))
        self._connected = False

    def _plan(self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None) -> tuple[int | str, ...]:
        if self._kin is not None:
            return tuple(dynamixel.plan_move(self._kin, self.cfg.dynamixel, x_mm, y_mm, z_mm, angle_deg))
        return tuple(serial_gcode.plan_move(self.cfg.serial, x_mm, y_mm, z_mm, angle_deg))

    def check_target(self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None) -> None:
        self._plan(x_mm, y_mm, z_mm, angle_deg)

    def home(self) -> None:
        self._require()
        if self._kin is None and not self.cfg.serial.commands.home:
            self.move_to(*self.cfg.serial.home_position_mm)
            return
        self.commands.append(MockCommand("home"))
        self._pose = self._home

    def move_to(
        self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None, *, wait: bool = True
    ) -> None:
        wire = self._plan(x_mm, y_mm, z_mm, angle_deg)
        self._require()
        self.commands.append(MockCommand("move_to", (x_mm, y_mm, z_mm, angle_deg), wire))
        if self._kin is not None:
            angle = math.degrees(math.atan2(y_mm, x_mm - self.cfg.dynamixel.geometry.yaw_axis_x_mm))
        else:
            angle = self._pose.angle_deg if angle_deg is None else angle_deg
        self._pose = Pose(x_mm, y_mm, z_mm, angle)

    def open_gripper(self) -> None:
        self._require()
        self.commands.append(MockCommand("open_gripper"))
        self._gripper_closed = False

    def close_gripper(self) -> None:
        self._require()
        self.commands.append(MockCommand("close_gripper"))
        self._gripper_closed = True

    def wait_until_idle(self, timeout_s: float | None = None) -> None:
        self._require()

    def stop(self) -> None:
        self.commands.append(MockCommand("stop"))

    def unlock(self) -> None:
        """Recorded and nothing else: a mocked controller never restarts, so its position is
        never lost (the real driver would unlock the way its own unlock() says)."""
        self._require()
        self.commands.append(MockCommand("unlock"))

    def status(self) -> ArmStatus:
        state: ArmState = "idle" if self._connected else "disconnected"
        return ArmStatus(state, self._pose, self._gripper_closed, f"mock of a {self.cfg.mock_of} arm")

    def _require(self) -> None:
        if not self._connected:
            raise NotConnected("the mock arm is not connected", port=self.port)

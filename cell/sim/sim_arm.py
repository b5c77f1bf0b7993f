"""A simulated arm acting on the simulated world: what it grips depends on geometry only.

Moves are instant unless `realtime`; the time a real arm would take (straight-line
distance at a constant tool speed, plus the gripper's open/close time) is added up in
`motion_time_s` so the cell can report it apart from its own software time.
"""

from __future__ import annotations

import collections
import logging
import math
import time

from cell.sim.world import World
from drivers.arm.base import Arm, ArmStatus
from drivers.arm.config import Workspace
from drivers.arm.errors import HardwareFault, NotConnected, OutOfReach
from drivers.arm.kinematics import Pose
from drivers.arm.mock import COMMANDS_KEPT

log = logging.getLogger(__name__)


class SimArm(Arm):
    def __init__(
        self,
        world: World,
        workspace: Workspace,
        home_mm: tuple[float, float, float] = (0.0, 150.0, 120.0),
        speed_mm_s: float = 150.0,
        gripper_s: float = 0.4,
        realtime: bool = False,
    ):
        self.port = "sim"
        self.world = world
        self.workspace = workspace
        self.home_mm = home_mm
        self.speed_mm_s = speed_mm_s
        self.gripper_s = gripper_s
        self.realtime = realtime
        self.motion_time_s = 0.0
        # the last commands accepted, in order (bounded: a rehearsal may run for days)
        self.commands: collections.deque[tuple] = collections.deque(maxlen=COMMANDS_KEPT)
        self.last_grip = ""
        self._connected = False
        self._torque = False
        self._pose = Pose(*home_mm, 0.0)
        self._closed = False

    def connect(self) -> None:
        self._connected = True
        self._torque = True

    def disconnect(self) -> None:
        self._connected = False
        self._torque = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def _need(self, command: str) -> None:
        if not self._connected:
            raise NotConnected(f"{command}: the simulated arm is not connected", port=self.port)
        if not self._torque:
            raise HardwareFault(f"{command}: torque is off", port=self.port)

    def _spend(self, seconds: float) -> None:
        self.motion_time_s += seconds
        if self.realtime:
            time.sleep(seconds)

    def home(self) -> None:
        self._need("home")
        self.move_to(*self.home_mm, 0.0)
        self.commands.append(("home",))

    def check_target(self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None) -> None:
        if why := self.workspace.violation(x_mm, y_mm, z_mm):
            raise OutOfReach(f"target ({x_mm:.1f}, {y_mm:.1f}, {z_mm:.1f}) mm refused: {why}", port=self.port)

    def move_to(
        self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None, *, wait: bool = True
    ) -> None:
        self._need("move_to")
        self.check_target(x_mm, y_mm, z_mm, angle_deg)
        table_z = self.world.truth.table_z_mm
        if z_mm < table_z - 0.5:
            self._torque = False
            raise HardwareFault(
                f"tool driven {table_z - z_mm:.1f} mm into the table at z = {z_mm:.1f} mm; torque released",
                port=self.port,
            )
        p = self._pose
        self._spend(math.dist((p.x_mm, p.y_mm, p.z_mm), (x_mm, y_mm, z_mm)) / self.speed_mm_s)
        self._pose = Pose(x_mm, y_mm, z_mm, p.angle_deg if angle_deg is None else angle_deg)
        self.commands.append(("move_to", x_mm, y_mm, z_mm, angle_deg))

    def open_gripper(self) -> None:
        self._need("open_gripper")
        self._spend(self.gripper_s)
        self._closed = False
        p = self._pose
        self.last_grip = self.world.release((p.x_mm, p.y_mm, p.z_mm))
        self.commands.append(("open_gripper",))

    def close_gripper(self) -> None:
        self._need("close_gripper")
        self._spend(self.gripper_s)
        self._closed = True
        p = self._pose
        self.last_grip = self.world.grip((p.x_mm, p.y_mm, p.z_mm), p.angle_deg).reason
        log.debug("sim grip: %s", self.last_grip)
        self.commands.append(("close_gripper",))

    def wait_until_idle(self, timeout_s: float | None = None) -> None:
        self._need("wait_until_idle")

    def stop(self) -> None:
        self._torque = False

    def unlock(self) -> None:
        """Recorded and nothing else: the simulated arm has no controller to restart, and its
        pose is the world's truth; a torque released by a fault stays released (as a real
        servo's hardware error needs more than an unlock)."""
        if not self._connected:
            raise NotConnected("unlock: the simulated arm is not connected", port=self.port)
        self.commands.append(("unlock",))

    def status(self) -> ArmStatus:
        if not self._connected:
            return ArmStatus("disconnected", None, None)
        return ArmStatus("idle" if self._torque else "fault", self._pose, self._closed)

"""The one set of test doubles above the driver layer: a fake table, camera, arm and locator.

The fake arm removes a part from the fake table when it closes within 1 mm of it (mapped
back through the true offset), so misses come from geometry as in the simulated cell.
Drivers themselves are tested against emulated firmware on a pty, never against these.
"""

from __future__ import annotations

import math

import numpy as np

from cell.errors import CellError
from cell.planning import TableToRobot
from cell.run_config import PlanningConfig
from cell.vision.types import LocatedPart, LocateResult
from drivers.arm.base import Arm, ArmStatus
from drivers.arm.errors import HardwareFault
from drivers.arm.kinematics import Pose
from drivers.cameras.base import Camera

PLANNING = PlanningConfig()
TRUE_FRAME = TableToRobot.from_offset(PLANNING)


class FakeTable:
    def __init__(self, parts):
        self.parts = dict(enumerate(parts, start=1))  # id -> (cls, x, y, angle)
        self.bins: list[int] = []
        self.held: int | None = None


class FakeCamera(Camera):
    def __init__(self, fail_at: int | None = None):
        self.source, self.width_px, self.height_px = "fake", 64, 48
        self.connected, self.frames, self.fail_at = False, 0, fail_at

    def connect(self):
        self.connected = True

    def disconnect(self):
        self.connected = False

    @property
    def is_connected(self):
        return self.connected

    def _grab(self):
        self.frames += 1
        if self.frames == self.fail_at:
            return None
        return np.zeros((48, 64, 3), np.uint8)


class FakeArm(Arm):
    """Records calls; `fail` maps a method name to the call number (1-based) that raises;
    `restart` to the call number during which the controller restarts: it raises PositionLost,
    and every motion after it is refused (not recorded) until home() or unlock(), as the real
    drivers do."""

    MOTION = ("move_to", "open_gripper", "close_gripper", "wait_until_idle")

    def __init__(
        self, table: FakeTable, truth: TableToRobot = TRUE_FRAME, fail: dict | None = None, restart: dict | None = None
    ):
        self.port, self.table, self.truth = "fake", table, truth
        self.calls: list[tuple] = []
        self.fail = fail or {}
        self.restart = restart or {}
        self.pose = Pose(0.0, 150.0, 100.0, 0.0)
        self.connected = False

    def _record(self, name, *args):
        if name in self.MOTION:
            self._refuse_while_position_lost(name)
        self.calls.append((name, *args))
        n = sum(c[0] == name for c in self.calls)
        if self.fail.get(name) == n:
            raise HardwareFault(f"{name} failed (injected)", port=self.port)
        if self.restart.get(name) == n:
            raise self._restarted("injected restart", name)

    def connect(self):
        self._record("connect")
        self.connected = True

    def disconnect(self):
        self.calls.append(("disconnect",))
        self.connected = False

    @property
    def is_connected(self):
        return self.connected

    def home(self):
        self._record("home")
        self._position_regained("homed")

    def unlock(self):
        self._record("unlock")
        self._position_regained("unlocked")

    def check_target(self, x_mm, y_mm, z_mm, angle_deg=None):
        pass

    def move_to(self, x_mm, y_mm, z_mm, angle_deg=None, *, wait=True):
        self._record("move_to", x_mm, y_mm, z_mm)
        self.pose = Pose(x_mm, y_mm, z_mm, angle_deg or 0.0)

    def open_gripper(self):
        self._record("open_gripper")
        if self.table.held is not None:
            self.table.bins.append(self.table.held)
            self.table.held = None

    def close_gripper(self):
        self._record("close_gripper")
        tx, ty = self.truth.to_table([self.pose.x_mm, self.pose.y_mm])[0]
        for pid, (_cls, x, y, _) in list(self.table.parts.items()):
            if math.hypot(x - tx, y - ty) <= 1.0:
                self.table.held = pid
                del self.table.parts[pid]
                return

    def wait_until_idle(self, timeout_s=None):
        self._record("wait_until_idle")

    def stop(self):
        self.calls.append(("stop",))

    def status(self):
        self._record("status")
        return ArmStatus("idle", self.pose, None)


def fake_locator(table: FakeTable, fail_at: int | None = None):
    calls = {"n": 0}

    def locate(frame):
        calls["n"] += 1
        if calls["n"] == fail_at:
            raise CellError("locate failed (injected)")
        objs = [
            LocatedPart(i, cls, "fake", (0.0, 0.0), (x, y), angle if cls == "bolt" else None, cls != "unknown")
            for i, (pid, (cls, x, y, angle)) in enumerate(table.parts.items(), start=1)
        ]
        return LocateResult(objs, (64, 48), 0.1)

    return locate

"""Where the gripper goes for a located part: table mm -> robot mm, per-class heights, jaw
angle and bin, pick order, and the workspace/reach check made before any motion.

Jaw angle convention: the direction in which the jaws close, degrees counter-clockwise
from the robot's +X, in [-90, 90) (a parallel gripper is symmetric under 180 degrees).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from cell.calibration.store import write_json_atomic
from cell.errors import CellError, InputError
from cell.run_config import ClassPlan, PlanningConfig, RobotWorkspace
from cell.vision.types import LocatedPart

SCHEMA = "pick-cell/robot-frame"
BUILT_IN_CLASS_NO = {"bolt": 1, "nut": 2}  # the class_no a robot program is told (docs/robots.md)


class TeachRejected(CellError):
    """A taught table -> robot fit is worse than the configured limit."""


@dataclass(frozen=True)
class TableToRobot:
    """robot_xy = scale * R(rotation) @ table_xy + (tx, ty); robot z of the table surface."""

    rotation_deg: float
    tx_mm: float
    ty_mm: float
    table_z_mm: float
    scale: float = 1.0

    @classmethod
    def from_offset(cls, cfg: PlanningConfig) -> TableToRobot:
        return cls(0.0, cfg.offset_x_mm, cfg.offset_y_mm, cfg.table_z_mm)

    def _matrix(self) -> np.ndarray:
        a = math.radians(self.rotation_deg)
        return self.scale * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])

    def to_robot(self, table_xy_mm: npt.ArrayLike) -> np.ndarray:
        xy = np.asarray(table_xy_mm, dtype=np.float64).reshape(-1, 2)
        return xy @ self._matrix().T + (self.tx_mm, self.ty_mm)

    def to_table(self, robot_xy_mm: npt.ArrayLike) -> np.ndarray:
        xy = np.asarray(robot_xy_mm, dtype=np.float64).reshape(-1, 2)
        return (xy - (self.tx_mm, self.ty_mm)) @ np.linalg.inv(self._matrix()).T

    def angle_to_robot(self, table_angle_deg: float) -> float:
        return wrap_jaw_deg(table_angle_deg + self.rotation_deg)

    def to_dict(self) -> dict[str, float]:
        return {
            "rotation_deg": self.rotation_deg,
            "tx_mm": self.tx_mm,
            "ty_mm": self.ty_mm,
            "table_z_mm": self.table_z_mm,
            "scale": self.scale,
        }


def wrap_jaw_deg(angle_deg: float) -> float:
    return (angle_deg + 90.0) % 180.0 - 90.0


def fit_table_to_robot(
    table_mm: np.ndarray, robot_mm: np.ndarray, table_z_mm: float, with_scale: bool = False
) -> tuple[TableToRobot, np.ndarray]:
    """Least-squares rigid (or similarity) fit from >= 3 point pairs; residuals in mm per point.

    Umeyama's closed form: rotation from the SVD of the cross-covariance, reflection excluded.
    """
    P = np.asarray(table_mm, dtype=np.float64).reshape(-1, 2)
    Q = np.asarray(robot_mm, dtype=np.float64).reshape(-1, 2)
    if len(P) < 3 or len(P) != len(Q):
        raise InputError(f"a robot-frame fit needs 3 or more point pairs, got {len(P)}")
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    Pc, Qc = P - mp, Q - mq
    U, S, Vt = np.linalg.svd(Qc.T @ Pc)
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    D = np.diag([1.0, d])
    R = U @ D @ Vt
    scale = float(np.trace(np.diag(S) @ D) / (Pc**2).sum()) if with_scale else 1.0
    t = mq - scale * R @ mp
    fit = TableToRobot(math.degrees(math.atan2(R[1, 0], R[0, 0])), float(t[0]), float(t[1]), table_z_mm, scale)
    residuals = np.hypot(*(fit.to_robot(P) - Q).T)
    return fit, residuals


def save_taught(path: Path, fit: TableToRobot, points: list[dict[str, Any]], residuals: np.ndarray) -> None:
    write_json_atomic(
        path,
        {"schema": SCHEMA, "transform": fit.to_dict(), "points": points, "residuals_mm": [float(r) for r in residuals]},
    )


def load_taught(path: Path) -> TableToRobot:
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: taught robot frame not found", hint="run `run-cell teach` first") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{path}: cannot read taught robot frame: {e}") from None
    if not isinstance(data, dict) or data.get("schema") != SCHEMA:
        raise InputError(f"{path}: not a taught robot frame (schema is not {SCHEMA!r})")
    try:
        return TableToRobot(**{k: float(v) for k, v in data["transform"].items()})
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{path}: corrupt taught robot frame ({type(e).__name__}: {e})") from None


def table_to_robot(cfg: PlanningConfig) -> TableToRobot:
    return load_taught(cfg.taught_path) if cfg.frame == "taught" else TableToRobot.from_offset(cfg)


class Unreachable(Exception):
    """A target the planner refuses before any motion; the part is marked unreachable."""


@dataclass(frozen=True)
class Target:
    """Everything the runner needs to pick one part and drop it in its bin (robot mm)."""

    part_id: int
    cls: str
    table_mm: tuple[float, float]
    robot_mm: tuple[float, float, float]  # where the jaws close
    approach_z_mm: float
    jaw_angle_deg: float | None
    bin_robot_mm: tuple[float, float, float]
    pixel: tuple[float, float] = (math.nan, math.nan)  # where the part was seen in the frame
    class_no: int = 0  # the number a robot program switches on (the recipe's; 0: none)

    def pick_points(self) -> list[tuple[float, float, float]]:
        """Above the part, then down to it: the moves that turn the jaws to jaw_angle_deg."""
        x, y, z = self.robot_mm
        return [(x, y, self.approach_z_mm), (x, y, z)]

    def place_points(self) -> list[tuple[float, float, float]]:
        """Above the bin, then down to it: these moves leave the jaws as they are (no angle)."""
        bx, by, bz = self.bin_robot_mm
        return [(bx, by, max(bz, self.approach_z_mm)), (bx, by, bz)]

    def waypoints(self) -> list[tuple[float, float, float]]:
        return self.pick_points() + self.place_points()


class Planner:
    """Turns located parts into targets; every point of the move is checked before motion."""

    def __init__(
        self,
        cfg: PlanningConfig,
        frame: TableToRobot,
        taught: Mapping[str, ClassPlan] | None = None,
        class_numbers: Mapping[str, int] | None = None,
    ):
        self.cfg = cfg
        self.frame = frame
        self.taught = dict(taught or {})  # a recipe's taught types with a bin: jaws along the model's grip
        # each class's class_no (a recipe's Recipe.class_numbers()); without a recipe: bolt 1, nut 2
        self.class_numbers = dict(BUILT_IN_CLASS_NO if class_numbers is None else class_numbers)

    def target(self, part: LocatedPart) -> Target:
        if part.cls in self.taught:
            return self._taught(part)
        if part.cls not in ("bolt", "nut"):
            raise Unreachable(f"class {part.cls!r} is not picked")
        plan = self.cfg.for_class(part.cls)
        table_xy = part.grasp_mm or part.table_mm
        if not all(math.isfinite(v) for v in (*table_xy, *(() if part.angle_deg is None else (part.angle_deg,)))):
            raise Unreachable(
                f"part at table {tuple(table_xy)} mm, angle {part.angle_deg} deg: not a finite number (calibration?)"
            )
        angle = None
        if plan.jaw_across_axis:
            if part.angle_deg is None:
                raise Unreachable("no axis angle to put the jaws across")
            angle = self.frame.angle_to_robot(part.angle_deg + 90.0)
        return self._checked(part, plan, (float(table_xy[0]), float(table_xy[1])), angle)

    def _taught(self, part: LocatedPart) -> Target:
        """A taught type: the jaws close at the model's grip point, along its grip direction turned
        by the angle the part was found at (cell.vision.shapes.ShapeModel.grip_on_table)."""
        plan = self.taught[part.cls]
        jaw = part.features.get("jaw_angle_deg")
        if part.grasp_mm is None or jaw is None:
            raise Unreachable(f"taught type {part.cls!r} found without its grip (no grasp point or jaw angle)")
        if not all(math.isfinite(v) for v in (*part.grasp_mm, float(jaw))):
            raise Unreachable(f"grip at table {part.grasp_mm} mm, jaws {jaw} deg: not a finite number (calibration?)")
        return self._checked(part, plan, part.grasp_mm, self.frame.angle_to_robot(float(jaw)))

    def _checked(
        self, part: LocatedPart, plan: ClassPlan, table_xy: tuple[float, float], angle: float | None
    ) -> Target:
        rx, ry = self.frame.to_robot(table_xy)[0]
        z = self.frame.table_z_mm
        t = Target(
            part.id,
            part.cls,
            (float(table_xy[0]), float(table_xy[1])),
            (float(rx), float(ry), z + plan.pick_above_table_mm),
            z + plan.approach_above_table_mm,
            angle,
            plan.bin_robot_mm,
            (float(part.pixel[0]), float(part.pixel[1])),
            self.class_numbers.get(part.cls, 0),
        )
        if not all(math.isfinite(v) for v in (*t.robot_mm, t.approach_z_mm, *(() if angle is None else (angle,)))):
            raise Unreachable(f"target {t.robot_mm} mm, jaws {angle} deg: not a finite number (calibration?)")
        for point in t.waypoints():
            if why := self.violation(*point):
                raise Unreachable(why)
        return t

    def bin_problems(self) -> list[str]:
        """Why a class's bin cannot be reached (checked once, before the first move)."""
        out = []
        for cls in ("bolt", "nut"):
            if why := self.violation(*self.cfg.for_class(cls).bin_robot_mm):
                out.append(f"planning.{cls}.bin_robot_mm: {why}")
        for name, plan in self.taught.items():
            if why := self.violation(*plan.bin_robot_mm):
                out.append(f"recipe types.{name}.bin_robot_mm: {why}")
        return out

    def violation(self, x_mm: float, y_mm: float, z_mm: float) -> str | None:
        """Why the point lies outside the configured workspace or reach, or None."""
        return workspace_violation(self.cfg.workspace, x_mm, y_mm, z_mm)

    def order(self, parts: list[LocatedPart], gripper_robot_xy: tuple[float, float] | None) -> list[LocatedPart]:
        """Candidates in the configured pick order."""
        if self.cfg.pick_order == "as-found" or not parts:
            return list(parts)
        if self.cfg.pick_order == "rows":
            return sorted(parts, key=lambda p: (round(p.table_mm[1], 1), p.table_mm[0]))
        here = np.asarray(gripper_robot_xy if gripper_robot_xy is not None else (0.0, 0.0))
        robot = self.frame.to_robot([p.table_mm for p in parts])
        dist = np.hypot(*(robot - here).T)
        return [parts[i] for i in np.argsort(dist, kind="stable")]


def workspace_violation(ws: RobotWorkspace, x_mm: float, y_mm: float, z_mm: float) -> str | None:
    """Why the point lies outside the workspace box or the reach ring, or None."""
    for axis, v in zip("xyz", (x_mm, y_mm, z_mm), strict=True):
        lo, hi = getattr(ws, f"{axis}_min_mm"), getattr(ws, f"{axis}_max_mm")
        if not (math.isfinite(v) and lo <= v <= hi):
            return f"robot {axis} = {v:.1f} mm is outside the workspace [{lo:g}, {hi:g}] mm"
    r = math.hypot(x_mm, y_mm)
    if not ws.reach_min_mm <= r <= ws.reach_max_mm:
        return f"radius {r:.1f} mm is outside the reach [{ws.reach_min_mm:g}, {ws.reach_max_mm:g}] mm"
    return None

"""The simulated table: which parts lie where, which one the gripper holds, what the bins hold.

The world knows the TRUE robot <-> table transform; the cell only knows its configured
one. A grip is judged in the table frame after mapping the commanded tool point through
the truth, so a wrong offset or calibration shows up as a miss, as it would on the line.

Jaw tolerances (defaults in SimConfig, for a parallel gripper opened 3 mm wider than the
part): along the closing direction the jaws centre the part as long as each jaw lands
beside it, not on it: +-1.5 mm. Along the jaw faces a nut or washer must sit under the
pads' middle: +-1.0 mm. A bolt is held wherever the jaws close on its body, at least
2 mm from either end, but only with the jaws across the axis within 5 degrees. A flat part
of any shape (a taught type's ExtrudedPart) is held when its material lies between the jaw
faces and is centred between the jaws within the tolerance across.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from cell.sim.parts import ExtrudedPart, PartSpec


@dataclass(frozen=True)
class Truth:
    """robot_xy = R(rotation) @ table_xy + (tx, ty); robot z of the table surface."""

    rotation_deg: float
    tx_mm: float
    ty_mm: float
    table_z_mm: float

    def robot_to_table(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        a = math.radians(self.rotation_deg)
        dx, dy = x_mm - self.tx_mm, y_mm - self.ty_mm
        return (math.cos(a) * dx + math.sin(a) * dy, -math.sin(a) * dx + math.cos(a) * dy)


@dataclass(frozen=True)
class JawTolerance:
    across_mm: float = 1.5
    along_mm: float = 1.0
    bolt_end_margin_mm: float = 2.0
    bolt_angle_deg: float = 5.0
    jaw_face_mm: float = 8.0  # how wide the jaw faces are (a taught part is held across that band)
    jaw_max_opening_mm: float = 30.0  # how far the jaws open: a part wider than that across them is not held


@dataclass(frozen=True)
class Bin:
    name: str
    robot_xy_mm: tuple[float, float]
    half_size_mm: float


@dataclass
class SimPart:
    id: int
    spec: PartSpec | ExtrudedPart
    where: str = "table"  # 'table', 'gripper', 'bin:<name>' or 'floor'


@dataclass(frozen=True)
class GripResult:
    part: SimPart | None
    reason: str


def _extent_mm(spec: PartSpec | ExtrudedPart) -> float:
    """Farthest point of the part's outline from its footprint centre."""
    outline = spec.top_view_outline_mm()
    return max(math.hypot(x - spec.x_mm, y - spec.y_mm) for x, y in outline)


class World:
    def __init__(
        self,
        parts: Sequence[PartSpec | ExtrudedPart],
        truth: Truth,
        bins: list[Bin],
        tolerance: JawTolerance = JawTolerance(),
    ):
        self.parts = [SimPart(i + 1, p) for i, p in enumerate(parts)]
        self.truth = truth
        self.bins = bins
        self.tolerance = tolerance
        self.version = 0  # bumped whenever what the camera sees changes

    def on_table(self) -> list[SimPart]:
        return [p for p in self.parts if p.where == "table"]

    def held(self) -> SimPart | None:
        return next((p for p in self.parts if p.where == "gripper"), None)

    def in_bin(self, name: str) -> list[SimPart]:
        return [p for p in self.parts if p.where == f"bin:{name}"]

    def grip(self, robot_xyz: tuple[float, float, float], jaw_angle_deg: float) -> GripResult:
        """Close the jaws at a robot-frame tool point; the best-placed part within tolerance is held."""
        tx, ty = self.truth.robot_to_table(robot_xyz[0], robot_xyz[1])
        height = robot_xyz[2] - self.truth.table_z_mm
        jaw_table_deg = jaw_angle_deg - self.truth.rotation_deg
        nearest, nearest_d = None, math.inf
        for part in self.on_table():
            d = math.hypot(part.spec.x_mm - tx, part.spec.y_mm - ty)
            if d < nearest_d and d <= _extent_mm(part.spec) + 2.0:
                nearest, nearest_d = part, d
        if nearest is None:
            return GripResult(None, "no part between the jaws")
        ok, why = self._holds(nearest.spec, tx, ty, height, jaw_table_deg)
        if not ok:
            return GripResult(None, f"part {nearest.id} ({nearest.spec.kind}) missed: {why}")
        nearest.where = "gripper"
        self.version += 1
        return GripResult(nearest, f"part {nearest.id} ({nearest.spec.kind}) held")

    def _holds(
        self, spec: PartSpec | ExtrudedPart, x: float, y: float, height: float, jaw_deg: float
    ) -> tuple[bool, str]:
        if height >= spec.height_mm - 0.5:
            return False, f"jaws at {height:.1f} mm close above the part ({spec.height_mm:.1f} mm high)"
        c = math.cos(math.radians(jaw_deg)), math.sin(math.radians(jaw_deg))
        ex, ey = x - spec.x_mm, y - spec.y_mm
        across = ex * c[0] + ey * c[1]  # along the closing direction
        along = -ex * c[1] + ey * c[0]  # along the jaw faces
        tol = self.tolerance
        if isinstance(spec, ExtrudedPart):
            return self._holds_extruded(spec, x, y, c)
        if spec.kind == "bolt":
            axis = spec.axis_angle_deg
            assert axis is not None  # a bolt's
            angle_err = abs((jaw_deg - (axis + 90.0) + 90.0) % 180.0 - 90.0)
            if angle_err > tol.bolt_angle_deg:
                return False, f"jaws {angle_err:.1f} deg off across the axis (tolerance {tol.bolt_angle_deg:g})"
            if abs(across) > tol.across_mm:
                return False, f"{across:+.2f} mm off the axis (tolerance {tol.across_mm:g})"
            d = math.cos(math.radians(spec.angle_deg)), math.sin(math.radians(spec.angle_deg))
            u = ex * d[0] + ey * d[1]  # along the axis, head -> tip, from the footprint centre
            head_end = spec._bolt_axis_offset_mm() - spec.dims["head_height"]
            tip_end = spec._bolt_axis_offset_mm() + spec.shaft_length_mm
            if not head_end + tol.bolt_end_margin_mm <= u <= tip_end - tol.bolt_end_margin_mm:
                return False, (
                    f"jaws {u:+.1f} mm along the axis, off the body "
                    f"[{head_end:+.1f}, {tip_end:+.1f}] mm less {tol.bolt_end_margin_mm:g} mm at each end"
                )
            return True, ""
        if abs(across) > tol.across_mm:
            return False, f"{across:+.2f} mm off across the jaws (tolerance {tol.across_mm:g})"
        if abs(along) > tol.along_mm:
            return False, f"{along:+.2f} mm off along the jaws (tolerance {tol.along_mm:g})"
        return True, ""

    def _holds_extruded(self, spec: ExtrudedPart, x: float, y: float, c: tuple[float, float]) -> tuple[bool, str]:
        """A flat part of any shape: the jaws, `jaw_face_mm` wide, closing along `c` about (x, y), hold
        it when its material lies in their band and is centred between them (within the tolerance
        across): what they close on is the extent of its outline inside the band."""
        polys = [spec.top_view_outline_mm(), *(spec.to_table(h) for h in spec.holes_mm)]
        dense = []
        for poly in polys:
            q = np.roll(poly, -1, axis=0)
            n = np.maximum(1, np.ceil(np.hypot(*(q - poly).T) / 0.2)).astype(int)
            for p0, p1, k in zip(poly, q, n, strict=True):
                dense.append(p0 + (np.arange(k)[:, None] / k) * (p1 - p0))
        pts = np.vstack(dense) - (x, y)
        u = pts @ np.array(c)
        v = pts @ np.array((-c[1], c[0]))
        band = np.abs(v) <= self.tolerance.jaw_face_mm / 2
        if not band.any():
            return False, "no material between the jaw faces"
        lo, hi = float(u[band].min()), float(u[band].max())
        if hi - lo > self.tolerance.jaw_max_opening_mm:
            return False, f"{hi - lo:.1f} mm wide across the jaws, which open {self.tolerance.jaw_max_opening_mm:g} mm"
        mid = (lo + hi) / 2
        if abs(mid) > self.tolerance.across_mm:
            return False, f"{mid:+.2f} mm off centre between the jaws (tolerance {self.tolerance.across_mm:g})"
        return True, ""

    def release(self, robot_xyz: tuple[float, float, float]) -> str:
        """Open the jaws: a held part drops into the bin below, else onto the table there."""
        part = self.held()
        if part is None:
            return "nothing held"
        for b in self.bins:
            if max(abs(robot_xyz[0] - b.robot_xy_mm[0]), abs(robot_xyz[1] - b.robot_xy_mm[1])) <= b.half_size_mm:
                part.where = f"bin:{b.name}"
                self.version += 1
                return f"part {part.id} dropped into bin {b.name}"
        tx, ty = self.truth.robot_to_table(robot_xyz[0], robot_xyz[1])
        part.spec = replace(part.spec, x_mm=float(tx), y_mm=float(ty))
        part.where = "table"
        self.version += 1
        return f"part {part.id} dropped on the table at ({tx:.1f}, {ty:.1f}) mm"

    def table_specs(self) -> list[tuple[int, PartSpec | ExtrudedPart]]:
        return [(p.id, p.spec) for p in self.on_table()]

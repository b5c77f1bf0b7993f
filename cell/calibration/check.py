"""Checking a calibration without refitting it: a fresh image of the plate, lying where it lay
when the cell was calibrated (in its fixture), is mapped through the calibration in use, and
every circle should land on its own table position. This is the touch-up check a cell runs
at the start of a shift: a bumped camera, a knocked fixture or a refocused lens shows up as
an error here, before it shows up as missed picks.

The error is also given after the best rigid motion of the plate is taken out: if that is
small while the plain error is large, the mapping still holds and the plate (or the camera)
has moved as a whole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cell.calibration.pipeline import PlatePoints, find_points, find_points_paper
from cell.calibration.store import Calibration
from cell.config import CellConfig
from cell.errors import InputError
from cell.wording import plural


@dataclass
class CheckResult:
    points: PlatePoints
    mapped_mm: np.ndarray  # (N, 2) each circle's pixel mapped through the calibration
    error_mm: np.ndarray  # (N, 2) table position - mapped (the Table III sign)
    rigid_error_mm: np.ndarray  # (N,) distance left after the best rigid motion of the plate
    limit_mm: float

    @property
    def distance_mm(self) -> np.ndarray:
        return np.hypot(self.error_mm[:, 0], self.error_mm[:, 1])

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.distance_mm**2)))

    @property
    def max_mm(self) -> float:
        return float(self.distance_mm.max())

    @property
    def passed(self) -> bool:
        return self.max_mm <= self.limit_mm


def check_calibration(image: np.ndarray, calibration: Calibration, config: CellConfig) -> CheckResult:
    """Map the plate's circles in `image` through `calibration`; the errors against the plate."""
    h, w = image.shape[:2]
    if (w, h) != tuple(calibration.image_size):
        cw, ch = calibration.image_size
        raise InputError(f"plate image is {w} x {h} px but the calibration was made at {cw} x {ch} px")
    _same_plate(calibration, config)
    pts = find_points_paper(image, config) if config.detection.preset == "paper" else find_points(image, config)
    mapped = calibration.pixel_to_table_mm(pts.pixel)
    error = pts.table_mm - mapped
    return CheckResult(pts, mapped, error, _rigid_residual(mapped, pts.table_mm), config.calibration.check_max_mm)


def _same_plate(calibration: Calibration, config: CellConfig) -> None:
    """The config's plate must be the one the calibration was made with, or every number is off."""
    plate, pattern = config.plate, calibration.pattern
    for key in ("columns", "rows", "pitch_x_mm", "pitch_y_mm"):
        if key in pattern and float(pattern[key]) != float(getattr(plate, key)):
            raise InputError(
                f"the calibration was made with plate.{key} = {pattern[key]}, the config says {getattr(plate, key)}",
                hint="check with the config the calibration was made with",
            )


def _rigid_residual(mapped: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Distances left after the least-squares rotation + translation of `mapped` onto `truth`."""
    a, b = mapped - mapped.mean(axis=0), truth - truth.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    r = (u @ vt).T
    if np.linalg.det(r) < 0:
        vt[-1] *= -1
        r = (u @ vt).T
    moved = a @ r.T + truth.mean(axis=0)
    return np.hypot(*(truth - moved).T)


def check_text(result: CheckResult, source: str) -> str:
    """The operator's report: every point, then the totals and the verdict."""
    pts = result.points
    lines = [
        f"calibration check on {source}: {plural(len(pts.number), 'circle')} measured"
        + (f", missing: {pts.missing}" if pts.missing else ""),
        f"{'point':>5}{'X mm':>9}{'Y mm':>9}{'X mapped':>11}{'Y mapped':>11}{'dX':>9}{'dY':>9}{'error':>9}",
    ]
    for num, t, m, e, d in zip(
        pts.number, pts.table_mm, result.mapped_mm, result.error_mm, result.distance_mm, strict=True
    ):
        lines.append(
            f"{int(num):>5}{t[0]:>9.1f}{t[1]:>9.1f}{m[0]:>11.4f}{m[1]:>11.4f}{e[0]:>9.4f}{e[1]:>9.4f}{d:>9.4f}"
        )
    mean = result.error_mm.mean(axis=0)
    lines += [
        "",
        f"error: RMS {result.rms_mm:.4f} mm, max {result.max_mm:.4f} mm, "
        f"mean shift dX {mean[0]:+.4f} dY {mean[1]:+.4f} mm",
        f"after the best rigid motion of the plate: RMS {np.sqrt(np.mean(result.rigid_error_mm**2)):.4f} mm, "
        f"max {result.rigid_error_mm.max():.4f} mm",
        ("PASS" if result.passed else "FAIL")
        + f": max error {result.max_mm:.4f} mm "
        + ("<=" if result.passed else ">")
        + f" calibration.check_max_mm {result.limit_mm} mm"
        + ("" if result.passed else "; recalibrate (run-cell recalibrate), or check the camera and the plate fixture"),
    ]
    return "\n".join(lines)

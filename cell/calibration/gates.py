"""Plausibility gates on a new calibration, before it may replace the active one.

A fit can be excellent and still wrong: a plate printed at 20 mm pitch but configured as
22 mm is fitted to within microns by a polynomial, which simply learns the wrong scale.
Physics catches it: the camera model (square pixels, a real lens) cannot bend that way,
so it fits far worse than the best model and lands the camera metres above the table.
Against the active calibration, a large jump in scale or origin is either a moved camera
(the operator says so with --accept-change) or a wrong plate.
"""

from __future__ import annotations

import math

import numpy as np

from cell.calibration.pipeline import CalibrationResult
from cell.calibration.store import Calibration
from cell.config import CalibrationConfig, PlateConfig


def plausibility_problems(result: CalibrationResult, limits: CalibrationConfig, plate: PlateConfig) -> list[str]:
    """What makes the fit physically implausible (empty: nothing)."""
    problems = []
    best = min(s.cv.rms_mm for s in result.scores)
    camera = next((s for s in result.scores if s.name == "camera"), None)
    if camera is not None:
        worst_allowed = max(limits.max_camera_model_ratio * best, best + limits.max_camera_model_excess_mm)
        if camera.cv.rms_mm > worst_allowed:
            problems.append(
                f"the physical camera model fits {camera.cv.rms_mm:.3f} mm RMS (cross-validated) against the best "
                f"model's {best:.4f} mm: the plate's geometry does not agree with the config (plate.pitch_x_mm "
                f"{plate.pitch_x_mm:g}, pitch_y_mm {plate.pitch_y_mm:g}; calibration.max_camera_model_ratio "
                f"{limits.max_camera_model_ratio:g})"
            )
    centre = result.calibration.camera_center_table_mm
    if centre is None or not np.all(np.isfinite(centre)):
        problems.append("no finite camera pose could be fitted")
    elif not limits.camera_height_min_mm <= centre[2] <= limits.camera_height_max_mm:
        problems.append(
            f"the fitted camera is {centre[2]:.0f} mm above the table, outside calibration.camera_height_min_mm "
            f"{limits.camera_height_min_mm:g} .. camera_height_max_mm {limits.camera_height_max_mm:g} (a wrong plate "
            f"pitch or size?)"
        )
    return problems


def change_problems(new: Calibration, active: Calibration, limits: CalibrationConfig) -> list[str]:
    """How far the new calibration moves from the active one beyond the configured limits."""
    w, h = new.image_size
    centre = ((w - 1) / 2, (h - 1) / 2)
    problems = []
    scale_new, scale_old = new.mm_per_px(centre), active.mm_per_px(centre)
    change_pct = 100.0 * abs(scale_new / scale_old - 1.0) if scale_old > 0 else math.inf
    if change_pct > limits.max_scale_change_pct:
        problems.append(
            f"scale {scale_new:.5f} mm/px against the active {scale_old:.5f} mm/px ({change_pct:.1f} % "
            f"> calibration.max_scale_change_pct {limits.max_scale_change_pct:g})"
        )
    moved = float(np.hypot(*(new.pixel_to_table_mm([centre]) - active.pixel_to_table_mm([centre]))[0]))
    if moved > limits.max_origin_change_mm:
        problems.append(
            f"the image centre maps {moved:.1f} mm from where the active calibration puts it "
            f"(> calibration.max_origin_change_mm {limits.max_origin_change_mm:g})"
        )
    return problems

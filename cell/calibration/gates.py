"""Plausibility gates on a new calibration, before it may replace the active one.

A fit can be excellent and still wrong: a plate printed at 20 mm pitch but configured as
22 mm is fitted to within microns by a polynomial, which simply learns the wrong scale.
The plate's circles catch it: they are round, and mapped back through the configured pitches
they stay round only if pitch_x_mm / pitch_y_mm is the plate's (roundness.py; no camera model,
so a real lens with glare, a crop or a bent sheet is judged as surely as a rendered plate).
A uniform scale error (both pitches off by one factor) cannot be seen in one image: it looks
like a camera at another height. The fitted height, where the plate pins it down, and against
the active calibration a jump in scale or origin catch that: a moved camera (the operator says
so with --accept-change) or a wrong plate.
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
    ratio = result.pitch_ratio
    floor, sds = limits.max_pitch_ratio_error_pct, limits.pitch_ratio_refuse_sd
    if ratio is not None and ratio.refused(floor, sds):
        configured = plate.pitch_x_mm / plate.pitch_y_mm
        sd_pct = 100.0 * ratio.log_sd
        problems.append(
            f"the plate's circles are round only if pitch_x_mm / pitch_y_mm is {configured / ratio.factor:.3f} "
            f"+- {configured / ratio.factor * ratio.log_sd:.3f}, not the configured {plate.pitch_x_mm:g} / "
            f"{plate.pitch_y_mm:g} = {configured:.3f} (the circles measure {100.0 * (ratio.factor - 1.0):+.1f} "
            f"+- {sd_pct:.1f} % (one standard error, median of {ratio.circles} circles); refused beyond "
            f"{ratio.threshold_pct(floor, sds):.1f} %: calibration.pitch_ratio_refuse_sd {sds:g} standard errors, "
            f"at least calibration.max_pitch_ratio_error_pct {floor:g}): a wrong pitch, or X and Y swapped? "
            f"(hint: measure the plate's pitches between circle centres far apart and set plate.pitch_x_mm and "
            f"plate.pitch_y_mm; X runs along the columns)"
        )
    centre = result.calibration.camera_center_table_mm
    if centre is None or not np.all(np.isfinite(centre)) or result.plate_height_mm is None:
        problems.append("no finite camera pose could be fitted")
        return problems
    height, sd = result.plate_height_mm, 3.0 * result.plate_height_sd_mm
    if height + sd < limits.camera_height_min_mm or height - sd > limits.camera_height_max_mm:
        problems.append(
            f"the plate puts the camera {height:.0f} +- {sd:.0f} mm (3 standard deviations) above the table, outside "
            f"calibration.camera_height_min_mm {limits.camera_height_min_mm:g} .. camera_height_max_mm "
            f"{limits.camera_height_max_mm:g} (a plate of another size, both pitches wrong by the same factor?)"
        )
    if limits.camera_height_mm is not None:
        allowed = 3.0 * math.hypot(result.plate_height_sd_mm, limits.camera_height_sd_mm)
        if abs(height - limits.camera_height_mm) > allowed:
            problems.append(
                f"the plate puts the camera {height:.0f} mm above the table, calibration.camera_height_mm says "
                f"{limits.camera_height_mm:g} mm (more than {allowed:.0f} mm apart, 3 standard deviations): both "
                f"pitches wrong by the same factor (that looks like another height), or the camera moved?"
            )
    raised = result.raised
    if raised is not None:
        others = [("the plate alone", height, result.plate_height_sd_mm)]
        if limits.camera_height_mm is not None:
            others.append(("calibration.camera_height_mm", limits.camera_height_mm, limits.camera_height_sd_mm))
        for name, other, other_sd in others:
            allowed = 3.0 * math.hypot(other_sd, raised.sd_mm)
            if abs(other - raised.height_mm) > allowed:
                problems.append(
                    f"the plate raised on the {raised.spacer_mm:g} mm spacer puts the camera {raised.height_mm:.0f} mm "
                    f"above the table, {name} {other:.0f} mm (more than {allowed:.0f} mm apart, 3 standard "
                    f"deviations): the spacer's thickness wrong, or both pitches wrong by the same factor (the raised "
                    f"plate measures the height in true mm, the flat plate in the configured pitch's)?"
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

"""The camera's height above the table: what one plate image can tell of it, and the configured
height (calibration.camera_height_mm) where it cannot (issue 19).

Seen nearly straight on, a plate fits about as well with a near camera and a short lens as with a
far one and a long lens: the calibration says how well it knows the height, and a configured
height decides where the plate cannot. Where both know it and disagree, the recalibration is
refused: a uniform scale error (both pitches wrong by one factor) looks like another height.
"""

from __future__ import annotations

import numpy as np
import pytest

from cell.calibration.gates import plausibility_problems
from cell.calibration.pipeline import calibrate
from cell.camera_model import CameraModel
from cell.config import CellConfig
from cell.sim.render import render_plate

W, H = 1280, 720


def camera(tilt_deg: float, principal_offset_px: tuple[float, float] = (0.0, 0.0)) -> CameraModel:
    """A webcam about 270 mm up, mild barrel distortion."""
    return CameraModel.looking_down(
        W,
        H,
        0.30,
        (132.0, 88.0),
        tilt_deg=tilt_deg,
        tilt_azimuth_deg=35.0,
        k1=-0.06,
        principal_offset_px=principal_offset_px,
    )


def config(height_mm: float | None = None, pitch_factor: float = 1.0) -> CellConfig:
    c = CellConfig()
    c.plate = c.plate.model_copy(
        update={"pitch_x_mm": 22.0 * pitch_factor, "pitch_y_mm": 16.0 * pitch_factor, "diameter_mm": 10 * pitch_factor}
    )
    c.calibration.camera_height_mm = height_mm
    return c


@pytest.fixture(scope="module")
def straight_on():
    cam = camera(0.3, principal_offset_px=(12.0, -7.0))  # 1 % off the centre
    return cam, render_plate(cam, CellConfig().plate, seed=3)


@pytest.fixture(scope="module")
def tilted():
    cam = camera(8.0)
    return cam, render_plate(cam, CellConfig().plate, seed=4)


def test_straight_on_the_plate_says_it_cannot_tell_the_height(straight_on):
    cam, image = straight_on
    result = calibrate(image, config())
    assert result.plate_height_sd_mm > 0.1 * cam.center_table_mm[2]
    assert plausibility_problems(result, config().calibration, config().plate) == []


def test_straight_on_the_configured_height_decides(straight_on):
    cam, image = straight_on
    true_height = float(cam.center_table_mm[2])
    c = config(true_height + 3.0)  # measured 3 mm high
    result = calibrate(image, c)
    fitted = result.calibration.camera_center_table_mm
    assert abs(fitted[2] - true_height) < 6.0
    assert np.hypot(*(fitted[:2] - cam.center_table_mm[:2])) < 3.0
    assert plausibility_problems(result, c.calibration, c.plate) == []


def test_tilted_the_plate_knows_the_height(tilted):
    cam, image = tilted
    result = calibrate(image, config())
    true_height = float(cam.center_table_mm[2])
    assert result.plate_height_sd_mm < 0.15 * true_height
    assert abs(result.plate_height_mm - true_height) < 3 * result.plate_height_sd_mm


def test_a_configured_height_the_plate_contradicts_is_refused(tilted):
    cam, image = tilted
    c = config(1.35 * float(cam.center_table_mm[2]))
    problems = plausibility_problems(calibrate(image, c), c.calibration, c.plate)
    assert len(problems) == 1 and "calibration.camera_height_mm says" in problems[0]


def test_a_uniform_scale_error_shows_as_another_height(tilted):
    """Both pitches (and the circles) configured 40 % large: the circles stay round, the fit is as
    good as ever, and only the height gives it away (smaller errors hide within what one tilted
    view knows of the height: the comparison with the active calibration's scale catches them)."""
    cam, image = tilted
    c = config(float(cam.center_table_mm[2]), pitch_factor=1.4)
    problems = plausibility_problems(calibrate(image, c), c.calibration, c.plate)
    assert len(problems) == 1 and "both pitches wrong by the same factor" in problems[0]

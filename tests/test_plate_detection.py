"""Plate detection and numbering on rendered plates, where the truth is exact."""

import cv2
import numpy as np
import pytest

from cell.calibration.pipeline import calibrate, find_points, find_points_paper
from cell.camera_model import CameraModel
from cell.config import CellConfig
from cell.errors import PlateNotFound
from cell.sim.render import Optics, render_plate
from cell.sim.rig import default_camera

CONFIG = CellConfig()
PLATE = CONFIG.plate


def truth_px(camera, points):
    """Projected centre of each numbered point (1-based, row by row)."""
    n = np.asarray(points.number) - 1
    cr = np.column_stack([n % PLATE.columns, n // PLATE.columns])
    return camera.project(cr * (PLATE.pitch_x_mm, PLATE.pitch_y_mm))


def wide_camera(roll_deg=0.0, tilt_deg=0.0, **kw):
    """1280 x 720 at 0.46 mm/px: room for the plate rotated by 30 degrees and tilted by 10."""
    return CameraModel.looking_down(
        1280, 720, 0.46, (132, 88), tilt_deg=tilt_deg, roll_deg=roll_deg, tilt_azimuth_deg=35, **kw
    )


def polygon_opacity(camera, polygon_mm):
    """A flat opaque shape lying on the table (a screw, a finger), anti-aliased."""
    px = camera.project(np.asarray(polygon_mm, dtype=np.float64))
    canvas = np.zeros((camera.height_px, camera.width_px), np.uint8)
    cv2.fillPoly(canvas, [np.round(px * 16).astype(np.int32)], 255, cv2.LINE_AA, shift=4)
    return canvas / 255.0


@pytest.mark.slow
def test_paper_preset_numbers_all_156_as_the_paper_does():
    cam = default_camera()
    pts = find_points_paper(render_plate(cam, PLATE), CONFIG)
    assert list(pts.number) == list(range(1, 157))
    # Whole-pixel (truncated) centres as in the paper's Table II, each on its own circle:
    # off by at most the truncation (< 1 px per axis) plus the binary moments' bias.
    assert np.all(pts.pixel == np.floor(pts.pixel))
    assert np.abs(pts.pixel - truth_px(cam, pts)).max() < 1.2


@pytest.mark.slow
def test_paper_preset_fails_without_every_circle():
    image = render_plate(default_camera(), PLATE, omit={(4, 4)})
    with pytest.raises(PlateNotFound, match="found 155 circles"):
        find_points_paper(image, CONFIG)


@pytest.mark.slow
@pytest.mark.parametrize("roll_deg", [-30.0, 0.0, 30.0])
def test_default_numbers_rotated_tilted_plates(roll_deg):
    cam = wide_camera(roll_deg=roll_deg, tilt_deg=10.0, k1=-0.1, k2=0.04)
    pts = find_points(render_plate(cam, PLATE, seed=3), CONFIG)
    assert len(pts.number) == 156
    err = np.abs(pts.pixel - truth_px(cam, pts)).max()
    assert err < 0.15, f"centre off its true position by {err:.3f} px"


@pytest.mark.slow
def test_default_survives_missing_circles_strays_and_a_screw():
    cam = wide_camera(roll_deg=12.0, tilt_deg=6.0)
    omit = {(0, 0), (3, 2), (4, 2), (12, 11), (7, 5), (8, 9)}
    rng = np.random.default_rng(5)
    dust = [
        [(x + 0.3 * np.cos(a), y + 0.3 * np.sin(a)) for a in np.linspace(0, 2 * np.pi, 12)]
        for x, y in rng.uniform((5, 5), (260, 170), (15, 2))
    ]
    screw = [(100.5, 41), (136, 44), (136, 48), (100.5, 45)]  # lying across two circles
    extra = np.maximum.reduce([polygon_opacity(cam, p) for p in dust + [screw]])
    pts = find_points(render_plate(cam, PLATE, omit=omit, extra_opacity=extra, seed=4), CONFIG)
    missing = {PLATE.columns * r + c + 1 for c, r in omit}
    assert missing <= set(pts.missing)
    assert len(pts.missing) <= 10
    assert np.abs(pts.pixel - truth_px(cam, pts)).max() < 0.15


@pytest.mark.slow
@pytest.mark.parametrize("exposure,gradient", [(0.45, 0.15), (1.25, 0.15), (1.0, 0.7)])
def test_default_adapts_to_exposure_and_uneven_backlight(exposure, gradient):
    cam = default_camera()
    image = render_plate(cam, PLATE, Optics(backlight_gradient=gradient), exposure=exposure)
    pts = find_points(image, CONFIG)
    assert len(pts.number) == 156
    assert np.abs(pts.pixel - truth_px(cam, pts)).max() < 0.2


@pytest.mark.slow
def test_a_missing_row_is_reported_not_guessed():
    omit = {(c, 11) for c in range(PLATE.columns)}
    with pytest.raises(PlateNotFound, match=r"found 143 blobs, 143 fit a 13 x 11 lattice.*1 row\(s\) missing"):
        find_points(render_plate(default_camera(), PLATE, omit=omit), CONFIG)


@pytest.mark.slow
def test_plate_partly_out_of_view_fails_with_what_was_seen():
    cam = CameraModel.looking_down(1280, 720, 0.26, (60, 40))  # sees only the top-left part
    with pytest.raises(PlateNotFound, match="expected 13 x 12"):
        find_points(render_plate(cam, PLATE), CONFIG)


@pytest.mark.slow
def test_config_grid_that_does_not_match_the_plate_fails():
    cfg = CONFIG.model_copy(deep=True)
    cfg.plate.columns, cfg.plate.rows = 7, 7
    with pytest.raises(PlateNotFound, match="expected 7 x 7"):
        find_points(render_plate(default_camera(), PLATE), cfg)


def test_empty_frame_is_no_plate():
    with pytest.raises(PlateNotFound, match="no plate"):
        calibrate(np.full((720, 1280, 3), 230, np.uint8), CONFIG)

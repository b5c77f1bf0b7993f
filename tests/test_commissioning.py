"""Looking through the camera before calibrating (cell.vision.commissioning): focus, exposure,
the plate's coverage, tilt and framing, each with the advice it should give."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cell.camera_model import CameraModel
from cell.config import CellConfig
from cell.sim.parts import random_scene, render_scene
from cell.sim.render import render_plate
from cell.vision.commissioning import FocusTracker, assess, find_plate, focus_score, histogram_text, measure_exposure

pytestmark = pytest.mark.timeout(120)

W, H = 960, 540
CONFIG = CellConfig(camera={"width_px": W, "height_px": H})
PLATE = CONFIG.plate
CENTRE = (132.0, 88.0)  # the middle of the plate's circle field


def camera(**kw) -> CameraModel:
    args = dict(mm_per_px=0.4, look_at_table_mm=CENTRE, hfov_deg=60.0)
    args.update(kw)
    return CameraModel.looking_down(W, H, **args)


def plate_image(cam: CameraModel, **kw) -> np.ndarray:
    return render_plate(cam, PLATE, seed=1, **kw)


def field_corners_px(cam: CameraModel) -> np.ndarray:
    r = PLATE.diameter_mm / 2
    x1, y1 = (PLATE.columns - 1) * PLATE.pitch_x_mm + r, (PLATE.rows - 1) * PLATE.pitch_y_mm + r
    return cam.project(np.array([[-r, -r], [x1, -r], [x1, y1], [-r, y1]]))


def test_a_square_well_exposed_plate_needs_nothing():
    cam = camera(roll_deg=2.0)
    view = assess(plate_image(cam), CONFIG)
    p = view.plate
    assert p is not None and p.circles_found == p.circles_expected == 156 and p.in_view
    truth = 100 * cv2.contourArea(field_corners_px(cam).astype(np.float32)) / (W * H)
    assert p.coverage_pct == pytest.approx(truth, abs=1.0)
    assert p.tilt_deg < 1.0 and p.nearer == ""
    assert p.turned_deg == pytest.approx(2.0, abs=0.3)
    assert max(abs(v) for v in p.centre_offset_pct) < 1.0
    assert view.advice == []


@pytest.mark.parametrize("azimuth_deg", [0.0, 90.0, 200.0])
def test_tilt_and_the_nearer_side(azimuth_deg):
    cam = camera(tilt_deg=10.0, tilt_azimuth_deg=azimuth_deg, mm_per_px=0.45)
    view = assess(plate_image(cam), CONFIG)
    assert view.plate.tilt_deg == pytest.approx(10.0, abs=1.0)
    # the truth: which edges of the circle field, as the image shows them, are nearer the camera
    corners = field_corners_px(cam)
    centre_mm = cam.center_table_mm
    r = PLATE.diameter_mm / 2
    x1, y1 = (PLATE.columns - 1) * PLATE.pitch_x_mm + r, (PLATE.rows - 1) * PLATE.pitch_y_mm + r
    mids_mm = {"a": (-r, CENTRE[1]), "b": (x1, CENTRE[1]), "c": (CENTRE[0], -r), "d": (CENTRE[0], y1)}
    px = {k: cam.project(np.array([v]))[0] for k, v in mids_mm.items()}
    dist = {k: math.dist((*v, 0.0), centre_mm) for k, v in mids_mm.items()}
    words = []
    for pair, names, axis in ((("c", "d"), ("top", "bottom"), 1), (("a", "b"), ("left", "right"), 0)):
        low, high = sorted(pair, key=lambda k: px[k][axis])  # the one higher / further left in the image first
        if abs(dist[low] - dist[high]) / max(dist.values()) > 0.01:
            words.append(names[0] if dist[low] < dist[high] else names[1])
    assert view.plate.nearer == "-".join(words) and words, corners
    assert any(a.startswith("camera: ") and "level the camera" in a for a in view.advice)


def test_a_plate_partly_out_of_view_says_which_way_to_move_it():
    cam = camera(look_at_table_mm=(20.0, 88.0), mm_per_px=0.45)  # looks left of the plate: its right part is cut
    view = assess(plate_image(cam), CONFIG)
    assert view.plate is None and view.partial is not None and view.partial.cut_at == ("right",)
    (advice,) = [a for a in view.advice if a.startswith("plate: ")]
    assert "not wholly in view" in advice and advice.endswith("move it towards the centre (in the image: left)")


def test_a_plate_larger_than_the_view():
    view = assess(plate_image(camera(mm_per_px=0.22)), CONFIG)
    assert view.plate is None and {"left", "right"} <= set(view.partial.cut_at)
    assert any(a.startswith("plate: larger than the view") and "zoom out" in a for a in view.advice)


def test_a_small_plate_in_a_wide_view():
    cam = camera(mm_per_px=1.0)
    view = assess(plate_image(cam), CONFIG)
    assert view.plate is not None and view.plate.coverage_pct < 25
    assert any("bring the camera closer" in a for a in view.advice)


def test_no_plate_in_view():
    image = render_scene(camera(), random_scene(2), seed=2)
    view = assess(image, CONFIG)
    assert view.plate is None and view.plate_note
    assert any(a.startswith("plate: not in view") for a in view.advice)


def test_exposure_too_bright_and_too_dark():
    cam = camera()
    bright = assess(plate_image(cam, exposure=1.3), CONFIG)
    assert bright.exposure.bright_clipped_pct > 5
    assert any("lower camera.exposure" in a for a in bright.advice)
    dark = assess(plate_image(cam, exposure=0.4), CONFIG)
    assert dark.exposure.backlight < 120 and dark.exposure.bright_clipped_pct == 0
    assert any("too dark" in a for a in dark.advice)
    gray = cv2.cvtColor(plate_image(cam), cv2.COLOR_BGR2GRAY)
    e = measure_exposure(gray)
    assert sum(e.histogram) == pytest.approx(1.0) and len(e.histogram) == 16
    assert len(histogram_text(e.histogram)) == 16 and histogram_text(e.histogram).strip()


def test_focus_falls_with_blur_and_the_tracker_keeps_the_best():
    gray = cv2.cvtColor(plate_image(camera()), cv2.COLOR_BGR2GRAY)
    scores = [focus_score(cv2.GaussianBlur(gray, (0, 0), s)) for s in (0.6, 1.0, 2.0, 4.0)]
    assert scores == sorted(scores, reverse=True)
    tracker = FocusTracker()
    shares = [tracker.update(s) for s in (scores[2], scores[0], scores[3])]
    assert shares[:2] == [1.0, 1.0] and shares[2] == pytest.approx(scores[3] / scores[0])
    assert tracker.best == scores[0] and tracker.best_frame == 2
    blurred = cv2.cvtColor(cv2.GaussianBlur(gray, (0, 0), 4.0), cv2.COLOR_GRAY2BGR)
    view = assess(blurred, CONFIG, tracker)
    assert any(a.startswith("focus: ") and "back towards it" in a for a in view.advice)


def test_find_plate_names_what_it_saw_when_there_is_none():
    from cell.errors import PlateNotFound

    with pytest.raises(PlateNotFound, match="no plate in view"):
        find_plate(np.full((H, W, 3), 200, np.uint8), CONFIG)

"""The 3-D part renderer: geometry a vision test can trust."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cell.camera_model import CameraModel
from cell.sim.parts import NUTS_MM, PartSpec, random_scene, render_scene, scene_opacity


def _camera(**kw) -> CameraModel:
    args = dict(width_px=640, height_px=480, mm_per_px=0.25, look_at_table_mm=(50.0, 40.0), hfov_deg=60.0)
    args.update(kw)
    return CameraModel.looking_down(**args)


def _polygon_centroid(poly: np.ndarray) -> np.ndarray:
    m = cv2.moments(poly.astype(np.float32))
    return np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])


def _polygon_area(poly: np.ndarray) -> float:
    return abs(cv2.contourArea(poly.astype(np.float32)))


@pytest.mark.parametrize(
    "part",
    [
        PartSpec("nut", "M8", 10.0, 20.0, 17.0),
        PartSpec("bolt", "M6", -5.0, 3.0, 123.0, 25.0),
        PartSpec("bolt", "M8", 0.0, 0.0, 0.0, 16.0),
        PartSpec("washer", "M10", 4.0, 4.0),
    ],
)
def test_spec_position_is_the_top_view_centroid(part):
    np.testing.assert_allclose(_polygon_centroid(part.top_view_outline_mm()), part.footprint_centre_mm, atol=1e-6)


def test_bolt_outline_dimensions_and_angle():
    bolt = PartSpec("bolt", "M8", 0.0, 0.0, 30.0, 20.0)
    outline = bolt.top_view_outline_mm()
    e = 13.0 * 2 / math.sqrt(3)
    assert _polygon_area(outline) == pytest.approx(5.3 * e + 20.0 * 8.0, rel=1e-6)  # float32 moments
    assert bolt.axis_angle_deg == pytest.approx(30.0)
    assert PartSpec("bolt", "M8", 0, 0, 210.0, 20.0).axis_angle_deg == pytest.approx(30.0)
    # The head lies on the side opposite the tip direction.
    head = np.array(bolt.head_centre_mm)
    assert np.dot(head, [math.cos(math.radians(30)), math.sin(math.radians(30))]) < -5
    assert bolt.height_mm == 13.0


def test_invalid_specs_are_refused():
    with pytest.raises(ValueError):
        PartSpec("nut", "M3", 0, 0)
    with pytest.raises(ValueError):
        PartSpec("bolt", "M6", 0, 0)
    with pytest.raises(ValueError):
        PartSpec("spring", "M6", 0, 0)


def test_nut_under_the_camera_matches_its_geometry():
    """Straight below the camera a nut's silhouette is its top face (the nearer, larger one)
    and its hole is the bottom rim (the farther, smaller one)."""
    cam = _camera()
    centre = cam.center_table_mm
    nut = PartSpec("nut", "M10", float(centre[0]), float(centre[1]), 10.0)
    opacity = scene_opacity(cam, [nut])
    H, t = centre[2], NUTS_MM["M10"]["thickness"]
    mm_px_top = 0.25 * (H - t) / H
    mm_px_bottom = 0.25
    hex_area_mm2 = math.sqrt(3) / 2 * 16.0**2
    hole_area_mm2 = math.pi * (NUTS_MM["M10"]["hole"] / 2) ** 2
    expected_px = hex_area_mm2 / mm_px_top**2 - hole_area_mm2 / mm_px_bottom**2
    assert opacity.sum() == pytest.approx(expected_px, rel=0.003)
    ys, xs = np.mgrid[0 : opacity.shape[0], 0 : opacity.shape[1]]
    c = np.array([(xs * opacity).sum(), (ys * opacity).sum()]) / opacity.sum()
    np.testing.assert_allclose(c, cam.project([centre[:2]], 0.0)[0], atol=0.02)


def test_off_axis_hole_is_the_intersection_of_its_rims():
    """Off-axis, the two rims project apart and the visible hole shrinks (backlight)."""
    cam = _camera()
    c = cam.center_table_mm
    near = scene_opacity(cam, [PartSpec("nut", "M6", float(c[0]), float(c[1]))])
    far = scene_opacity(cam, [PartSpec("nut", "M6", float(c[0]) + 70, float(c[1]) + 45)])

    def hole_px(op):
        filled = (op > 0.5).astype(np.uint8)
        contours, _ = cv2.findContours(filled, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        solid = np.zeros_like(filled)
        cv2.drawContours(solid, contours, -1, 1, -1)
        return int((solid & (1 - filled)).sum())

    assert hole_px(far) < 0.8 * hole_px(near)
    assert hole_px(far) > 0


def test_silhouette_spreads_away_from_the_camera_foot():
    """A tall part's silhouette centroid lies farther from the camera's foot than its footprint."""
    cam = _camera()
    c = cam.center_table_mm
    bolt = PartSpec("bolt", "M8", float(c[0]) + 60, float(c[1]), 90.0, 20.0)
    op = scene_opacity(cam, [bolt])
    ys, xs = np.mgrid[0 : op.shape[0], 0 : op.shape[1]]
    centroid_px = np.array([(xs * op).sum(), (ys * op).sum()]) / op.sum()
    on_table = cam.pixel_to_table(centroid_px, 0.0)[0]
    assert on_table[0] - bolt.x_mm > 1.0


def test_random_scene_mix_and_spacing():
    parts = random_scene(seed=5)
    assert 15 <= len(parts) <= 20
    kinds = [p.kind for p in parts]
    assert kinds.count("washer") == 2
    assert {"nut", "bolt"} <= set(kinds)
    for p in parts:
        o = p.top_view_outline_mm()
        assert o[:, 0].min() >= 0 and o[:, 0].max() <= 264 and o[:, 1].min() >= 0 and o[:, 1].max() <= 176
        if p.kind == "bolt":
            assert 16 <= p.length_mm <= 35 and p.size in ("M5", "M6", "M8")
    # Outlines are at least the requested gap apart (checked on a fine grid).
    res = 0.25
    masks = []
    for p in parts:
        m = np.zeros((int(200 / res), int(300 / res)), np.uint8)
        cv2.fillPoly(m, [np.rint(p.top_view_outline_mm() / res).astype(np.int32)], 1)
        masks.append(cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (27, 27))))
    total = np.sum(masks, axis=0)
    assert total.max() == 1
    assert random_scene(seed=5) == parts


def test_render_scene_is_a_backlit_frame():
    cam = _camera()
    parts = [PartSpec("nut", "M8", 40.0, 40.0), PartSpec("bolt", "M5", 70.0, 30.0, 45.0, 20.0)]
    frame = render_scene(cam, parts, seed=1)
    assert frame.shape == (480, 640, 3) and frame.dtype == np.uint8
    centre_px = np.rint(cam.project([[40.0 + 5.5, 40.0]], 3.0)[0]).astype(int)  # on the nut's face
    assert frame[centre_px[1], centre_px[0]].mean() < 60
    assert frame[5, 5].mean() > 120
    assert np.array_equal(frame, render_scene(cam, parts, seed=1))
    darker = render_scene(cam, parts, seed=1, exposure=0.5)
    assert darker[5, 5].mean() < 0.6 * frame[5, 5].mean()

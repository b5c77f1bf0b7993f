"""Segmentation and shape features on drawn shapes: holes, hexagonality, profiles, edges."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cell.vision.config import PartsConfig
from cell.vision.features import hexagonality, measure, width_profile
from cell.vision.segment import segment


def _hexagon(centre, r_px, angle_deg=0.0):
    a = np.deg2rad(angle_deg + 60 * np.arange(6))
    return np.column_stack([centre[0] + r_px * np.cos(a), centre[1] + r_px * np.sin(a)])


def _frame(draw, size=(400, 300), level=220):
    img = np.full((size[1], size[0]), level, np.uint8)
    draw(img)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def _contour(points):
    return np.rint(points).astype(np.int32).reshape(-1, 1, 2)


@pytest.mark.parametrize("angle", [0.0, 13.0, 41.0])
def test_hexagonality_tells_hexagons_from_circles_and_squares(angle):
    hexa = _contour(_hexagon((100, 100), 40, angle))
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    circle = _contour(np.column_stack([100 + 40 * np.cos(t), 100 + 40 * np.sin(t)]))
    square = _contour(np.array([[60, 60], [140, 60], [140, 140], [60, 140]], float))
    assert hexagonality(hexa, (100, 100)) == pytest.approx(1.0, abs=0.1)
    assert hexagonality(circle, (100, 100)) < 0.1
    assert hexagonality(square, (100, 100)) < 0.15


def test_holes_are_kept_by_default_and_dropped_by_the_paper_preset():
    def draw(img):
        cv2.fillPoly(img, [_contour(_hexagon((150, 150), 50))], 20)
        cv2.circle(img, (150, 150), 20, 220, -1)

    frame = _frame(draw)
    default = segment(frame, PartsConfig(), part_width_px=120, noise_area_px=10)
    assert len(default.blobs) == 1 and len(default.blobs[0].holes) == 1
    feat = measure(default.blobs[0], default.mask)
    assert feat.centroid_px == pytest.approx((150, 150), abs=0.05)
    assert feat.outer_area_px - feat.area_px == pytest.approx(math.pi * 20**2, rel=0.05)
    assert feat.elongation < 1.2 and feat.hexagonality > 0.8 and 0.78 < feat.roundness < 0.9
    paper = segment(frame, PartsConfig(preset="paper"), part_width_px=120, noise_area_px=10)
    assert len(paper.blobs) == 1 and paper.blobs[0].holes == []


def test_threshold_follows_an_uneven_backlight():
    """A ramp from 90 to 250 across the frame: a fixed threshold would fail on one side."""
    ramp = np.tile(np.linspace(90, 250, 400), (300, 1))
    img = ramp.copy()
    for x in (60, 200, 340):
        cv2.circle(img, (x, 150), 25, 0, -1)
    img = (img * 0.9 + ramp * 0.1 * (img == 0)).astype(np.uint8)  # "dark" is 10 % of the light
    seg = segment(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), PartsConfig(), part_width_px=60, noise_area_px=10)
    assert len(seg.blobs) == 3
    for blob in seg.blobs:
        assert measure(blob, seg.mask).area_px == pytest.approx(math.pi * 25**2, rel=0.06)


def test_dark_edge_lines_are_cleared_but_a_part_on_them_still_touches_the_border():
    def draw(img):
        img[:2, :] = 15  # a sensor's dark top rows, as in the real photos
        cv2.circle(img, (200, 20), 25, 20, -1)  # a part running into them
        cv2.circle(img, (100, 150), 25, 20, -1)

    seg = segment(_frame(draw), PartsConfig(), part_width_px=60, noise_area_px=10)
    assert len(seg.blobs) == 2
    touching = {tuple(np.round(measure(b, seg.mask).centroid_px).astype(int)): b.touches_border for b in seg.blobs}
    assert touching[(100, 150)] is False
    assert [v for k, v in touching.items() if k != (100, 150)] == [True]


def test_width_profile_puts_the_head_first():
    # A "bolt" drawn tip-first from the left: shaft 20 px wide, head 44 px wide on the right.
    def draw(img):
        cv2.rectangle(img, (60, 140), (259, 159), 20, -1)
        cv2.rectangle(img, (260, 128), (289, 171), 20, -1)

    seg = segment(_frame(draw), PartsConfig(), part_width_px=80, noise_area_px=10)
    feat = measure(seg.blobs[0], seg.mask)
    prof = width_profile(seg.blobs[0].outer, feat.centroid_px, feat.axis_px)
    assert prof.axis_px[0] == pytest.approx(-1.0, abs=1e-3)  # head -> tip points left
    assert prof.origin_px[0] == pytest.approx(289.5, abs=0.6)
    assert prof.length_px == pytest.approx(230.0, abs=1.0)
    assert np.median(prof.widths_px[:25]) == pytest.approx(44.0, abs=1.0)
    assert np.median(prof.widths_px[60:]) == pytest.approx(20.0, abs=1.0)

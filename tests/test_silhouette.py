"""A part's footprint centre from its shadow (cell/vision/silhouette.py), on exact geometry.

The vision's nut and bolt solids must be the renderer's (cell/sim/parts.py), and inverting the
shadow's centroid must give back the footprint centre wherever the part lies in the view; the
old rule (the silhouette's centroid mapped at half the part's height) is 0.1-0.2 mm off for a
large nut, which is why it was replaced.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.sim.parts import BOLTS_MM, NUTS_MM, PartSpec
from cell.vision.silhouette import (
    Bolt,
    Nut,
    footprint_centre,
    nut_from_outline,
    polygon_moments,
    shadow,
    shadow_moments,
)

CAMERA_CENTRE = np.array([130.0, 90.0, 300.0])  # table mm: the camera 300 mm above (130, 90)


def _shadow_hulls(part: PartSpec) -> list[np.ndarray]:
    """The renderer's solids, each one's shadow hull on the table plane."""
    import cv2

    solids, _ = part.solids()
    return [cv2.convexHull(shadow(s, CAMERA_CENTRE).astype(np.float32)).reshape(-1, 2).astype(float) for s in solids]


def _vision_shape(part: PartSpec) -> Nut | Bolt:
    d = part.dims
    if part.kind == "nut":
        return Nut(d["across_flats"], d["thickness"], part.angle_deg)
    return Bolt(d["across_flats"], d["head_height"], d["shaft"], part.length_mm, part.angle_deg)


@pytest.mark.parametrize(
    "part",
    [
        PartSpec("nut", "M10", 20.0, 30.0, 17.0),
        PartSpec("nut", "M5", 250.0, 160.0, 41.0),
        PartSpec("bolt", "M8", 30.0, 150.0, 123.0, 35.0),
        PartSpec("bolt", "M5", 230.0, 20.0, 300.0, 16.0),
    ],
)
def test_vision_solids_are_the_renderers(part):
    ours = _vision_shape(part).solids(np.array(part.footprint_centre_mm))
    theirs, _ = part.solids()
    for a, b in zip(ours, theirs, strict=True):
        # Same points, up to order: each point has its counterpart, both ways.
        dist = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
        assert dist.min(axis=1).max() < 1e-9 and dist.min(axis=0).max() < 1e-9


@pytest.mark.parametrize("size", list(NUTS_MM))
@pytest.mark.parametrize("where", [(20.0, 20.0), (130.0, 90.0), (250.0, 170.0), (40.0, 160.0)])
def test_nut_centre_from_its_shadow(size, where):
    part = PartSpec("nut", size, *where, 23.0)
    (hull,) = _shadow_hulls(part)
    _, measured = polygon_moments(hull)
    nut = nut_from_outline(hull, NUTS_MM[size]["across_flats"] * 1.05, 0.5, CAMERA_CENTRE)  # a rough first size
    assert nut.across_flats_mm == pytest.approx(NUTS_MM[size]["across_flats"], rel=0.01)
    centre = footprint_centre(nut, measured, CAMERA_CENTRE)
    assert np.hypot(*(centre - part.footprint_centre_mm)) < 0.005
    # The half-height rule is what this replaces: off by up to 0.2 mm for the largest nut.
    t, c = part.dims["thickness"], CAMERA_CENTRE
    half_height = c[:2] + (measured - c[:2]) * (1 - t / 2 / c[2])
    if size == "M10" and math.dist(where, c[:2]) > 50:
        assert np.hypot(*(half_height - part.footprint_centre_mm)) > 0.1


@pytest.mark.parametrize("size", list(BOLTS_MM))
@pytest.mark.parametrize(("where", "angle"), [((20.0, 20.0), 10.0), ((250.0, 170.0), 200.0), ((40.0, 160.0), 95.0)])
def test_bolt_centre_from_its_shadow(size, where, angle):
    part = PartSpec("bolt", size, *where, angle, 25.0)
    head, shaft = _shadow_hulls(part)
    bolt = _vision_shape(part)
    # The union's centroid, as the measured outline would give it (head and shaft overlap a little).
    import cv2

    a1, c1 = polygon_moments(head)
    a2, c2 = polygon_moments(shaft)
    overlap, inter = cv2.intersectConvexConvex(head.astype(np.float32), shaft.astype(np.float32))
    a12, c12 = (0.0, c1) if inter is None else polygon_moments(inter.reshape(-1, 2).astype(float))
    measured = (a1 * c1 + a2 * c2 - a12 * c12) / (a1 + a2 - a12)
    centre = footprint_centre(bolt, measured, CAMERA_CENTRE, np.array(where) + (1.0, -1.0))
    assert np.hypot(*(centre - part.footprint_centre_mm)) < 0.005


RASTER_CASES = [  # (bolt, camera centre): random ones, and one where OpenCV's intersection failed
    *[(np.random.default_rng(seed), None) for seed in range(6)],
    (PartSpec("bolt", "M8", 84.925, 98.25, 99.6887, 30.0), np.array([138.9, 96.7, 342.6])),
]


@pytest.mark.parametrize(("case", "camera_centre"), RASTER_CASES)
def test_bolt_shadow_area_and_centroid_match_a_rasterised_union(case, camera_centre):
    """The head's and the shaft's shadows share an edge where they join: their union's moments
    must still be right (OpenCV's convex intersection returned the wrong polygon there)."""
    import cv2

    if isinstance(case, PartSpec):
        part = case
    else:
        size = str(case.choice(list(BOLTS_MM)))
        centre = CAMERA_CENTRE[:2] + case.uniform(-60, 60, 2)
        part = PartSpec("bolt", size, *centre, float(case.uniform(0, 360)), float(case.choice([16, 25, 35])))
    camera_centre = CAMERA_CENTRE if camera_centre is None else camera_centre
    solids, _ = part.solids()
    hulls = [cv2.convexHull(shadow(s, camera_centre).astype(np.float32)).reshape(-1, 2).astype(float) for s in solids]
    area, centroid = shadow_moments(_vision_shape(part), np.array(part.footprint_centre_mm), camera_centre)
    scale = 100.0  # raster px per mm
    lo = np.vstack(hulls).min(axis=0) - 1
    shape = tuple((np.ceil((np.vstack(hulls).max(axis=0) - lo + 1) * scale)).astype(int)[::-1])
    mask = np.zeros(shape, np.uint8)
    for h in hulls:
        cv2.fillPoly(mask, [np.rint((h - lo) * scale * 16).astype(np.int32)], 1, cv2.LINE_8, 4)
    m = cv2.moments(mask, binaryImage=True)
    assert area == pytest.approx(m["m00"] / scale**2, rel=0.005)
    raster = np.array([m["m10"], m["m01"]]) / m["m00"] / scale + lo  # pixel i covers i +- 0.5
    assert np.hypot(*(centroid - raster)) < 0.01

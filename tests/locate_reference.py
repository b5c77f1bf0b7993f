"""The previous implementation of the part-location geometry, kept verbatim as the reference the
faster code in cell/vision is pinned against (tests/test_locate_speed.py) and timed beside
(scripts/bench_parts.py --speed): the shadow model of cell/vision/silhouette.py as of commit
f35e21a (pure-Python polygon geometry per part), and the sub-pixel outline of
cell/vision/subpixel.py as of the same commit. `previous_locate()` runs cell.vision.locate with them.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import cv2
import numpy as np

_SWEEP_DEG = 12.0  # edges this close to the sweep's direction are the sweep's, not a side's
_RING = 96  # points on a shaft's rim (as the renderer draws it)


def shadow(points_xyz: np.ndarray, camera_centre: np.ndarray) -> np.ndarray:
    """(N, 2) where each point (X, Y, height) is seen on the table plane from the camera centre."""
    p = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(camera_centre, dtype=np.float64)
    k = c[2] / np.maximum(c[2] - p[:, 2], 1e-9)
    return c[:2] + (p[:, :2] - c[:2]) * k[:, None]


def polygon_moments(poly: np.ndarray) -> tuple[float, np.ndarray]:
    """Area (positive) and area centroid of a simple polygon (N, 2)."""
    x, y = poly[:, 0], poly[:, 1]
    xs, ys = np.concatenate((x[1:], x[:1])), np.concatenate((y[1:], y[:1]))
    cross = x * ys - xs * y
    a = cross.sum() / 2
    if abs(a) < 1e-12:
        return 0.0, poly.mean(axis=0)
    return abs(a), np.array([((x + xs) * cross).sum(), ((y + ys) * cross).sum()]) / (6 * a)


def _hull(points: np.ndarray) -> np.ndarray:
    origin = points.mean(axis=0)
    hull = cv2.convexHull((points - origin).astype(np.float32)).reshape(-1, 2)
    return hull.astype(np.float64) + origin


def _union_moments(hulls: list[np.ndarray]) -> tuple[float, np.ndarray]:
    """Area and area centroid of the union of two convex polygons (or of one)."""
    moments = [polygon_moments(h) for h in hulls]
    if len(hulls) == 1:
        return moments[0]
    (a1, c1), (a2, c2) = moments
    inter = _intersection(hulls[0], hulls[1])
    a12, c12 = (0.0, c1) if len(inter) < 3 else polygon_moments(inter)
    area = a1 + a2 - a12
    return area, (a1 * c1 + a2 * c2 - a12 * c12) / max(area, 1e-12)


def _intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The intersection of two convex polygons: `a` clipped by each edge of `b` in turn
    (Sutherland-Hodgman, float64). OpenCV's intersectConvexConvex returns the wrong polygon for
    the head's and the shaft's shadows, which share an edge where they join."""
    if len(b) > len(a):
        a, b = b, a  # the work grows with the clipping polygon's edges
    x, y = b[:, 0], b[:, 1]
    if float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) < 0:
        b = b[::-1]  # counter-clockwise: inside is to the left of every edge
    out = a
    for p, q in zip(b, np.roll(b, -1, axis=0), strict=True):
        if len(out) < 3:
            return np.zeros((0, 2))
        nxt = np.roll(out, -1, axis=0)
        side = (q[0] - p[0]) * (out[:, 1] - p[1]) - (q[1] - p[1]) * (out[:, 0] - p[0])
        side_nxt = np.roll(side, -1)
        inside = side >= 0
        crossing = inside != (side_nxt >= 0)
        t = side / np.where(crossing, side - side_nxt, 1.0)
        cut = out + (nxt - out) * t[:, None]
        out = np.stack([out, cut], axis=1).reshape(-1, 2)[np.stack([inside, crossing], axis=1).reshape(-1)]
    return out


@dataclass(frozen=True)
class Nut:
    """A hexagonal prism lying flat: across flats, thickness, corner direction (table degrees)."""

    across_flats_mm: float
    thickness_mm: float
    corner_deg: float

    def solids(self, centre: np.ndarray) -> list[np.ndarray]:
        r = self.across_flats_mm / math.sqrt(3)
        a = np.deg2rad(self.corner_deg + 60.0 * np.arange(6))
        hexagon = centre + r * np.column_stack([np.cos(a), np.sin(a)])
        z = np.repeat([0.0, self.thickness_mm], 6)
        return [np.column_stack([np.vstack([hexagon, hexagon]), z])]


@dataclass(frozen=True)
class Bolt:
    """A hex-head bolt on its side, head on a flat: head across flats and length, shaft diameter
    and length, axis direction head -> tip (table degrees). Its footprint centre (the top view's
    area centroid) is the origin of its own frame."""

    head_across_flats_mm: float
    head_length_mm: float
    shaft_mm: float
    shaft_length_mm: float
    axis_deg: float

    def solids(self, centre: np.ndarray) -> list[np.ndarray]:
        s, k, d, L = self.head_across_flats_mm, self.head_length_mm, self.shaft_mm, self.shaft_length_mm
        e = 2 * s / math.sqrt(3)  # the head's width seen from above (across corners)
        u0 = -(k * e * (-k / 2) + L * d * (L / 2)) / (k * e + L * d)  # head-shaft junction
        a = math.radians(self.axis_deg)
        axis, side = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
        corners = np.deg2rad(60.0 * np.arange(6))
        ring = np.linspace(0.0, 2 * np.pi, _RING, endpoint=False)
        head_vz = np.column_stack([e / 2 * np.cos(corners), s / 2 + e / 2 * np.sin(corners)])
        shaft_vz = np.column_stack([d / 2 * np.cos(ring), s / 2 + d / 2 * np.sin(ring)])

        def prism(vz: np.ndarray, u_from: float, u_to: float) -> np.ndarray:
            ends = [centre + u * axis + vz[:, :1] * side for u in (u_from, u_to)]
            return np.column_stack([np.vstack(ends), np.concatenate([vz[:, 1], vz[:, 1]])])

        return [prism(head_vz, u0 - k, u0), prism(shaft_vz, u0, u0 + L)]


Shape = Nut | Bolt


def shadow_moments(shape: Shape, centre: np.ndarray, camera_centre: np.ndarray) -> tuple[float, np.ndarray]:
    """Area and area centroid of the shadow `shape` casts on the table plane from the camera centre."""
    return _union_moments([_hull(shadow(s, camera_centre)) for s in shape.solids(np.asarray(centre, float))])


def footprint_centre(
    shape: Shape, measured_mm: np.ndarray, camera_centre: np.ndarray, start_mm: np.ndarray | None = None, steps: int = 2
) -> np.ndarray:
    """The footprint centre whose shadow's centroid is `measured_mm` (the outline's centroid on
    the table plane); `start_mm` a first guess (default: the measured centroid)."""
    measured = np.asarray(measured_mm, dtype=np.float64)
    c = measured.copy() if start_mm is None else np.asarray(start_mm, dtype=np.float64).copy()
    for _ in range(steps):
        c = c + (measured - shadow_moments(shape, c, camera_centre)[1])
    return c


def nut_from_outline(outline_mm: np.ndarray, across_flats_mm: float, thickness_ratio: float, camera_centre) -> Nut:
    """The nut whose shadow has this outline (on the table plane): the corner direction from the
    outline's edges, the across flats from its area (which grows as the square), the thickness
    `thickness_ratio` times that.

    The shadow is the bottom hexagon swept to the top one: its edges run along the hexagon's six
    sides, and two along the sweep (towards the camera's foot), which are left out. So the sides'
    direction is the sixth harmonic of the edge directions weighed by length, the sweep's excepted.
    """
    area, centre = polygon_moments(outline_mm)
    edges = np.diff(np.vstack([outline_mm, outline_mm[:1]]), axis=0)
    length = np.hypot(edges[:, 0], edges[:, 1])
    direction = np.arctan2(edges[:, 1], edges[:, 0])
    sweep = math.atan2(centre[1] - camera_centre[1], centre[0] - camera_centre[0])
    off_sweep = np.abs(np.angle(np.exp(2j * (direction - sweep)))) > np.deg2rad(2 * _SWEEP_DEG)
    # A side runs at 120 degrees to the corner it leaves: modulo 60 the sides' and corners'
    # directions are the same.
    corner = math.degrees(float(np.angle(np.sum(length * off_sweep * np.exp(6j * direction))))) / 6
    af = across_flats_mm
    for _ in range(2):
        model, _ = shadow_moments(Nut(af, thickness_ratio * af, corner), centre, camera_centre)
        af *= math.sqrt(area / max(model, 1e-9))
    return Nut(af, thickness_ratio * af, corner)


# ---- cell/vision/subpixel.py -------------------------------------------------------------------
UPSAMPLE = 4
_MARGIN_PX = 4


def subpixel_outline(gray: np.ndarray, outline: np.ndarray, fraction: float) -> np.ndarray | None:
    """(N, 2) float outline in image pixels, or None where no paper is seen around the part."""
    H, W = gray.shape
    x, y, w, h = cv2.boundingRect(outline)
    x0, y0 = max(x - _MARGIN_PX, 0), max(y - _MARGIN_PX, 0)
    x1, y1 = min(x + w + _MARGIN_PX, W), min(y + h + _MARGIN_PX, H)
    roi = gray[y0:y1, x0:x1].astype(np.float32)
    part = np.zeros(roi.shape, np.uint8)
    cv2.drawContours(part, [outline], -1, 255, -1, offset=(-x0, -y0))
    paper = roi[cv2.dilate(part, np.ones((5, 5), np.uint8)) == 0]
    if paper.size < 16:
        return None
    up = cv2.resize(roi, None, fx=UPSAMPLE, fy=UPSAMPLE, interpolation=cv2.INTER_LINEAR)
    dark = (up < fraction * float(np.median(paper))).astype(np.uint8)
    contours, _ = cv2.findContours(dark, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    pts = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
    return (pts + 0.5) / UPSAMPLE - 0.5 + (x0, y0)


@contextmanager
def previous_locate() -> Iterator[None]:
    """cell.vision.locate.locate runs the previous geometry while inside (one thread at a time)."""
    from cell.vision import locate as module

    names = {
        "Bolt": Bolt,
        "Nut": Nut,
        "footprint_centre": footprint_centre,
        "nut_from_outline": nut_from_outline,
        "polygon_moments": polygon_moments,
        "subpixel_outline": subpixel_outline,
    }
    saved = {name: getattr(module, name) for name in names}
    try:
        for name, value in names.items():
            setattr(module, name, value)
        yield
    finally:
        for name, value in saved.items():
            setattr(module, name, value)

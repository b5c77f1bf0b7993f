"""Where a part stands, from the shadow it casts: the forward model of a backlit silhouette.

A backlit part's outline is the outline of its shadow on the table as seen from the camera
centre C: every point of the part, at height z above the table, is seen where its ray meets
the table plane, X0 = C + (X - C) H / (H - z). The calibration maps pixels onto that plane
exactly (whatever the lens), so the outline mapped at height 0 is that shadow, and the shadow's
area centroid can be predicted for a part of known shape standing at footprint centre c:

- a nut is a hexagonal prism: its shadow is the hull of the bottom hexagon and the top one,
  the top one magnified by H / (H - t) about C's foot; that hull's centroid is not the
  half-height point (the nearer, larger face weighs more: 0.15 mm for an M10 nut 300 mm below
  the camera, whatever its place in the view);
- a bolt on its side is a hexagonal head on a flat and a round shaft: the union of two hulls.

The footprint centre is then the c whose predicted shadow centroid is the measured one: c moves
by the difference until they agree (the offset changes slowly with c: two steps suffice).
Only the camera centre enters, never the lens.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

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
    xs, ys = np.roll(x, -1), np.roll(y, -1)
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
    origin = hulls[0].mean(axis=0)
    overlap, inter = cv2.intersectConvexConvex(
        (hulls[0] - origin).astype(np.float32), (hulls[1] - origin).astype(np.float32)
    )
    a12, c12 = (0.0, c1) if inter is None or overlap <= 0 else polygon_moments(inter.reshape(-1, 2) + origin)
    area = a1 + a2 - a12
    return area, (a1 * c1 + a2 * c2 - a12 * c12) / max(area, 1e-12)


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
    shape: Shape, measured_mm: np.ndarray, camera_centre: np.ndarray, start_mm: np.ndarray | None = None, steps: int = 3
) -> np.ndarray:
    """The footprint centre whose shadow's centroid is `measured_mm` (the outline's centroid on
    the table plane); `start_mm` a first guess (default: the measured centroid)."""
    measured = np.asarray(measured_mm, dtype=np.float64)
    c = measured.copy() if start_mm is None else np.asarray(start_mm, dtype=np.float64).copy()
    for _ in range(steps):
        c = c + (measured - shadow_moments(shape, c, camera_centre)[1])
    return c


def nut_from_outline(outline_mm: np.ndarray, across_flats_mm: float, thickness_ratio: float, camera_centre) -> Nut:
    """The nut whose shadow best covers this outline (on the table plane): the corner direction
    first from the outline's sixth harmonic, then the one whose shadow overlaps the outline most
    (the shadow's stretch skews the harmonic), the across flats from the area (which grows as
    its square), the thickness `thickness_ratio` times that."""
    area, centre = polygon_moments(outline_mm)
    z = (outline_mm[:, 0] - centre[0]) + 1j * (outline_mm[:, 1] - centre[1])
    turn = np.angle(np.roll(z, -1) * np.conj(z))
    corner = -math.degrees(float(np.angle(np.sum(np.abs(z) * np.exp(-6j * np.angle(z)) * turn)))) / 6
    outline = _hull(outline_mm)
    af = across_flats_mm

    def miss(corner_deg: float) -> float:
        """Area of the outline and the shadow outside each other (the shadow placed on the outline's centroid)."""
        nut = Nut(af, thickness_ratio * af, corner_deg)
        hull = _hull(shadow(nut.solids(centre)[0], camera_centre))
        hull += centre - polygon_moments(hull)[1]
        origin = centre
        both, _ = cv2.intersectConvexConvex((outline - origin).astype(np.float32), (hull - origin).astype(np.float32))
        return area + polygon_moments(hull)[0] - 2 * both

    for _ in range(2):
        model, _ = shadow_moments(Nut(af, thickness_ratio * af, corner), centre, camera_centre)
        af *= math.sqrt(area / max(model, 1e-9))
        corner = _golden_minimum(miss, corner - 10.0, corner + 10.0, 10)
    model, _ = shadow_moments(Nut(af, thickness_ratio * af, corner), centre, camera_centre)
    af *= math.sqrt(area / max(model, 1e-9))
    return Nut(af, thickness_ratio * af, corner)


def _golden_minimum(f: Callable[[float], float], lo: float, hi: float, steps: int) -> float:
    g = (math.sqrt(5) - 1) / 2
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = f(a), f(b)
    for _ in range(steps):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = f(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = f(b)
    return (a + b) / 2

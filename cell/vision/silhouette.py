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
from dataclasses import dataclass

import cv2
import numpy as np

_SWEEP_DEG = 12.0  # edges this close to the sweep's direction are the sweep's, not a side's
_RING = 96  # points on a shaft's rim (as the renderer draws it)


def _unit_circle(angles: np.ndarray) -> np.ndarray:
    return np.column_stack([np.cos(angles), np.sin(angles)])


_RING_COS_SIN = _unit_circle(np.linspace(0.0, 2 * np.pi, _RING, endpoint=False))  # a shaft's rim
_HEX_COS_SIN = _unit_circle(np.deg2rad(60.0 * np.arange(6)))  # a bolt head's corners


def shadow(points_xyz: np.ndarray, camera_centre: np.ndarray) -> np.ndarray:
    """(N, 2) where each point (X, Y, height) is seen on the table plane from the camera centre."""
    p = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(camera_centre, dtype=np.float64)
    k = c[2] / np.maximum(c[2] - p[:, 2], 1e-9)
    return c[:2] + (p[:, :2] - c[:2]) * k[:, None]


def polygon_moments(poly: np.ndarray) -> tuple[float, np.ndarray]:
    """Area (positive) and area centroid of a simple polygon (N, 2)."""
    nxt = np.concatenate((poly[1:], poly[:1]))
    cross = poly[:, 0] * nxt[:, 1] - nxt[:, 0] * poly[:, 1]
    a = float(cross.sum()) / 2
    if abs(a) < 1e-12:
        return 0.0, poly.mean(axis=0)
    return abs(a), (cross @ (poly + nxt)) / (6 * a)


def _hull(points: np.ndarray) -> np.ndarray:
    """The convex hull of (N, 2) points, counter-clockwise (positive area), in float64: OpenCV picks
    the vertices (in float32, about the points' mean) and the float64 points are kept."""
    origin = points.mean(axis=0)
    index = cv2.convexHull((points - origin).astype(np.float32), clockwise=False, returnPoints=False).reshape(-1)
    hull = points[index]
    x, y = hull[:, 0], hull[:, 1]
    if float(x[:-1] @ y[1:] - x[1:] @ y[:-1] + x[-1] * y[0] - x[0] * y[-1]) < 0:
        hull = hull[::-1]
    return hull


def _union_moments(hulls: list[np.ndarray]) -> tuple[float, np.ndarray]:
    """Area and area centroid of the union of two convex polygons (or of one), each counter-clockwise."""
    if len(hulls) == 1:
        return polygon_moments(hulls[0])
    (a1, c1), (a2, c2) = polygon_moments(hulls[0]), polygon_moments(hulls[1])
    inter = _intersection(hulls[0], hulls[1])
    a12, c12 = (0.0, c1) if len(inter) < 3 else polygon_moments(inter)
    area = a1 + a2 - a12
    return area, (a1 * c1 + a2 * c2 - a12 * c12) / max(area, 1e-12)


def _intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The intersection of two counter-clockwise convex polygons, in float64, all at once: the
    vertices of each inside the other, and the points where an edge of one crosses an edge of the
    other, in order of their angle about their mean. (OpenCV's intersectConvexConvex returns the
    wrong polygon for the head's and the shaft's shadows, which share an edge where they join.)

    A vertex counts as inside when it lies within a hair of every edge (a cross product of 1e-12
    mm^2): a point on a shared edge is kept, and what this adds or leaves out is that small."""
    na = len(a)
    ea = np.concatenate((a[1:], a[:1])) - a
    eb = np.concatenate((b[1:], b[:1])) - b
    bx, by = b.T.copy()  # contiguous: the products below run along b
    ebx, eby = eb.T.copy()
    ax, ay = a[:, 0:1], a[:, 1:2]
    # Both (len(a), len(b)): side_a[i, j], where a's vertex i lies from b's edge j (> 0: to its left,
    # inside); side_b[i, j], where b's vertex j lies from a's edge i.
    side_a = ebx * (ay - by) - eby * (ax - bx)
    side_b = ea[:, 0:1] * (by - ay) - ea[:, 1:2] * (bx - ax)
    hair = 1e-12  # mm^2: about the part (the caster's frame), 1e-12 / an edge's length off it
    kept = [a[(side_a >= -hair).all(axis=1)], b[(side_b >= -hair).all(axis=0)]]
    # a's edge i (from vertex i to i + 1) crosses b's edge j where both change side.
    pa, pb = side_a >= 0, side_b >= 0
    crosses = (pa != np.concatenate((pa[1:], pa[:1]))) & (pb != np.concatenate((pb[:, 1:], pb[:, :1]), axis=1))
    i, j = np.nonzero(crosses)
    if len(i):
        from_i = side_a[i, j]
        i_next = i + 1
        i_next[i_next == na] = 0
        t = from_i / (from_i - side_a[i_next, j])
        kept.append(a[i] + ea[i] * t[:, None])
    pts = np.concatenate(kept)
    if len(pts) < 3:
        return np.zeros((0, 2))
    d = pts - np.add.reduce(pts, axis=0) / len(pts)  # pts.mean(axis=0), without its overhead
    return pts[np.argsort(np.arctan2(d[:, 1], d[:, 0]), kind="stable")]


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

    def frame(self) -> tuple[np.ndarray, tuple[float, float], np.ndarray, tuple[float, float], np.ndarray, np.ndarray]:
        """The head's and the shaft's rings (across the axis, height: (n, 2)) and where along the
        axis each prism begins and ends, then the axis and across-axis unit vectors."""
        s, k, d, L = self.head_across_flats_mm, self.head_length_mm, self.shaft_mm, self.shaft_length_mm
        e = 2 * s / math.sqrt(3)  # the head's width seen from above (across corners)
        u0 = -(k * e * (-k / 2) + L * d * (L / 2)) / (k * e + L * d)  # head-shaft junction
        a = math.radians(self.axis_deg)
        axis, side = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
        head_vz = (e / 2) * _HEX_COS_SIN + (0.0, s / 2)
        shaft_vz = (d / 2) * _RING_COS_SIN + (0.0, s / 2)
        return head_vz, (u0 - k, u0), shaft_vz, (u0, u0 + L), axis, side

    def solids(self, centre: np.ndarray) -> list[np.ndarray]:
        head_vz, head_u, shaft_vz, shaft_u, axis, side = self.frame()

        def prism(vz: np.ndarray, u_from: float, u_to: float) -> np.ndarray:
            ends = [centre + u * axis + vz[:, :1] * side for u in (u_from, u_to)]
            return np.column_stack([np.vstack(ends), np.concatenate([vz[:, 1], vz[:, 1]])])

        return [prism(head_vz, *head_u), prism(shaft_vz, *shaft_u)]


Shape = Nut | Bolt


class _Caster:
    """One shape's shadows from one camera centre, for any footprint centre c: each solid's points
    and their magnifications k = H / (H - z) are computed once, at footprint centre 0; at c a point
    is seen at base + k c, which is kept relative to c (c + (base + (k - 1) c)), where float32 holds
    it to 1e-6 mm: OpenCV then takes the hulls and their moments in one call each."""

    def __init__(self, shape: Shape, camera_centre: np.ndarray):
        c = np.asarray(camera_centre, dtype=np.float64)
        self.solids: list[tuple[np.ndarray, np.ndarray]] = []
        if isinstance(shape, Nut):  # the bottom hexagon (k = 1) and the top one
            r = shape.across_flats_mm / math.sqrt(3)
            hexagon = r * _unit_circle(np.deg2rad(shape.corner_deg + 60.0 * np.arange(6)))
            k = c[2] / max(c[2] - shape.thickness_mm, 1e-9)
            base = np.concatenate((hexagon, c[:2] + (hexagon - c[:2]) * k))
            self.solids.append((base, np.repeat([[0.0], [k - 1.0]], 6, axis=0)))
            return
        # A bolt: the head's end faces (6 corners each) and the shaft's (_RING points each), all at
        # the heights of their ring, so the magnifications are computed once per ring.
        head_vz, head_u, shaft_vz, shaft_u, axis, side = shape.frame()
        for vz, ends in ((head_vz, head_u), (shaft_vz, shaft_u)):
            k = c[2] / np.maximum(c[2] - vz[:, 1:], 1e-9)  # (n, 1)
            local = vz[:, :1] * side  # (n, 2): across the axis
            along = np.array(ends, dtype=np.float64).reshape(-1, 1, 1) * axis  # (2, 1, 2): each end face's
            base = (c[:2] + (along + local - c[:2]) * k).reshape(-1, 2)  # the two faces' points, one after the other
            self.solids.append((base, np.concatenate((k, k)) - 1.0))

    def moments(self, centre: np.ndarray) -> tuple[float, np.ndarray]:
        hulls = [cv2.convexHull((base + k1 * centre).astype(np.float32), clockwise=False) for base, k1 in self.solids]
        area, offset = _hull_moments(hulls[0])
        if len(hulls) == 2:  # the union: both areas, less their overlap
            a2, c2 = _hull_moments(hulls[1])
            overlap = _intersection(
                hulls[0].reshape(-1, 2).astype(np.float64), hulls[1].reshape(-1, 2).astype(np.float64)
            )
            a12, c12 = (0.0, offset) if len(overlap) < 3 else polygon_moments(overlap)
            union = area + a2 - a12
            # the 2-vectors' arithmetic in Python floats: the same operations, without numpy's overhead
            (o0, o1), (d0, d1), (e0, e1), u = offset.tolist(), c2.tolist(), c12.tolist(), max(union, 1e-12)
            offset = np.array([(area * o0 + a2 * d0 - a12 * e0) / u, (area * o1 + a2 * d1 - a12 * e1) / u])
            area = union
        return area, centre + offset


def _hull_moments(hull: np.ndarray) -> tuple[float, np.ndarray]:
    """Area and area centroid of a polygon OpenCV holds (float32, N x 1 x 2)."""
    m = cv2.moments(hull)
    if m["m00"] <= 0:
        return 0.0, hull.reshape(-1, 2).astype(np.float64).mean(axis=0)
    return m["m00"], np.array([m["m10"], m["m01"]]) / m["m00"]


def shadow_moments(shape: Shape, centre: np.ndarray, camera_centre: np.ndarray) -> tuple[float, np.ndarray]:
    """Area and area centroid of the shadow `shape` casts on the table plane from the camera centre."""
    return _Caster(shape, camera_centre).moments(np.asarray(centre, dtype=np.float64))


def footprint_centre(
    shape: Shape, measured_mm: np.ndarray, camera_centre: np.ndarray, start_mm: np.ndarray | None = None, steps: int = 2
) -> np.ndarray:
    """The footprint centre whose shadow's centroid is `measured_mm` (the outline's centroid on
    the table plane); `start_mm` a first guess (default: the measured centroid)."""
    measured = np.asarray(measured_mm, dtype=np.float64)
    c = measured.copy() if start_mm is None else np.asarray(start_mm, dtype=np.float64).copy()
    caster = _Caster(shape, camera_centre)
    for _ in range(steps):
        c = c + (measured - caster.moments(c)[1])
    return c


def nut_from_outline(
    outline_mm: np.ndarray,
    across_flats_mm: float,
    thickness_ratio: float,
    camera_centre,
    moments: tuple[float, np.ndarray] | None = None,
) -> Nut:
    """The nut whose shadow has this outline (on the table plane): the corner direction from the
    outline's edges, the across flats from its area (which grows as the square), the thickness
    `thickness_ratio` times that.

    The shadow is the bottom hexagon swept to the top one: its edges run along the hexagon's six
    sides, and two along the sweep (towards the camera's foot), which are left out. So the sides'
    direction is the sixth harmonic of the edge directions weighed by length, the sweep's excepted.
    `moments`: polygon_moments(outline_mm) where the caller has them.
    """
    area, centre = polygon_moments(outline_mm) if moments is None else moments
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

"""Bolts, nuts and washers on the backlit table, seen through the same camera as the plate.

Each part is a small set of convex 3-D solids (hex prism, cylinder) standing on the table
(height 0 = table, heights in mm above it, X/Y in the table frame). A backlit part is an
opaque silhouette: a convex solid's silhouette is the convex hull of its projected
corners, computed on undistorted pixels (perspective keeps convexity) and then bent by the
lens distortion. A through-hole passes light only where both its openings project, so
its visible opening is the intersection of the two projected rims. Edges are
anti-aliased by 8x supersampling inside each part's bounding box.

Poses are idealised: nuts and washers lie flat; a bolt lies on its side with its head
on a flat and its axis parallel to the table, at half the head's across-flats height.

Typical use (helper code for the simulated cell reuses these):

    parts = random_scene(seed=3)
    frame = render_scene(camera, parts)                 # BGR uint8
    opacity = scene_opacity(camera, parts)              # float 0..1, to composite
    truth = [(p.kind, p.footprint_centre_mm, p.axis_angle_deg) for p in parts]
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from cell.camera_model import CameraModel
from cell.sim.render import Optics, expose

# ISO 4032 nuts: across flats, thickness (rounded as in the issue), thread minor diameter
# (what light passes through).
NUTS_MM = {
    "M5": {"across_flats": 8.0, "thickness": 4.0, "hole": 4.13},
    "M6": {"across_flats": 10.0, "thickness": 5.0, "hole": 4.92},
    "M8": {"across_flats": 13.0, "thickness": 6.5, "hole": 6.65},
    "M10": {"across_flats": 16.0, "thickness": 8.0, "hole": 8.38},
}
# ISO 4017 hex-head bolts: head across flats, head height, shaft diameter.
BOLTS_MM = {
    "M5": {"across_flats": 8.0, "head_height": 3.5, "shaft": 5.0},
    "M6": {"across_flats": 10.0, "head_height": 4.0, "shaft": 6.0},
    "M8": {"across_flats": 13.0, "head_height": 5.3, "shaft": 8.0},
}
# ISO 7089 plain washers: outer and inner diameter, thickness.
WASHERS_MM = {
    "M5": {"outer": 10.0, "inner": 5.3, "thickness": 1.0},
    "M6": {"outer": 12.0, "inner": 6.4, "thickness": 1.6},
    "M8": {"outer": 16.0, "inner": 8.4, "thickness": 1.6},
    "M10": {"outer": 20.0, "inner": 10.5, "thickness": 2.0},
}
COIN_MM = {"diameter": 23.25, "thickness": 2.33}  # a 1-euro coin: round, no hole

_CIRCLE_SAMPLES = 96
_SUPERSAMPLE = 8


@dataclass(frozen=True)
class PartSpec:
    """One part on the table.

    kind: 'nut' | 'bolt' | 'washer' | 'coin'. size: 'M5'...'M10' (ignored for coins).
    length_mm: bolts only, shaft length under the head. (x_mm, y_mm): the footprint
    centre in the table frame, i.e. the area centroid of the outline seen from straight
    above. angle_deg: table frame, counter-clockwise from +X; for a bolt the direction
    from the head towards the tip, for a nut the direction of one corner.
    """

    kind: str
    size: str
    x_mm: float
    y_mm: float
    angle_deg: float = 0.0
    length_mm: float | None = None

    def __post_init__(self) -> None:
        tables = {"nut": NUTS_MM, "bolt": BOLTS_MM, "washer": WASHERS_MM}
        if self.kind == "coin":
            return
        if self.kind not in tables:
            raise ValueError(f"unknown part kind {self.kind!r}")
        if self.size not in tables[self.kind]:
            raise ValueError(f"no {self.kind} of size {self.size!r} (have {sorted(tables[self.kind])})")
        if self.kind == "bolt" and not (self.length_mm and self.length_mm > 0):
            raise ValueError("a bolt needs length_mm > 0")

    @property
    def dims(self) -> dict:
        if self.kind == "coin":
            return COIN_MM
        return {"nut": NUTS_MM, "bolt": BOLTS_MM, "washer": WASHERS_MM}[self.kind][self.size]

    @property
    def footprint_centre_mm(self) -> tuple[float, float]:
        return (self.x_mm, self.y_mm)

    @property
    def axis_angle_deg(self) -> float | None:
        """Bolts: the axis direction in the table frame, 0-180 degrees; else None."""
        return self.angle_deg % 180.0 if self.kind == "bolt" else None

    @property
    def height_mm(self) -> float:
        """Highest point above the table."""
        d = self.dims
        if self.kind == "bolt":
            return d["across_flats"]
        return d["thickness"]

    @property
    def head_centre_mm(self) -> tuple[float, float] | None:
        """Bolts: centre of the head's top-view rectangle, table mm."""
        if self.kind != "bolt":
            return None
        u0 = self._bolt_axis_offset_mm()
        u = u0 - self.dims["head_height"] / 2
        return tuple(self._to_table(np.array([[u, 0.0]]))[0])

    @property
    def shaft_length_mm(self) -> float:
        """Bolts: the shaft length under the head; ValueError for any other part."""
        if self.length_mm is None:
            raise ValueError(f"a {self.kind} has no shaft length")
        return self.length_mm

    @property
    def shaft_middle_offset_mm(self) -> float | None:
        """Bolts: how far the middle of the shaft (where the cell grips) lies from the footprint
        centre, along the axis towards the tip; else None."""
        return self._bolt_axis_offset_mm() + self.shaft_length_mm / 2 if self.kind == "bolt" else None

    def _dir(self) -> np.ndarray:
        a = math.radians(self.angle_deg)
        return np.array([math.cos(a), math.sin(a)])

    def _to_table(self, uv: np.ndarray) -> np.ndarray:
        """Part frame (u along angle_deg, v to its left) -> table (X, Y)."""
        d = self._dir()
        n = np.array([-d[1], d[0]])
        return np.array([self.x_mm, self.y_mm]) + uv[:, :1] * d + uv[:, 1:2] * n

    def _bolt_axis_offset_mm(self) -> float:
        """u of the head's underside relative to the footprint centre (centre at u = 0)."""
        d = self.dims
        k, e = d["head_height"], d["across_flats"] * 2 / math.sqrt(3)
        L, ds = self.shaft_length_mm, d["shaft"]
        u_c = (k * e * (-k / 2) + L * ds * (L / 2)) / (k * e + L * ds)
        return -u_c

    def top_view_outline_mm(self) -> np.ndarray:
        """(N, 2) table-mm polygon of the outer outline seen from straight above."""
        d = self.dims
        if self.kind == "nut":
            r = d["across_flats"] / math.sqrt(3)
            a = np.deg2rad(self.angle_deg + 60.0 * np.arange(6))
            return np.column_stack([self.x_mm + r * np.cos(a), self.y_mm + r * np.sin(a)])
        if self.kind == "bolt":
            u0 = self._bolt_axis_offset_mm()
            k, e = d["head_height"], d["across_flats"] * 2 / math.sqrt(3)
            L, r = self.shaft_length_mm, d["shaft"] / 2
            uv = np.array(
                [
                    [u0 - k, -e / 2],
                    [u0, -e / 2],
                    [u0, -r],
                    [u0 + L, -r],
                    [u0 + L, r],
                    [u0, r],
                    [u0, e / 2],
                    [u0 - k, e / 2],
                ]
            )
            return self._to_table(uv)
        radius = (d["outer"] if self.kind == "washer" else d["diameter"]) / 2
        a = np.linspace(0, 2 * np.pi, _CIRCLE_SAMPLES, endpoint=False)
        return np.column_stack([self.x_mm + radius * np.cos(a), self.y_mm + radius * np.sin(a)])

    def solids(self) -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
        """(convex solids, through-holes) as 3-D points (X, Y, height) in table mm.

        A solid is the convex hull of its points; a hole is its two rims (bottom, top).
        """
        d = self.dims
        circle = np.linspace(0, 2 * np.pi, _CIRCLE_SAMPLES, endpoint=False)
        ring = np.column_stack([np.cos(circle), np.sin(circle)])

        def at(xy: np.ndarray, h: float) -> np.ndarray:
            return np.column_stack([xy, np.full(len(xy), h)])

        c = np.array([self.x_mm, self.y_mm])
        if self.kind == "nut":
            hexagon = self.top_view_outline_mm()
            t = d["thickness"]
            rim = c + ring * d["hole"] / 2
            return [np.vstack([at(hexagon, 0.0), at(hexagon, t)])], [(at(rim, 0.0), at(rim, t))]
        if self.kind in ("washer", "coin"):
            t = d["thickness"]
            outer = c + ring * (d["outer"] if self.kind == "washer" else d["diameter"]) / 2
            disc = np.vstack([at(outer, 0.0), at(outer, t)])
            if self.kind == "coin":
                return [disc], []
            rim = c + ring * d["inner"] / 2
            return [disc], [(at(rim, 0.0), at(rim, t))]
        # Bolt on its side: axis along u at height s / 2, head on a flat.
        s, k, L = d["across_flats"], d["head_height"], self.shaft_length_mm
        z_axis = s / 2
        u0 = self._bolt_axis_offset_mm()
        R = s / math.sqrt(3)
        a = np.deg2rad(60.0 * np.arange(6))
        hex_vz = np.column_stack([R * np.cos(a), z_axis + R * np.sin(a)])
        shaft_vz = np.column_stack([ring[:, 0] * d["shaft"] / 2, z_axis + ring[:, 1] * d["shaft"] / 2])

        def prism(vz: np.ndarray, u_from: float, u_to: float) -> np.ndarray:
            ends = [self._to_table(np.column_stack([np.full(len(vz), u), vz[:, 0]])) for u in (u_from, u_to)]
            return np.column_stack([np.vstack(ends), np.concatenate([vz[:, 1], vz[:, 1]])])

        return [prism(hex_vz, u0 - k, u0), prism(shaft_vz, u0, u0 + L)], []


def _ideal_pixels(camera: CameraModel, pts_mm: np.ndarray) -> np.ndarray:
    """Undistorted pixel positions (pinhole only) of 3-D table points (X, Y, height)."""
    obj = np.column_stack([pts_mm[:, :2], -pts_mm[:, 2]])
    cam = obj @ camera.rotation.T + camera.tvec
    xn = cam[:, :2] / cam[:, 2:3]
    K = camera.camera_matrix
    return xn @ K[:2, :2].T + K[:2, 2]


def _distort(camera: CameraModel, ideal_px: np.ndarray) -> np.ndarray:
    K = camera.camera_matrix
    xn = (ideal_px - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T
    pts = np.column_stack([xn, np.ones(len(xn))])
    px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, camera.dist_coeffs)
    return px.reshape(-1, 2)


def _densify(poly: np.ndarray, step_px: float = 1.0) -> np.ndarray:
    out = []
    for p, q in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        n = max(1, int(math.ceil(np.hypot(*(q - p)) / step_px)))
        t = np.arange(n)[:, None] / n
        out.append(p + t * (q - p))
    return np.vstack(out)


def _convex_outline_px(camera: CameraModel, pts_mm: np.ndarray) -> np.ndarray:
    """Distorted-pixel polygon of the silhouette of the convex hull of `pts_mm`."""
    ideal = _ideal_pixels(camera, pts_mm).astype(np.float32)
    hull = cv2.convexHull(ideal).reshape(-1, 2).astype(np.float64)
    return _distort(camera, _densify(hull))


@dataclass(frozen=True, eq=False)
class ExtrudedPart:
    """A flat part of any shape: its top-view outline and holes (its own frame, mm, the origin at
    the footprint's area centroid with the holes taken out) extruded to `height_mm`, lying at
    (x_mm, y_mm) turned by `angle_deg` (counter-clockwise from +X). A taught part type's stand-in."""

    name: str
    outline_mm: np.ndarray
    holes_mm: tuple[np.ndarray, ...]
    height_mm: float
    x_mm: float = 0.0
    y_mm: float = 0.0
    angle_deg: float = 0.0

    kind = "extruded"

    @property
    def footprint_centre_mm(self) -> tuple[float, float]:
        return (self.x_mm, self.y_mm)

    def placed(self, x_mm: float, y_mm: float, angle_deg: float) -> ExtrudedPart:
        return ExtrudedPart(self.name, self.outline_mm, self.holes_mm, self.height_mm, x_mm, y_mm, angle_deg)

    def to_table(self, uv: np.ndarray) -> np.ndarray:
        """Part frame -> table mm."""
        a = math.radians(self.angle_deg)
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        return np.asarray(uv, dtype=np.float64) @ rot.T + (self.x_mm, self.y_mm)

    def top_view_outline_mm(self) -> np.ndarray:
        return self.to_table(self.outline_mm)

    def top_view_holes_mm(self) -> list[np.ndarray]:
        return [self.to_table(h) for h in self.holes_mm]


def _polygon_px(camera: CameraModel, pts_mm: np.ndarray) -> np.ndarray:
    """Distorted-pixel polygon of a flat polygon (X, Y, height), convex or not."""
    return _distort(camera, _densify(_ideal_pixels(camera, pts_mm)))


def _extruded_polygons(
    camera: CameraModel, part: ExtrudedPart
) -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """The pixel polygons whose union is an extruded part's silhouette (bottom, top, each wall),
    and each hole's two openings."""
    h = part.height_mm

    def at(xy: np.ndarray, z: float) -> np.ndarray:
        return np.column_stack([xy, np.full(len(xy), z)])

    outline = part.top_view_outline_mm()
    polys = [_polygon_px(camera, at(outline, 0.0)), _polygon_px(camera, at(outline, h))]
    for p, q in zip(outline, np.roll(outline, -1, axis=0), strict=True):
        wall = np.array([[*p, 0.0], [*q, 0.0], [*q, h], [*p, h]])
        polys.append(_convex_outline_px(camera, wall))
    holes = [(_polygon_px(camera, at(x, 0.0)), _polygon_px(camera, at(x, h))) for x in part.top_view_holes_mm()]
    return polys, holes


def part_coverage(camera: CameraModel, part: PartSpec | ExtrudedPart) -> tuple[tuple[int, int], np.ndarray] | None:
    """((x0, y0), coverage) of one part: fraction of each pixel in its box that is dark."""
    if isinstance(part, ExtrudedPart):
        solid_polys, hole_polys = _extruded_polygons(camera, part)
    else:
        solids, holes = part.solids()
        solid_polys = [_convex_outline_px(camera, s) for s in solids]
        hole_polys = [(_convex_outline_px(camera, b), _convex_outline_px(camera, t)) for b, t in holes]
    allpts = np.vstack(solid_polys)
    x0 = max(int(math.floor(allpts[:, 0].min())) - 2, 0)
    y0 = max(int(math.floor(allpts[:, 1].min())) - 2, 0)
    x1 = min(int(math.ceil(allpts[:, 0].max())) + 3, camera.width_px)
    y1 = min(int(math.ceil(allpts[:, 1].max())) + 3, camera.height_px)
    if x1 <= x0 or y1 <= y0:
        return None
    S, shift = _SUPERSAMPLE, 4
    shape = ((y1 - y0) * S, (x1 - x0) * S)

    def fill(poly: np.ndarray) -> np.ndarray:
        # Pixel (u, v) covers [u - 0.5, u + 0.5]; sub-pixel centres sit at k / S - 0.5 + 1 / 2S.
        sub = ((poly - (x0, y0) + 0.5) * S - 0.5) * (1 << shift)
        m = np.zeros(shape, np.uint8)
        cv2.fillPoly(m, [np.rint(sub).astype(np.int32)], 255, cv2.LINE_8, shift)
        return m

    mask = np.zeros(shape, np.uint8)
    for poly in solid_polys:  # painted one by one: a union (fillPoly of a list would not be one)
        sub = ((poly - (x0, y0) + 0.5) * S - 0.5) * (1 << shift)
        cv2.fillPoly(mask, [np.rint(sub).astype(np.int32)], 255, cv2.LINE_8, shift)
    for bottom, top in hole_polys:
        mask &= ~(fill(bottom) & fill(top))
    cov = cv2.resize(mask.astype(np.float32) / 255.0, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
    return (x0, y0), cov


def scene_opacity(camera: CameraModel, parts: Sequence[PartSpec | ExtrudedPart]) -> np.ndarray:
    """Opacity (0 clear, 1 opaque) of all parts, float64 at the camera's resolution."""
    opacity = np.zeros((camera.height_px, camera.width_px), np.float64)
    for part in parts:
        got = part_coverage(camera, part)
        if got is None:
            continue
        (x0, y0), cov = got
        sl = (slice(y0, y0 + cov.shape[0]), slice(x0, x0 + cov.shape[1]))
        np.maximum(opacity[sl], cov, out=opacity[sl])
    return opacity


def render_scene(
    camera: CameraModel,
    parts: Sequence[PartSpec | ExtrudedPart],
    optics: Optics = Optics(),
    seed: int = 0,
    exposure: float = 1.0,
) -> np.ndarray:
    """The backlit table with `parts` on it as the camera sees it (BGR uint8)."""
    return expose(camera, scene_opacity(camera, parts), optics, np.random.default_rng(seed), exposure)


def random_scene(
    seed: int = 0,
    n_parts: tuple[int, int] = (15, 20),
    n_washers: int = 2,
    area_mm: tuple[float, float, float, float] = (0.0, 0.0, 264.0, 176.0),
    gap_mm: float = 8.0,
    bolt_lengths_mm: tuple[float, ...] = (16, 20, 25, 30, 35),
) -> list[PartSpec]:
    """Non-touching nuts (M5-M10), bolts (M5-M8 x 16-35) and `n_washers` washers.

    Outlines stay inside `area_mm` (x0, y0, x1, y1: the plate's area by default) and at
    least `gap_mm` apart seen from above; the gap leaves room for parallax, which spreads
    a tall part's silhouette outwards by several mm near the edge of the view.
    """
    rng = np.random.default_rng(seed)
    total = int(rng.integers(n_parts[0], n_parts[1] + 1))
    kinds = ["washer"] * n_washers + [str(k) for k in rng.choice(["nut", "bolt"], total - n_washers)]
    x0, y0, x1, y1 = area_mm
    space = FreeSpace(area_mm, gap_mm)
    parts: list[PartSpec] = []
    for kind in kinds:
        for _ in range(500):
            if kind == "bolt":
                size = str(rng.choice(list(BOLTS_MM)))
                length = float(rng.choice(bolt_lengths_mm))
            else:
                size = str(rng.choice(list(NUTS_MM if kind == "nut" else WASHERS_MM)))
                length = None
            p = PartSpec(
                kind,
                size,
                float(rng.uniform(x0, x1)),
                float(rng.uniform(y0, y1)),
                float(rng.uniform(0, 360)),
                length,
            )
            if not space.claim(p.top_view_outline_mm()):
                continue
            parts.append(p)
            break
    return parts


class FreeSpace:
    """An occupancy grid of a table area (x0, y0, x1, y1 mm, 0.5 mm a cell) that places outlines at
    least `gap_mm` apart, each wholly inside the area."""

    RES_MM = 0.5

    def __init__(self, area_mm: tuple[float, float, float, float], gap_mm: float):
        self.x0, self.y0, self.x1, self.y1 = area_mm
        res = self.RES_MM
        self.grid = np.zeros((int((self.y1 - self.y0) / res) + 1, int((self.x1 - self.x0) / res) + 1), np.uint8)
        pad = int(math.ceil(gap_mm / 2 / res))
        self.kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * pad + 1, 2 * pad + 1))

    def claim(self, outline_mm: np.ndarray) -> bool:
        """Take the room for this outline (True), or leave the grid as it was: outside the area, or too near another."""
        if outline_mm[:, 0].min() < self.x0 or outline_mm[:, 0].max() > self.x1:
            return False
        if outline_mm[:, 1].min() < self.y0 or outline_mm[:, 1].max() > self.y1:
            return False
        filled = np.zeros_like(self.grid)
        cv2.fillPoly(filled, [np.rint((outline_mm - (self.x0, self.y0)) / self.RES_MM).astype(np.int32)], 1)
        cells = np.asarray(cv2.dilate(filled, self.kernel), dtype=np.uint8)
        if np.any(cells & self.grid):
            return False
        self.grid |= cells
        return True

"""Taught part types: a shape model learnt from example silhouettes, found at any angle with a score.

A taught part is a flat part of known height lying on the backlit table (a bracket, a plate, a
spacer, a clip): a prism, its top-view outline with holes extruded to its height. Its model is
data (`ShapeModel`, a JSON file the recipe names by its sha256):

- the footprint in the part's own frame: the outline and its holes in table millimetres, the
  origin at the footprint's area centroid (holes taken out), the x axis along its principal axis
  (for a shape whose inertia is round, the frame of the example it was learnt from);
- the rotational symmetry found from the shape (order n: the part looks the same turned by
  360/n degrees; 0 for a round part) and whether its mirror image is another part;
- the grip: where and at what angle the jaws close, and how far they must open.

The footprint seen in a frame comes from the silhouette through the calibration, corrected for
the part's height without any lens model: a backlit prism's outline is, on the side facing the
camera's foot, its bottom edge, and on the far side its top edge (seen further out). So each
outline point is mapped on the table plane or on the plane at the part's height by the direction
its outward normal faces; holes likewise (the light passes where both openings overlap).

Finding: the footprint is rasterised about its centroid; its angular harmonics per ring (the
Fourier series of the area in rings about the centroid) against the model's give the rotation
(the correlation's peak, refined by the harmonics' phases); the model drawn at that pose against
the footprint gives the fit: the area where they differ beyond an opening of `FIT_OPENING_MM` (so
an edge a tenth of a millimetre off does not count, a missing hole or a mirrored arm does), and
the overlap (intersection over union) as the score.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from cell.errors import CellError
from cell.vision.subpixel import median_level

SCHEMA = "pick-cell.shape-model"
SCHEMA_VERSION = 1
HARMONICS = 12  # angular harmonics compared per ring
HARMONIC_STEPS = 3  # the harmonics' raster is this many times coarser than the fit's (anti-aliased)
RINGS = 8
AREA_TOLERANCE = 0.05  # a footprint's area against the model's, relative (at least)
EXAMPLE_SPREAD = 2.0  # a found part may misfit its model this many times its worst example (up to 2 x the shape's)
FIT_OPENING_MM = 0.3  # differences thinner than twice this are edge noise, not shape
SYMMETRY_ORDERS = (8, 6, 5, 4, 3, 2)
_UPSAMPLE = 4  # at most; a large blob less (about 400 outline samples across it suffice)
_SAMPLES_ACROSS = 400
_MARGIN_PX = 4
_COARSE_STEPS = 720


class ShapeModelError(CellError):
    """A shape model file that cannot be used: unreadable, invalid, or not the file the recipe names."""


class TeachRefused(CellError):
    """The examples cannot make a model: they disagree, touch, leave the image, or cannot be gripped."""


# ---- the footprint of one silhouette ----------------------------------------------------------


@dataclass
class Footprint:
    """A part's footprint on the table: outer outline and holes (table mm, closed polygons)."""

    outer: np.ndarray
    holes: list[np.ndarray]
    area_mm2: float = 0.0
    centroid_mm: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def __post_init__(self) -> None:
        self._centre(net_moments([self.outer, *self.holes], second=False))

    @classmethod
    def _of_stacked(cls, pts: np.ndarray, bounds: Sequence[int], nxt: np.ndarray) -> Footprint:
        """The footprint of the outline and holes stacked in `pts` (each polygon from one bound to
        the next, `nxt` their _next_index): the same as Footprint(outer, holes), without stacking
        them again."""
        fp = cls.__new__(cls)
        fp.outer = pts[bounds[0] : bounds[1]]
        fp.holes = [pts[a:b] for a, b in zip(bounds[1:-1], bounds[2:], strict=True)]
        if len(bounds) == 2:
            fp._centre(_moments(fp.outer)[:3])
        else:
            fp._centre(_net_stacked(pts, nxt, bounds[:-1], second=False))
        return fp

    def _centre(self, moments: np.ndarray) -> None:
        a, sx, sy = moments[:3]
        if a <= 0:
            self.area_mm2, self.centroid_mm = 0.0, self.outer.mean(axis=0)
            return
        self.area_mm2 = float(a)
        self.centroid_mm = np.array([sx / a, sy / a])

    def _inertia(self) -> tuple[float, float, float]:
        """Second moments about the centroid per unit area (mxx, myy, mxy): made when asked (teaching)."""
        a, sx, sy, sxx, syy, sxy = net_moments([self.outer, *self.holes])
        if a <= 0:
            return 0.0, 0.0, 0.0
        cx, cy = sx / a, sy / a
        return sxx / a - cx * cx, syy / a - cy * cy, sxy / a - cx * cy

    @property
    def principal_deg(self) -> float:
        mxx, myy, mxy = self._inertia()
        return math.degrees(0.5 * math.atan2(2 * mxy, mxx - myy))

    @property
    def anisotropy(self) -> float:
        """(l1 - l2) / (l1 + l2) of the second moments: 0 round inertia."""
        mxx, myy, mxy = self._inertia()
        return float(math.hypot(mxx - myy, 2 * mxy) / max(mxx + myy, 1e-12))

    def in_frame(self, centre: np.ndarray, angle_deg: float) -> tuple[np.ndarray, list[np.ndarray]]:
        """The outline and holes moved to `centre` and turned by -angle (into a part's frame)."""
        a = math.radians(angle_deg)
        rot = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
        return (self.outer - centre) @ rot.T, [(h - centre) @ rot.T for h in self.holes]


def net_moments(polys: Sequence[np.ndarray], second: bool = True) -> np.ndarray:
    """_moments of the first polygon less those of the others (its holes), all in one pass; without
    `second`, the area and first moments alone."""
    if len(polys) == 1:
        return _moments(polys[0]) if second else _moments(polys[0])[:3]
    return _net_stacked(
        np.concatenate(polys), _next_index(polys), np.cumsum([0, *(len(p) for p in polys[:-1])]), second
    )


def _net_stacked(pts: np.ndarray, nxt: np.ndarray, starts: Sequence[int] | np.ndarray, second: bool) -> np.ndarray:
    """net_moments of the polygons stacked in `pts` (`nxt`: their _next_index; `starts`: where each begins)."""
    x, y = pts[:, 0], pts[:, 1]
    xn, yn = x[nxt], y[nxt]
    c = x * yn - xn * y
    rows = [c / 2, (x + xn) * c / 6, (y + yn) * c / 6]
    if second:
        rows += [
            (x * x + x * xn + xn * xn) * c / 12,
            (y * y + y * yn + yn * yn) * c / 12,
            (x * yn + 2 * x * y + 2 * xn * yn + xn * y) * c / 24,
        ]
    per = np.add.reduceat(np.stack(rows), starts, axis=1)  # (terms, polygons)
    per *= np.where(per[0] < 0, -1.0, 1.0)  # each orientation-free
    return per[:, 0] - per[:, 1:].sum(axis=1)


def _next_index(polys: Sequence[np.ndarray]) -> np.ndarray:
    """For the polygons stacked, the index of each point's successor along its own polygon."""
    n = np.array([len(p) for p in polys])
    ends = np.cumsum(n)
    nxt = np.arange(1, ends[-1] + 1)
    nxt[ends - 1] = ends - n
    return nxt


def _moments(poly: np.ndarray) -> np.ndarray:
    """Area, first and second moments (A, Sx, Sy, Sxx, Syy, Sxy) of a simple polygon, orientation-free."""
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.concatenate((x[1:], x[:1])), np.concatenate((y[1:], y[:1]))
    c = x * yn - xn * y
    a = c.sum() / 2
    sx = ((x + xn) * c).sum() / 6
    sy = ((y + yn) * c).sum() / 6
    sxx = ((x * x + x * xn + xn * xn) * c).sum() / 12
    syy = ((y * y + y * yn + yn * yn) * c).sum() / 12
    sxy = ((x * yn + 2 * x * y + 2 * xn * yn + xn * y) * c).sum() / 24
    m = np.array([a, sx, sy, sxx, syy, sxy])
    return -m if a < 0 else m


def fine_outlines(
    gray: np.ndarray, outline: np.ndarray, fraction: float, min_hole_px: float
) -> tuple[np.ndarray, list[np.ndarray]] | None:
    """The blob's outer outline and its holes to a fraction of a pixel (image px): the threshold's
    contour on the grey image interpolated 4x (as subpixel.py does for the outer outline alone)."""
    H, W = gray.shape
    x, y, w, h = cv2.boundingRect(outline)
    x0, y0 = max(x - _MARGIN_PX, 0), max(y - _MARGIN_PX, 0)
    x1, y1 = min(x + w + _MARGIN_PX, W), min(y + h + _MARGIN_PX, H)
    roi = gray[y0:y1, x0:x1]
    part = np.zeros(roi.shape, np.uint8)
    cv2.drawContours(part, [outline], -1, 255, -1, offset=(-x0, -y0))
    paper = roi[cv2.dilate(part, np.ones((5, 5), np.uint8)) == 0]
    if paper.size < 16:
        return None
    level = fraction * median_level(paper)
    k = int(np.clip(round(_SAMPLES_ACROSS / max(w, h, 1)), 1, _UPSAMPLE))
    up = cv2.resize(roi, None, fx=k, fy=k, interpolation=cv2.INTER_LINEAR) if k > 1 else roi
    # 1 where up < level: for whole levels, up <= ceil(level) - 1.
    _, dark = cv2.threshold(up, math.ceil(level) - 1, 1, cv2.THRESH_BINARY_INV)
    # Only this blob: its filled outline, grown a little (a neighbour's edge in the box is not it).
    keep = cv2.dilate(part, np.ones((3, 3), np.uint8))
    # An upsampled pixel is a convex mix (whole weights) of the ROI's pixels within one of the one
    # it is upsampled from, so it is below the level only if one of those is: when every ROI pixel
    # below the level lies within `keep` shrunk by one, every dark upsampled pixel lies in `keep`
    # upsampled, and the mask would change nothing (most blobs: no neighbour in the box).
    _, below = cv2.threshold(roi, math.ceil(level) - 1, 1, cv2.THRESH_BINARY_INV)
    if cv2.countNonZero(cv2.subtract(cv2.dilate(below, np.ones((3, 3), np.uint8)), keep)):
        keep = cv2.resize(keep, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST) if k > 1 else keep
        cv2.bitwise_and(dark, keep, dst=dark)
    contours, hierarchy = cv2.findContours(dark, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    if not contours or hierarchy is None:
        return None
    hier = hierarchy[0]
    outers = [i for i in range(len(contours)) if hier[i][3] == -1]
    best = max(outers, key=lambda i: cv2.contourArea(contours[i]))

    def px(c: np.ndarray) -> np.ndarray:
        return (c.reshape(-1, 2).astype(np.float64) + 0.5) / k - 0.5 + (x0, y0)

    holes = []
    j = hier[best][2]
    while j != -1:
        if cv2.contourArea(contours[j]) >= min_hole_px * k**2:
            holes.append(px(contours[j]))
        j = hier[j][0]
    return px(contours[best]), holes


def far_sides(polys: Sequence[np.ndarray], foot: np.ndarray) -> list[np.ndarray]:
    """Per point of the outer outline (first) and the holes: whether its side faces away from the
    camera's foot (what is seen there is the part's top edge)."""
    st = _Stack.of(polys)
    return np.split(st.far(foot), st.bounds[1:-1])


@dataclass(frozen=True)
class _Stack:
    """An outline and its holes stacked in one array (each polygon from one bound to the next),
    with each point's successor along its polygon: made once per silhouette, for every height."""

    pts: np.ndarray
    n: list[int]
    bounds: list[int]
    nxt: np.ndarray

    @staticmethod
    def of(polys: Sequence[np.ndarray]) -> _Stack:
        n = [len(p) for p in polys]
        return _Stack(np.concatenate(polys), n, [0, *np.cumsum(n).tolist()], _next_index(polys))

    def far(self, foot: np.ndarray) -> np.ndarray:
        """far_sides, as one array."""
        pts, nxt, n = self.pts, self.nxt, self.n
        prv = np.arange(-1, len(pts) - 1)
        ends = np.asarray(self.bounds[1:]) - 1
        starts = nxt[ends]
        prv[starts] = ends
        x, y = pts[:, 0], pts[:, 1]
        dx, dy = x[nxt] - x[prv], y[nxt] - y[prv]  # the right-hand normal is (dy, -dx)
        # Clockwise: the right-hand normal points in; a hole's normal from the material into the air
        # is the one pointing into the hole.
        turn = x * y[nxt] - x[nxt] * y
        sign = np.where(np.add.reduceat(turn, starts) < 0, -1.0, 1.0)
        sign[1:] *= -1.0
        facing = (dy * (foot[0] - x) - dx * (foot[1] - y)) * np.repeat(sign, n)
        return facing < 0

    def footprint(self, height_mm: float, camera_centre: np.ndarray | None, far: np.ndarray | None) -> Footprint:
        """footprint_from_table of the stacked silhouette (`far`: self.far(foot), or None to make it)."""
        if camera_centre is None or height_mm <= 0:
            return Footprint._of_stacked(self.pts, self.bounds, self.nxt)
        foot, cam_h = np.asarray(camera_centre[:2], float), float(camera_centre[2])
        shrink = 1.0 - height_mm / cam_h
        f = self.far(foot) if far is None else far
        moved = self.pts.copy()
        moved[f] = foot + (self.pts[f] - foot) * shrink
        return Footprint._of_stacked(moved, self.bounds, self.nxt)


def footprint_from_table(
    outer_mm: np.ndarray,
    holes_mm: Sequence[np.ndarray],
    height_mm: float,
    camera_centre: np.ndarray | None,
    far: Sequence[np.ndarray] | None = None,
) -> Footprint:
    """The footprint of a prism `height_mm` tall whose silhouette, mapped on the table plane, is
    `outer_mm` with `holes_mm`: points whose side faces away from the camera's foot are its top
    edge, seen further out, and are moved back onto the plane at its height (`far`: those points,
    from far_sides, where the caller has them)."""
    polys = [np.asarray(outer_mm, float), *(np.asarray(h, float) for h in holes_mm)]
    if camera_centre is None or height_mm <= 0:
        return Footprint(polys[0], polys[1:])
    return _Stack.of(polys).footprint(height_mm, camera_centre, None if far is None else np.concatenate(far))


# ---- rasters and harmonics ---------------------------------------------------------------------


@dataclass(frozen=True)
class _Grid:
    """A square raster about a part's centroid: `size` px of `step_mm`; per pixel its ring and angle."""

    step_mm: float
    size: int
    ring: np.ndarray  # int, per pixel (RINGS: outside the largest ring)
    rotor: np.ndarray  # complex e^{-i phi} per pixel
    tabled: bool = False  # the harmonics from a table of every pixel's powers (a model's matching grid)

    @staticmethod
    def make(step_mm: float, radius_mm: float, tabled: bool = False) -> _Grid:
        size = int(2 * math.ceil(radius_mm / step_mm) + 8)
        c = (size - 1) / 2
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
        x, y = (xx - c) * step_mm, (c - yy) * step_mm  # y up: the table frame's angles
        r = np.hypot(x, y)
        ring = np.minimum((r / radius_mm * RINGS).astype(np.int64), RINGS)
        rotor = np.exp(-1j * np.arctan2(y, x))
        return _Grid(step_mm, size, ring, rotor, tabled)

    def draw(self, outer: np.ndarray, holes: Sequence[np.ndarray], soft: bool = False) -> np.ndarray:
        """uint8 mask of a footprint given in the grid's frame (origin at the centre, mm): 0/1, or
        with `soft` 0-255 with anti-aliased edges (for the harmonics)."""
        c = (self.size - 1) / 2
        shift = 4

        flip = np.array([self.step_mm, -self.step_mm])

        def px(p: np.ndarray) -> np.ndarray:
            return np.rint((p / flip + c) * (1 << shift)).astype(np.int32)

        m = np.zeros((self.size, self.size), np.uint8)
        on, line = (255, cv2.LINE_AA) if soft else (1, cv2.LINE_8)
        cv2.fillPoly(m, [px(outer)], on, line, shift)
        if holes:
            cv2.fillPoly(m, [px(h) for h in holes], 0, line, shift)
        return m

    def fixed(self, poly: np.ndarray) -> np.ndarray:
        """A polygon (the grid's frame, mm) in the grid's pixels, fixed point (4 bits), as fill() paints it."""
        c = (self.size - 1) / 2
        return np.rint((poly / np.array([self.step_mm, -self.step_mm]) + c) * 16).astype(np.int32)

    def fill(self, mask: np.ndarray, poly: np.ndarray) -> None:
        """Paint a polygon (the grid's frame, mm) into a 0/1 mask."""
        cv2.fillPoly(mask, [self.fixed(poly)], 1, cv2.LINE_8, 4)

    def harmonics(self, mask: np.ndarray) -> np.ndarray:
        """(RINGS, HARMONICS) complex: per ring, sum over the part's pixels (weighed by the mask) of
        e^{-i k phi}, k = 1..K."""
        if not self.tabled:
            return self._harmonics_direct(mask)
        order, starts, powers = self._powers()
        w = mask.ravel()[order].astype(np.float64)
        out = np.empty((2 * HARMONICS, RINGS))
        ends = [*starts[1:], len(order)]
        for r in range(RINGS):
            out[:, r] = powers[:, starts[r] : ends[r]] @ w[starts[r] : ends[r]]
        return (out[:HARMONICS] + 1j * out[HARMONICS:]).T

    def _harmonics_direct(self, mask: np.ndarray) -> np.ndarray:
        """harmonics() without the table (a grid used a few times: teaching's)."""
        idx = np.flatnonzero(mask)
        ring = self.ring.ravel()[idx]
        inside = ring < RINGS
        ring, z = ring[inside], self.rotor.ravel()[idx][inside]
        order = np.argsort(ring, kind="stable")
        ring, z = ring[order], z[order] * 1.0
        powers = np.cumprod(np.broadcast_to(z, (HARMONICS, z.size)), axis=0)  # e^{-i k phi}, k = 1..K
        powers *= mask.ravel()[idx][inside][order]
        out = np.zeros((RINGS, HARMONICS), np.complex128)
        present = np.flatnonzero(np.bincount(ring, minlength=RINGS))
        if present.size:
            starts = np.searchsorted(ring, present)
            out[present] = np.add.reduceat(powers, starts, axis=1).T
        return out

    def _powers(self) -> tuple[np.ndarray, list[int], np.ndarray]:
        """The pixels inside the rings ordered by ring, where each ring starts, and per pixel the
        real and imaginary parts of e^{-i k phi}, k = 1..K ((2K, N), in that order): made once per
        grid (a model's), so that a footprint's harmonics are a product per ring."""
        cached = self.__dict__.get("_powers_cache")
        if cached is None:
            ring = self.ring.ravel()
            order = np.flatnonzero(ring < RINGS)
            order = order[np.argsort(ring[order], kind="stable")]
            starts = [int(v) for v in np.searchsorted(ring[order], np.arange(RINGS))]
            z = np.power.outer(self.rotor.ravel()[order], _K).T  # (K, N)
            cached = (order, starts, np.ascontiguousarray(np.vstack([z.real, z.imag])))
            object.__setattr__(self, "_powers_cache", cached)
        return cached

    def soft_harmonics(self, outer: np.ndarray, holes: Sequence[np.ndarray]) -> np.ndarray:
        return self.harmonics(self.draw(outer, holes, soft=True))


_K = np.arange(1, HARMONICS + 1)
_K_SQUARED = _K**2
_COARSE_PHASE = np.outer(_K, np.linspace(0, 2 * np.pi, _COARSE_STEPS, endpoint=False))
_COARSE_COS, _COARSE_SIN = np.cos(_COARSE_PHASE), np.sin(_COARSE_PHASE)


def rotation_deg(measured: np.ndarray, model: np.ndarray, order: int = 1) -> float:
    """The angle the model is turned by to look like the measured shape (harmonics of both,
    `_Grid.harmonics`), degrees in [0, 360 / order)."""
    g = np.sum(measured * np.conj(model), axis=0)  # per k: |.|^2 e^{-i k alpha}
    corr = g.real @ _COARSE_COS - g.imag @ _COARSE_SIN  # Re(g e^{i k beta}) summed over k, per beta
    beta = 2 * np.pi * int(np.argmax(corr)) / _COARSE_STEPS
    w = np.abs(g)
    wk, norm = w * _K, max(np.sum(w * _K_SQUARED), 1e-30)
    for _ in range(3):
        e = np.angle(g * np.exp(1j * _K * beta))  # k (beta - alpha), wrapped
        beta -= float(np.sum(wk * e) / norm)
    period = 360.0 / max(order, 1)
    return math.degrees(beta) % period


def misfit_mm2(a: np.ndarray, b: np.ndarray, step_mm: float) -> float:
    """Area where two masks differ, beyond an opening of FIT_OPENING_MM (edge noise left out)."""
    return fit(a, b, step_mm)[0]


def fit(a: np.ndarray, b: np.ndarray, step_mm: float) -> tuple[float, float]:
    """misfit_mm2 of two 0/1 masks and their overlap (intersection over union), from one difference."""
    diff = cv2.bitwise_xor(a, b)
    r = max(1, int(round(FIT_OPENING_MM / step_mm)))
    na, nb, nd = cv2.countNonZero(a), cv2.countNonZero(b), cv2.countNonZero(diff)
    overlap = (na + nb - nd) / (na + nb + nd) if na + nb + nd else 0.0  # twice the intersection over twice the union
    # Only about the differences (the opening of a region keeps within r of it: the same count).
    x, y, w, h = cv2.boundingRect(diff)
    if w == 0 or h == 0:
        return 0.0, overlap
    roi = diff[max(y - r, 0) : y + h + r, max(x - r, 0) : x + w + r]
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return float(np.count_nonzero(cv2.morphologyEx(roi, cv2.MORPH_OPEN, kernel))) * step_mm**2, overlap


def _turn(points: np.ndarray, angle_deg: float) -> np.ndarray:
    a = math.radians(angle_deg)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return np.asarray(points, float) @ rot.T


_SWEEP_LAYERS = 6  # at most: the bottom face, the top face and copies between them...
_SWEEP_STEP_MM = 0.4  # ...at most this far apart (the gaps at corners are less than the fit's opening)


@functools.cache
def _layer_steps(layers: int) -> np.ndarray:
    """np.linspace(0, 1, layers) shaped to scale an outline's points, made once per count."""
    steps = np.linspace(0.0, 1.0, layers)[:, None, None]
    steps.flags.writeable = False
    return steps


def predicted_silhouette(
    grid: _Grid,
    outer: np.ndarray,
    holes: Sequence[np.ndarray],
    centre_mm: np.ndarray,
    angle_deg: float,
    height_mm: float,
    camera_centre: np.ndarray | None,
) -> np.ndarray:
    """The mask (grid about `centre_mm`, table axes) of the shadow a prism with this footprint
    (part frame), placed at `centre_mm` turned by `angle_deg`, casts on the table seen from the
    camera centre: its bottom face swept to its top face, the holes open where both openings are."""
    if camera_centre is None or height_mm <= 0:
        return grid.draw(_turn(outer, angle_deg), [_turn(h, angle_deg) for h in holes])
    # Every point at once: the outline's first, then the holes'.
    n = len(outer)
    placed = _turn(np.concatenate([outer, *holes]) if holes else outer, angle_deg)
    foot = np.asarray(camera_centre[:2], float) - centre_mm
    grow = float(camera_centre[2]) / (float(camera_centre[2]) - height_mm)
    top = foot + (placed - foot) * grow
    up = top[:n] - placed[:n]
    sweep = float(np.sqrt(np.max(np.einsum("ij,ij->i", up, up))))
    layers = int(min(_SWEEP_LAYERS, max(2, math.ceil(sweep / _SWEEP_STEP_MM) + 1)))
    mask = np.zeros((grid.size, grid.size), np.uint8)
    steps = _layer_steps(layers)
    for q in grid.fixed(placed[:n] + steps * up):
        cv2.fillPoly(mask, [q], 1, cv2.LINE_8, 4)
    if not holes:
        return mask
    # The light passes where a hole's bottom and top openings overlap, each hole on its own: all
    # the holes in two masks when no hole's box meets another's (holes further apart than the
    # sweep), drawn in the holes' box alone.
    bottoms, tops = grid.fixed(placed[n:]), grid.fixed(top[n:])
    cuts = np.cumsum([len(h) for h in holes[:-1]])
    groups = [[(b, t) for b, t in zip(np.split(bottoms, cuts), np.split(tops, cuts), strict=True)]]
    if len(holes) > 1:
        starts = np.concatenate(([0], cuts))
        lo = np.minimum(np.minimum.reduceat(bottoms, starts), np.minimum.reduceat(tops, starts)) // 16 - 1
        hi = np.maximum(np.maximum.reduceat(bottoms, starts), np.maximum.reduceat(tops, starts)) // 16 + 1
        meet = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), axis=2)
        if np.count_nonzero(meet) > len(holes):  # some hole's box meets another's
            groups = [[pair] for pair in groups[0]]
    for group in groups:
        every = np.concatenate([q for pair in group for q in pair])
        x0, y0 = np.maximum(every.min(axis=0) // 16 - 1, 0)
        x1, y1 = np.minimum(every.max(axis=0) // 16 + 2, grid.size)
        corner = np.array([16 * x0, 16 * y0], np.int32)
        light = []
        for side in (0, 1):
            m = np.zeros((y1 - y0, x1 - x0), np.uint8)
            for pair in group:
                cv2.fillPoly(m, [pair[side] - corner], 1, cv2.LINE_8, 4)
            light.append(m)
        box = mask[y0:y1, x0:x1]
        cv2.subtract(box, cv2.bitwise_and(light[0], light[1]), dst=box)
    return mask


def sweep_mm(centre_mm: np.ndarray, height_mm: float, camera_centre: np.ndarray | None) -> float:
    """How far a part's top face is seen beyond its bottom face (0 straight below the camera)."""
    if camera_centre is None:
        return 0.0
    c = np.asarray(camera_centre, float)
    return float(np.hypot(*(centre_mm - c[:2]))) * height_mm / max(c[2] - height_mm, 1e-9)


# ---- the model ---------------------------------------------------------------------------------


class _Grip(BaseModel):
    model_config = ConfigDict(extra="forbid")
    point_mm: tuple[float, float] = Field(description="where the jaws close, part frame")
    angle_deg: float = Field(description="direction the jaws close along, part frame")
    width_mm: float = Field(gt=0, description="the part's width between the jaws")
    opening_mm: float = Field(gt=0, description="jaw opening: width plus clearance")


class _ModelFile(BaseModel):
    model_config = ConfigDict(extra="forbid")
    schema_: str = Field(alias="schema")
    version: int
    name: str
    height_mm: float = Field(gt=0, le=200)
    area_mm2: float = Field(gt=0)
    outline_mm: list[tuple[float, float]] = Field(min_length=3)
    holes_mm: list[list[tuple[float, float]]]
    symmetry: int = Field(ge=0, le=8, description="rotational symmetry order; 0 round")
    mirror_distinct: bool
    tolerance_mm2: float = Field(gt=0)
    grip: _Grip
    examples: int = Field(ge=1)
    consistency: dict[str, float]


@dataclass
class Match:
    """A footprint against one model."""

    name: str
    centre_mm: np.ndarray
    angle_deg: float  # the part frame's x axis on the table, modulo 360 / symmetry
    misfit_mm2: float
    score: float  # intersection over union, 0-1
    accepted: bool


@dataclass
class Grip:
    point_mm: tuple[float, float]
    angle_deg: float
    width_mm: float
    opening_mm: float


@dataclass
class ShapeModel:
    """One taught part type (see the module's docstring)."""

    name: str
    height_mm: float
    outline_mm: np.ndarray
    holes_mm: list[np.ndarray]
    symmetry: int
    mirror_distinct: bool
    tolerance_mm2: float
    grip: Grip
    examples: int = 1
    consistency: dict[str, float] = field(default_factory=dict)
    area_mm2: float = 0.0

    def __post_init__(self) -> None:
        fp = Footprint(self.outline_mm, self.holes_mm)
        self.area_mm2 = fp.area_mm2
        self.radius_mm = float(np.max(np.hypot(*self.outline_mm.T)))
        step = grid_step_mm(self.area_mm2)
        self._grid = _Grid.make(step, self.radius_mm * 1.1 + 3.0)
        # The matching grid's powers are tabled on the first match (a few MB): a taught type is
        # matched against many blobs, its harmonics then a product per ring.
        self._coarse = _Grid.make(HARMONIC_STEPS * step, self.radius_mm * 1.1 + 3.0, tabled=True)
        self._harm = self._coarse.soft_harmonics(self.outline_mm, self.holes_mm)

    # -- finding
    def candidate(self, area_mm2: float, holes: int) -> bool:
        return holes == len(self.holes_mm) and abs(area_mm2 / self.area_mm2 - 1.0) <= 0.15

    def match(
        self,
        fp: Footprint,
        silhouette: tuple[np.ndarray, list[np.ndarray]] | None = None,
        camera_centre: np.ndarray | None = None,
    ) -> Match:
        """This model against a footprint (the pose) and the silhouette it came from, on the table
        plane (the fit: the model's predicted silhouette against it; without one, the footprint)."""
        # The footprint about its centroid (fp.in_frame(fp.centroid_mm, 0.0), without the turn by 0).
        outer, holes = fp.outer - fp.centroid_mm, [h - fp.centroid_mm for h in fp.holes]
        g = self._grid
        harm = self._coarse.soft_harmonics(outer, holes)
        angle = 0.0 if self.symmetry == 0 else rotation_deg(harm, self._harm, self.symmetry)
        if silhouette is None:
            seen = g.draw(outer, holes)
            drawn = predicted_silhouette(g, self.outline_mm, self.holes_mm, fp.centroid_mm, angle, 0.0, None)
        else:
            seen = g.draw(silhouette[0] - fp.centroid_mm, [h - fp.centroid_mm for h in silhouette[1]])
            drawn = predicted_silhouette(
                g, self.outline_mm, self.holes_mm, fp.centroid_mm, angle, self.height_mm, camera_centre
            )
        bad, score = fit(seen, drawn, g.step_mm)
        size_ok = abs(fp.area_mm2 / self.area_mm2 - 1.0) <= self.area_tolerance
        return Match(self.name, fp.centroid_mm, angle, bad, score, bad <= self.tolerance_mm2 and size_ok)

    @property
    def area_tolerance(self) -> float:
        """How far a footprint's area may be from the model's, relative: 5 %, or 3 standard deviations
        of the examples' areas if more (a part slightly larger all round differs only in thin bands,
        which the fit's opening does not count)."""
        return max(AREA_TOLERANCE, 3.0 * self.consistency.get("area_sd_mm2", 0.0) / self.area_mm2)

    def grip_on_table(self, centre_mm: np.ndarray, angle_deg: float) -> tuple[np.ndarray, float]:
        """Where the jaws close on the table and the direction they close along (0-180 degrees)."""
        p = centre_mm + _turn(np.array([self.grip.point_mm]), angle_deg)[0]
        return p, (self.grip.angle_deg + angle_deg) % 180.0

    # -- the file
    def to_json(self) -> str:
        data = {
            "schema": SCHEMA,
            "version": SCHEMA_VERSION,
            "name": self.name,
            "height_mm": round(self.height_mm, 4),
            "area_mm2": round(self.area_mm2, 4),
            "outline_mm": np.round(self.outline_mm, 4).tolist(),
            "holes_mm": [np.round(h, 4).tolist() for h in self.holes_mm],
            "symmetry": self.symmetry,
            "mirror_distinct": self.mirror_distinct,
            "tolerance_mm2": round(self.tolerance_mm2, 4),
            "grip": {
                "point_mm": [round(v, 4) for v in self.grip.point_mm],
                "angle_deg": round(self.grip.angle_deg, 3),
                "width_mm": round(self.grip.width_mm, 3),
                "opening_mm": round(self.grip.opening_mm, 3),
            },
            "examples": self.examples,
            "consistency": {k: round(v, 5) for k, v in self.consistency.items()},
        }
        return json.dumps(data, indent=1) + "\n"

    @staticmethod
    def from_json(text: str, where: str) -> ShapeModel:
        try:
            d = _ModelFile.model_validate_json(text)
        except ValidationError as e:
            problems = "; ".join(f"{'.'.join(map(str, x['loc']))}: {x['msg']}" for x in e.errors()[:5])
            raise ShapeModelError(f"{where}: not a valid shape model: {problems}") from None
        if d.schema_ != SCHEMA or d.version != SCHEMA_VERSION:
            raise ShapeModelError(
                f"{where}: a {d.schema_!r} version {d.version} file, expected {SCHEMA!r} version {SCHEMA_VERSION}",
                hint="teach the part again with this version (run-cell part teach)",
            )
        g = d.grip
        return ShapeModel(
            d.name,
            d.height_mm,
            np.array(d.outline_mm, float),
            [np.array(h, float) for h in d.holes_mm],
            d.symmetry,
            d.mirror_distinct,
            d.tolerance_mm2,
            Grip((g.point_mm[0], g.point_mm[1]), g.angle_deg, g.width_mm, g.opening_mm),
            d.examples,
            dict(d.consistency),
        )


def sha256_of(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def load_model(path: Path, sha256: str) -> ShapeModel:
    """The model file at `path`, refused unless its bytes hash to `sha256` (the recipe's)."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise ShapeModelError(f"{path}: cannot read shape model: {e.strerror}", hint="teach the part again") from None
    got = sha256_of(data)
    if got != sha256.lower():
        raise ShapeModelError(
            f"{path}: shape model changed since the recipe named it (sha256 {got[:12]}..., recipe says {sha256[:12]}...)",
            hint="teach the part again (run-cell part teach), or restore the file the recipe names",
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise ShapeModelError(f"{path}: shape model is not UTF-8 text") from None
    return ShapeModel.from_json(text, str(path))


def perimeter_mm(polys: Sequence[np.ndarray]) -> float:
    return float(sum(np.hypot(*(np.roll(p, -1, axis=0) - p).T).sum() for p in polys))


def fit_tolerance_mm2(area_mm2: float, perimeter: float) -> float:
    """How much a found part may differ from its model beyond the fit's opening: 0.4 % of its area
    or 0.02 mm along its whole outline and holes (corners rounded by the blur, a tall part's
    sweep approximated), at least 0.8 mm2. A missing hole of 3 mm or a mirrored arm is far more."""
    return max(0.8, 0.004 * area_mm2, 0.02 * perimeter)


def grid_step_mm(area_mm2: float) -> float:
    """Raster step for a part of this area: about 150 px across, 0.05-0.2 mm."""
    return float(np.clip(math.sqrt(area_mm2) / 150.0, 0.05, 0.2))


# ---- teaching ----------------------------------------------------------------------------------


@dataclass
class Example:
    """One example part: its silhouette on the table plane and the footprint made of it."""

    silhouette: tuple[np.ndarray, list[np.ndarray]]
    footprint: Footprint
    source: str  # "IMG, part 2"
    camera_centre: np.ndarray | None = None
    touches_border: bool = False

    @staticmethod
    def of(
        silhouette: tuple[np.ndarray, list[np.ndarray]],
        height_mm: float,
        camera_centre: np.ndarray | None,
        source: str,
        touches_border: bool = False,
    ) -> Example:
        fp = footprint_from_table(silhouette[0], silhouette[1], height_mm, camera_centre)
        return Example(silhouette, fp, source, camera_centre, touches_border)


@dataclass
class TeachReport:
    model: ShapeModel
    lines: list[str]


def _symmetry(grid: _Grid, outer: np.ndarray, holes: list[np.ndarray], mask: np.ndarray, tol: float) -> int:
    def same(angle: float) -> bool:
        turned = grid.draw(_turn(outer, angle), [_turn(h, angle) for h in holes])
        return misfit_mm2(mask, turned, grid.step_mm) <= tol

    if all(same(a) for a in (13.0, 37.0, 90.0, 151.0)):
        return 0
    for n in SYMMETRY_ORDERS:
        if all(same(360.0 * j / n) for j in range(1, n)):
            return n
    return 1


def grip_for(outer: np.ndarray, holes: list[np.ndarray], jaw_face_mm: float, clearance_mm: float) -> tuple[Grip, float]:
    """The narrowest width through the centroid (part frame) that jaws `jaw_face_mm` wide close on:
    per direction, the part's extent along it within the band the jaw faces cover. Returns the grip
    and the widest such extent (what any direction needs)."""
    pts = np.vstack([outer, *holes]) if holes else outer
    # Dense points along the outline: a long edge crossing the band has no vertex in it.
    dense = []
    for poly in [outer, *holes]:
        q = np.roll(poly, -1, axis=0)
        n = np.maximum(1, np.ceil(np.hypot(*(q - poly).T) / 0.2)).astype(int)
        for p0, p1, k in zip(poly, q, n, strict=True):
            t = np.arange(k)[:, None] / k
            dense.append(p0 + t * (p1 - p0))
    pts = np.vstack(dense)
    best: tuple[float, float, float] | None = None
    for deg in np.arange(0.0, 180.0, 1.0):
        a = math.radians(deg)
        d, side = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
        u, v = pts @ d, pts @ side
        band = np.abs(v) <= jaw_face_mm / 2
        if not band.any():
            continue
        lo, hi = float(u[band].min()), float(u[band].max())
        if best is None or hi - lo < best[0]:
            best = (hi - lo, deg, (lo + hi) / 2)
    if best is None:
        raise TeachRefused("no grip: the part has no material about its centroid")
    width, deg, mid = best
    a = math.radians(deg)
    point = (mid * math.cos(a), mid * math.sin(a))
    return Grip(point, deg, width, width + clearance_mm), width


def teach(
    name: str,
    examples: Sequence[Example],
    height_mm: float,
    *,
    max_opening_mm: float,
    jaw_face_mm: float,
    clearance_mm: float,
) -> TeachReport:
    """A model from example footprints, or TeachRefused saying why in words."""
    if not examples:
        raise TeachRefused(
            f"no part found to teach {name!r} from", hint="each image: the part alone on the backlit table"
        )
    cut = [e.source for e in examples if e.touches_border]
    if cut:
        raise TeachRefused(
            f"cannot teach {name!r}: the part leaves the image ({', '.join(cut)})",
            hint="put each example wholly in view, away from the image's edges",
        )
    areas = np.array([e.footprint.area_mm2 for e in examples])
    median = float(np.median(areas))
    big = [e.source for e, a in zip(examples, areas, strict=True) if a > 1.6 * median]
    if big:
        raise TeachRefused(
            f"cannot teach {name!r}: {', '.join(big)} is {max(areas) / median:.1f} x the others' area: parts touching?",
            hint="lay the examples apart, a few millimetres at least",
        )
    # The model is the example seen most nearly from straight above (the least of it hidden);
    # every other example must fit it, its predicted silhouette against theirs.
    sweeps = [sweep_mm(e.footprint.centroid_mm, height_mm, e.camera_centre) for e in examples]
    ref = int(np.argmin(sweeps))
    fp = examples[ref].footprint
    outer, holes = fp.in_frame(fp.centroid_mm, fp.principal_deg if fp.anisotropy >= 0.05 else 0.0)
    tol = fit_tolerance_mm2(median, perimeter_mm([outer, *holes]))
    placeholder = Grip((0.0, 0.0), 0.0, 1.0, 1.0)
    trial = ShapeModel(name, height_mm, outer, holes, 1, True, tol, placeholder)
    fits = {k: trial.match(e.footprint, e.silhouette, e.camera_centre) for k, e in enumerate(examples) if k != ref}
    worst = max(fits, key=lambda k: fits[k].misfit_mm2, default=ref)
    if worst != ref and fits[worst].misfit_mm2 > tol:
        counts = {len(e.footprint.holes) for e in examples}
        why = (
            f"{len(examples[ref].footprint.holes)} against {len(examples[worst].footprint.holes)} holes"
            if len(counts) > 1
            else f"they differ by {fits[worst].misfit_mm2:.1f} mm2 (areas {areas[ref]:.1f} and {areas[worst]:.1f} mm2)"
        )
        raise TeachRefused(
            f"cannot teach {name!r}: the examples disagree: {examples[worst].source} is not {examples[ref].source} "
            f"({why}): two different parts, or a mirror image?",
            hint="teach each part type from images of that type only",
        )
    grid = trial._grid
    step = grid.step_mm
    mask = grid.draw(outer, holes)
    symmetry = _symmetry(grid, outer, holes, mask, 1.5 * tol)
    flipped = outer * (1, -1), [h * (1, -1) for h in holes]
    angle = rotation_deg(grid.harmonics(mask), grid.harmonics(grid.draw(*flipped)))
    turned = grid.draw(_turn(flipped[0], angle), [_turn(h, angle) for h in flipped[1]])
    mirror_distinct = misfit_mm2(mask, turned, step) > tol
    grip, _ = grip_for(outer, holes, jaw_face_mm, clearance_mm)
    if grip.opening_mm > max_opening_mm:
        raise TeachRefused(
            f"cannot teach {name!r}: it cannot be gripped: its narrowest width through its centre is "
            f"{grip.width_mm:.1f} mm, the jaws open {max_opening_mm:g} mm ({clearance_mm:g} mm clearance)",
            hint="parts.jaw_max_opening_mm is the gripper's opening; a wider part needs another gripper",
        )
    n = len(examples)
    model = ShapeModel(name, height_mm, outer, holes, symmetry, mirror_distinct, tol, grip, n, {})
    # The examples against the model as it will be used (its symmetry sets how its angle is found:
    # a many-toothed part's angle modulo its period is found less closely than a plain one's), and the
    # tolerance widened to twice their worst misfit, at most twice the shape's own: the found parts of
    # this camera spread as its examples do (a gear at 0.28 mm/px: examples up to 2.1 mm2 against 2.3).
    fits = {k: model.match(e.footprint, e.silhouette, e.camera_centre) for k, e in enumerate(examples) if k != ref}
    worst_mm2 = max((f.misfit_mm2 for f in fits.values()), default=0.0)
    model.tolerance_mm2 = min(max(tol, EXAMPLE_SPREAD * worst_mm2), EXAMPLE_SPREAD * tol)
    model.consistency = {
        "worst_misfit_mm2": worst_mm2,
        "worst_score": min((f.score for f in fits.values()), default=1.0),
        "area_sd_mm2": float(np.std(areas)),
    }
    consistency = model.consistency
    tol = model.tolerance_mm2
    sym = "round (no angle)" if symmetry == 0 else ("none" if symmetry == 1 else f"{symmetry}-fold")
    lines = [
        f"{name}: {n} example(s), area {median:.1f} mm2 (sd {consistency['area_sd_mm2']:.2f}), "
        f"{len(holes)} hole(s), height {height_mm:g} mm",
        f"consistency: worst misfit {consistency['worst_misfit_mm2']:.2f} mm2 (limit {tol:.2f}), "
        f"worst overlap {consistency['worst_score']:.4f}",
        f"symmetry: {sym}; angles are reported modulo {360 // symmetry if symmetry else 360} deg"
        if symmetry
        else "symmetry: round; no angle reported",
        "mirror image: another part (told apart)" if mirror_distinct else "mirror image: the same part",
        f"grip: jaws close along {grip.angle_deg:.0f} deg (part frame) at ({grip.point_mm[0]:.1f}, "
        f"{grip.point_mm[1]:.1f}) mm, width {grip.width_mm:.1f} mm, opening {grip.opening_mm:.1f} of "
        f"{max_opening_mm:g} mm",
    ]
    return TeachReport(model, lines)


# ---- finding in a frame ------------------------------------------------------------------------


def footprint_of_blob(
    gray: np.ndarray,
    outline_px: np.ndarray,
    mapper,
    fraction: float,
    min_hole_px: float,
) -> tuple[np.ndarray, list[np.ndarray]] | None:
    """The blob's silhouette (outer, holes) on the table plane, table mm; None if no edge is seen."""
    return footprints_of_blobs(gray, [outline_px], mapper, fraction, [min_hole_px])[0]


def footprints_of_blobs(
    gray: np.ndarray,
    outlines_px: Sequence[np.ndarray],
    mapper,
    fraction: float,
    min_hole_px: Sequence[float],
) -> list[tuple[np.ndarray, list[np.ndarray]] | None]:
    """footprint_of_blob for many blobs, their outlines mapped onto the table in one call (a
    calibration's mapping costs mostly per call)."""
    polys_of: list[list[np.ndarray] | None] = []
    for outline_px, min_hole in zip(outlines_px, min_hole_px, strict=True):
        got = fine_outlines(gray, outline_px, fraction, min_hole)
        polys_of.append(None if got is None else [_thin(got[0]), *(_thin(h) for h in got[1])])
    given = [p for polys in polys_of if polys is not None for p in polys]
    if not given:
        return [None] * len(polys_of)
    mapped = np.asarray(mapper.pixel_to_table_mm(np.vstack(given))).reshape(-1, 2)
    pieces = iter(np.split(mapped, np.cumsum([len(p) for p in given])[:-1]))
    out: list[tuple[np.ndarray, list[np.ndarray]] | None] = []
    for polys in polys_of:
        if polys is None:
            out.append(None)
            continue
        mine = [next(pieces) for _ in polys]
        out.append((mine[0], mine[1:]))
    return out


def _thin(outline_px: np.ndarray) -> np.ndarray:
    poly = cv2.approxPolyDP(np.asarray(outline_px, dtype=np.float32).reshape(-1, 1, 2), 0.02, True)
    return poly.reshape(-1, 2).astype(np.float64) if len(poly) >= 3 else np.asarray(outline_px, dtype=np.float64)


def best_match(
    silhouette: tuple[np.ndarray, list[np.ndarray]], models: Sequence[ShapeModel], camera_centre
) -> tuple[Match | None, Footprint | None, str]:
    """The best model for a silhouette on the table plane: (match, its footprint, why not) ; the
    match is None when no model is even a candidate."""
    outer, holes = silhouette
    corrected: dict[float, Footprint] = {}
    best: tuple[Match, Footprint] | None = None
    stack = _Stack.of([np.asarray(outer, float), *(np.asarray(h, float) for h in holes)])
    far = None if camera_centre is None else stack.far(np.asarray(camera_centre[:2], float))
    for m in models:
        if len(m.holes_mm) != len(holes):
            continue
        if m.height_mm not in corrected:
            corrected[m.height_mm] = stack.footprint(m.height_mm, camera_centre, far)
        fp = corrected[m.height_mm]
        if not m.candidate(fp.area_mm2, len(holes)):
            continue
        got = m.match(fp, silhouette, camera_centre)
        if best is None or (got.misfit_mm2, -got.score) < (best[0].misfit_mm2, -best[0].score):
            best = (got, fp)
    if best is None:
        flat = Footprint(outer, holes)
        largest = max(models, key=lambda m: m.area_mm2)
        if flat.area_mm2 > 1.3 * largest.area_mm2:
            return None, flat, f"larger than any taught type ({flat.area_mm2:.0f} mm2): parts touching?"
        return None, flat, f"matches no taught type ({flat.area_mm2:.0f} mm2, {len(holes)} hole(s))"
    assert best is not None
    match, fp = best
    if match.accepted:
        return match, fp, ""
    return (
        match,
        fp,
        f"matches no taught type (nearest {match.name}: differs by {match.misfit_mm2:.1f} mm2, "
        f"area {fp.area_mm2:.1f} mm2 against {next(m for m in models if m.name == match.name).area_mm2:.1f}, "
        f"score {match.score:.3f})",
    )

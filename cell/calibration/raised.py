"""The camera's height from a second image of the plate, raised on a spacer of known thickness.

Seen nearly straight down, one image of a flat plate cannot tell a near camera with a short lens
from a far one with a long lens: both give the same picture. The part-height correction needs
that height. Raise the plate by a known `spacer_mm` and photograph it again: mapped onto the
table through the first image's calibration, the raised circles spread out from the point below
the camera by exactly

    s = H / (H - spacer_mm)        (H: the camera's height above the table)

whatever the camera's tilt, lens or distortion (each circle's ray meets the table farther out,
in proportion). So a similarity fit (scale, turn, shift) of the plate's own grid onto the mapped
circles gives s, and H = spacer_mm * s / (s - 1). The plate may lie anywhere on the spacer,
turned or not, and part of it may be out of view. How well H is known follows from the fit's
residuals and the spacer's tolerance: with a 20 mm spacer at 400 mm the scale is 1.053; a scale
known to 1e-5 pins the height to 0.07 mm, a spacer known to 0.1 mm to 2 mm (the height's error
is the spacer's times height / spacer).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cell.calibration.candidates import Candidates, find_candidates
from cell.calibration.detect import refine_candidates, size_groups, to_gray
from cell.config import PlateConfig
from cell.errors import CalibrationRejected, PlateNotFound

MIN_CIRCLES = 6
SPACER_SD_MM = 0.1  # a spacer's thickness as made (a machined block, gauge blocks: better)
MIN_SPREAD = 1e-4  # a raised plate whose scale differs from 1 by less than this (plus 3 sd) was not raised


@dataclass(frozen=True)
class RaisedHeight:
    """The camera's height from the raised plate, and what it rests on."""

    height_mm: float
    sd_mm: float
    scale: float  # raised circles on the table / the plate's own spacing
    scale_sd: float
    spacer_mm: float
    points: int
    residual_rms_mm: float

    def to_dict(self) -> dict[str, float | int]:
        return {
            "height_mm": round(self.height_mm, 2),
            "sd_mm": round(self.sd_mm, 3),
            "scale": round(self.scale, 7),
            "scale_sd": round(self.scale_sd, 8),
            "spacer_mm": self.spacer_mm,
            "points": self.points,
            "residual_rms_mm": round(self.residual_rms_mm, 4),
        }


def similarity_fit(src: np.ndarray, dst: np.ndarray) -> tuple[float, float, np.ndarray]:
    """dst ~ s R src + t (least squares, Umeyama): the scale, its standard deviation and the residuals."""
    src = np.asarray(src, dtype=np.float64).reshape(-1, 2)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 2)
    a, b = src - src.mean(axis=0), dst - dst.mean(axis=0)
    # in complex numbers a similarity is one complex factor z = s e^{i theta}: b ~ z a
    ac, bc = a[:, 0] + 1j * a[:, 1], b[:, 0] + 1j * b[:, 1]
    spread = float(np.sum(np.abs(ac) ** 2))
    z = complex(np.sum(np.conj(ac) * bc) / spread)
    residual = bc - z * ac
    res = np.column_stack([residual.real, residual.imag])
    dof = max(2 * len(src) - 4, 1)
    sigma = math.sqrt(float(np.sum(np.abs(residual) ** 2)) / dof)  # per coordinate
    return abs(z), sigma / math.sqrt(spread), res


def raised_circles(
    image: np.ndarray, to_table_mm: Callable[[np.ndarray], np.ndarray], plate: PlateConfig, where: str
) -> tuple[np.ndarray, np.ndarray]:
    """The raised plate's circles: their centres mapped onto the table (mm) and their places on the
    plate (mm, up to a turn and a shift).

    The raised plate is larger in the image than the flat one and need not be wholly in view, so it
    is not numbered as the flat plate is: its circles are mapped onto the table first, where they
    form the plate's lattice grown by the unknown scale, and numbered there along the two steps
    its circles' neighbours show."""
    cands = find_candidates(to_gray(image))
    if len(cands) < MIN_CIRCLES:
        raise PlateNotFound(f"{where}: {len(cands)} round dark blobs, too few for the plate")
    found = [  # refined a size group at a time (one window size fits blobs of one size)
        _circles_on_table(cands, members, to_table_mm, plate)
        for members in size_groups(cands.diameter_px, cands.depth, MIN_CIRCLES)
        if len(members) >= MIN_CIRCLES
    ]
    points = np.concatenate([f[0] for f in found]) if found else np.zeros((0, 2))
    sizes = np.concatenate([f[1] for f in found]) if found else np.zeros(0)
    on_table = _one_per_circle(points, sizes, 0.4 * min(plate.pitch_x_mm, plate.pitch_y_mm))
    if len(on_table) < MIN_CIRCLES:
        raise PlateNotFound(f"{where}: {len(on_table)} circles of the plate's size, too few")
    u, v, pitch_u, pitch_v = _lattice_steps(on_table, plate, where)
    basis = np.column_stack([u, v])
    seed = int(np.argmin(np.hypot(*(on_table - np.median(on_table, axis=0)).T)))
    mn = np.linalg.solve(basis, (on_table - on_table[seed]).T).T
    near = np.all(np.abs(mn - np.rint(mn)) < 0.2, axis=1)
    mn = np.rint(mn).astype(int)
    places = Counter(map(tuple, mn))
    unique = np.array([places[tuple(x)] == 1 for x in mn])
    keep = near & unique
    handed = 1.0 if np.linalg.det(basis) > 0 else -1.0  # the lattice's steps as the table's axes turn
    grid = np.column_stack([mn[:, 0] * pitch_u, handed * mn[:, 1] * pitch_v])
    return on_table[keep], grid[keep]


def _circles_on_table(
    cands: Candidates, members: np.ndarray, to_table_mm: Callable[[np.ndarray], np.ndarray], plate: PlateConfig
) -> tuple[np.ndarray, np.ndarray]:
    """The centres (table mm) of the blobs in `members` that are the plate's circles by their size
    on the table, and those sizes (mm)."""
    centres, diam, ok = refine_candidates(cands, members, cands.diameter_px[members])
    centres, diam = centres[ok], diam[ok]
    if not len(centres):
        return np.zeros((0, 2)), np.zeros(0)
    on_table = to_table_mm(centres)
    # each circle's size on the table: the local scale from a step of half its diameter
    edge = to_table_mm(centres + np.column_stack([diam / 2, np.zeros(len(diam))]))
    d_mm = 2.0 * np.hypot(*(edge - on_table).T)
    size_ok = (d_mm > 0.8 * plate.diameter_mm) & (d_mm < 1.6 * plate.diameter_mm)  # raised: 1.0-1.4 x larger
    return on_table[size_ok], d_mm[size_ok]


def _one_per_circle(points: np.ndarray, d_mm: np.ndarray, apart_mm: float) -> np.ndarray:
    """One blob per circle: of blobs closer than `apart_mm` (a circle's dark core found beside the
    whole circle, under uneven light), the largest."""
    near = np.hypot(*(points[:, None, :] - points[None, :, :]).transpose(2, 0, 1)) < apart_mm
    taken = np.zeros(len(points), bool)
    keep = []
    for i in np.argsort(-d_mm):
        if not taken[i]:
            keep.append(int(i))
            taken |= near[i]
    return points[sorted(keep)]


def _lattice_steps(points: np.ndarray, plate: PlateConfig, where: str) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The lattice's two steps (table mm) from each circle's nearest neighbours, and the plate pitch
    each one is: the two directions the neighbours lie in most, their median lengths."""
    k = min(5, len(points))
    d2 = np.sum((points[:, None, :] - points[None, :, :]) ** 2, axis=2)
    near = np.argsort(d2, axis=1)[:, 1:k]
    steps = (points[near] - points[:, None, :]).reshape(-1, 2)
    angle = np.degrees(np.arctan2(steps[:, 1], steps[:, 0])) % 180.0
    hist = np.bincount(np.rint(angle).astype(int) % 180, minlength=180).astype(float)
    hist = hist + np.roll(hist, 1) + np.roll(hist, -1)
    first = int(np.argmax(hist))
    away = np.abs(((np.arange(180) - first + 90) % 180) - 90)
    second = int(np.argmax(np.where(away > 30, hist, -1.0)))

    def step(direction_deg: float) -> np.ndarray:
        diff = np.abs(((angle - direction_deg + 90.0) % 180.0) - 90.0)
        chosen = steps[diff < 4.0]
        unit = np.array([math.cos(math.radians(direction_deg)), math.sin(math.radians(direction_deg))])
        along = chosen @ unit
        return float(np.median(np.abs(along))) * unit

    u, v = step(first), step(second)
    ratio, want = float(np.hypot(*u) / np.hypot(*v)), plate.pitch_x_mm / plate.pitch_y_mm
    if abs(ratio / want - 1.0) < 0.03:
        return u, v, plate.pitch_x_mm, plate.pitch_y_mm
    if abs(ratio * want - 1.0) < 0.03:
        return u, v, plate.pitch_y_mm, plate.pitch_x_mm
    raise PlateNotFound(
        f"{where}: the circles' steps are {ratio:.3f} to one, the plate's pitches {want:.3f} "
        f"({plate.pitch_x_mm:g} x {plate.pitch_y_mm:g} mm): not this plate",
        hint="photograph the same plate as the flat image, lying flat on the spacer",
    )


def height_from_raised_plate(
    image: np.ndarray,
    to_table_mm: Callable[[np.ndarray], np.ndarray],
    plate: PlateConfig,
    spacer_mm: float,
    where: str = "the raised plate image",
    spacer_sd_mm: float = SPACER_SD_MM,
) -> RaisedHeight:
    """The camera's height from an image of `plate` raised on a `spacer_mm` spacer (known to
    `spacer_sd_mm`); `to_table_mm` is the flat plate's calibration (pixel -> table mm)."""
    if not spacer_mm > 0:
        raise CalibrationRejected(
            f"{where}: spacer thickness {spacer_mm:g} mm",
            hint="give the thickness of what the plate was raised on, in mm (e.g. --spacer-mm 20)",
        )
    on_table, grid = raised_circles(image, to_table_mm, plate, where)
    if len(on_table) < MIN_CIRCLES:
        raise PlateNotFound(
            f"{where}: only {len(on_table)} circles on one lattice, too few to measure the camera's height",
            hint="lay the plate flat on the spacer, most of it in view",
        )
    scale, scale_sd, res = similarity_fit(grid, on_table)
    worst = np.hypot(*res.T)
    far = worst > max(4.0 * float(np.sqrt(np.mean(worst**2))), 0.05)
    if far.any() and (~far).sum() >= MIN_CIRCLES:  # a blob taken for a circle: fit without it
        on_table, grid = on_table[~far], grid[~far]
        scale, scale_sd, res = similarity_fit(grid, on_table)
    if scale - 1.0 < max(MIN_SPREAD, 3.0 * scale_sd):
        raise CalibrationRejected(
            f"{where}: the plate looks no larger than on the table (scale {scale:.5f} +- {scale_sd:.5f}): "
            "it was not raised, or this is the same picture",
            hint=f"put the plate on the {spacer_mm:g} mm spacer and take the second image again",
        )
    height = spacer_mm * scale / (scale - 1.0)
    # |dH/ds| sd(s), and the spacer's own tolerance: dH/dt = H / t
    sd = math.hypot(spacer_mm * scale_sd / (scale - 1.0) ** 2, height / spacer_mm * spacer_sd_mm)
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    return RaisedHeight(height, sd, scale, scale_sd, spacer_mm, len(on_table), rms)

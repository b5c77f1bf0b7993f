"""Is the configured pitch ratio the plate's own? Its circles answer that, through any lens.

Every circle on the plate is round. Around each one, the lattice steps to its neighbours give
the local map from plate millimetres to pixels, A = [column step / pitch_x, row step / pitch_y]:
over so small a patch any lens, pose or bend of the paper is affine. The circle's image is an
ellipse whose second moments C are A (r^2 / 4) A^T, so mapped back through A it is round again:
N = A^-1 C A^-T is a multiple of the identity. When pitch_x_mm is configured k times what it
is on the plate relative to pitch_y_mm (a wrong pitch, X and Y swapped), A's first column is k
times too short and N becomes diag(k^2, 1) times a round one: sqrt(N11 / N22) = k at every
circle, whatever the camera. Nothing here needs a camera model, the principal point or the
lens's distortion, which is why a real hand-held photo with glare and a crop is judged as
surely as a rendered plate.

A uniform scale error (both pitches k times the plate's) leaves every N round: one image
cannot see it, it only looks like another camera height. The height gate and the comparison
with the active calibration (scale, origin) are what catch that.

C is measured on a soft threshold at half each circle's depth (fully dark above 3/4, clear
below 1/4, linear between: a blurred edge then counts where it crosses the half level, to a
fraction of a pixel), the paper level a plane fitted to a ring around the circle (glare, light
gradients), in a window shaped by A (a circle seen at a slant is an ellipse).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cell.calibration.refine import Windows
from cell.config import PlateConfig

_PIXEL_VARIANCE = 1.0 / 12.0  # a pixel's own extent adds this to each axis's second moment


@dataclass(frozen=True)
class PitchRatio:
    """How the plate's circles see the configured pitch ratio."""

    factor: float  # configured pitch_x / pitch_y over the plate's own (1: right; median over the circles)
    circles: int  # circles measured
    spread: float  # interquartile range of the per-circle factors


def lattice_jacobians(pixel: np.ndarray, col_row: np.ndarray, plate: PlateConfig) -> np.ndarray:
    """(N, 2, 2) pixels per plate mm at each circle: columns d(pixel)/dX, d(pixel)/dY.

    Central differences where both neighbours were found, second-order one-sided ones at the
    plate's edges and beside gaps, first-order ones where only one neighbour is left; NaN where
    a circle has no neighbour along an axis.
    """
    pad = 2
    grid = np.full((plate.rows + 2 * pad, plate.columns + 2 * pad, 2), np.nan)
    c, r = col_row[:, 0] + pad, col_row[:, 1] + pad
    grid[r, c] = pixel

    def step(dc: int, dr: int) -> np.ndarray:
        f1, f2 = grid[r + dr, c + dc], grid[r + 2 * dr, c + 2 * dc]
        b1, b2 = grid[r - dr, c - dc], grid[r - 2 * dr, c - 2 * dc]
        best = (f1 - b1) / 2
        for other in ((-3 * pixel + 4 * f1 - f2) / 2, (3 * pixel - 4 * b1 + b2) / 2, f1 - pixel, pixel - b1):
            best = np.where(np.isnan(best), other, best)
        return best

    return np.stack([step(1, 0) / plate.pitch_x_mm, step(0, 1) / plate.pitch_y_mm], axis=2)


def measure_pitch_ratio(
    gray: np.ndarray, pixel: np.ndarray, col_row: np.ndarray, plate: PlateConfig
) -> PitchRatio | None:
    """The pitch ratio the circles see, or None where fewer than 4 circles can be measured."""
    jac = lattice_jacobians(np.asarray(pixel, dtype=np.float64), np.asarray(col_row), plate)
    usable = np.isfinite(jac).all(axis=(1, 2)) & (np.abs(np.linalg.det(np.nan_to_num(jac))) > 1e-9)
    if np.count_nonzero(usable) < 4:
        return None
    jac, centres = jac[usable], np.asarray(pixel, dtype=np.float64)[usable]
    gray, scale = _reduced(gray, plate.diameter_mm * float(np.median(np.sqrt(np.abs(np.linalg.det(jac))))))
    jac, centres = jac / scale, (centres + 0.5) / scale - 0.5
    inv = np.linalg.inv(jac)
    radius = plate.diameter_mm / 2
    gap = min(plate.pitch_x_mm, plate.pitch_y_mm) - plate.diameter_mm
    r_in, r_out = radius + min(0.4 * radius, 0.3 * gap), radius + min(0.8 * radius, 0.7 * gap)
    reach_px = r_out * np.linalg.norm(jac, ord=2, axis=(1, 2))
    win = Windows(gray, centres, int(np.ceil(np.nanmax(reach_px))) + 1)
    r2 = win.quadratic(win.offset, np.transpose(inv, (0, 2, 1)) @ inv)  # plate mm^2 from the centre
    inner = r2 <= r_in**2
    darkness, good = win.darkness(inner, ~inner & (r2 <= r_out**2), plane=True)
    core = (r2 <= (0.6 * radius) ** 2).astype(np.float32)
    depth = win.sums(core * darkness, 1)[:, 0] / np.maximum(win.sums(core, 1)[:, 0], 1.0)
    good &= win.inside & (depth > 0.05)
    coverage = np.clip((darkness / np.maximum(depth, 1e-6)[:, None] - 0.25) / 0.5, 0.0, 1.0) * inner
    _, cov, total = win.moments(coverage.astype(np.float32))
    cov = cov - _PIXEL_VARIANCE * np.eye(2)
    n = inv @ cov @ np.transpose(inv, (0, 2, 1))
    good &= (total > 0) & (n[:, 0, 0] > 0) & (n[:, 1, 1] > 0)
    if np.count_nonzero(good) < 4:
        return None
    factor = np.sqrt(n[good, 0, 0] / n[good, 1, 1])
    q1, q3 = np.percentile(factor, [25, 75])
    return PitchRatio(float(np.median(factor)), int(factor.size), float(q3 - q1))


def _reduced(gray: np.ndarray, diameter_px: float) -> tuple[np.ndarray, float]:
    """The image halved (pyrDown) while the circles stay 16 px or more across, and by how much."""
    scale = 1.0
    while diameter_px / scale >= 32 and min(gray.shape) >= 64:
        gray, scale = cv2.pyrDown(gray), 2 * scale
    return gray, scale

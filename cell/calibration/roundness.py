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

Each circle's shape is its sharp ellipse fitted to the pixels with the blur (measure_pitch_ratio):
the half-level contour or thresholded moments, which measured it before (moment_pitch_ratio, kept
as the bench's reference), are pulled in by the blur where the rim curves most, and on circles
8 px across seen at 45 deg that read a right pitch 5-8 % off. The circles' spread gives the
estimate's standard error; the gate refuses beyond a number of those (gates.py).
"""

from __future__ import annotations

import math
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
    log_sd: float  # standard error of log(factor): the circles' spread, robust (MAD), over sqrt(circles)

    def refused(self, floor_pct: float, sds: float) -> bool:
        """Off by more than `sds` standard errors and more than `floor_pct`: a wrong pitch explains the
        circles better than the configured one, beyond what this image can measure."""
        off = abs(math.log(self.factor))
        return off > sds * self.log_sd and off > math.log1p(floor_pct / 100.0)

    def threshold_pct(self, floor_pct: float, sds: float) -> float:
        """The smallest error this image refuses, in percent."""
        return 100.0 * math.expm1(max(sds * self.log_sd, math.log1p(floor_pct / 100.0)))

    def can_show(self, error_pct: float, floor_pct: float, sds: float) -> bool:
        """Whether this image refuses a pitch ratio `error_pct` off but in 2.5 % of draws: the error beyond
        the threshold by 2 standard errors."""
        threshold = max(sds * self.log_sd, math.log1p(floor_pct / 100.0))
        return math.log1p(error_pct / 100.0) >= threshold + 2.0 * self.log_sd


_SHARED_ERROR = 2.0  # the circles' errors are not independent: the spread over sqrt(n), times this


def _summary(log_factor: np.ndarray) -> PitchRatio:
    """Median and its standard error: 1.2533 x the robust sd over sqrt(n) (a median of n), times
    _SHARED_ERROR. Neighbouring circles share their blur, light and lens, so their errors are partly
    one error: on scripts/bench_pitch_gate.py's views the right pitch's median was off by 0.89 of the
    plain figure at the median and 3.97 at the 95th percentile (independent errors: 0.67 and 1.96)."""
    med = float(np.median(log_factor))
    mad_sd = 1.4826 * float(np.median(np.abs(log_factor - med)))
    q1, q3 = np.percentile(np.exp(log_factor), [25, 75])
    n = int(log_factor.size)
    return PitchRatio(math.exp(med), n, float(q3 - q1), _SHARED_ERROR * 1.2533 * mad_sd / math.sqrt(n))


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


def moment_pitch_ratio(
    gray: np.ndarray, pixel: np.ndarray, col_row: np.ndarray, plate: PlateConfig
) -> PitchRatio | None:
    """The earlier estimate, from each circle's thresholded moments (kept as the bench's reference:
    biased by blur on small tilted circles), or None where fewer than 4 circles can be measured."""
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
    return _summary(np.log(factor))


def _reduced(gray: np.ndarray, diameter_px: float) -> tuple[np.ndarray, float]:
    """The image halved (pyrDown) while the circles stay 16 px or more across, and by how much."""
    scale = 1.0
    while diameter_px / scale >= 32 and min(gray.shape) >= 64:
        gray, scale = cv2.pyrDown(gray), 2 * scale
    return gray, scale


_FIT_DIAMETER_PX = 16.0  # the image is halved while the circles are at least this wide (8-16 px fitted)
_SIGMA_MAX_PX = 2.5  # the widest blur fitted (after halving); a circle blurred more is left out
_MARGIN_PX = 3.0  # pixels fitted beyond each circle's edge
_ITERATIONS = 4  # from the lattice's ellipse: as close as 10 on the bench's views (0.1 %)
_MAX_CIRCLES = 64  # fitted, spread evenly over the plate: enough for the median, a bounded time
_NEIGHBOURS = np.array([(dc, dr) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dc or dr])


def measure_pitch_ratio(
    gray: np.ndarray, pixel: np.ndarray, col_row: np.ndarray, plate: PlateConfig
) -> PitchRatio | None:
    """The pitch ratio the circles see and how surely, or None where fewer than 4 circles can be measured.

    Each circle's sharp image is fitted to its pixels: an ellipse {c + A u : |u| <= r M^1/2} in its
    lattice frame A (M = identity when the configured pitches are the plate's), covering each pixel
    by its signed distance to the rim, blurred by a Gaussian whose width is fitted too, on a paper
    level that is a plane, its 8 neighbours' dots drawn where the lattice puts them (their blurred
    rims reach into the window on a tilted plate). A blur only widens the rim, it does not move the
    ellipse: the half-level contour or the thresholded moments that measured it before are pulled
    in by the blur where the rim curves most, which on a circle 8 px across seen at 45 deg made a
    right pitch read 5-8 % off. factor = (M11 / M22)^1/2 at each circle; the median over the circles,
    its standard error from their spread.
    """
    pixel = np.asarray(pixel, dtype=np.float64)
    col_row = np.asarray(col_row)
    jac = lattice_jacobians(pixel, col_row, plate)
    usable = np.isfinite(jac).all(axis=(1, 2)) & (np.abs(np.linalg.det(np.nan_to_num(jac))) > 1e-9)
    if np.count_nonzero(usable) < 4:
        return None
    diameter_px = plate.diameter_mm * float(np.median(np.sqrt(np.abs(np.linalg.det(jac[usable])))))
    scale = 1.0
    while diameter_px / scale >= _FIT_DIAMETER_PX and min(gray.shape) >= 64:
        gray, scale = cv2.pyrDown(gray), 2 * scale
    jac, at = jac / scale, (pixel + 0.5) / scale - 0.5
    # Neighbours on the plate: where found, their measured centres; else where the lattice puts them.
    on = (col_row >= 0).all(axis=1) & (col_row[:, 0] < plate.columns) & (col_row[:, 1] < plate.rows)
    usable &= on
    grid = np.full((plate.columns, plate.rows, 2), np.nan)
    grid[col_row[on, 0], col_row[on, 1]] = at[on]
    nb_cr = col_row[:, None, :] + _NEIGHBOURS[None]
    on_plate = (nb_cr >= 0).all(axis=2) & (nb_cr[..., 0] < plate.columns) & (nb_cr[..., 1] < plate.rows)
    nb = grid[np.clip(nb_cr[..., 0], 0, plate.columns - 1), np.clip(nb_cr[..., 1], 0, plate.rows - 1)]
    steps = _NEIGHBOURS * (plate.pitch_x_mm, plate.pitch_y_mm)
    predicted = at[:, None, :] + np.einsum("nij,kj->nki", np.nan_to_num(jac), steps)
    nb = np.where(np.isnan(nb), predicted, nb)
    nb[~on_plate] = np.nan
    chosen = np.flatnonzero(usable)
    if chosen.size < 4:
        return None
    chosen = chosen[np.linspace(0, chosen.size - 1, min(chosen.size, _MAX_CIRCLES)).round().astype(int)]
    jac, at, nb = jac[chosen], at[chosen], nb[chosen]
    log_factor, ok = _fit_shapes(gray, at, jac, nb, plate.diameter_mm / 2)
    if np.count_nonzero(ok) < 4:
        return None
    return _summary(log_factor[ok])


def _fit_shapes(
    gray: np.ndarray, centre: np.ndarray, jac: np.ndarray, neighbours: np.ndarray, radius_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """log (M11 / M22)^1/2 per circle and whether its fit holds (Levenberg-Marquardt on the ellipse's
    centre, M and the blur's log width; the paper plane and the dot's depth solved linearly inside)."""
    n = len(centre)
    radius_px = radius_mm * np.linalg.norm(jac, ord=2, axis=(1, 2))
    reach = 3.0 * _SIGMA_MAX_PX
    half = int(np.ceil(float(np.max(radius_px)) + _MARGIN_PX + reach + 1.0))
    win = Windows(gray, centre, half)
    grey = win.grey.astype(np.float64)
    x, y = win.basis[:, 1].astype(np.float64), win.basis[:, 2].astype(np.float64)
    size = 2 * half + 1
    aat = jac @ np.transpose(jac, (0, 2, 1)) * radius_mm**2

    def inverse_shape(m: np.ndarray) -> np.ndarray:  # (n, 2, 2): pixels u inside where u' Q^-1 u <= 1
        q = radius_mm**2 * jac @ m @ np.transpose(jac, (0, 2, 1))
        return np.linalg.inv(q)

    qi0 = np.linalg.inv(aat)
    # The fit's pixels lie in the inner box (the blur's reach beyond it is in the window); the circle
    # itself covers only the core box: its coverage is drawn there, the rest of the window's is fixed.
    inner = half - reach
    rows = np.flatnonzero(np.abs(np.arange(-half, half + 1)) <= inner)
    box = ((np.abs(x) <= inner) & (np.abs(y) <= inner)).reshape(-1)
    core_half = min(half, int(np.ceil(1.3 * float(np.max(radius_px)) + 2.0)))
    core = (np.abs(x) <= core_half) & (np.abs(y) <= core_half)
    grey, xi, yi = grey[:, box], x[box], y[box]
    u, v = xi[None] - win.offset[:, :1], yi[None] - win.offset[:, 1:]
    s0 = np.sqrt(qi0[:, 0, :1] * u * u + 2 * qi0[:, 0, 1:] * u * v + qi0[:, 1, 1:] * v * v)
    mask = (s0 <= 1.0 + _MARGIN_PX / radius_px[:, None]).astype(np.float64)
    # The neighbours' dots, drawn once with the configured shape (their rims only reach the margin).
    rel = neighbours - win.middle[:, None, :]
    rel = np.where(np.isnan(rel), 1e6, rel).reshape(-1, 2)
    others = _coverage(x, y, rel, np.repeat(qi0, 8, axis=0)).reshape(n, 8, -1).max(axis=1)
    xc, yc = x[core], y[core]

    def residual(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m = np.stack([np.stack([phi[:, 2], phi[:, 3]], -1), np.stack([phi[:, 3], phi[:, 4]], -1)], -2)
        cover = others.copy()
        cover[:, core] = np.maximum(cover[:, core], _coverage(xc, yc, win.offset + phi[:, :2], inverse_shape(m)))
        g = _blur_matrices(np.clip(np.exp(phi[:, 5]), 0.2, _SIGMA_MAX_PX), size, rows)
        blurred = (g @ cover.reshape(n, size, size) @ np.transpose(g, (0, 2, 1))).reshape(n, -1)
        design = np.stack(
            [np.ones_like(blurred), np.broadcast_to(xi, blurred.shape), np.broadcast_to(yi, blurred.shape), -blurred],
            -1,
        )
        weighted = np.transpose(design * mask[..., None], (0, 2, 1))
        beta = np.linalg.solve(weighted @ design + 1e-9 * np.eye(4), weighted @ grey[..., None])
        return (grey - (design @ beta)[..., 0]) * mask, beta[:, 3, 0]

    phi = np.zeros((n, 6))
    phi[:, 2] = phi[:, 4] = 1.0
    res, depth = residual(phi)
    cost = (res**2).sum(axis=1)
    damping = np.full(n, 1e-3)
    h = 1e-3
    for _ in range(_ITERATIONS):
        jt = np.empty((n, 6, res.shape[1]))
        for k in range(6):
            moved = phi.copy()
            moved[:, k] += h
            jt[:, k] = (residual(moved)[0] - res) / h
        jtj, jtr = jt @ np.transpose(jt, (0, 2, 1)), (jt @ res[..., None])[..., 0]
        diag = np.diagonal(jtj, axis1=1, axis2=2)
        for _ in range(3):
            step = np.linalg.solve(
                jtj + damping[:, None, None] * (diag[:, None, :] * np.eye(6) + 1e-9 * np.eye(6)), -jtr[..., None]
            )
            trial = phi + step[..., 0]
            res2, depth2 = residual(trial)
            cost2 = (res2**2).sum(axis=1)
            better = cost2 < cost
            phi[better], res[better], cost[better], depth[better] = (
                trial[better],
                res2[better],
                cost2[better],
                depth2[better],
            )
            damping = np.where(better, damping / 4, damping * 8)
            if better.all():
                break
    m11, m22, sigma = phi[:, 2], phi[:, 4], np.exp(phi[:, 5])
    ok = win.inside & (m11 > 0) & (m22 > 0) & (depth > 0) & (sigma < _SIGMA_MAX_PX) & np.isfinite(phi).all(axis=1)
    ok &= np.hypot(phi[:, 0], phi[:, 1]) < 0.5 * radius_px
    return 0.5 * np.log(np.where(ok, m11, 1.0) / np.where(ok, m22, 1.0)), ok


def _coverage(x: np.ndarray, y: np.ndarray, centre: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """How much of each pixel (x, y) the ellipses u' inv u <= 1 about `centre` cover: (n, P), from the
    signed distance to the rim (its first-order estimate), a pixel wide ramp."""
    u, v = x[None] - centre[:, :1], y[None] - centre[:, 1:]
    a, b, c = inv[:, 0, :1], inv[:, 0, 1:], inv[:, 1, 1:]
    gu, gv = a * u + b * v, b * u + c * v
    s = np.sqrt(np.maximum(u * gu + v * gv, 0.0))
    return np.clip(0.5 - (s - 1.0) * s / np.maximum(np.hypot(gu, gv), 1e-9), 0.0, 1.0)


def _blur_matrices(sigma: np.ndarray, size: int, rows: np.ndarray) -> np.ndarray:
    """(n, len(rows), size): a Gaussian blur along one axis of `size` pixels, the output's `rows` only,
    each summing to what the whole kernel does (pixels beyond the window count as clear)."""
    d = rows[:, None] - np.arange(size)[None, :]
    s = sigma[:, None, None]
    kernel = np.exp(-0.5 * (d[None] / s) ** 2)
    full = np.exp(-0.5 * (np.arange(-size, size + 1)[None, :] / sigma[:, None]) ** 2).sum(axis=1)
    return kernel / full[:, None, None]

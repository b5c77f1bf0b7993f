"""Sub-pixel circle centres, measured at full resolution in a small window around each one.

The centre is the darkness-weighted centroid over the circle and its blurred rim, where
darkness is 1 - grey / paper, the paper a plane fitted to a ring just outside the rim:
background pixels inside the window weigh zero on average (they do not pull the centre
towards the window's middle), and glare or a light gradient across the window does not
tilt it. Darkness is saturated at 70 % of the circle's depth, so the rim decides the
position and uneven ink inside a faded dot does not; nothing depends on a threshold. Two passes: a disc from the coarse size gives the circle's moment ellipse
(perspective, distortion), the second pass weighs over that ellipse grown by the rim.
All circles are measured at once on a stack of equal windows (no per-circle Python work).
"""
from __future__ import annotations

import numpy as np

_SATURATION = 0.7


def refine_centres(
    gray: np.ndarray, centre_px: np.ndarray, diameter_px: np.ndarray, coarse_error_px: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centres (N, 2), moment diameters (N,), ok (N,)): ok is False for circles cut by the border
    or with no contrast, whose centre would be biased or meaningless."""
    n = len(centre_px)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0, bool)
    d = np.asarray(diameter_px, dtype=np.float64)
    rim = np.maximum(1.5, 0.1 * d)
    ring = np.maximum(3.0, 0.15 * d)
    r_in = 0.6 * d + rim + np.asarray(coarse_error_px, dtype=np.float64)
    half = int(np.ceil((r_in + ring).max() + 1))
    H, W = gray.shape
    ix0 = np.round(centre_px[:, 0]).astype(int) - half
    iy0 = np.round(centre_px[:, 1]).astype(int) - half
    ok = (ix0 >= 0) & (iy0 >= 0) & (ix0 + 2 * half < W) & (iy0 + 2 * half < H)
    off = np.arange(2 * half + 1)
    iy = np.clip(iy0[:, None, None] + off[None, :, None], 0, H - 1)
    ix = np.clip(ix0[:, None, None] + off[None, None, :], 0, W - 1)
    patch = gray[iy, ix].astype(np.float32)
    shape = patch.shape  # relative to the coarse centre:
    xx = np.broadcast_to(ix0[:, None, None] + off[None, None, :] - centre_px[:, 0, None, None], shape).astype(np.float32)
    yy = np.broadcast_to(iy0[:, None, None] + off[None, :, None] - centre_px[:, 1, None, None], shape).astype(np.float32)
    # Pass 1: a disc around the coarse centre, large enough for its error.
    rho = np.sqrt(xx * xx + yy * yy) / r_in[:, None, None]
    w, _ = _darkness(patch, rho <= 1.0, (rho > 1.0) & (rho <= 1.0 + ring[:, None, None] / r_in[:, None, None]))
    # Its shape from the pixels darker than half its depth: glare or a gradient across the
    # window cannot stretch that ellipse the way they skew plain weights.
    half_depth = 0.5 * w.reshape(n, -1).max(axis=1)[:, None, None]
    mx, my, cov, _ = _moments((w > half_depth).astype(np.float32), xx, yy)
    # Then the moment ellipse (a uniform ellipse: boundary at rho = 1), grown by the rim, twice:
    # the second ellipse comes from weights that no longer include the disc's background noise.
    for _ in range(2):
        mx, my, cov, total, good = _ellipse_pass(patch, xx, yy, mx, my, cov, rim, ring)
    det = np.clip(np.linalg.det(cov), 0.0, None)
    centres = np.column_stack([centre_px[:, 0] + mx, centre_px[:, 1] + my])
    ok &= good & (total > 0) & np.isfinite(centres).all(axis=1) & (np.hypot(mx, my) <= r_in)
    return centres, 4.0 * det**0.25, ok


def _ellipse_pass(patch, xx, yy, mx, my, cov, rim, ring):
    """Darkness-weighted moments over the ellipse of `cov` at (mx, my) grown by the rim."""
    inv = np.linalg.inv(4.0 * cov + 1e-6 * np.eye(2)).astype(np.float32)
    r_min = 2.0 * np.sqrt(np.clip(np.linalg.eigvalsh(cov)[:, 0], 1e-6, None))
    dx, dy = xx - mx[:, None, None].astype(np.float32), yy - my[:, None, None].astype(np.float32)
    q = inv[:, 0, 0, None, None] * dx * dx + 2 * inv[:, 0, 1, None, None] * dx * dy + inv[:, 1, 1, None, None] * dy * dy
    rho = np.sqrt(np.maximum(q, 0.0))
    grow_in = (1.0 + rim / r_min)[:, None, None]
    grow_out = (1.0 + (rim + ring) / r_min)[:, None, None]
    w, good = _darkness(patch, rho <= grow_in, (rho > grow_in) & (rho <= grow_out), xx, yy)
    # Saturate at 70 % of the circle's depth: the rim (partly covered pixels) carries the
    # sub-pixel position; uneven ink inside a faded print must not pull the centre.
    depth = np.percentile(w.reshape(len(w), -1), 95, axis=1)[:, None, None]
    return (*_moments(np.minimum(w, _SATURATION * depth), xx, yy), good)


def _darkness(patch, inner, ring, xx=None, yy=None):
    """1 - grey / paper inside `inner` (0 elsewhere). The paper is the median of the `ring` pixels
    or, given coordinates, the plane fitted to them (glare or a light gradient across the window)."""
    n = ring.sum(axis=(1, 2))
    if xx is None:
        level = np.nanmedian(np.where(ring, patch, np.nan).reshape(len(patch), -1), axis=1) if len(patch) else n
        good = (n >= 8) & (level > 1.0)
        paper = np.where(good, level, 1.0).astype(np.float32)[:, None, None]
        return (1.0 - patch / paper) * inner, good
    m = ring.astype(np.float32)
    mx, my = m * xx, m * yy
    s = lambda a: a.sum(axis=(1, 2), dtype=np.float64)  # noqa: E731
    n, sx, sy, sxx, sxy, syy = s(m), s(mx), s(my), s(mx * xx), s(mx * yy), s(my * yy)
    normal = np.stack([np.stack([n, sx, sy], -1), np.stack([sx, sxx, sxy], -1), np.stack([sy, sxy, syy], -1)], -2)
    rhs = np.stack([s(m * patch), s(mx * patch), s(my * patch)], -1)
    good = n >= 8
    normal[~good] = np.eye(3)
    coef = np.linalg.solve(normal, rhs[..., None])[..., 0].astype(np.float32)
    paper = coef[:, 0, None, None] + coef[:, 1, None, None] * xx + coef[:, 2, None, None] * yy
    good &= coef[:, 0] > 1.0
    return (1.0 - patch / np.maximum(paper, 1.0)) * inner, good


def _moments(w, xx, yy):
    """Centroid, covariance and sum of the weights."""
    sums = w.sum(axis=(1, 2))
    total = np.where(sums > 1e-9, sums, np.nan)
    mx = (w * xx).sum(axis=(1, 2)) / total
    my = (w * yy).sum(axis=(1, 2)) / total
    dx, dy = xx - mx[:, None, None], yy - my[:, None, None]
    cxx = (w * dx * dx).sum(axis=(1, 2)) / total
    cyy = (w * dy * dy).sum(axis=(1, 2)) / total
    cxy = (w * dx * dy).sum(axis=(1, 2)) / total
    cov = np.stack([np.stack([cxx, cxy], -1), np.stack([cxy, cyy], -1)], -2)
    cov = np.where(np.isfinite(cov) & (np.abs(cov) < 1e12), cov, 1.0)
    return np.nan_to_num(mx), np.nan_to_num(my), cov, sums


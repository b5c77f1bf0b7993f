"""Sub-pixel circle centres, measured in a small window around each one.

The centre is the darkness-weighted centroid over the circle and its blurred rim, where
darkness is 1 - grey / paper, the paper a plane fitted to a ring just outside the rim:
background pixels inside the window weigh zero on average (they do not pull the centre
towards the window's middle), and glare or a light gradient across the window does not
tilt it. Darkness is saturated at 70 % of the circle's depth, so the rim decides the
position and uneven ink inside a faded dot does not; nothing depends on a threshold.

Two passes. The shape pass, on a disc around the coarse centre (on the half-resolution
image where the circle is large enough there: a quarter of the pixels), takes the pixels
darker than half the circle's depth: their moments give the circle's ellipse (perspective,
distortion) and a better centre. The final pass, at the resolution asked for, weighs over
that ellipse grown by the rim, in a window just large enough for it.

All circles are measured at once: windows of one size share one pixel grid, so every sum
(moments, the plane's normal equations) and every quadratic form (the ellipses) is one
matrix product of the stacked windows with the grid's monomials 1, x, y, x2, xy, y2.
"""

from __future__ import annotations

import functools

import numpy as np

_SATURATION = 0.7
_MIN_SHAPE_DIAMETER = 8.0  # px on the half-resolution image for the shape pass to use it


def refine_centres(
    gray: np.ndarray,
    centre_px: np.ndarray,
    diameter_px: np.ndarray,
    coarse_error_px: np.ndarray,
    half_res: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centres (N, 2), moment diameters (N,), ok (N,)) in `gray`'s pixels; ok is False for circles
    cut by the border or with no contrast, whose centre would be biased or meaningless.

    `half_res`: gray reduced 2x by pyrDown (pixel i at 2i), used for the shape pass when given."""
    n = len(centre_px)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0, bool)
    d = np.asarray(diameter_px, dtype=np.float64)
    err = np.asarray(coarse_error_px, dtype=np.float64)
    c, cov, ok = _shape_at(gray, half_res, np.asarray(centre_px, dtype=np.float64), d, err)
    # A candidate can be part of its circle (a faded half): where the shape fills the window,
    # measure it again in a window sized by what was seen.
    seen_d = 4.0 * np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, 1], 0.0))
    again = ok & (seen_d > 1.15 * d)
    if again.any():
        d = np.where(again, np.maximum(d, 1.2 * seen_d), d)
        c2, cov2, ok2 = _shape_at(gray, half_res, c[again], d[again], np.ones(int(again.sum())))
        c[again], cov[again], ok[again] = c2, cov2, ok2
    rim = np.maximum(1.5, 0.1 * d)
    ring = np.maximum(3.0, 0.15 * d)
    eig = np.linalg.eigvalsh(cov)
    radius = 2.0 * np.sqrt(np.maximum(eig[:, 1], 1e-6))
    half = int(np.ceil(np.nanmax(radius + rim + ring) + 1.5))
    win = Windows(gray, c, half)
    inv = np.linalg.inv(4.0 * cov + 1e-6 * np.eye(2))
    r_min = 2.0 * np.sqrt(np.maximum(eig[:, 0], 1e-6))
    r2 = win.quadratic(win.offset, inv)
    inner = r2 <= ((1.0 + rim / r_min) ** 2)[:, None]
    ring_px = ~inner & (r2 <= ((1.0 + (rim + ring) / r_min) ** 2)[:, None])
    w, good = win.darkness(inner, ring_px, plane=True)
    # Saturate: the rim (partly covered pixels) carries the sub-pixel position; uneven ink
    # inside a faded print must not pull the centre.
    w = np.minimum(w, _SATURATION * w.max(axis=1, keepdims=True))
    centre, cov, total = win.moments(w)
    det = np.maximum(np.linalg.det(cov), 0.0)
    shift = np.hypot(*(centre - c).T)
    ok &= win.inside & good & (total > 0) & np.isfinite(centre).all(axis=1) & (shift <= radius)
    return centre, 4.0 * det**0.25, ok


@functools.lru_cache(maxsize=32)
def _grid(half: int) -> tuple[np.ndarray, np.ndarray]:
    """The monomials 1, x, y, x2, xy, y2 over a (2 half + 1)^2 window, (P, 6) and transposed
    (read-only: shared by every window of that size)."""
    off = np.arange(-half, half + 1)
    yy, xx = np.meshgrid(off, off, indexing="ij")
    x, y = xx.ravel().astype(np.float32), yy.ravel().astype(np.float32)
    basis = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    basis_t = np.ascontiguousarray(basis.T)
    basis.flags.writeable = basis_t.flags.writeable = False
    return basis, basis_t


class Windows:
    """Square windows of one size around each centre, flattened: grey levels (N, P) and the shared
    grid's monomials (P, 6), x and y relative to the window's middle pixel."""

    def __init__(self, image: np.ndarray, centre: np.ndarray, half: int):
        H, W = image.shape
        safe = np.nan_to_num(np.asarray(centre, dtype=np.float64), nan=-1e6)
        self.middle = np.round(safe).astype(int)
        x0, y0 = self.middle[:, 0] - half, self.middle[:, 1] - half
        self.inside = (x0 >= 0) & (y0 >= 0) & (x0 + 2 * half < W) & (y0 + 2 * half < H)
        size = 2 * half + 1
        if size > min(H, W):  # no window fits: all outside, grey levels of a clipped one
            off = np.arange(-half, half + 1)
            ix = np.clip(self.middle[:, 0, None] + off[None, :], 0, W - 1)
            iy = np.clip(self.middle[:, 1, None] + off[None, :], 0, H - 1)
            grey = image[iy[:, :, None], ix[:, None, :]]
        else:  # windows cut by the border are moved inside: they are not `inside`, nothing uses them
            views = np.lib.stride_tricks.sliding_window_view(image, (size, size))
            grey = views[np.minimum(np.maximum(y0, 0), H - size), np.minimum(np.maximum(x0, 0), W - size)]
        self.grey = grey.reshape(len(safe), -1).astype(np.float32)
        self.basis, self.basis_t = _grid(half)
        self.offset = safe - self.middle  # each centre in its window's coordinates

    def quadratic(self, centre: np.ndarray, inv: np.ndarray) -> np.ndarray:
        """(p - centre)' inv (p - centre) at every window pixel: (N, P)."""
        a, b, c = inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]
        u, v = centre[:, 0], centre[:, 1]
        q = np.column_stack(
            [a * u * u + 2 * b * u * v + c * v * v, -2 * (a * u + b * v), -2 * (b * u + c * v), a, 2 * b, c]
        )
        return self.expand(q.astype(np.float32))

    def expand(self, coef: np.ndarray) -> np.ndarray:
        """sum_k coef[:, k] * monomial_k at every window pixel: (N, P)."""
        return coef @ self.basis_t[: coef.shape[1]]

    def sums(self, w: np.ndarray, terms: int = 6) -> np.ndarray:
        """sum over each window of w * monomial_k, k < terms: (N, terms)."""
        return w @ self.basis[:, :terms]

    def darkness(self, inner: np.ndarray, ring: np.ndarray, plane: bool) -> tuple[np.ndarray, np.ndarray]:
        """1 - grey / paper inside `inner` (0 elsewhere): the paper the mean of the `ring` pixels, or
        the plane fitted to them (glare or a light gradient across the window)."""
        m = ring.astype(np.float32)
        sums = self.sums(m)  # n, sx, sy, sxx, sxy, syy
        n = sums[:, 0]
        good = n >= 8
        if plane:
            normal = sums[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3).astype(np.float64)
            normal[~good] = np.eye(3)
            rhs = self.sums(m * self.grey, 3).astype(np.float64)
            coef = np.linalg.solve(normal, rhs[..., None])[..., 0].astype(np.float32)
            paper = self.expand(coef)
            good &= coef[:, 0] > 1.0
        else:
            level = (m * self.grey).sum(axis=1) / np.maximum(n, 1)
            good &= level > 1.0
            paper = np.where(good, level, 1.0).astype(np.float32)[:, None]
        return (1.0 - self.grey / np.maximum(paper, 1.0)) * inner, good

    def moments(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centroid (image px), covariance and sum of the weights (N, P)."""
        s = self.sums(w).astype(np.float64)
        total = s[:, 0]
        t = np.where(total > 1e-9, total, np.nan)
        mx, my = s[:, 1] / t, s[:, 2] / t
        cxx, cxy, cyy = s[:, 3] / t - mx * mx, s[:, 4] / t - mx * my, s[:, 5] / t - my * my
        cov = np.stack([np.stack([cxx, cxy], -1), np.stack([cxy, cyy], -1)], -2)
        cov = np.where(np.isfinite(cov) & (np.abs(cov) < 1e12), cov, 1.0)
        return self.middle + np.column_stack([mx, my]), cov, total


def _shape_at(gray, half_res, centre, d, err):
    """The shape pass on the half-resolution image where the circles are large enough there."""
    if half_res is not None and np.median(d) / 2 >= _MIN_SHAPE_DIAMETER:
        c, cov, ok = _shape(half_res, centre / 2, d / 2, err / 2)
        return c * 2, cov * 4, ok
    return _shape(gray, centre, d, err)


def _shape(image, centre, d, err):
    """Centre and covariance of each circle's pixels darker than half its depth (a disc window)."""
    ring = np.maximum(2.0, 0.15 * d)
    r_in = 0.6 * d + np.maximum(1.5, 0.1 * d) + err
    win = Windows(image, centre, int(np.ceil(np.nanmax(r_in + ring) + 1)))
    r2 = win.quadratic(win.offset, np.eye(2)[None] / (r_in**2)[:, None, None])
    w, good = win.darkness(r2 <= 1.0, (r2 > 1.0) & (r2 <= ((1.0 + ring / r_in) ** 2)[:, None]), plane=False)
    dark = (w > 0.5 * w.max(axis=1, keepdims=True)).astype(np.float32)
    c, cov, total = win.moments(dark)
    return c, cov, win.inside & good & (total > 0)

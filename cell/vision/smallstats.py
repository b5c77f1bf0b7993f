"""np.median and np.percentile (its default, linear method) of a short 1-D array of finite numbers,
to the bit, without numpy's overhead per call (about 20 us each; locate takes several per part), and
a least-squares line in closed form."""

from __future__ import annotations

import math

import numpy as np


def median(values: np.ndarray) -> float:
    """np.median(values): the middle value of the sorted ones, or the mean of the middle two."""
    s = np.sort(np.asarray(values, dtype=np.float64).ravel())
    n = len(s)
    if n == 0:
        raise ValueError("median of no values: give at least one")
    if n % 2:
        return float(s[n // 2])
    return (float(s[n // 2 - 1]) + float(s[n // 2])) / 2


def percentile(values: np.ndarray, q_pct: float) -> float:
    """np.percentile(values, q_pct) (method "linear"): between the two sorted values about the
    index (n - 1) q / 100, interpolated as numpy does (from the nearer one, for its rounding)."""
    s = np.sort(np.asarray(values, dtype=np.float64).ravel())
    n = len(s)
    if n == 0:
        raise ValueError("percentile of no values: give at least one")
    index = (n - 1) * (q_pct / 100)
    if index >= n - 1:
        return float(s[-1])
    i = math.floor(index)
    gamma = index - i
    a, b = float(s[i]), float(s[i + 1])
    d = b - a
    return b - d * (1 - gamma) if gamma >= 0.5 else a + d * gamma


def line_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """The least-squares line y = slope x + offset (np.polyfit(x, y, 1) to about 1e-15 of its values,
    in a tenth of its time), about the points' mean; x must not be all the same."""
    xm, ym = float(x.mean()), float(y.mean())
    dx = x - xm
    slope = float(dx @ (y - ym)) / float(dx @ dx)
    return slope, ym - slope * xm

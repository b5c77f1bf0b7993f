"""The short-array statistics locate uses instead of numpy's (cell/vision/smallstats.py, issue 29
speed): np.median and np.percentile to the bit, and the bolt axis's line fit as np.polyfit's."""

from __future__ import annotations

import numpy as np
import pytest

from cell.vision.smallstats import line_fit, median, percentile
from cell.vision.subpixel import median_level


def _samples(rng: np.random.Generator, count: int):
    """Short arrays as locate sees them: widths with ties (quarter pixels), smooth ones, wide ranges."""
    for i in range(count):
        n = int(rng.integers(1, 80))
        kind = i % 3
        if kind == 0:
            yield rng.integers(0, 6, n) * 0.25 + 3.0
        elif kind == 1:
            yield rng.normal(10.0, 3.0, n)
        else:
            yield rng.uniform(-1e3, 1e3, n)


def test_median_and_percentile_are_numpys_to_the_bit():
    rng = np.random.default_rng(29)
    for values in _samples(rng, 20000):
        assert median(values) == float(np.median(values))
        for q in (90, 50, 10, 33.3, 99.9, 0, 100):
            assert percentile(values, q) == float(np.percentile(values, q)), (values, q)


def test_no_values_is_an_error_that_says_so():
    with pytest.raises(ValueError, match="median of no values"):
        median(np.zeros(0))
    with pytest.raises(ValueError, match="percentile of no values"):
        percentile(np.zeros(0), 90)


def test_background_median_from_the_histogram_is_numpys():
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 4, 57600, 57601):
        levels = rng.integers(0, 256, n).astype(np.uint8)
        assert median_level(levels) == float(np.median(levels))


def test_line_fit_is_polyfits():
    rng = np.random.default_rng(3)
    for _ in range(2000):
        n = int(rng.integers(5, 120))
        x = np.arange(n) + 0.5 + rng.uniform(0, 30)
        y = rng.uniform(-2, 2) + rng.uniform(-0.05, 0.05) * x + rng.normal(0, 0.3, n)
        slope, offset = line_fit(x, y)
        want_slope, want_offset = np.polyfit(x, y, 1)
        assert slope == pytest.approx(want_slope, rel=1e-12, abs=1e-14)
        assert offset == pytest.approx(want_offset, rel=1e-12, abs=1e-12)

"""Real photos (../shared/data/circles-opencv): a hand-held 7 x 7 dot grid in an office.

OpenCV's reference centres are one detector's answer, not truth: they check numbering (up
to the square grid's 8 symmetries) and sub-pixel agreement (within 0.5 px).
"""
import csv

import cv2
import numpy as np
import pytest

from cell.calibration.pipeline import find_points
from cell.config import CellConfig, PlateConfig
from tests.helpers import DATA

CIRCLES = DATA / "circles-opencv"
IMAGES = [f"opencv_circles{i:02d}.png" for i in range(1, 8)]
CONFIG = CellConfig(plate=PlateConfig(columns=7, rows=7, pitch_x_mm=10, pitch_y_mm=10, diameter_mm=5))

# The 8 symmetries of a square 7 x 7 grid, as maps of (col, row).
SYMMETRIES = [
    lambda c, r: (c, r), lambda c, r: (6 - c, r), lambda c, r: (c, 6 - r), lambda c, r: (6 - c, 6 - r),
    lambda c, r: (r, c), lambda c, r: (6 - r, c), lambda c, r: (r, 6 - c), lambda c, r: (6 - r, 6 - c),
]


@pytest.fixture(scope="module")
def reference():
    if not CIRCLES.exists():
        pytest.skip(f"{CIRCLES} is absent: the real photos live in ../shared/data, outside the repo")
    with open(CIRCLES / "opencv_circles_centers.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return {
        name: (
            np.array([[float(r["x_px"]), float(r["y_px"])] for r in rows if r["image"] == name]),
            np.array([[int(r["grid_col"]), int(r["grid_row"])] for r in rows if r["image"] == name]),
        )
        for name in IMAGES
    }


@pytest.mark.parametrize("name", IMAGES)
def test_numbering_and_centres_agree_with_opencv(reference, name):
    ref_px, ref_cr = reference[name]
    pts = find_points(cv2.imread(str(CIRCLES / name)), CONFIG)
    # Every dot we number is a reference dot, within 0.5 px.
    dist = np.linalg.norm(pts.pixel[:, None, :] - ref_px[None, :, :], axis=2)
    nearest = dist.argmin(axis=1)
    assert dist.min(axis=1).max() < 0.5
    # Dots we could not find are reported, not guessed: found + missing = all 49.
    assert len(pts.number) + len(pts.missing) == 49
    assert len(set(pts.number) | set(pts.missing)) == 49
    # One grid symmetry maps our (col, row) onto OpenCV's for every dot.
    ours = [((n - 1) % 7, (n - 1) // 7) for n in pts.number]
    theirs = [tuple(ref_cr[j]) for j in nearest]
    assert any(all(sym(*o) == t for o, t in zip(ours, theirs, strict=True)) for sym in SYMMETRIES)

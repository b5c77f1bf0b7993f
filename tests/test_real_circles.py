"""Real photos (../shared/data/circles-opencv): a hand-held 7 x 7 dot grid in an office, and
the same photos made hard on purpose (cell/sim/degrade.py: noise, blur, glare, uneven light,
low contrast, scale, crops), each compared with cv2.findCirclesGrid on the same image.

Wherever OpenCV finds the grid, ours must number all of its points the same way (up to the
square grid's 8 symmetries) with centres within 0.2 px of OpenCV's. OpenCV is one detector,
not the truth: a photometric degradation leaves the geometry as it was, so each detector's
answer should stay where it was on the untouched photo. On those variants a centre more than
0.2 px from OpenCV's passes only where OpenCV's own answer moved further than ours did.
"""

import cv2
import numpy as np
import pytest

from cell.calibration.agreement import agreement, opencv_grid
from cell.calibration.pipeline import find_points
from cell.config import CellConfig, PlateConfig
from cell.sim.degrade import VARIANTS, variant
from tests.helpers import DATA

CIRCLES = DATA / "circles-opencv"
IMAGES = [f"opencv_circles{i:02d}.png" for i in range(1, 8)]
CONFIG = CellConfig(plate=PlateConfig(columns=7, rows=7, pitch_x_mm=10, pitch_y_mm=10, diameter_mm=5))
PHOTOMETRIC = ["noise", "blur", "glare", "uneven light", "low contrast", "noise+blur+glare"]
TOLERANCE_PX = 0.2


def photo(name: str) -> np.ndarray:
    if not CIRCLES.exists():
        pytest.skip(f"{CIRCLES} is absent: the real photos live in ../shared/data, outside the repo")
    return cv2.imread(str(CIRCLES / name), cv2.IMREAD_GRAYSCALE)


def check_against_opencv(gray: np.ndarray, clean_gray: np.ndarray | None = None) -> None:
    """Assert the module docstring's rule on one image; `clean_gray`: the untouched photo."""
    ref = opencv_grid(gray, 7, 7)
    if ref is None:
        return  # OpenCV sees no grid: nothing to match (ours may still find it)
    pts = find_points(gray, CONFIG)
    assert len(pts.number) == 49, f"numbered {len(pts.number)}, missing {pts.missing}"
    clean = None if clean_gray is None else opencv_grid(clean_gray, 7, 7)
    if clean_gray is None:
        a = agreement(pts.number, pts.pixel, ref, 7, 7)
        assert a.matched == 49 and a.same_numbering
        assert a.max_px <= TOLERANCE_PX, f"max {a.max_px:.3f} px from OpenCV"
        return
    # The geometry is the photo's: pair each dot through OpenCV's untouched-photo centre, and
    # measure how far each detector's answer moved from its own answer on the untouched photo.
    assert agreement(pts.number, pts.pixel, clean, 7, 7).same_numbering
    ours = _paired(pts.pixel, clean)
    ours_clean = _paired(find_points(clean_gray, CONFIG).pixel, clean)
    off = np.linalg.norm(ours - ref, axis=1)
    cv_moved = np.linalg.norm(ref - clean, axis=1)
    ours_moved = np.linalg.norm(ours - ours_clean, axis=1)
    bad = (off > TOLERANCE_PX) & (ours_moved > cv_moved)
    assert not bad.any(), (
        f"{off[bad]} px from OpenCV, where ours moved {ours_moved[bad]} px and OpenCV {cv_moved[bad]} px"
    )


def _paired(pixel: np.ndarray, clean: np.ndarray) -> np.ndarray:
    return pixel[np.linalg.norm(pixel[None, :, :] - clean[:, None, :], axis=2).argmin(axis=1)]


@pytest.mark.parametrize("name", IMAGES)
def test_shared_photo_agrees_with_opencv(name):
    check_against_opencv(photo(name))


@pytest.mark.slow
@pytest.mark.parametrize("kind", PHOTOMETRIC)
@pytest.mark.parametrize("name", IMAGES)
def test_photometric_variant(name, kind):
    gray = photo(name)
    check_against_opencv(variant(kind, gray, seed=IMAGES.index(name)), gray)


@pytest.mark.slow
@pytest.mark.parametrize("kind", [k for k in VARIANTS if k not in PHOTOMETRIC])
@pytest.mark.parametrize("name", IMAGES)
def test_geometric_variant(name, kind):
    check_against_opencv(variant(kind, photo(name), seed=IMAGES.index(name)))


def test_a_dot_that_is_not_there_is_reported_missing():
    gray = photo("opencv_circles01.png").copy()
    ref = opencv_grid(gray, 7, 7)
    x, y = ref[10]
    cv2.circle(gray, (int(round(x)), int(round(y))), 8, int(np.median(gray[int(y) - 12 : int(y) + 12, int(x) + 8])), -1)
    pts = find_points(gray, CONFIG)
    assert len(pts.number) == 48 and len(pts.missing) == 1

"""Finding the plate's circle centres in an image.

Two detectors:
- `detect_paper`: the paper's pipeline exactly (HSV inRange, bitwise_not, external
  contours, 500-2000 px area, moment centres): whole-pixel-quality centres, fixed areas.
- `find_candidates` + `refine_centres`: the default, coarse to fine so that it is
  scale-free and costs little at any image size. Candidates come from an image pyramid
  (candidates.py); each numbered circle's centre is then measured at full resolution in a
  small window (refine.py).
"""

from __future__ import annotations

import cv2
import numpy as np

from cell.calibration.candidates import Candidates, find_candidates
from cell.calibration.refine import refine_centres
from cell.config import PaperDetectionConfig

__all__ = ["Candidates", "detect_paper", "find_candidates", "refine_centres", "to_gray"]


def to_gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def detect_paper(image: np.ndarray, cfg: PaperDetectionConfig) -> np.ndarray:
    """Centres (N, 2) exactly as the paper's section III-D finds them (whole pixels), unordered."""
    bgr = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
    mask = cv2.inRange(hsv, np.array(cfg.hsv_lower), np.array(cfg.hsv_upper))
    mask = cv2.bitwise_not(mask)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    centres = []
    for c in contours:
        area = cv2.contourArea(c)
        if cfg.min_area_px < area < cfg.max_area_px:
            m = cv2.moments(c)
            if m["m00"] > 0:
                # int(): whole pixels, as the paper's Table II prints them.
                centres.append((int(m["m10"] / m["m00"]), int(m["m01"] / m["m00"])))
    return np.array(centres, dtype=np.float64).reshape(-1, 2)


_FINEST_COARSE_LEVEL = 2  # refinement never on a level coarser than this (a quarter resolution)


def refine_candidates(
    group: Candidates, idx: np.ndarray, lattice_d: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refined centres and diameters (full-resolution px) of the numbered candidates.

    Each is measured on the finest level where the circles are at most 24 px across (full
    resolution for smaller ones), but never coarser than a quarter resolution: pyrDown's blur
    is symmetric, so it moves no centroid, and larger windows would only cost time; but a
    centre is good to about 0.015 px of its level, which a coarser level would multiply. The
    size that decides is the larger of the blob's and the one the lattice pitch predicts
    (`lattice_d`): a faint circle's blob is only its core.
    """
    d = np.maximum(group.diameter_px[idx], lattice_d)
    k = min(max(int(np.floor(np.log2(max(float(np.median(d)), 1.0) / 12.0))), 0), _FINEST_COARSE_LEVEL)
    k = min(k, len(group.pyramid) - 1)
    s = 2.0**k
    half_res = group.pyramid[k + 1] if k + 1 < len(group.pyramid) else None
    coarse_error = np.maximum(0.5 * 2.0 ** group.level[idx] / s, 1.0)
    centres, diam, ok = refine_centres(group.pyramid[k], group.centre_px[idx] / s, d / s, coarse_error, half_res)
    return centres * s, diam * s, ok


def size_groups(
    diameter_px: np.ndarray, depth: np.ndarray, need: int, tries: int = 6, spread: float = 1.8
) -> list[np.ndarray]:
    """Blob index sets of similar size: the plate's circles are one of them. Those with at least
    `need` blobs come first (fewer cannot be the plate), the deepest (printed dots, not specks
    of texture) first among them."""
    logd = np.log(diameter_px)
    width = np.log(spread)
    ordered = np.sort(logd)
    counts = np.searchsorted(ordered, logd + width, "right") - np.searchsorted(ordered, logd - width, "left")
    groups: list[np.ndarray] = []
    centres: list[float] = []
    used = np.zeros(len(logd), bool)
    for i in np.argsort(-counts, kind="stable"):
        if used[i] or len(groups) == tries:
            continue
        centre = np.median(logd[np.abs(logd - logd[i]) <= width])  # one mean-shift step onto the crowd
        members = np.abs(logd - centre) <= width
        used |= members
        if all(abs(centre - c) > width / 2 for c in centres):
            groups.append(np.flatnonzero(members))
            centres.append(centre)
    return sorted(groups, key=lambda g: (len(g) < need, -float(np.median(depth[g]))))

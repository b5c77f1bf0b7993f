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

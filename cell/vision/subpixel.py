"""A part's outline to a fraction of a pixel: the segmentation threshold's contour on the grey
image interpolated 4x, instead of the mask's whole-pixel outline.

A bolt's footprint is rebuilt from where its width crosses a level along the axis and from
its ends; at 0.3 mm/px a whole-pixel outline puts those up to half a pixel (0.15 mm) off,
and the footprint centre inherits it. The paper level is the median grey around the part.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

UPSAMPLE = 4
EDGE_PX = 0.5 / UPSAMPLE  # the contour runs through the inner upsampled pixels' centres
_MARGIN_PX = 4
_DILATE = np.ones((5, 5), np.uint8)


def median_level(levels: np.ndarray) -> float:
    """np.median of 8-bit levels, from their histogram (the middle one, or the mean of the middle two)."""
    below = np.cumsum(np.bincount(levels, minlength=256))
    n = int(below[-1])
    hi = int(np.searchsorted(below, n // 2 + 1))  # the level of the (n // 2)-th, from 0
    if n % 2:
        return float(hi)
    return (int(np.searchsorted(below, n // 2)) + hi) / 2


def subpixel_outline(
    gray: np.ndarray, outline: np.ndarray, fraction: float, mid_level: bool = False
) -> np.ndarray | None:
    """(N, 2) float outline in image pixels, or None where no paper is seen around the part.

    `mid_level`: the contour halfway between the paper's level and the part's own (the median of its
    inside, 2 px in from its outline) where the part is clearly darker than the threshold: there a
    blurred straight edge's contour lies on the edge whatever the blur. At `fraction` x the paper
    it lies inside the edge by about 0.18 blur sigmas (backlight 200, part 25: the contour at 57 %
    cover), which shortened a bolt's head by 0.1-0.25 mm at 0.3-0.4 mm/px."""
    H, W = gray.shape
    x, y, w, h = cv2.boundingRect(outline)
    x0, y0 = max(x - _MARGIN_PX, 0), max(y - _MARGIN_PX, 0)
    x1, y1 = min(x + w + _MARGIN_PX, W), min(y + h + _MARGIN_PX, H)
    roi = gray[y0:y1, x0:x1]
    part = np.zeros(roi.shape, np.uint8)
    cv2.drawContours(part, [outline], -1, 255, -1, offset=(-x0, -y0))
    paper = roi[cv2.dilate(part, _DILATE) == 0]
    if paper.size < 16:
        return None
    # The bilinear 4x upsampling of 8-bit levels is exact in 1/64ths of a level (its weights are
    # eighths): OpenCV computes it on 64 x the levels in 16 bits, in half the time of float32, and
    # each upsampled level (a whole number of 64ths) is below the (float32) threshold exactly when
    # it is below the threshold's 64ths rounded up.
    up64 = cv2.resize(roi.astype(np.uint16) << 6, None, fx=UPSAMPLE, fy=UPSAMPLE, interpolation=cv2.INTER_LINEAR)
    paper_level = median_level(paper)
    level = float(np.float32(fraction * paper_level))
    if mid_level:
        inside = roi[cv2.erode(part, _DILATE) > 0]
        if inside.size >= 16:
            own = median_level(inside)
            if own <= 0.6 * level:
                level = float(np.float32((paper_level + own) / 2))
    dark = (up64 < math.ceil(64.0 * level)).view(np.uint8)
    contours, _ = cv2.findContours(dark, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    largest = contours[0] if len(contours) == 1 else max(contours, key=cv2.contourArea)
    # (p + 0.5) / UPSAMPLE - 0.5 + the corner, in one step: every value on the way is a whole number of
    # eighths well within a double's 53 bits, so both forms are exact and the same
    offset = np.array([x0, y0], dtype=np.float64) + (0.5 / UPSAMPLE - 0.5)
    return largest.reshape(-1, 2) * (1.0 / UPSAMPLE) + offset

"""Dark parts on a bright table: a binary mask and the outline (with holes) of each blob.

The default threshold follows the backlight: the local background level is estimated on
a downscaled frame by a max filter wider than any part (which erases the parts), and a
pixel is part where it is darker than a fraction of that level. This adapts to exposure,
vignetting and an uneven backlight without a reference frame. The paper preset is the
paper's HSV range, inverted, with external contours only (no holes).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from cell.vision.config import PartsConfig
from cell.vision.subpixel import median_level

log = logging.getLogger(__name__)

_EDGE_LINE_FILL = 0.9  # an image edge line this full of "part" is a sensor artefact
_MAX_EDGE_LINES = 4


@dataclass
class Blob:
    outer: np.ndarray  # (N, 1, 2) int32 outline, image px
    holes: list[np.ndarray]  # outlines of holes, same form
    touches_border: bool


@dataclass
class Segmentation:
    blobs: list[Blob]
    mask: np.ndarray  # uint8 0/255, full frame: 255 = part
    background_level: float  # median backlight grey level (0 when not estimated)
    warnings: list[str] = field(default_factory=list)


def to_gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def segment(
    image: np.ndarray, config: PartsConfig, part_width_px: float, noise_area_px: float, gray: np.ndarray | None = None
) -> Segmentation:
    """Blobs of `image`; `part_width_px` is the widest part's narrow width in pixels; `gray`: the
    image in grey levels where the caller has it already."""
    if config.preset == "paper":
        return _segment_paper(image, config, noise_area_px)
    return _segment_default(to_gray(image) if gray is None else gray, config, part_width_px, noise_area_px)


def _segment_default(gray: np.ndarray, config: PartsConfig, part_width_px: float, noise_area_px: float) -> Segmentation:
    h, w = gray.shape
    radius_px = max(part_width_px / 2 + 2, 3)
    factor = max(1, int(radius_px // 8))
    small = cv2.resize(gray, (max(1, w // factor), max(1, h // factor)), interpolation=cv2.INTER_AREA)
    r = int(math.ceil(radius_px / factor))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    background = cv2.dilate(small, kernel, borderType=cv2.BORDER_REPLICATE)
    background = cv2.blur(background, (r + 1, r + 1), borderType=cv2.BORDER_REPLICATE)
    level = median_level(background.ravel())  # np.median's, from the levels' histogram
    if level < config.segment.min_background_level:
        msg = f"frame too dark (backlight level {level:.0f} < {config.segment.min_background_level:.0f}): no parts can be seen"
        return Segmentation([], np.zeros_like(gray), level, [msg])
    threshold = cv2.convertScaleAbs(background, alpha=config.segment.threshold_fraction)
    threshold = cv2.resize(threshold, (w, h), interpolation=cv2.INTER_LINEAR)
    mask = cv2.compare(gray, threshold, cv2.CMP_LT)
    warnings = []
    if level >= 250 and np.count_nonzero(small >= 254) > 0.5 * small.size:
        warnings.append("frame overexposed: most of it is saturated")
    margins = _clear_edge_lines(mask)
    blobs = _blobs(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE, margins, noise_area_px)
    return Segmentation(blobs, mask, level, warnings)


def _segment_paper(image: np.ndarray, config: PartsConfig, noise_area_px: float) -> Segmentation:
    bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image[:, :, :3]
    hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
    mask = cv2.bitwise_not(cv2.inRange(hsv, np.array(config.paper.hsv_lower), np.array(config.paper.hsv_upper)))
    blobs = _blobs(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE, (0, 0, 0, 0), noise_area_px)
    return Segmentation(blobs, mask, 0.0)


def _clear_edge_lines(mask: np.ndarray) -> tuple[int, int, int, int]:
    """Clear dark lines along the image edges (sensor artefacts); return how deep, per side.

    Sides are (left, top, right, bottom); a part touching a cleared band still counts as
    touching the border.
    """
    h, w = mask.shape
    depth = [0, 0, 0, 0]
    views = [
        lambda i: mask[:, i],
        lambda i: mask[i, :],
        lambda i: mask[:, w - 1 - i],
        lambda i: mask[h - 1 - i, :],
    ]
    for side, line in enumerate(views):
        for i in range(min(_MAX_EDGE_LINES, (w if side % 2 == 0 else h) // 4)):
            values = line(i)
            if np.count_nonzero(values) < _EDGE_LINE_FILL * values.size:
                break
            values[:] = 0
            depth[side] = i + 1
    if any(depth):
        log.debug("cleared dark edge lines (left, top, right, bottom) = %s", depth)
    return depth[0], depth[1], depth[2], depth[3]


def _blobs(
    mask: np.ndarray, mode: int, method: int, margins: tuple[int, int, int, int], noise_area_px: float
) -> list[Blob]:
    h, w = mask.shape
    contours, hierarchy = cv2.findContours(mask, mode, method)
    if hierarchy is None:
        return []
    hier = hierarchy[0]
    left, top, right, bottom = margins
    blobs = []
    for i, c in enumerate(contours):
        if hier[i][3] != -1 or cv2.contourArea(c) < noise_area_px:
            continue
        holes = []
        j = hier[i][2]
        while j != -1:
            if cv2.contourArea(contours[j]) >= noise_area_px:
                holes.append(contours[j])
            j = hier[j][0]
        x, y, bw, bh = cv2.boundingRect(c)
        touches = x <= left or y <= top or x + bw >= w - right or y + bh >= h - bottom
        blobs.append(Blob(c, holes, touches))
    return blobs

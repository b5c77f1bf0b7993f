"""Finding the plate's circle centres in an image.

Two detectors:
- `detect_paper`: the paper's pipeline exactly (HSV inRange, bitwise_not, external
  contours, 500-2000 px area, moment centres): whole-pixel-quality centres, fixed areas.
- `detect_blobs`: the default. Normalises the image by its own local backlight (so exposure
  and uneven light do not matter), thresholds at half the local background, and measures
  each centre as the darkness-weighted centroid over the blob and its rim, after
  subtracting the residual background measured in a ring around it: sub-pixel and
  unbiased by the threshold.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cell.config import PaperDetectionConfig


@dataclass
class Blob:
    """A dark, roughly round blob: candidate circle."""

    centre_px: tuple[float, float]
    diameter_px: float  # equivalent-area diameter
    area_px: float
    axis_ratio: float  # minor / major axis of the moment ellipse
    solidity: float


def to_gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
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


def _blob_shape(contour: np.ndarray) -> tuple[float, float, float, float, float]:
    m = cv2.moments(contour)
    area = m["m00"]
    if area <= 0:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    cx, cy = m["m10"] / area, m["m01"] / area
    mu20, mu02, mu11 = m["mu20"] / area, m["mu02"] / area, m["mu11"] / area
    common = np.sqrt(((mu20 - mu02) / 2) ** 2 + mu11**2)
    lam1 = (mu20 + mu02) / 2 + common
    lam2 = (mu20 + mu02) / 2 - common
    ratio = float(np.sqrt(max(lam2, 0.0) / lam1)) if lam1 > 0 else 0.0
    hull_area = cv2.contourArea(cv2.convexHull(contour))
    solidity = area / hull_area if hull_area > 0 else 0.0
    return cx, cy, area, ratio, solidity


def local_background(gray: np.ndarray, dark_mask: np.ndarray, sigma_px: float) -> np.ndarray:
    """Backlight level under every pixel, interpolated from the pixels that are not dark blobs.

    Normalised convolution on a reduced image: the result is smooth, and unbiased by noise
    (unlike a morphological closing, which follows the noise's upper envelope).
    """
    h, w = gray.shape
    f = max(1, int(sigma_px // 4))
    small = cv2.resize(gray.astype(np.float32), (w // f, h // f), interpolation=cv2.INTER_AREA)
    keep = cv2.resize((~dark_mask).astype(np.float32), (w // f, h // f), interpolation=cv2.INTER_AREA)
    keep = (keep > 0.99).astype(np.float32)
    s = sigma_px / f
    num = cv2.GaussianBlur(small * keep, (0, 0), s)
    den = cv2.GaussianBlur(keep, (0, 0), s)
    bg = num / np.maximum(den, 1e-3)
    # Where no background is near (large dark areas), fall back to the global level.
    fallback = float(np.median(small[keep > 0])) if keep.any() else float(small.max())
    bg = np.where(den > 0.05, bg, fallback)
    return cv2.resize(bg, (w, h), interpolation=cv2.INTER_LINEAR)


def _typical_diameter(contours) -> float | None:
    diam = []
    for c in contours:
        _, _, area, ratio, solidity = _blob_shape(c)
        if area >= 12 and ratio > 0.4 and solidity > 0.85:
            diam.append(np.sqrt(4 * area / np.pi))
    if len(diam) < 4:
        return None
    diam = np.sort(np.array(diam))
    # The plate's circles are the largest group of similar sizes: take the densest window.
    best, best_n = None, 0
    for d in diam:
        n = np.count_nonzero((diam > d * 0.8) & (diam < d * 1.25))
        if n > best_n:
            best, best_n = d, n
    return float(best)


def normalised_image(gray: np.ndarray) -> tuple[np.ndarray, float]:
    """gray / local backlight (1 = clear backlight, ~0 = opaque), and the typical blob diameter."""
    g = gray.astype(np.float32)
    blur = cv2.GaussianBlur(gray, (5, 5), 0)
    _, otsu = cv2.threshold(blur, 0, 255, cv2.THRESH_BINARY_INV | cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(otsu, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    d = _typical_diameter(contours) or min(gray.shape) / 30
    dark = cv2.dilate(otsu, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))) > 0
    bg = local_background(g, dark, sigma_px=1.5 * d)
    return g / np.maximum(bg, 1.0), d


def detect_blobs(
    image: np.ndarray,
    min_area_px: float = 12.0,
    min_axis_ratio: float = 0.35,
    min_solidity: float = 0.85,
    threshold: float = 0.65,
) -> list[Blob]:
    """Dark round blobs with sub-pixel centres. Size limits come later, from the lattice.

    `threshold` is a fraction of the local background: low-contrast (grey) dots still fall
    below it; the centre itself does not depend on it (it is darkness-weighted).
    """
    gray = to_gray(image)
    norm, _ = normalised_image(gray)
    binary = (norm < threshold).astype(np.uint8)
    # CCOMP, not EXTERNAL: dots on a sheet held in front of a dark room are islands inside
    # the hole that the sheet makes in the room's dark region; keep every outer boundary.
    contours, hierarchy = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    h, w = gray.shape
    blobs = []
    outer = [c for c, hier in zip(contours, hierarchy[0] if hierarchy is not None else [], strict=True) if hier[3] < 0]
    for c in outer:
        cx, cy, area, ratio, solidity = _blob_shape(c)
        if area < min_area_px or ratio < min_axis_ratio or solidity < min_solidity:
            continue
        x, y, bw, bh = cv2.boundingRect(c)
        d = np.sqrt(4 * area / np.pi)
        centre = _subpixel_centre(norm, c, (x, y, bw, bh), d, (w, h))
        if centre is None:
            continue
        blobs.append(Blob(centre, float(d), float(area), ratio, solidity))
    return blobs


def _subpixel_centre(norm, contour, rect, d, size) -> tuple[float, float] | None:
    """Darkness-weighted centroid over the blob's moment ellipse grown by its blurred rim.

    Weights are (ring level - normalised intensity): the ring just outside the rim gives
    the residual background, so background pixels inside the window weigh zero on
    average and do not pull the centre towards the window's middle.
    """
    w, h = size
    x, y, bw, bh = rect
    rim = max(2.0, 0.15 * d)
    ring = rim + max(2.0, 0.1 * d)
    x0, y0 = max(0, x - int(ring) - 1), max(0, y - int(ring) - 1)
    x1, y1 = min(w, x + bw + int(ring) + 1), min(h, y + bh + int(ring) + 1)
    if x0 == 0 or y0 == 0 or x1 == w or y1 == h:
        return None  # cut by the image border: its centroid would be biased
    m = cv2.moments(contour)
    cx, cy = m["m10"] / m["m00"], m["m01"] / m["m00"]
    cov = np.array([[m["mu20"], m["mu11"]], [m["mu11"], m["mu02"]]]) / m["m00"]
    inv = np.linalg.inv(cov * 4.0)  # a uniform ellipse: boundary at rho = 1
    r_min = 2.0 * np.sqrt(max(np.linalg.eigvalsh(cov)[0], 1e-6))
    roi = norm[y0:y1, x0:x1]
    yy, xx = np.mgrid[y0:y1, x0:x1]
    dx, dy = xx - cx, yy - cy
    rho = np.sqrt(inv[0, 0] * dx * dx + 2 * inv[0, 1] * dx * dy + inv[1, 1] * dy * dy)
    inner = rho <= 1.0 + rim / r_min
    ring_px = roi[~inner & (rho <= 1.0 + ring / r_min)]
    if ring_px.size < 8:
        return None
    level = float(np.median(ring_px))
    weight = (level - roi) * inner
    total = float(weight.sum())
    if total <= 0:
        return None
    return float((weight * xx).sum() / total), float((weight * yy).sum() / total)

"""Shape measurements of one blob, in pixels; classify.py turns them into millimetres.

The centroid comes from the moments of the blob's own pixels (holes excluded), which is
unbiased to a small fraction of a pixel. Hexagonality is the outline's sixth angular
harmonic relative to a regular hexagon's: about 1 for a hexagon, near 0 for circles,
squares and thin rectangles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from cell.vision.segment import Blob

_OUTLINE_SAMPLES = 180


def _hexagon_harmonic_ratio() -> float:
    phi = np.linspace(-np.pi, np.pi, 3600, endpoint=False)
    local = (phi + np.pi / 6) % (np.pi / 3) - np.pi / 6
    r = 1.0 / np.cos(local)
    return float(abs(np.mean(r * np.exp(-6j * phi))) * 2 / np.mean(r))


_HEXAGON_RATIO = _hexagon_harmonic_ratio()


@dataclass
class Hole:
    area_px: float
    centroid_px: tuple[float, float]


@dataclass
class Features:
    centroid_px: tuple[float, float]  # of the part's pixels, holes excluded
    area_px: float  # part pixels, holes excluded
    outer_area_px: float  # inside the outer outline, holes included
    outer_centroid_px: tuple[float, float]
    bbox_px: tuple[int, int, int, int]  # x, y, w, h
    min_rect: tuple  # cv2.minAreaRect: ((cx, cy), (w, h), angle)
    holes: list[Hole]
    solidity: float  # outer area / convex hull area
    elongation: float  # long / short side of the minimum-area rectangle
    roundness: float  # outer area / area of the minimum enclosing circle (circle 1, hexagon 0.83)
    enclosing_diameter_px: float
    hexagonality: float
    axis_px: tuple[float, float]  # unit vector along the major axis (second moments)
    touches_border: bool


def _part_moments(blob: Blob, mask: np.ndarray) -> tuple[int, int, np.ndarray, dict]:
    """The blob's bounding box corner, its filled outline there, and the moments of its own pixels."""
    outer = blob.outer
    x, y, w, h = cv2.boundingRect(outer)
    filled = np.zeros((h, w), np.uint8)
    cv2.drawContours(filled, [outer], -1, 255, -1, offset=(-x, -y))
    part = cv2.bitwise_and(mask[y : y + h, x : x + w], filled)
    m = cv2.moments(part, binaryImage=True)
    if m["m00"] <= 0:  # a contour with no interior pixels: use the outline itself
        m = cv2.moments(outer)
        m["m00"] = m["m00"] or 1.0
    return x, y, filled, m


def part_centroid_px(blob: Blob, mask: np.ndarray) -> tuple[float, float]:
    """The centroid of the blob's own pixels (holes excluded): measure()'s, alone."""
    x, y, _, m = _part_moments(blob, mask)
    return (x + m["m10"] / m["m00"], y + m["m01"] / m["m00"])


def measure(blob: Blob, mask: np.ndarray) -> Features:
    outer = blob.outer
    x, y, filled, m = _part_moments(blob, mask)
    centroid = (x + m["m10"] / m["m00"], y + m["m01"] / m["m00"])
    mf = cv2.moments(filled, binaryImage=True)
    outer_area = mf["m00"]
    outer_centroid = (x + mf["m10"] / max(outer_area, 1), y + mf["m01"] / max(outer_area, 1))
    mu20, mu02, mu11 = m["mu20"], m["mu02"], m["mu11"]
    theta = 0.5 * math.atan2(2 * mu11, mu20 - mu02)
    rect = cv2.minAreaRect(outer)
    sides = sorted(rect[1])
    hull_area = cv2.contourArea(cv2.convexHull(outer))
    outline_area = cv2.contourArea(outer)
    _, radius = cv2.minEnclosingCircle(outer)
    enclosing_d = 2 * radius + 1  # outline runs through edge pixel centres
    holes = []
    for hc in blob.holes:
        hm = cv2.moments(hc)
        if hm["m00"] > 0:
            holes.append(Hole(float(hm["m00"]), (hm["m10"] / hm["m00"], hm["m01"] / hm["m00"])))
    return Features(
        centroid_px=centroid,
        area_px=float(m["m00"]),
        outer_area_px=float(outer_area),
        outer_centroid_px=outer_centroid,
        bbox_px=(x, y, filled.shape[1], filled.shape[0]),
        min_rect=rect,
        holes=holes,
        solidity=float(outline_area / hull_area) if hull_area > 0 else 1.0,
        elongation=float((sides[1] + 1) / (sides[0] + 1)),
        roundness=float(outer_area / (math.pi * (enclosing_d / 2) ** 2)),
        enclosing_diameter_px=float(enclosing_d),
        hexagonality=hexagonality(outer, outer_centroid),
        axis_px=(math.cos(theta), math.sin(theta)),
        touches_border=blob.touches_border,
    )


def resample(outline: np.ndarray, count: int | None = None, step_px: float = 0.5) -> np.ndarray:
    """Points evenly spaced along the closed outline: `count` of them, or `step_px` apart."""
    pts = outline.reshape(-1, 2).astype(np.float64)
    closed = np.concatenate((pts, pts[:1]))
    step = closed[1:] - closed[:-1]
    s = np.empty(len(closed))  # the length along the outline at each point
    s[0] = 0.0
    np.cumsum(np.hypot(step[:, 0], step[:, 1]), out=s[1:])
    total = s[-1]
    if total <= 0:
        return pts[:1]
    n = count or max(3, int(total / step_px))
    t = np.arange(n) * (total / n)  # np.linspace(0, total, n, endpoint=False), without its overhead
    out = np.empty((n, 2))
    out[:, 0] = np.interp(t, s, closed[:, 0])
    out[:, 1] = np.interp(t, s, closed[:, 1])
    return out


def hexagonality(outline: np.ndarray, centre: tuple[float, float]) -> float:
    """Sixth angular harmonic of the outline's radius, relative to a regular hexagon's."""
    d = resample(outline, _OUTLINE_SAMPLES) - centre
    z = d.view(np.complex128)[:, 0]  # x + i y, as they lie in memory
    theta = np.arctan2(d[:, 1], d[:, 0])  # np.angle(z)
    r = np.abs(z)
    turn = np.concatenate((z[1:], z[:1])) * np.conj(z)
    dtheta = np.arctan2(turn.imag, turn.real)  # turn from each sample to the next
    mean_r = np.sum(r * dtheta) / (2 * np.pi)
    if abs(mean_r) < 1e-9:
        return 0.0
    c6 = np.sum(r * np.exp(-6j * theta) * dtheta) / np.pi
    return float(abs(c6) / abs(mean_r) / _HEXAGON_RATIO)


@dataclass
class Profile:
    """Width of a blob along its axis, with the head (wider) end first."""

    origin_px: np.ndarray  # the head end's outer edge, on the axis through the centroid
    axis_px: np.ndarray  # unit vector head -> tip
    positions_px: np.ndarray  # distance of each 1-px bin's centre from the origin
    widths_px: np.ndarray  # width across the axis in each bin
    centres_px: np.ndarray  # offset of each bin's mid-width from the axis (to its left)
    length_px: float  # edge to edge along the axis


def width_profile(
    outline: np.ndarray, centre: tuple[float, float], axis: tuple[float, float], edge_px: float = 0.5
) -> Profile:
    """Width across the axis in 1-px bins, oriented so that the wider end comes first.

    `edge_px`: how far the true edge lies outside the outline. A mask's outline runs through
    edge-pixel centres (0.5: widths and length gain one pixel); a sub-pixel outline needs less.
    """
    pts = resample(outline) - centre  # dense enough that every bin sees both edges
    a = np.asarray(axis, dtype=np.float64)
    n = np.array([-a[1], a[0]])
    u, v = pts @ a, pts @ n
    u0, u1 = float(u.min()), float(u.max())
    bins = np.floor(u - u0).astype(int)
    nb = bins.max() + 1
    vmax = np.full(nb, -np.inf)
    vmin = np.full(nb, np.inf)
    np.maximum.at(vmax, bins, v)
    np.minimum.at(vmin, bins, v)
    ok = np.isfinite(vmax)
    idx = np.arange(nb)
    if not ok.all():  # bins no point fell in: between their neighbours (np.interp returns the rest as they are)
        vmax = np.interp(idx, idx[ok], vmax[ok])
        vmin = np.interp(idx, idx[ok], vmin[ok])
    widths = vmax - vmin + 2 * edge_px
    mids = (vmax + vmin) / 2
    k = max(1, nb // 5)
    c = np.asarray(centre, dtype=np.float64)
    length = u1 - u0 + 2 * edge_px
    if widths[:k].mean() >= widths[-k:].mean():
        return Profile(c + (u0 - edge_px) * a, a, idx + 0.5 + edge_px, widths, mids, length)
    positions = (u1 + edge_px) - (u0 + idx[::-1] + 0.5)
    return Profile(c + (u1 + edge_px) * a, -a, positions, widths[::-1].copy(), -mids[::-1], length)

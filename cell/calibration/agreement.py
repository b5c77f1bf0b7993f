"""How far our plate points are from cv2.findCirclesGrid's on the same image, and whether both
number the grid the same way (up to the grid's symmetries: neither knows which corner is point 1
on a symmetric plate). For tests and benchmarks that use OpenCV as the reference detector."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Agreement:
    matched: int  # OpenCV's points we also numbered
    max_px: float  # largest centre distance over them
    mean_px: float
    same_numbering: bool


def opencv_grid(gray: np.ndarray, columns: int, rows: int) -> np.ndarray | None:
    """cv2.findCirclesGrid's centres (columns * rows, 2) in its order, or None where it finds no grid."""
    found, centres = cv2.findCirclesGrid(gray, (columns, rows), flags=cv2.CALIB_CB_SYMMETRIC_GRID)
    return centres.reshape(-1, 2).astype(np.float64) if found else None


def _symmetries(columns: int, rows: int):
    c, r = columns - 1, rows - 1
    maps = [lambda a, b: (a, b), lambda a, b: (c - a, b), lambda a, b: (a, r - b), lambda a, b: (c - a, r - b)]
    if columns == rows:
        maps += [lambda a, b: (b, a), lambda a, b: (c - b, a), lambda a, b: (b, c - a), lambda a, b: (c - b, c - a)]
    return maps


def agreement(number: np.ndarray, pixel: np.ndarray, reference: np.ndarray, columns: int, rows: int) -> Agreement:
    """Compare our numbered points (1-based numbers, row by row) with OpenCV's ordered centres."""
    dist = np.linalg.norm(pixel[:, None, :] - reference[None, :, :], axis=2)
    nearest = dist.argmin(axis=1)
    d = dist[np.arange(len(pixel)), nearest]
    ours = [((int(n) - 1) % columns, (int(n) - 1) // columns) for n in number]
    theirs = [(int(j) % columns, int(j) // columns) for j in nearest]
    same = len(set(nearest)) == len(nearest) and any(
        all(sym(*o) == t for o, t in zip(ours, theirs, strict=True)) for sym in _symmetries(columns, rows)
    )
    return Agreement(len(set(nearest)), float(d.max(initial=0.0)), float(d.mean()) if len(d) else 0.0, same)

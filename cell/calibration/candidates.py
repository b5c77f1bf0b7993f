"""Dark round blobs at any size, found on an image pyramid.

At every pyramid level a pixel is dark where it is below a fraction of the paper level
around it, the paper level being the image's morphological closing with a fixed window: a
dot narrower than the window is erased by it, and a bright patch (glare) is not spread
beyond itself, as a plain max filter would. That is a local-contrast threshold that follows
uneven light, glare and exposure without knowing the dot size. Each level finds dots up
to `_D_MAX` px across at that level (and from `_D_MIN` px, smaller ones being better seen
one level finer), so the levels together cover dots from 5 px to the whole frame; a dot
found at two levels is kept at the finer one. Two thresholds: a strict one (dots beside
glare stay apart) and a lax one (faded dots). Connected components give every blob's size
and centre in one vectorised call, so clutter costs almost nothing. Only the coarse
position comes from here: refine.py measures each numbered circle at full resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

_WINDOW = 17  # closing window at every level, px of that level: wider than any dot the level keeps
_D_MAX = 11.0  # widest dot a level sees whole: the window still reaches the paper around it
_D_MIN = 4.5  # narrower dots are left to the finer level
_D_MIN_FIRST = 2.5  # at the first level searched (half resolution: dots from 5 px across)
_FIRST_LEVEL = 1  # circles of 5 px and more need no full-resolution search; refinement is at full resolution
_MIN_FILL = (
    0.55  # blob area / its bounding box (a disc: 0.79, a 2:1 ellipse at 45 deg 0.63; a ring's broken piece less)
)
_MAX_ASPECT = 3.0  # bounding-box sides (a circle seen at up to ~70 deg)
_MIN_SIDE = 24  # stop the pyramid when the image gets this small
_KERNEL = cv2.getStructuringElement(cv2.MORPH_RECT, (_WINDOW, _WINDOW))


@dataclass
class Candidates:
    """Blob centres and sizes in full-resolution pixels (coarse: within about a pixel of the level)."""

    centre_px: np.ndarray  # (N, 2)
    diameter_px: np.ndarray  # (N,) equivalent-area diameter of the dark part
    level: np.ndarray  # (N,) pyramid level it was found at (0 = full resolution)
    depth: np.ndarray  # (N,) 1 - grey / paper at its centre: printed dots are deep, specks shallow
    pyramid: list[np.ndarray]  # level k is the image reduced 2**k times (pyrDown: pixel i at 2**k * i)

    def __len__(self) -> int:
        return len(self.diameter_px)

    def subset(self, keep) -> Candidates:
        return Candidates(
            self.centre_px[keep], self.diameter_px[keep], self.level[keep], self.depth[keep], self.pyramid
        )


def find_candidates(gray: np.ndarray, dark_fractions=(0.8, 0.92), min_contrast: float = 10.0) -> Candidates:
    """Every dark round blob, from 3 px across to most of the frame.

    `dark_fractions`: a pixel is dark below this fraction of the paper level around it (the
    closing); the first finds dots beside glare, whose bright surround would merge them at a
    laxer level, the second faded or low-contrast dots; a dot both find counts once.
    `min_contrast`: and at least this many grey levels below it (noise is not a dot).
    """
    levels = [gray]
    while min(levels[-1].shape) >= 2 * _MIN_SIDE:
        levels.append(cv2.pyrDown(levels[-1]))
    found: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []  # centre, d, level, depth
    seen: list[tuple[np.ndarray, np.ndarray, float]] = []  # a level's labels, the dots kept, its scale
    for k, img in enumerate(levels):
        if k < _FIRST_LEVEL and min(gray.shape) >= 4 * _MIN_SIDE:
            continue
        scale = float(2**k)
        bright = cv2.morphologyEx(img, cv2.MORPH_CLOSE, _KERNEL, borderType=cv2.BORDER_REPLICATE)
        # (OpenCV takes a scalar for src2; its stubs list arrays only)
        contrasty = cv2.compare(cv2.subtract(bright, img), min_contrast, cv2.CMP_GT)  # type: ignore[call-overload]
        here: list[tuple[np.ndarray, np.ndarray, float]] = []
        for fraction in dark_fractions:
            labels, stats, centroids, keep = _level_blobs(
                img, bright, contrasty, fraction, _D_MIN_FIRST if not seen else _D_MIN
            )
            centre = centroids[keep] * scale
            d = np.sqrt(4 * stats[keep, cv2.CC_STAT_AREA] / np.pi) * scale
            ix, iy = np.round(centroids[keep]).astype(int).T
            depth = 1.0 - img[iy, ix] / np.maximum(bright[iy, ix], 1.0)
            for maps in (seen, here):  # the finer level's dots, then this level's first threshold
                for labels_seen, is_kept, s in maps:
                    unseen = _unseen(centre, labels_seen, is_kept, s)
                    centre, d, depth = centre[unseen], d[unseen], depth[unseen]
            found.append((centre, d, np.full(len(d), k), depth))
            here.append((labels, keep, scale))
        seen = here
    centre = np.concatenate([f[0] for f in found]).reshape(-1, 2)
    d, level, depth = (np.concatenate([f[i] for f in found]) for i in (1, 2, 3))
    return Candidates(centre, d, level, depth, levels)


def _level_blobs(img: np.ndarray, bright: np.ndarray, contrasty: np.ndarray, fraction: float, d_min: float):
    """Labels, stats, centroids of the dark blobs at one level, and which of them are dots.

    `bright`: the paper level around each pixel (a closing wider than the level's dots);
    `contrasty`: 255 where a pixel is far enough below it."""
    mask = cv2.bitwise_and(cv2.compare(img, cv2.convertScaleAbs(bright, alpha=fraction), cv2.CMP_LT), contrasty)
    n, labels, stats, centroids = cv2.connectedComponentsWithStatsWithAlgorithm(mask, 8, cv2.CV_32S, cv2.CCL_BBDT)
    x, y, w, h, area = (stats[:, i] for i in range(5))
    d = np.sqrt(4 * area / np.pi)
    fill = area / np.maximum(w * h, 1)
    aspect = np.maximum(w, h) / np.maximum(np.minimum(w, h), 1)
    H, W = img.shape
    ok = (d >= d_min) & (d <= _D_MAX) & (fill >= _MIN_FILL) & (aspect <= _MAX_ASPECT)
    ok &= (x > 0) & (y > 0) & (x + w < W) & (y + h < H)
    ok[0] = False  # the background
    # A dot wider than the window leaves a ring of dark pixels: its centre is not in the blob.
    idx = np.flatnonzero(ok)
    cx = np.minimum(np.maximum(np.rint(centroids[idx, 0]).astype(int), 0), W - 1)
    cy = np.minimum(np.maximum(np.rint(centroids[idx, 1]).astype(int), 0), H - 1)
    ok[idx[labels[cy, cx] != idx]] = False
    return labels, stats, centroids, ok


def _unseen(centre, labels, is_kept, scale) -> np.ndarray:
    """Which blobs do not lie on a dot already kept in `labels` (an image reduced `scale` times);
    `is_kept`: per label of that map, whether it was kept."""
    if not len(centre):
        return np.zeros(0, bool)
    H, W = labels.shape
    fine = centre / scale
    ix = np.minimum(np.maximum(np.rint(fine[:, 0]).astype(int), 0), W - 1)
    iy = np.minimum(np.maximum(np.rint(fine[:, 1]).astype(int), 0), H - 1)
    return ~is_kept[labels[iy, ix]]

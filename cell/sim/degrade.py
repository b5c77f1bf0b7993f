"""Real photos made harder on purpose: what a hand-held plate under office light goes through.

Each variant is a function of a grey image and a seed, so tests and benchmarks can compare
detectors on the same hard image without storing it.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np


def noise(gray: np.ndarray, rng: np.random.Generator, sigma: float = 6.0) -> np.ndarray:
    return np.clip(gray + rng.normal(0.0, sigma, gray.shape), 0, 255).astype(np.uint8)


def blur(gray: np.ndarray, rng: np.random.Generator, sigma_px: float = 1.2) -> np.ndarray:
    return cv2.GaussianBlur(gray, (0, 0), sigma_px)


def glare(gray: np.ndarray, rng: np.random.Generator, patches: int = 4) -> np.ndarray:
    """Soft bright reflections (a lamp on glossy paper), some near saturation, anywhere in the frame."""
    h, w = gray.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    light = np.zeros((h, w), np.float32)
    for _ in range(patches):
        cx, cy = rng.uniform(0.15, 0.85) * w, rng.uniform(0.15, 0.85) * h
        sx, sy = rng.uniform(0.03, 0.08) * w, rng.uniform(0.03, 0.08) * h
        light += rng.uniform(60, 140) * np.exp(-(((xx - cx) / sx) ** 2 + ((yy - cy) / sy) ** 2))
    return np.clip(gray.astype(np.float32) + light, 0, 255).astype(np.uint8)


def uneven_light(gray: np.ndarray, rng: np.random.Generator, low: float = 0.45) -> np.ndarray:
    """Light falling off across the frame to `low` of its brightest, in a random direction."""
    h, w = gray.shape
    a = rng.uniform(0, 2 * np.pi)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    t = (np.cos(a) * (xx / w - 0.5) + np.sin(a) * (yy / h - 0.5)) + 0.5
    gain = low + (1.0 - low) * np.clip(t, 0, 1)
    return np.clip(gray * gain, 0, 255).astype(np.uint8)


def low_contrast(gray: np.ndarray, rng: np.random.Generator, keep: float = 0.4) -> np.ndarray:
    """Faded print, washed-out exposure: grey levels squeezed towards the paper."""
    g = gray.astype(np.float32)
    top = float(np.percentile(g, 95))
    return np.clip(top - (top - g) * keep, 0, 255).astype(np.uint8)


def scaled(factor: float) -> Callable[[np.ndarray, np.random.Generator], np.ndarray]:
    def apply(gray: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        interp = cv2.INTER_AREA if factor < 1 else cv2.INTER_CUBIC
        return cv2.resize(gray, None, fx=factor, fy=factor, interpolation=interp)

    return apply


def crop(gray: np.ndarray, rng: np.random.Generator, keep: float = 0.7) -> np.ndarray:
    """A random window `keep` of the frame each way (the plate may be cut: then no grid)."""
    h, w = gray.shape
    ch, cw = int(h * keep), int(w * keep)
    y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    return np.ascontiguousarray(gray[y0 : y0 + ch, x0 : x0 + cw])


def crop_edges(gray: np.ndarray, rng: np.random.Generator, most: float = 0.15) -> np.ndarray:
    """Up to `most` of the frame cut from each side, independently: the plate usually stays whole,
    but the image centre (where a camera model puts the principal point) moves."""
    h, w = gray.shape
    left, right = (int(rng.uniform(0, most) * w) for _ in range(2))
    top, bottom = (int(rng.uniform(0, most) * h) for _ in range(2))
    return np.ascontiguousarray(gray[top : h - bottom, left : w - right])


def perspective(gray: np.ndarray, rng: np.random.Generator, degrees: tuple[float, float] = (4.0, 10.0)) -> np.ndarray:
    """The camera turned about its centre by a few degrees about a random axis across the view
    (the homography K R K^-1, a focal length of one image width), then shifted so that the image
    centre stays in place: keystone, as a hand-held plate seen at another slant. Same size; the
    border repeats the edge pixels."""
    h, w = gray.shape
    f = float(w)
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    a = rng.uniform(0, 2 * np.pi)
    axis = np.array([np.cos(a), np.sin(a), 0.0]) * np.deg2rad(rng.uniform(*degrees))
    H = K @ cv2.Rodrigues(axis)[0] @ np.linalg.inv(K)
    centre = H @ [(w - 1) / 2, (h - 1) / 2, 1.0]
    H = (
        np.array(
            [
                [1.0, 0.0, (w - 1) / 2 - centre[0] / centre[2]],
                [0.0, 1.0, (h - 1) / 2 - centre[1] / centre[2]],
                [0, 0, 1],
            ]
        )
        @ H
    )
    return cv2.warpPerspective(gray, H, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


VARIANTS: dict[str, Callable[[np.ndarray, np.random.Generator], np.ndarray]] = {
    "noise": noise,
    "blur": blur,
    "glare": glare,
    "uneven light": uneven_light,
    "low contrast": low_contrast,
    "scale 0.75": scaled(0.75),
    "scale 1.5": scaled(1.5),
    "crop": crop,
    "crop edges": crop_edges,
    "perspective": perspective,
    "noise+blur+glare": lambda g, rng: noise(glare(blur(g, rng), rng), rng),
}


def variant(name: str, gray: np.ndarray, seed: int) -> np.ndarray:
    return VARIANTS[name](gray, np.random.default_rng(seed))

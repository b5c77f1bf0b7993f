"""What a camera sees of a backlit table: exact geometry, then optics and sensor effects.

Shapes are described in table millimetres; each pixel's ray is cast onto the table (or a
plane above it) through the camera model, so perspective and lens distortion are exact.
Edges are anti-aliased analytically (signed distance divided by the local scale), which
keeps sub-pixel truth without supersampling the whole frame.
"""

from __future__ import annotations

import functools
from collections.abc import Set as AbstractSet
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from cell.camera_model import CameraModel


class PlateGeometry(Protocol):
    columns: int
    rows: int
    pitch_x_mm: float
    pitch_y_mm: float
    diameter_mm: float


@dataclass(frozen=True)
class Optics:
    """Everything between the light and the pixel values."""

    blur_sigma_px: float = 0.8
    noise_sigma: float = 2.0
    vignetting: float = 0.25  # relative fall-off at the image corners
    backlight_gradient: float = 0.15  # relative change of backlight across the frame
    backlight_angle_deg: float = 30.0
    bright_level: float = 225.0  # backlight seen through nothing (below 250: paper preset)
    dark_level: float = 25.0  # an opaque print or part
    tint_bgr: tuple[float, float, float] = (1.0, 0.95, 0.88)  # cool white LED backlight


def table_maps(camera: CameraModel, height_mm: float = 0.0):
    """(X, Y, J): table mm seen by each pixel at `height_mm`, and the local Jacobian.

    Cached on the camera: a simulated cell renders many frames through one camera.
    """
    cache = camera.cache
    if height_mm not in cache:
        h, w = camera.height_px, camera.width_px
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        xy = camera.pixel_to_table(np.column_stack([u.ravel(), v.ravel()]), height_mm)
        X = xy[:, 0].reshape(h, w)
        Y = xy[:, 1].reshape(h, w)
        J = np.stack([np.gradient(X, axis=1), np.gradient(X, axis=0), np.gradient(Y, axis=1), np.gradient(Y, axis=0)])
        if len(cache) >= 4:
            cache.pop(next(iter(cache)))
        cache[height_mm] = (X, Y, J)
    return cache[height_mm]


def circles_coverage(
    camera: CameraModel,
    centres_table_mm: np.ndarray,
    radius_mm: float,
    height_mm: float = 0.0,
) -> np.ndarray:
    """Fraction of each pixel covered by any of the circles (flat discs at `height_mm`)."""
    X, Y, J = table_maps(camera, height_mm)
    coverage = np.zeros(X.shape, dtype=np.float64)
    px_mm = float(np.median(np.hypot(J[0], J[2])))
    margin_mm = radius_mm + 3 * px_mm
    for cx, cy in np.asarray(centres_table_mm, dtype=np.float64).reshape(-1, 2):
        # Restrict to a window around the circle's projection.
        box = np.abs(X - cx) < margin_mm
        box &= np.abs(Y - cy) < margin_mm
        rows = np.flatnonzero(box.any(axis=1))
        cols = np.flatnonzero(box.any(axis=0))
        if rows.size == 0 or cols.size == 0:
            continue
        sl = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        dx, dy = X[sl] - cx, Y[sl] - cy
        rho = np.hypot(dx, dy)
        nx, ny = dx / np.maximum(rho, 1e-12), dy / np.maximum(rho, 1e-12)
        # Gradient of the signed distance with respect to pixel coordinates.
        gu = nx * J[0][sl] + ny * J[2][sl]
        gv = nx * J[1][sl] + ny * J[3][sl]
        d_px = (rho - radius_mm) / np.maximum(np.hypot(gu, gv), 1e-12)
        cov = np.clip(0.5 - d_px, 0.0, 1.0)
        coverage[sl] = np.maximum(coverage[sl], cov)
    return coverage


def plate_centres_mm(plate: PlateGeometry, omit: AbstractSet[tuple[int, int]] = frozenset()) -> np.ndarray:
    """Circle centres in table mm, row by row, (column, row) zero-based, minus `omit`."""
    pts = [
        (c * plate.pitch_x_mm, r * plate.pitch_y_mm)
        for r in range(plate.rows)
        for c in range(plate.columns)
        if (c, r) not in omit
    ]
    return np.array(pts, dtype=np.float64).reshape(-1, 2)


@functools.lru_cache(maxsize=2)
def backlight(h: int, w: int, vignetting: float, gradient: float, angle_deg: float) -> np.ndarray:
    """Relative backlight reaching each pixel (vignetting times the backlight's gradient).

    The same for every frame of a camera, so computed once (read-only; two sizes kept).
    """
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    ru = (u - w / 2) / (w / 2)
    rv = (v - h / 2) / (w / 2)
    r2 = (ru**2 + rv**2) / (1 + (h / w) ** 2)
    light = 1.0 - vignetting * r2
    a = np.deg2rad(angle_deg)
    light *= 1.0 + gradient * 0.5 * (np.cos(a) * ru + np.sin(a) * rv * w / h)
    light.flags.writeable = False
    return light


def expose(
    camera: CameraModel,
    opacity: np.ndarray,
    optics: Optics = Optics(),
    rng: np.random.Generator | None = None,
    exposure: float = 1.0,
) -> np.ndarray:
    """BGR uint8 frame of a backlight seen through `opacity` (0 clear, 1 opaque)."""
    rng = rng or np.random.default_rng(0)
    h, w = opacity.shape
    light = backlight(h, w, optics.vignetting, optics.backlight_gradient, optics.backlight_angle_deg)
    signal = optics.dark_level + (optics.bright_level - optics.dark_level) * light * (1 - opacity)
    signal *= exposure
    if optics.blur_sigma_px > 0:
        signal = cv2.GaussianBlur(signal, (0, 0), optics.blur_sigma_px)
    bgr = signal[:, :, None] * np.array(optics.tint_bgr)[None, None, :]
    bgr += rng.normal(0.0, optics.noise_sigma, bgr.shape)
    return np.clip(np.rint(bgr), 0, 255).astype(np.uint8)


def render_plate(
    camera: CameraModel,
    plate: PlateGeometry,
    optics: Optics = Optics(),
    seed: int = 0,
    omit: AbstractSet[tuple[int, int]] = frozenset(),
    extra_opacity: np.ndarray | None = None,
    exposure: float = 1.0,
) -> np.ndarray:
    """The backlit plate as the camera sees it (BGR uint8)."""
    opacity = circles_coverage(camera, plate_centres_mm(plate, omit), plate.diameter_mm / 2)
    if extra_opacity is not None:
        opacity = np.maximum(opacity, extra_opacity)
    return expose(camera, opacity, optics, np.random.default_rng(seed), exposure)


def plate_field_error_mm(
    camera: CameraModel, calibration, plate: PlateGeometry, step_mm: float = 2.0
) -> tuple[float, float]:
    """RMS and max error of a calibration over the plate field, against this camera's exact truth.

    Points every `step_mm` across the plate, most of them between circles, so the figure is
    the mapping's error where parts lie, not only at the fitted centres.
    """
    X, Y = np.meshgrid(
        np.arange(0.0, (plate.columns - 1) * plate.pitch_x_mm + 1e-9, step_mm),
        np.arange(0.0, (plate.rows - 1) * plate.pitch_y_mm + 1e-9, step_mm),
    )
    table = np.column_stack([X.ravel(), Y.ravel()])
    err = np.hypot(*(calibration.pixel_to_table_mm(camera.project(table)) - table).T)
    return float(np.sqrt(np.mean(err**2))), float(err.max())

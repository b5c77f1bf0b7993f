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


def _window_maps(camera: CameraModel, boxes: list[tuple[int, int, int, int]], height_mm: float) -> list:
    """(X, Y, J) per pixel box (x0, y0, x1, y1): table mm seen by each pixel at `height_mm`, and the
    local Jacobian (dX/du, dX/dv, dY/du, dY/dv). One ray casting for all boxes."""
    grids = [np.mgrid[y0:y1, x0:x1][::-1].reshape(2, -1).T for x0, y0, x1, y1 in boxes]
    xy = camera.pixel_to_table(np.concatenate(grids).astype(np.float64), height_mm)
    out, start = [], 0
    for x0, y0, x1, y1 in boxes:
        n = (y1 - y0) * (x1 - x0)
        X = xy[start : start + n, 0].reshape(y1 - y0, x1 - x0)
        Y = xy[start : start + n, 1].reshape(y1 - y0, x1 - x0)
        start += n
        J = np.stack([np.gradient(X, axis=1), np.gradient(X, axis=0), np.gradient(Y, axis=1), np.gradient(Y, axis=0)])
        out.append((X, Y, J))
    return out


def circles_coverage(
    camera: CameraModel,
    centres_table_mm: np.ndarray,
    radius_mm: float,
    height_mm: float = 0.0,
) -> np.ndarray:
    """Fraction of each pixel covered by any of the circles (flat discs at `height_mm`)."""
    coverage = np.zeros((camera.height_px, camera.width_px), dtype=np.float64)
    for (x0, y0), cov in circles_windows(camera, centres_table_mm, radius_mm, height_mm):
        window = coverage[y0 : y0 + cov.shape[0], x0 : x0 + cov.shape[1]]
        np.maximum(window, cov, out=window)
    return coverage


Window = tuple[tuple[int, int], np.ndarray]  # (x0, y0) of a pixel box, and the coverage in it


def circles_windows(
    camera: CameraModel,
    centres_table_mm: np.ndarray,
    radius_mm: float,
    height_mm: float = 0.0,
) -> list[Window]:
    """Each circle's coverage in the pixel box around its projection (a few pixels beyond its
    edge, where the coverage is zero): rays are cast only there, not through the whole frame."""
    h, w = camera.height_px, camera.width_px
    centres = np.asarray(centres_table_mm, dtype=np.float64).reshape(-1, 2)
    a = np.linspace(0.0, 2 * np.pi, 48, endpoint=False)
    rim = np.column_stack([np.cos(a), np.sin(a)]) * radius_mm
    boxes = []
    for c in centres:
        px = camera.project(c + rim, height_mm)
        x0, y0 = np.floor(px.min(axis=0)).astype(int) - 5
        x1, y1 = np.ceil(px.max(axis=0)).astype(int) + 6
        box = (max(x0, 0), max(y0, 0), min(x1, w), min(y1, h))
        if box[2] - box[0] >= 3 and box[3] - box[1] >= 3:
            boxes.append((c, box))
    maps = _window_maps(camera, [box for _, box in boxes], height_mm) if boxes else []
    windows: list[Window] = []
    for ((cx, cy), (x0, y0, _, _)), (X, Y, J) in zip(boxes, maps, strict=True):
        dx, dy = X - cx, Y - cy
        rho = np.hypot(dx, dy)
        nx, ny = dx / np.maximum(rho, 1e-12), dy / np.maximum(rho, 1e-12)
        # Gradient of the signed distance with respect to pixel coordinates.
        gu = nx * J[0] + ny * J[2]
        gv = nx * J[1] + ny * J[3]
        d_px = (rho - radius_mm) / np.maximum(np.hypot(gu, gv), 1e-12)
        windows.append(((int(x0), int(y0)), np.clip(0.5 - d_px, 0.0, 1.0)))
    return windows


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
    u = np.arange(w, dtype=np.float64)[None, :]  # a row and a column, broadcast: two frame-sized arrays at most
    v = np.arange(h, dtype=np.float64)[:, None]
    ru = (u - w / 2) / (w / 2)
    rv = (v - h / 2) / (w / 2)
    light = ru**2 + rv**2
    light /= 1 + (h / w) ** 2
    light *= vignetting
    np.subtract(1.0, light, out=light)  # 1 - vignetting * r2
    a = np.deg2rad(angle_deg)
    tilt = np.cos(a) * ru + np.sin(a) * rv * w / h
    tilt *= gradient * 0.5
    tilt += 1.0
    light *= tilt
    light.flags.writeable = False
    return light


_BAND_ROWS = 64  # rows exposed at a time: the float temporaries stay a few MB whatever the frame size


class Scene:
    """A frame's opacity as small windows (marks, parts) on a clear table, made a band of rows
    at a time as `expose` reads it (`scene[lo:hi]`): no frame-sized image is kept or made."""

    def __init__(self, height_px: int, width_px: int, windows: list[Window]):
        self.shape = (height_px, width_px)
        self.windows = windows

    def __getitem__(self, rows: slice) -> np.ndarray:
        lo, hi, _ = rows.indices(self.shape[0])
        band = np.zeros((hi - lo, self.shape[1]), dtype=np.float64)
        for (x0, y0), cov in self.windows:
            top, bottom = max(y0, lo), min(y0 + cov.shape[0], hi)
            if top < bottom:
                part = band[top - lo : bottom - lo, x0 : x0 + cov.shape[1]]
                np.maximum(part, cov[top - y0 : bottom - y0], out=part)
        return band


class SensorNoise:
    """A live simulated camera's sensor noise, drawn once into a pool a few bands tall: each band of
    each frame takes its noise from a random place in the pool, flipped at random.

    Drawing fresh normal deviates for every pixel of every frame was over half of a 1080p frame's
    exposure (and so of a dry run's time); the pool gives the same noise level and a pattern that
    never lines up with the parts. Stills (the plate, the benches' scenes) keep fresh draws."""

    ROWS = 4 * _BAND_ROWS
    SPARE_COLUMNS = 97

    def __init__(self, width_px: int, sigma: float, rng: np.random.Generator):
        shape = (self.ROWS, width_px + self.SPARE_COLUMNS, 3)
        self.width_px = width_px
        self.pool = rng.standard_normal(shape, dtype=np.float32)
        self.pool *= np.float32(sigma)

    def band(self, rows: int, rng: np.random.Generator) -> np.ndarray:
        """Noise for `rows` rows of the frame (a read-only view into the pool)."""
        r = int(rng.integers(0, self.ROWS - rows + 1))
        c = int(rng.integers(0, self.SPARE_COLUMNS + 1))
        flip_rows, flip_columns = rng.integers(0, 2, size=2)
        view = self.pool[r : r + rows, c : c + self.width_px]
        return view[:: -1 if flip_rows else 1, :: -1 if flip_columns else 1]


def expose(
    camera: CameraModel,
    opacity: np.ndarray | Scene,
    optics: Optics = Optics(),
    rng: np.random.Generator | None = None,
    exposure: float = 1.0,
    noise_pool: SensorNoise | None = None,
) -> np.ndarray:
    """BGR uint8 frame of a backlight seen through `opacity` (0 clear, 1 opaque).

    Computed in bands of rows, each band's light blurred with the rows the blur reaches beyond
    it and the noise drawn band after band: the same values in the same order as for the whole
    frame at once, but a 1080p frame needs a few MB of float temporaries beside its result, not
    the half a gigabyte the whole-frame expressions took (nor OpenCV's frame-sized copy for a blur).
    `noise_pool`: a live camera's noise (SensorNoise) in place of fresh draws.
    """
    rng = rng or np.random.default_rng(0)
    h, w = opacity.shape
    light = backlight(h, w, optics.vignetting, optics.backlight_gradient, optics.backlight_angle_deg)
    reach = _blur_reach_rows(optics.blur_sigma_px)
    tint = np.array(optics.tint_bgr)[None, None, :]
    frame = np.empty((h, w, 3), dtype=np.uint8)
    noise = np.empty((min(_BAND_ROWS, h), w, 3) if noise_pool is None else (0, 0, 3), dtype=np.float64)
    for r0 in range(0, h, _BAND_ROWS):
        r1 = min(r0 + _BAND_ROWS, h)
        lo, hi = max(r0 - reach, 0), min(r1 + reach, h)  # the band and what its blur reaches
        signal = optics.dark_level + (optics.bright_level - optics.dark_level) * light[lo:hi] * (1 - opacity[lo:hi])
        signal *= exposure
        if reach:
            signal = cv2.GaussianBlur(signal, (0, 0), optics.blur_sigma_px)
        bgr = signal[r0 - lo : r1 - lo, :, None] * tint
        if noise_pool is not None:
            bgr += noise_pool.band(r1 - r0, rng)
        else:
            z = noise[: r1 - r0]
            rng.standard_normal(out=z)  # what rng.normal(0, sigma, ...) draws, in the same order
            z *= optics.noise_sigma
            bgr += z
        np.rint(bgr, out=bgr)
        np.clip(bgr, 0, 255, out=bgr)
        frame[r0:r1] = bgr
    return frame


def _blur_reach_rows(sigma_px: float) -> int:
    """Rows a Gaussian blur of float images reaches on either side (OpenCV's kernel: 8 sigma + 1
    wide, rounded to odd), one spare: 0 without blur."""
    if sigma_px <= 0:
        return 0
    return (int(round(sigma_px * 8 + 1)) | 1) // 2 + 1


def render_plate(
    camera: CameraModel,
    plate: PlateGeometry,
    optics: Optics = Optics(),
    seed: int = 0,
    omit: AbstractSet[tuple[int, int]] = frozenset(),
    extra_opacity: np.ndarray | None = None,
    exposure: float = 1.0,
    height_mm: float = 0.0,
    offset_mm: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """The backlit plate as the camera sees it (BGR uint8); `height_mm` above the table (raised on a
    spacer), moved by `offset_mm` on it."""
    centres = plate_centres_mm(plate, omit) + np.asarray(offset_mm, dtype=np.float64)
    opacity = circles_coverage(camera, centres, plate.diameter_mm / 2, height_mm)
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

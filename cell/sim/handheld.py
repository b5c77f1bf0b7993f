"""Hand-held-style views of a circle plate, drawn from a seed: small circles, tilted, through a
strongly distorting lens, blurred, lit unevenly and saved as JPEG (the pitch gate's bench and tests).

`rendered` draws the plate through the renderer (exact geometry); `from_photo` makes a real photo
of a plate (the shared 640 x 480 ones) turned further, distorted, shrunk and degraded.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cell.camera_model import CameraModel
from cell.config import PlateConfig
from cell.sim.cameras import plate_in_view
from cell.sim.degrade import perspective, uneven_light
from cell.sim.render import Optics, render_plate

PHOTO_PLATE = PlateConfig(columns=7, rows=7, pitch_x_mm=10, pitch_y_mm=10, diameter_mm=5)
PAPER_PLATE = PlateConfig(columns=13, rows=12, pitch_x_mm=22, pitch_y_mm=16, diameter_mm=10)


def jpeg(gray: np.ndarray, quality: int) -> np.ndarray:
    _, buf = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return np.asarray(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))


def barrel(gray: np.ndarray, k1: float) -> np.ndarray:
    """The image as a lens with radial distortion k1 (focal length one image width) would show it."""
    h, w = gray.shape
    f = float(w)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    out = np.column_stack([xx.ravel(), yy.ravel()])[:, None, :]
    source = cv2.undistortPoints(out, K, np.array([k1, 0, 0, 0, 0.0]), P=K).reshape(h, w, 2).astype(np.float32)
    return cv2.remap(gray, source[..., 0], source[..., 1], cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


@dataclass
class View:
    """One view: its grey image, the plate it shows (the right pitches) and what made it."""

    name: str
    gray: np.ndarray
    plate: PlateConfig
    about: str


def rendered(
    seed: int,
    diameter_px: float | None = None,
    tilt_deg: float | None = None,
    k1: float | None = None,
    blur_px: float | None = None,
) -> View:
    """A rendered plate: the photos' 7 x 7 (odd seeds) or the paper's (as many as fit), 640 x 480 or
    1280 x 720, circles 6-12 px across at the image centre, tilt 0-45 deg any way, any roll, barrel
    distortion k1 0 .. -0.35, blur 0.4-1.5 px, noise, vignetting, a backlight gradient, uneven light,
    JPEG 60-95; each drawn from the seed unless given."""
    rng = np.random.default_rng(seed)
    plate = PHOTO_PLATE if seed % 2 else PAPER_PLATE
    w, h = (640, 480) if rng.uniform() < 0.7 else (1280, 720)
    d_px, tilt, k = rng.uniform(6, 12), rng.uniform(0, 45), rng.uniform(-0.35, 0)
    blur, quality = rng.uniform(0.4, 1.5), int(rng.integers(60, 96))
    d_px = d_px if diameter_px is None else diameter_px
    tilt = tilt if tilt_deg is None else tilt_deg
    k1 = k if k1 is None else k1
    blur = blur if blur_px is None else blur_px
    hfov = rng.uniform(60, 90)
    mm_per_px = plate.diameter_mm / d_px
    if plate is PAPER_PLATE:  # as many columns and rows as fit in the view, at least 4 x 4
        fit = plate_in_view(w * mm_per_px, h * mm_per_px)
        plate = plate.model_copy(update={"columns": max(fit.columns, 4), "rows": max(fit.rows, 4)})
    centre = ((plate.columns - 1) * plate.pitch_x_mm / 2, (plate.rows - 1) * plate.pitch_y_mm / 2)
    camera = CameraModel.looking_down(
        w,
        h,
        mm_per_px,
        centre,
        hfov_deg=hfov,
        tilt_deg=tilt,
        tilt_azimuth_deg=rng.uniform(0, 360),
        roll_deg=rng.uniform(-180, 180),
        k1=k1,
        principal_offset_px=(rng.uniform(-0.05, 0.05) * w, rng.uniform(-0.05, 0.05) * h),
    )
    optics = Optics(
        blur_sigma_px=blur,
        noise_sigma=rng.uniform(1, 5),
        vignetting=rng.uniform(0.1, 0.5),
        backlight_gradient=rng.uniform(0, 0.4),
        backlight_angle_deg=rng.uniform(0, 360),
        bright_level=rng.uniform(150, 240),
        dark_level=rng.uniform(15, 60),
    )
    gray = cv2.cvtColor(render_plate(camera, plate, optics, seed=seed), cv2.COLOR_BGR2GRAY)
    gray = jpeg(uneven_light(gray, rng, rng.uniform(0.5, 1.0)), quality)
    about = f"{w}x{h} tilt {tilt:4.1f} k1 {k1:+.2f} blur {blur:.2f} jpeg {quality}"
    return View(f"render {seed}", gray, plate, about)


def from_photo(index: int, photo: np.ndarray, seed: int) -> View:
    """A real photo of the 7 x 7 plate turned 0-35 deg more in perspective, through barrel distortion
    k1 0 .. -0.35, shrunk to 0.35-0.7 (its circles 6-12 px across), blurred, lit unevenly, JPEG."""
    rng = np.random.default_rng(seed)
    turn, k1 = rng.uniform(0, 35), rng.uniform(-0.35, 0)
    scale, blur, quality = rng.uniform(0.35, 0.7), rng.uniform(0.3, 1.2), int(rng.integers(60, 96))
    gray = perspective(photo, rng, (turn, turn)) if turn > 0.5 else photo
    gray = barrel(gray, k1)
    gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    gray = cv2.GaussianBlur(gray, (0, 0), blur)
    gray = jpeg(uneven_light(gray, rng, rng.uniform(0.5, 1.0)), quality)
    about = f"photo {index:02d} turned {turn:4.1f} k1 {k1:+.2f} x{scale:.2f} blur {blur:.2f} jpeg {quality}"
    return View(f"photo {index:02d}/{seed}", gray, PHOTO_PLATE, about)

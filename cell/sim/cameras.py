"""Cameras nobody tuned for: a seeded random camera per frame-size family, for benches and tests.

Each camera is drawn from its family's ranges: the scale at the image centre, the field of
view, lens distortion (barrel or pincushion, given as the displacement it causes at the image
corner), tilt and its direction, roll, the principal point's offset, and the light and the
sensor (blur, noise, vignetting, the backlight's gradient and direction, its level). The
calibration plate is the paper's (22 x 16 mm pitch, 10 mm circles) with as many columns and
rows as fit well inside the view (at most the paper's 13 x 12); parts lie over the plate's area.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cell.camera_model import CameraModel
from cell.config import PlateConfig
from cell.sim.render import Optics


@dataclass(frozen=True)
class CameraFamily:
    name: str
    width_px: int
    height_px: int
    mm_per_px: tuple[float, float]  # range of the scale at the image centre


FAMILIES = (
    CameraFamily("640 x 480", 640, 480, (0.30, 0.40)),
    CameraFamily("1280 x 720", 1280, 720, (0.25, 0.40)),
    CameraFamily("1920 x 1080", 1920, 1080, (0.15, 0.30)),
    CameraFamily("2592 x 1944", 2592, 1944, (0.12, 0.22)),
    CameraFamily("3840 x 2160", 3840, 2160, (0.10, 0.16)),
)
FAMILY = {f.name: f for f in FAMILIES}

_PITCH_MM = (22.0, 16.0)
_DIAMETER_MM = 10.0
_PLATE_FILL = 0.8  # the plate spans at most this much of the view each way


@dataclass(frozen=True)
class SimulatedCamera:
    family: str
    seed: int
    camera: CameraModel
    optics: Optics
    plate: PlateConfig
    corner_distortion: float  # radial displacement at the image corner, relative (< 0: barrel)
    tilt_deg: float

    @property
    def mm_per_px(self) -> float:
        c = np.array([[(self.camera.width_px - 1) / 2, (self.camera.height_px - 1) / 2]])
        q = self.camera.pixel_to_table(np.vstack([c, c + (1, 0), c + (0, 1)]))
        (ax, ay), (bx, by) = q[1] - q[0], q[2] - q[0]
        return math.sqrt(abs(ax * by - ay * bx))

    @property
    def scene_area_mm(self) -> tuple[float, float, float, float]:
        """Where parts may lie: the plate's area (x0, y0, x1, y1), table mm."""
        p = self.plate
        return (0.0, 0.0, (p.columns - 1) * p.pitch_x_mm, (p.rows - 1) * p.pitch_y_mm)

    def describe(self) -> str:
        c = self.camera
        return (
            f"{c.width_px}x{c.height_px} {self.mm_per_px:.3f} mm/px, distortion {100 * self.corner_distortion:+.1f} % "
            f"at the corner, tilt {self.tilt_deg:.1f} deg, plate {self.plate.columns}x{self.plate.rows}, "
            f"blur {self.optics.blur_sigma_px:.2f} px, noise {self.optics.noise_sigma:.1f}, "
            f"backlight gradient {self.optics.backlight_gradient:.2f}"
        )


def random_camera(family: CameraFamily, seed: int) -> SimulatedCamera:
    """One camera of `family`, the same for the same seed."""
    rng = np.random.default_rng(seed)
    w, h = family.width_px, family.height_px
    mm_per_px = float(rng.uniform(*family.mm_per_px))
    hfov = float(rng.uniform(55.0, 85.0))
    corner = float(rng.uniform(-0.12, 0.06))
    tilt = float(rng.uniform(0.0, 8.0))
    # k1 (and a little k2) so that the corner moves by `corner` of its radius.
    f_px = (w / 2) / math.tan(math.radians(hfov) / 2)
    r2 = (w**2 + h**2) / 4 / f_px**2
    k2_share = float(rng.uniform(0.0, 0.3))
    k1, k2 = corner * (1 - k2_share) / r2, corner * k2_share / r2**2
    plate = plate_in_view(w * mm_per_px, h * mm_per_px)
    centre = ((plate.columns - 1) * plate.pitch_x_mm / 2, (plate.rows - 1) * plate.pitch_y_mm / 2)
    camera = CameraModel.looking_down(
        w,
        h,
        mm_per_px,
        centre,
        hfov_deg=hfov,
        tilt_deg=tilt,
        tilt_azimuth_deg=float(rng.uniform(0, 360)),
        roll_deg=float(rng.uniform(-8, 8)),
        k1=k1,
        k2=k2,
        p1=float(rng.uniform(-1e-3, 1e-3)),
        p2=float(rng.uniform(-1e-3, 1e-3)),
        principal_offset_px=(float(rng.uniform(-0.015, 0.015) * w), float(rng.uniform(-0.015, 0.015) * h)),
    )
    optics = Optics(
        blur_sigma_px=float(rng.uniform(0.5, 1.3)),
        noise_sigma=float(rng.uniform(1.0, 4.5)),
        vignetting=float(rng.uniform(0.1, 0.4)),
        backlight_gradient=float(rng.uniform(0.0, 0.35)),
        backlight_angle_deg=float(rng.uniform(0, 360)),
        bright_level=float(rng.uniform(170, 240)),
        dark_level=float(rng.uniform(15, 35)),
    )
    return SimulatedCamera(family.name, seed, camera, optics, plate, corner, tilt)


def plate_in_view(view_w_mm: float, view_h_mm: float) -> PlateConfig:
    """The paper's plate with as many columns and rows as fit in `_PLATE_FILL` of the view."""
    px, py = _PITCH_MM
    columns = int(min(13, (view_w_mm * _PLATE_FILL - _DIAMETER_MM) // px + 1))
    rows = int(min(12, (view_h_mm * _PLATE_FILL - _DIAMETER_MM) // py + 1))
    return PlateConfig(columns=columns, rows=rows, pitch_x_mm=px, pitch_y_mm=py, diameter_mm=_DIAMETER_MM)

"""The built-in simulated rig: a webcam-like camera above the paper's plate."""

from __future__ import annotations

from cell.camera_model import CameraModel


def default_camera(width_px: int = 1920, height_px: int = 1080) -> CameraModel:
    """A C525-like webcam about 340 mm above the table, slightly tilted, with barrel distortion.

    It looks at the middle of the paper's 264 x 176 mm plate at about 0.26 mm/px, as the
    paper's Table II suggests (its plate spans 960 px).
    """
    return CameraModel.looking_down(
        width_px,
        height_px,
        mm_per_px=0.26 * 1920 / width_px,
        look_at_table_mm=(132.0, 88.0),
        hfov_deg=70.0,
        tilt_deg=4.0,
        tilt_azimuth_deg=20.0,
        roll_deg=2.0,
        k1=-0.08,
        k2=0.03,
    )

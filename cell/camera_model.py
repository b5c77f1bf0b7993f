"""Pinhole + Brown distortion camera looking down at the table.

Frames: the table (plate) frame has X along the plate's columns, Y along its rows and
its origin at circle 1; heights are millimetres *above* the table, towards the camera.
OpenCV's object frame has Z = X x Y; with point 1 at the top-left that points into the
table (z = -height), with point 1 at another corner the frame may be mirrored and Z
point at the camera (z = +height). `_up` holds that sign.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


def _rotation(axis: str, angle_deg: float) -> np.ndarray:
    a = np.deg2rad(angle_deg)
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@dataclass
class CameraModel:
    """Intrinsics, Brown distortion (k1, k2, p1, p2, k3) and pose of the table in the camera."""

    width_px: int
    height_px: int
    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    _R: np.ndarray = field(init=False, repr=False)
    cache: dict = field(init=False, repr=False, compare=False, default_factory=dict)

    def __post_init__(self) -> None:
        self.camera_matrix = np.asarray(self.camera_matrix, dtype=np.float64).reshape(3, 3)
        self.dist_coeffs = np.asarray(self.dist_coeffs, dtype=np.float64).ravel()
        self.rvec = np.asarray(self.rvec, dtype=np.float64).reshape(3)
        self.tvec = np.asarray(self.tvec, dtype=np.float64).reshape(3)
        self._R = cv2.Rodrigues(self.rvec)[0]

    @classmethod
    def looking_down(
        cls,
        width_px: int,
        height_px: int,
        mm_per_px: float,
        look_at_table_mm: tuple[float, float],
        hfov_deg: float = 70.0,
        tilt_deg: float = 0.0,
        tilt_azimuth_deg: float = 0.0,
        roll_deg: float = 0.0,
        k1: float = 0.0,
        k2: float = 0.0,
        p1: float = 0.0,
        p2: float = 0.0,
        principal_offset_px: tuple[float, float] = (0.0, 0.0),
    ) -> CameraModel:
        """A camera whose optical axis meets the table at `look_at_table_mm`.

        The distance is chosen so that the centre of the image sees `mm_per_px`; tilt turns
        the optical axis away from the table normal (towards `tilt_azimuth_deg`), roll
        turns the image about the optical axis.
        """
        f_px = (width_px / 2) / np.tan(np.deg2rad(hfov_deg) / 2)
        distance_mm = f_px * mm_per_px
        K = np.array(
            [
                [f_px, 0, width_px / 2 - 0.5 + principal_offset_px[0]],
                [0, f_px, height_px / 2 - 0.5 + principal_offset_px[1]],
                [0, 0, 1],
            ]
        )
        # Camera looking straight down: camera x = table X, camera y = table Y, camera z
        # = table z (into the table). Then roll about the optical axis, then tilt.
        R_roll = _rotation("z", roll_deg)
        R_tilt = _rotation("z", tilt_azimuth_deg) @ _rotation("x", tilt_deg) @ _rotation("z", -tilt_azimuth_deg)
        R = R_roll @ R_tilt  # table -> camera
        target = np.array([look_at_table_mm[0], look_at_table_mm[1], 0.0])
        # Camera centre C = target - distance * (optical axis in table frame).
        axis_table = R.T @ np.array([0.0, 0.0, 1.0])
        C = target - distance_mm * axis_table
        t = -R @ C
        dist = np.array([k1, k2, p1, p2, 0.0])
        return cls(width_px, height_px, K, dist, cv2.Rodrigues(R)[0], t)

    @property
    def rotation(self) -> np.ndarray:
        """Rotation table -> camera."""
        return self._R

    def _centre(self) -> tuple[np.ndarray, np.ndarray]:
        """The camera centre in the object frame, and as (X, Y, height above the table): computed once
        and kept in `cache` (locate asks for them several times per part)."""
        kept = self.cache.get("centre")
        if kept is None:
            C = -self._R.T @ self.tvec
            kept = self.cache["centre"] = (C, np.array([C[0], C[1], abs(C[2])]))
        return kept

    @property
    def _up(self) -> float:
        """+1 if object z grows towards the camera, -1 if away from it."""
        return 1.0 if self._centre()[0][2] > 0 else -1.0

    @property
    def center_table_mm(self) -> np.ndarray:
        """Camera centre as (X, Y, height above the table) in table mm."""
        return self._centre()[1].copy()

    def project(self, xy_table_mm: np.ndarray, height_mm: float | np.ndarray = 0.0) -> np.ndarray:
        """Pixel positions (N, 2) of table points (N, 2) at `height_mm` above the table."""
        xy = np.asarray(xy_table_mm, dtype=np.float64).reshape(-1, 2)
        z = self._up * np.broadcast_to(np.asarray(height_mm, dtype=np.float64), (len(xy),))
        obj = np.column_stack([xy, z])
        px, _ = cv2.projectPoints(obj, self.rvec, self.tvec, self.camera_matrix, self.dist_coeffs)
        return px.reshape(-1, 2)

    def pixel_to_table(self, pixels: np.ndarray, height_mm: float = 0.0) -> np.ndarray:
        """Table (X, Y) in mm where each pixel's ray meets the plane at `height_mm`."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        norm = cv2.undistortPoints(
            px,
            self.camera_matrix,
            self.dist_coeffs,
            None,
            np.eye(3),
            np.eye(3),
            (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12),
        ).reshape(-1, 2)
        rays_cam = np.column_stack([norm, np.ones(len(norm))])
        rays_table = rays_cam @ self._R  # R.T @ ray for each row
        C = self._centre()[0]
        z_plane = self._up * height_mm
        s = (z_plane - C[2]) / rays_table[:, 2]
        return C[:2] + s[:, None] * rays_table[:, :2]

    def to_dict(self) -> dict:
        return {
            "width_px": self.width_px,
            "height_px": self.height_px,
            "camera_matrix": self.camera_matrix.tolist(),
            "dist_coeffs": self.dist_coeffs.tolist(),
            "rvec": self.rvec.tolist(),
            "tvec": self.tvec.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> CameraModel:
        return cls(
            int(d["width_px"]),
            int(d["height_px"]),
            np.array(d["camera_matrix"]),
            np.array(d["dist_coeffs"]),
            np.array(d["rvec"]),
            np.array(d["tvec"]),
        )

"""Pixel -> table-mm models, each fitted by least squares.

Polynomials and the homography work on normalised pixel coordinates (centred on the fitted
points and scaled to about +-1) so that the normal equations are well conditioned and the
stored float64 coefficients lose nothing (ERRATA.md: Eq. 5's rounding alone costs 1.6 mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cell.camera_model import CameraModel


@dataclass(frozen=True)
class Normaliser:
    """u_n = (u - centre) / scale, the same for both axes."""

    centre_px: tuple[float, float]
    scale_px: float

    @classmethod
    def fit(cls, pixels: np.ndarray) -> Normaliser:
        c = pixels.mean(axis=0)
        s = float(np.abs(pixels - c).max()) or 1.0
        return cls((float(c[0]), float(c[1])), s)

    def apply(self, pixels: np.ndarray) -> np.ndarray:
        return (pixels - np.asarray(self.centre_px)) / self.scale_px

    def to_dict(self) -> dict:
        return {"centre_px": list(self.centre_px), "scale_px": self.scale_px}

    @classmethod
    def from_dict(cls, d: dict) -> Normaliser:
        return cls(tuple(map(float, d["centre_px"])), float(d["scale_px"]))


IDENTITY = Normaliser((0.0, 0.0), 1.0)


def monomial_exponents(degree: int) -> list[tuple[int, int]]:
    """Exponents (i, j) of x^i y^j; for degree 2 in the paper's order x2, xy, y2, x, y, 1."""
    terms = []
    for total in range(degree, -1, -1):
        for j in range(total + 1):
            terms.append((total - j, j))
    return terms


class PolynomialMap:
    """X = sum a_ij x^i y^j, Y likewise. Degree 2 is the paper's Eq. 3."""

    def __init__(self, degree: int, norm: Normaliser, coef_x: np.ndarray, coef_y: np.ndarray):
        self.degree = degree
        self.norm = norm
        self.exponents = monomial_exponents(degree)
        self.coef_x = np.asarray(coef_x, dtype=np.float64)
        self.coef_y = np.asarray(coef_y, dtype=np.float64)

    @property
    def name(self) -> str:
        return "quadratic" if self.degree == 2 else "polynomial"

    @staticmethod
    def _design(xy: np.ndarray, exponents) -> np.ndarray:
        x, y = xy[:, 0], xy[:, 1]
        return np.column_stack([x**i * y**j for i, j in exponents])

    @classmethod
    def fit(cls, pixels: np.ndarray, table_mm: np.ndarray, degree: int) -> PolynomialMap:
        norm = Normaliser.fit(pixels)
        A = cls._design(norm.apply(pixels), monomial_exponents(degree))
        coef, *_ = np.linalg.lstsq(A, table_mm, rcond=None)
        return cls(degree, norm, coef[:, 0], coef[:, 1])

    def __call__(self, pixels: np.ndarray) -> np.ndarray:
        A = self._design(self.norm.apply(np.asarray(pixels, dtype=np.float64).reshape(-1, 2)), self.exponents)
        return np.column_stack([A @ self.coef_x, A @ self.coef_y])

    def to_dict(self) -> dict:
        return {
            "degree": self.degree,
            "normaliser": self.norm.to_dict(),
            "terms": [f"x^{i}*y^{j}" for i, j in self.exponents],
            "X": self.coef_x.tolist(),
            "Y": self.coef_y.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> PolynomialMap:
        degree = int(d["degree"])
        n = len(monomial_exponents(degree))
        cx, cy = np.asarray(d["X"], dtype=np.float64), np.asarray(d["Y"], dtype=np.float64)
        if cx.shape != (n,) or cy.shape != (n,):
            raise ValueError(f"degree {degree} needs {n} coefficients per axis, got {cx.size} and {cy.size}")
        return cls(degree, Normaliser.from_dict(d["normaliser"]), cx, cy)


class HomographyMap:
    """The plane-to-plane perspective transform (paper section III-B)."""

    name = "homography"

    def __init__(self, norm: Normaliser, H: np.ndarray):
        self.norm = norm
        self.H = np.asarray(H, dtype=np.float64).reshape(3, 3)

    @classmethod
    def fit(cls, pixels: np.ndarray, table_mm: np.ndarray) -> HomographyMap:
        norm = Normaliser.fit(pixels)
        H, _ = cv2.findHomography(norm.apply(pixels), table_mm, 0)
        if H is None:
            raise ValueError("homography fit failed: points are degenerate")
        return cls(norm, H)

    def __call__(self, pixels: np.ndarray) -> np.ndarray:
        p = self.norm.apply(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))
        q = np.column_stack([p, np.ones(len(p))]) @ self.H.T
        return q[:, :2] / q[:, 2:3]

    def to_dict(self) -> dict:
        return {"normaliser": self.norm.to_dict(), "H": self.H.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> HomographyMap:
        return cls(Normaliser.from_dict(d["normaliser"]), np.asarray(d["H"], dtype=np.float64))


class CameraMap:
    """Full camera model (section III-A): undistort the pixel, intersect its ray with the table."""

    name = "camera"

    def __init__(self, camera: CameraModel):
        self.camera = camera

    @classmethod
    def fit(cls, pixels: np.ndarray, table_mm: np.ndarray, image_size: tuple[int, int]) -> CameraMap:
        return cls(fit_camera(pixels, table_mm, image_size))

    def __call__(self, pixels: np.ndarray) -> np.ndarray:
        return self.camera.pixel_to_table(pixels, 0.0)

    def to_dict(self) -> dict:
        return self.camera.to_dict()

    @classmethod
    def from_dict(cls, d: dict) -> CameraMap:
        return cls(CameraModel.from_dict(d))


def fit_camera(pixels: np.ndarray, table_mm: np.ndarray, image_size: tuple[int, int]) -> CameraModel:
    """OpenCV calibrateCamera on one view of the plane: focal length, k1, k2, p1, p2 and pose.

    One planar view cannot separate everything, so the principal point is fixed at the
    image centre, the pixels are square and k3 is not fitted; the rest is well determined by
    a plate that fills much of the frame.
    """
    w, h = image_size
    obj = np.column_stack([table_mm, np.zeros(len(table_mm))]).astype(np.float32)
    img = pixels.astype(np.float32)
    f0 = 1.2 * max(w, h)
    K0 = np.array([[f0, 0, (w - 1) / 2], [0, f0, (h - 1) / 2], [0, 0, 1]], dtype=np.float64)
    flags = (
        cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K3
    )
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [obj], [img], (w, h), K0, np.zeros(5), flags=flags, criteria=criteria
    )
    return CameraModel(w, h, K, dist.ravel(), rvecs[0].ravel(), tvecs[0].ravel())


def fit_model(name: str, pixels: np.ndarray, table_mm: np.ndarray, image_size: tuple[int, int], degree: int = 3):
    """Fit one named model to matched pixel/table points."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    table_mm = np.asarray(table_mm, dtype=np.float64).reshape(-1, 2)
    if name == "quadratic":
        return PolynomialMap.fit(pixels, table_mm, 2)
    if name == "polynomial":
        return PolynomialMap.fit(pixels, table_mm, degree)
    if name == "homography":
        return HomographyMap.fit(pixels, table_mm)
    if name == "camera":
        return CameraMap.fit(pixels, table_mm, image_size)
    raise ValueError(f"unknown model {name!r}")


def model_from_dict(name: str, d: dict):
    if name in ("quadratic", "polynomial"):
        return PolynomialMap.from_dict(d)
    if name == "homography":
        return HomographyMap.from_dict(d)
    if name == "camera":
        return CameraMap.from_dict(d)
    raise ValueError(f"unknown model {name!r}")


def camera_height_sd_mm(camera: CameraModel, pixels: np.ndarray, table_mm: np.ndarray) -> float:
    """Standard deviation of the fitted camera's height above the table, from the fit's own
    residuals and Jacobian (focal length, k1, k2, p1, p2 and pose free, as fit_camera fits them).

    A plate seen nearly straight on cannot tell a near camera with a short lens from a far one
    with a long lens (only the tilt's keystone separates them): then this is large, and the
    fitted height means little.
    """
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    obj = np.column_stack([np.asarray(table_mm, dtype=np.float64).reshape(-1, 2), np.zeros(len(pixels))])
    projected, jac = cv2.projectPoints(obj, camera.rvec, camera.tvec, camera.camera_matrix, camera.dist_coeffs)
    J = np.hstack([jac[:, :6], jac[:, 6:7] + jac[:, 7:8], jac[:, 10:14]])  # pose, f, k1 k2 p1 p2
    dof = J.shape[0] - J.shape[1]
    if dof <= 0:
        return float("inf")
    variance = float(np.sum((projected.reshape(-1, 2) - pixels) ** 2)) / dof
    norms = np.maximum(np.linalg.norm(J, axis=0), 1e-12)
    Jn = J / norms
    cov = np.linalg.pinv(Jn.T @ Jn, rcond=1e-12) * variance / np.outer(norms, norms)
    grad = np.zeros(J.shape[1])
    for k in range(6):
        step = 1e-6 * max(1.0, abs(float(np.r_[camera.rvec, camera.tvec][k])))
        params = np.r_[camera.rvec, camera.tvec]
        params[k] += step
        grad[k] = (_height(params) - _height(np.r_[camera.rvec, camera.tvec])) / step
    return float(np.sqrt(max(grad @ cov @ grad, 0.0)))


def _height(pose: np.ndarray) -> float:
    """The camera's distance from the table plane for a pose (rvec, tvec)."""
    R = cv2.Rodrigues(pose[:3])[0]
    return abs(float((-R.T @ pose[3:])[2]))

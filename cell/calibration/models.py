"""Pixel -> table-mm models, each fitted by least squares.

Polynomials and the homography work on normalised pixel coordinates (centred on the fitted
points and scaled to about +-1) so that the normal equations are well conditioned and the
stored float64 coefficients lose nothing (ERRATA.md: Eq. 5's rounding alone costs 1.6 mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from cell.camera_model import CameraModel


class PixelMap(Protocol):
    """A fitted model: pixels (N, 2) -> table mm (N, 2), and its coefficients for the calibration file."""

    def __call__(self, pixels: np.ndarray) -> np.ndarray: ...

    def to_dict(self) -> dict[str, Any]: ...


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
        x, y = (float(v) for v in d["centre_px"])
        return cls((x, y), float(d["scale_px"]))


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
        return cls(fit_camera(pixels, table_mm, image_size, free_principal=True))

    def __call__(self, pixels: np.ndarray) -> np.ndarray:
        return self.camera.pixel_to_table(pixels, 0.0)

    def to_dict(self) -> dict:
        return self.camera.to_dict()

    @classmethod
    def from_dict(cls, d: dict) -> CameraMap:
        return cls(CameraModel.from_dict(d))


def fit_camera(
    pixels: np.ndarray,
    table_mm: np.ndarray,
    image_size: tuple[int, int],
    focal_px: float | None = None,
    principal_px: tuple[float, float] | None = None,
    free_principal: bool = False,
    principal_start_px: tuple[float, float] | None = None,
) -> CameraModel:
    """OpenCV calibrateCamera on one view of the plane: focal length, k1, k2, p1, p2 and pose
    (square pixels, no k3), the principal point held at the image centre. `focal_px`,
    `principal_px`: hold them there instead; `free_principal`: fit the principal point too,
    its search starting at `principal_start_px` (default: the image centre).

    A real camera's principal point is some pixels off the image centre; held at the centre,
    that offset becomes a wrong tilt, focal length and camera height. But one view of a plane
    places it poorly (shifting it, turning the camera and changing the focal length fit about
    equally well): fit_camera_pose weighs the two.
    """
    w, h = image_size
    obj = np.column_stack([table_mm, np.zeros(len(table_mm))]).astype(np.float32)
    img = pixels.astype(np.float32)
    f0 = focal_px or 1.2 * max(w, h)
    start = principal_start_px if free_principal else None
    cx, cy = principal_px or start or ((w - 1) / 2, (h - 1) / 2)
    cx, cy = float(np.clip(cx, 0.0, w - 1.0)), float(np.clip(cy, 0.0, h - 1.0))  # OpenCV refuses any other
    K0 = np.array([[f0, 0, cx], [0, f0, cy], [0, 0, 1]], dtype=np.float64)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K3
    if focal_px:
        flags |= cv2.CALIB_FIX_FOCAL_LENGTH
    if principal_px or not free_principal:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [obj], [img], (w, h), K0, np.zeros(5), flags=flags, criteria=criteria
    )
    return CameraModel(w, h, K, dist.ravel(), rvecs[0].ravel(), tvecs[0].ravel())


# How far a camera's principal point strays from the image centre, one standard deviation, as a
# fraction of the larger side (an assumption: a camera module's is rarely further off).
PRINCIPAL_POINT_SD = 0.01
_FOCAL_GRID = np.geomspace(0.3, 4.0, 11)  # focal lengths profiled, in units of the image's larger side
_GOLDEN = (math.sqrt(5) - 1) / 2


@dataclass
class _FocalFit:
    """The fits at one focal length: the principal point free and held at the image centre."""

    free: CameraModel
    free_error: float  # squared reprojection error, px^2
    centred_error: float

    def penalised(self, weight: float, centre: np.ndarray) -> tuple[float, float]:
        """(error with the principal point's prior, how far towards the free fit's principal point)."""
        prior = weight * float(np.sum((self.free.camera_matrix[:2, 2] - centre) ** 2))
        rise = max(self.centred_error - self.free_error, 0.0)
        if rise + prior <= 0:
            return self.free_error, 1.0
        return self.free_error + rise * prior / (rise + prior), rise / (rise + prior)


def fit_camera_pose(
    pixels: np.ndarray, table_mm: np.ndarray, image_size: tuple[int, int], focal_px: float | None = None
) -> tuple[CameraModel, float]:
    """The camera that fits the plate best with its principal point held near the image centre by
    a prior (PRINCIPAL_POINT_SD), and the standard deviation of its height above the table.

    Seen nearly straight on, a plate fits almost as well with a near camera and a short lens as
    with a far one and a long lens, and with the principal point shifted and the camera turned:
    the error is nearly flat along those valleys, and a free fit stops wherever it tires (on
    cameras with the principal point 1.5 % off, 10-40 % off in height; the prior alone makes it
    flat). So the focal length is profiled: at each focal length of a wide grid, then a
    golden-section search around the best, the plate is fitted with the principal point free
    and held at the centre; between them (the error rises about quadratically) the prior's
    optimum and its error follow in closed form. The heights whose error stays within one
    variance of the best give the height's uncertainty: a flat profile gives a large one.
    `focal_px`: the focal length is known (a configured camera height); only the prior's fit.
    """
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    table_mm = np.asarray(table_mm, dtype=np.float64).reshape(-1, 2)
    w, h = image_size
    centre = np.array([(w - 1) / 2, (h - 1) / 2])
    fits: dict[float, _FocalFit] = {}

    def fitted(focal: float) -> _FocalFit:
        if focal not in fits:
            free = fit_camera(pixels, table_mm, image_size, focal_px=focal, free_principal=True)
            centred = fit_camera(pixels, table_mm, image_size, focal_px=focal)
            fits[focal] = _FocalFit(
                free, squared_error_px2(free, pixels, table_mm), squared_error_px2(centred, pixels, table_mm)
            )
        return fits[focal]

    dof = max(2 * len(pixels) - 13, 1)  # 13 parameters
    grid = [focal_px] if focal_px else list(max(w, h) * _FOCAL_GRID)
    variance = min(fitted(f).free_error for f in grid) / dof
    weight = variance / (PRINCIPAL_POINT_SD * max(w, h)) ** 2
    error = lambda f: fitted(f).penalised(weight, centre)[0]  # noqa: E731
    if not focal_px:
        _search_around_best(error, grid)
    best = min(fits, key=error)
    fits[best] = _free_from_several_starts(fits[best], pixels, table_mm, image_size, best)
    toward = fits[best].penalised(weight, centre)[1]
    principal = centre + toward * (fits[best].free.camera_matrix[:2, 2] - centre)
    camera = fit_camera(pixels, table_mm, image_size, focal_px=best, principal_px=tuple(principal))
    spread = (
        math.inf
        if focal_px
        else _height_spread({f: (error(f), fit.free) for f, fit in fits.items()}, error(best) + variance)
    )
    return camera, spread


def _search_around_best(error, grid: list[float], steps: int = 8) -> None:
    """Golden-section search of `error` (in log focal length) between the grid's best point's
    neighbours; `error` keeps what it evaluates."""
    k = int(np.argmin([error(f) for f in grid]))
    lo, hi = math.log(grid[max(k - 1, 0)]), math.log(grid[min(k + 1, len(grid) - 1)])
    a, b = hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo)
    for _ in range(steps):
        if error(math.exp(a)) < error(math.exp(b)):
            hi, b = b, a
            a = hi - _GOLDEN * (hi - lo)
        else:
            lo, a = a, b
            b = lo + _GOLDEN * (hi - lo)


def _free_from_several_starts(
    fit: _FocalFit, pixels: np.ndarray, table_mm: np.ndarray, image_size: tuple[int, int], focal: float
) -> _FocalFit:
    """The free fit again from principal points 1.5 % of the larger side off the centre each way:
    its error has local minima along the valley (the wrong one 0.02 px RMS worse and 12 mm off in
    the camera's foot, on a camera seen straight on)."""
    w, h = image_size
    step = 0.015 * max(w, h)
    for dx, dy in ((-step, 0), (step, 0), (0, -step), (0, step)):
        start = ((w - 1) / 2 + dx, (h - 1) / 2 + dy)
        free = fit_camera(pixels, table_mm, image_size, focal_px=focal, free_principal=True, principal_start_px=start)
        free_error = squared_error_px2(free, pixels, table_mm)
        if free_error < fit.free_error:
            fit = _FocalFit(free, free_error, fit.centred_error)
    return fit


def squared_error_px2(camera: CameraModel, pixels: np.ndarray, table_mm: np.ndarray) -> float:
    """Sum of squared reprojection errors of the plate points, px^2."""
    obj = np.column_stack([table_mm, np.zeros(len(table_mm))])
    projected, _ = cv2.projectPoints(obj, camera.rvec, camera.tvec, camera.camera_matrix, camera.dist_coeffs)
    return float(np.sum((projected.reshape(-1, 2) - pixels) ** 2))


def _height_spread(fits: dict[float, tuple[float, CameraModel]], limit: float) -> float:
    """Half the range of camera heights whose fit's squared error stays under `limit`, the range's
    ends interpolated between profiled focal lengths; infinite where the profile never rises."""
    focals = sorted(fits)
    error = np.array([fits[f][0] for f in focals])
    height = np.array([fits[f][1].center_table_mm[2] for f in focals])
    inside = np.flatnonzero(error <= limit)
    i, j = int(inside.min()), int(inside.max())
    if i == 0 or j == len(focals) - 1:
        return math.inf
    below = height[i - 1] + (limit - error[i - 1]) / (error[i] - error[i - 1]) * (height[i] - height[i - 1])
    above = height[j] + (limit - error[j]) / (error[j + 1] - error[j]) * (height[j + 1] - height[j])
    return float(abs(above - below) / 2)


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


def model_from_dict(name: str, d: dict[str, Any]) -> PixelMap:
    if name in ("quadratic", "polynomial"):
        return PolynomialMap.from_dict(d)
    if name == "homography":
        return HomographyMap.from_dict(d)
    if name == "camera":
        return CameraMap.from_dict(d)
    raise ValueError(f"unknown model {name!r}")

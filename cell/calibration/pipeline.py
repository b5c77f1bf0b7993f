"""Plate image -> numbered centres -> fitted, cross-validated calibration."""
from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime

import numpy as np

from cell.calibration.detect import Blob, detect_blobs, detect_paper
from cell.calibration.lattice import number_lattice
from cell.calibration.models import PolynomialMap, fit_camera, fit_model, monomial_exponents
from cell.calibration.store import Calibration
from cell.config import CellConfig, PlateConfig
from cell.errors import PlateNotFound

log = logging.getLogger(__name__)

CANDIDATES = [("quadratic", 2), ("homography", 0), ("polynomial", 3), ("polynomial", 4), ("camera", 0)]


@dataclass
class PlatePoints:
    """Numbered plate centres: point number (1-based), pixel centre, table position."""

    number: np.ndarray
    pixel: np.ndarray
    table_mm: np.ndarray
    missing: list[int] = field(default_factory=list)
    strays: int = 0
    blobs_found: int = 0


@dataclass
class ModelScore:
    name: str
    degree: int
    fit: ErrorStats  # on the fitted points
    cv: ErrorStats  # on points left out of the fit

    @property
    def label(self) -> str:
        return f"polynomial (degree {self.degree})" if self.name == "polynomial" else self.name


@dataclass
class CalibrationResult:
    calibration: Calibration
    points: PlatePoints
    calibrated_mm: np.ndarray  # the chosen model applied to every point
    scores: list[ModelScore]
    chosen: ModelScore
    why: str
    timings_ms: dict


def point_numbers(col_row: np.ndarray, plate: PlateConfig) -> np.ndarray:
    return col_row[:, 1] * plate.columns + col_row[:, 0] + 1


def find_points_paper(image: np.ndarray, config: CellConfig) -> PlatePoints:
    """The paper's detection, numbered 1..N row by row from the top-left.

    The paper does not say how it sorts; sorting by y fails as soon as a row's drift across
    the image exceeds half the row pitch (its own Table II drifts 47 px on a 60 px pitch),
    so the lattice numbering puts its centres in that order. Every circle must be found.
    """
    plate = config.plate
    centres = detect_paper(image, config.detection.paper)
    n = plate.columns * plate.rows
    if len(centres) != n:
        raise PlateNotFound(
            f"paper preset found {len(centres)} circles of {config.detection.paper.min_area_px:g}-"
            f"{config.detection.paper.max_area_px:g} px area, expected {n} "
            f"({plate.columns} x {plate.rows})"
        )
    numbering = number_lattice(centres, plate, config.detection.lattice_tolerance, 0)
    cr = numbering.col_row
    order = np.lexsort((cr[:, 0], cr[:, 1]))
    cr = cr[order]
    pixel = centres[numbering.index[order]]
    return PlatePoints(point_numbers(cr, plate), pixel, cr * (plate.pitch_x_mm, plate.pitch_y_mm), [], 0, n)


def find_points(image: np.ndarray, config: CellConfig) -> PlatePoints:
    """Default detection: sub-pixel blobs numbered by lattice growth, sizes checked against the plate."""
    plate, det = config.plate, config.detection
    blobs: list[Blob] = detect_blobs(image)
    if len(blobs) < 4:
        raise PlateNotFound(f"found {len(blobs)} round dark blobs: no plate in view")
    centres = np.array([b.centre_px for b in blobs])
    numbering = number_lattice(centres, plate, det.lattice_tolerance, det.max_missing)
    idx, cr = numbering.index, numbering.col_row
    # Size check: each blob against the circle size the local lattice pitch predicts.
    pitch_px = _local_pitch_px(centres[idx], cr, plate)
    expected_d = pitch_px * plate.diameter_mm / np.sqrt(plate.pitch_x_mm * plate.pitch_y_mm)
    d = np.array([blobs[i].diameter_px for i in idx])
    ok = (d > det.min_diameter_ratio * expected_d) & (d < det.max_diameter_ratio * expected_d)
    rejected = [tuple(x) for x in cr[~ok]]
    if rejected:
        log.info("circles at (col, row) %s rejected: wrong size for the lattice", rejected)
    idx, cr = idx[ok], cr[ok]
    missing_cr = sorted(set(numbering.missing) | set(rejected), key=lambda t: (t[1], t[0]))
    if len(missing_cr) > det.max_missing:
        raise PlateNotFound(
            f"found {len(blobs)} blobs, {len(idx)} fit a {plate.columns} x {plate.rows} lattice "
            f"at the right size: {len(missing_cr)} circles missing or covered "
            f"(at most {det.max_missing} allowed)"
        )
    order = np.lexsort((cr[:, 0], cr[:, 1]))
    idx, cr = idx[order], cr[order]
    missing = [r * plate.columns + c + 1 for c, r in missing_cr]
    return PlatePoints(
        point_numbers(cr, plate),
        centres[idx],
        cr * np.array([plate.pitch_x_mm, plate.pitch_y_mm]),
        missing,
        len(numbering.strays),
        len(blobs),
    )


def _local_pitch_px(pixel: np.ndarray, cr: np.ndarray, plate: PlateConfig) -> np.ndarray:
    """Geometric-mean lattice pitch in pixels at each point, from a quadratic fit of the lattice."""
    fit = PolynomialMap.fit(cr.astype(np.float64), pixel, 2)
    c = cr.astype(np.float64)
    J = np.stack([(fit(c + (0.5, 0)) - fit(c - (0.5, 0))), (fit(c + (0, 0.5)) - fit(c - (0, 0.5)))], axis=2)
    return np.sqrt(np.abs(np.linalg.det(J)))


@dataclass(frozen=True)
class ErrorStats:
    """Deviation = original - calibrated (the paper's Table III sign), over a set of points."""

    rms_x_mm: float
    rms_y_mm: float
    rms_mm: float
    max_mm: float
    max_pos_x_mm: float
    max_neg_x_mm: float
    max_pos_y_mm: float
    max_neg_y_mm: float

    def to_dict(self) -> dict:
        """As stored in a calibration file's `statistics`."""
        return asdict(self)


def error_stats(predicted: np.ndarray, truth: np.ndarray) -> ErrorStats:
    dev = truth - predicted
    r = np.hypot(dev[:, 0], dev[:, 1])
    return ErrorStats(
        rms_x_mm=float(np.sqrt(np.mean(dev[:, 0] ** 2))),
        rms_y_mm=float(np.sqrt(np.mean(dev[:, 1] ** 2))),
        rms_mm=float(np.sqrt(np.mean(r**2))),
        max_mm=float(r.max()),
        max_pos_x_mm=float(dev[:, 0].max()),
        max_neg_x_mm=float(dev[:, 0].min()),
        max_pos_y_mm=float(dev[:, 1].max()),
        max_neg_y_mm=float(dev[:, 1].min()),
    )


def cross_validate(name: str, degree: int, pts: PlatePoints, image_size, folds: int) -> ErrorStats:
    """K-fold: every point predicted by a model fitted without it."""
    n = len(pts.pixel)
    folds = min(folds, n)
    order = np.random.default_rng(12345).permutation(n)
    pred = np.empty_like(pts.table_mm)
    for k in range(folds):
        test = order[k::folds]
        train = np.setdiff1d(order, test)
        model = fit_model(name, pts.pixel[train], pts.table_mm[train], image_size, degree)
        pred[test] = model(pts.pixel[test])
    return error_stats(pred, pts.table_mm)


def _parameters(name: str, degree: int) -> int:
    """Unknowns per axis (camera: intrinsics, distortion and pose over both axes)."""
    if name in ("quadratic", "polynomial"):
        return len(monomial_exponents(2 if name == "quadratic" else degree))
    return {"homography": 4, "camera": 8}[name]


def calibrate(image: np.ndarray, config: CellConfig, model: str | None = None) -> CalibrationResult:
    """Detect, number, fit every candidate model, cross-validate, choose, and package."""
    t0 = time.perf_counter()
    h, w = image.shape[:2]
    if config.detection.preset == "paper":
        pts = find_points_paper(image, config)
    else:
        pts = find_points(image, config)
    t1 = time.perf_counter()
    want = model or config.calibration.model
    candidates = [c for c in CANDIDATES if want in ("auto", c[0])]
    scores = []
    for name, degree in candidates:
        if len(pts.pixel) < 2 * _parameters(name, degree):
            continue  # too few points to fit and cross-validate this model
        fitted = fit_model(name, pts.pixel, pts.table_mm, (w, h), degree)
        fit_stats = error_stats(fitted(pts.pixel), pts.table_mm)
        cv = cross_validate(name, degree, pts, (w, h), config.calibration.cv_folds)
        scores.append(ModelScore(name, degree, fit_stats, cv))
    if not scores:
        raise PlateNotFound(f"only {len(pts.pixel)} plate points: too few to fit {want}")
    chosen = min(scores, key=lambda s: s.cv.rms_mm)
    others = ", ".join(f"{s.label} {s.cv.rms_mm:.4f}" for s in scores if s is not chosen)
    why = (
        f"{chosen.label}: lowest cross-validated RMS error, {chosen.cv.rms_mm:.4f} mm"
        + (f" (others: {others} mm)" if others else " (the only model asked for)")
    )
    final = fit_model(chosen.name, pts.pixel, pts.table_mm, (w, h), chosen.degree)
    camera = final.camera if chosen.name == "camera" else fit_camera(pts.pixel, pts.table_mm, (w, h))
    t2 = time.perf_counter()
    plate = config.plate
    cal = Calibration(
        model_name=chosen.name,
        model=final,
        image_size=(w, h),
        camera=camera,
        pattern={
            "columns": plate.columns,
            "rows": plate.rows,
            "pitch_x_mm": plate.pitch_x_mm,
            "pitch_y_mm": plate.pitch_y_mm,
            "diameter_mm": plate.diameter_mm,
            "first_point": plate.first_point,
            "detector": config.detection.preset,
            "points_used": int(len(pts.pixel)),
            "points_missing": pts.missing,
        },
        image_sha256=hashlib.sha256(np.ascontiguousarray(image).tobytes()).hexdigest(),
        created_utc=datetime.now(UTC).isoformat(timespec="seconds"),
        statistics={"fit": chosen.fit.to_dict(), "cross_validated": chosen.cv.to_dict(), "why": why},
    )
    timings = {"detect_number_ms": 1e3 * (t1 - t0), "fit_cv_ms": 1e3 * (t2 - t1), "total_ms": 1e3 * (t2 - t0)}
    return CalibrationResult(cal, pts, final(pts.pixel), scores, chosen, why, timings)

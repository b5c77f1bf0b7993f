"""Plate image -> numbered centres -> fitted, cross-validated calibration."""

from __future__ import annotations

import hashlib
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np

from cell.calibration.detect import (
    Candidates,
    detect_paper,
    find_candidates,
    refine_candidates,
    size_groups,
    to_gray,
)
from cell.calibration.lattice import Numbering, number_lattice
from cell.calibration.models import (
    CameraMap,
    fit_camera_pose,
    fit_model,
    monomial_exponents,
)
from cell.calibration.raised import RaisedHeight, height_from_raised_plate
from cell.calibration.roundness import PitchRatio, measure_pitch_ratio
from cell.calibration.store import HEIGHT_DOUBT_SDS, Calibration
from cell.camera_model import CameraModel
from cell.config import CellConfig, PlateConfig
from cell.errors import CalibrationRejected, PlateNotFound
from cell.wording import plural

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
    pitch_ratio: PitchRatio | None = None  # the configured pitch ratio as the circles see it
    plate_height_mm: float | None = None  # the camera's height above the table from the plate alone
    plate_height_sd_mm: float = 0.0  # how well the plate pins it down (one standard deviation)
    raised: RaisedHeight | None = None  # the height measured from the plate raised on a spacer, when given


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
    """Default detection: blob candidates on a pyramid, numbered by lattice growth, each centre
    refined at full resolution, sizes checked against the plate."""
    plate, det = config.plate, config.detection
    cands = find_candidates(to_gray(image))
    if len(cands) < 4:
        raise PlateNotFound(f"found {plural(len(cands), 'round dark blob')}: no plate in view")
    group, numbering = _number_by_size(cands, plate, det)
    idx, cr = numbering.index, numbering.col_row
    centres, diam, ok = refine_candidates(group, idx, _lattice_diameter_px(group.centre_px[idx], cr, plate))
    unseen = [tuple(x) for x in cr[~ok]]
    if unseen:
        log.info("circles at (col, row) %s not measured: cut by the image border or no contrast", unseen)
    idx, cr, centres, diam = idx[ok], cr[ok], centres[ok], diam[ok]
    # Size check: each circle against the size the local lattice pitch predicts.
    expected_d = _lattice_diameter_px(centres, cr, plate)
    size_ok = (diam > det.min_diameter_ratio * expected_d) & (diam < det.max_diameter_ratio * expected_d)
    rejected = [tuple(x) for x in cr[~size_ok]]
    if rejected:
        log.info("circles at (col, row) %s rejected: wrong size for the lattice", rejected)
    cr, centres = cr[size_ok], centres[size_ok]
    missing_cr = sorted(set(numbering.missing) | set(unseen) | set(rejected), key=lambda t: (t[1], t[0]))
    if len(missing_cr) > det.max_missing:
        raise PlateNotFound(
            f"found {len(cands)} blobs, {len(cr)} fit a {plate.columns} x {plate.rows} lattice "
            f"at the right size: {len(missing_cr)} circles missing or covered "
            f"(at most {det.max_missing} allowed)"
        )
    order = np.lexsort((cr[:, 0], cr[:, 1]))
    cr, centres = cr[order], centres[order]
    missing = [int(r * plate.columns + c + 1) for c, r in missing_cr]
    return PlatePoints(
        point_numbers(cr, plate),
        centres,
        cr * np.array([plate.pitch_x_mm, plate.pitch_y_mm]),
        missing,
        len(numbering.strays),
        len(cands),
    )


def _lattice_diameter_px(pixel: np.ndarray, cr: np.ndarray, plate: PlateConfig) -> np.ndarray:
    """Each circle's diameter in pixels as the local lattice pitch predicts it."""
    return _local_pitch_px(pixel, cr, plate) * plate.diameter_mm / np.sqrt(plate.pitch_x_mm * plate.pitch_y_mm)


def _number_by_size(cands: Candidates, plate: PlateConfig, det) -> tuple[Candidates, Numbering]:
    """Number the first size group that forms the whole plate; else fail with what the first one tried showed."""
    errors = []
    for members in size_groups(cands.diameter_px, cands.depth, plate.count - det.max_missing):
        group = cands.subset(members)
        try:
            return group, number_lattice(
                group.centre_px, plate, det.lattice_tolerance, det.max_missing, group.diameter_px
            )
        except PlateNotFound as e:
            errors.append(e)
    raise errors[0]


def _local_pitch_px(pixel: np.ndarray, cr: np.ndarray, plate: PlateConfig) -> np.ndarray:
    """Geometric-mean lattice pitch in pixels at each point: the area of the cell its lattice
    neighbours span (central differences, one-sided at edges and gaps; the median where none)."""
    grid = np.full((plate.rows + 2, plate.columns + 2, 2), np.nan)
    c, r = cr[:, 0] + 1, cr[:, 1] + 1
    grid[r, c] = pixel

    def step(dc: int, dr: int) -> np.ndarray:
        fwd, back = grid[r + dr, c + dc] - pixel, pixel - grid[r - dr, c - dc]
        return np.where(np.isnan(fwd), back, np.where(np.isnan(back), fwd, (fwd + back) / 2))

    u, v = step(1, 0), step(0, 1)
    pitch = np.sqrt(np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]))
    return np.where(np.isnan(pitch), np.nanmedian(pitch), pitch)


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


@dataclass(frozen=True)
class RaisedPlate:
    """A second image of the plate lying on a spacer `spacer_mm` thick: it gives the camera's height."""

    image: np.ndarray
    spacer_mm: float
    source: str = "the raised plate image"


def _points(image: np.ndarray, config: CellConfig) -> PlatePoints:
    return find_points_paper(image, config) if config.detection.preset == "paper" else find_points(image, config)


def calibrate(
    image: np.ndarray, config: CellConfig, model: str | None = None, raised: RaisedPlate | None = None
) -> CalibrationResult:
    """Detect, number, fit every candidate model, cross-validate, choose, and package; with `raised`,
    the camera's height measured from the plate raised on a spacer (cell.calibration.raised)."""
    t0 = time.perf_counter()
    h, w = image.shape[:2]
    if raised is not None and raised.image.shape[:2] != (h, w):
        rh, rw = raised.image.shape[:2]
        raise CalibrationRejected(
            f"{raised.source}: {rw} x {rh} px, the plate image {w} x {h}: not the same camera",
            hint="take both images with the same camera at the same resolution",
        )
    pts = _points(image, config)
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
    why = f"{chosen.label}: lowest cross-validated RMS error, {chosen.cv.rms_mm:.4f} mm" + (
        f" (others: {others} mm)" if others else " (the only model asked for)"
    )
    camera, plate_sd = fit_camera_pose(pts.pixel, pts.table_mm, (w, h))
    plate_height = float(camera.center_table_mm[2])
    # The camera model's best fit is the profiled one (a free fit stops anywhere along its valley).
    final = (
        CameraMap(camera)
        if chosen.name == "camera"
        else fit_model(chosen.name, pts.pixel, pts.table_mm, (w, h), chosen.degree)
    )
    raised_height = None
    if raised is not None:
        raised_height = height_from_raised_plate(raised.image, final, config.plate, raised.spacer_mm, raised.source)
    camera, height = _with_known_height(camera, plate_sd, pts, (w, h), config.calibration, raised_height)
    t2 = time.perf_counter()
    plate = config.plate
    col_row = np.rint(pts.table_mm / (plate.pitch_x_mm, plate.pitch_y_mm)).astype(int)
    pitch_ratio = measure_pitch_ratio(to_gray(image), pts.pixel, col_row, plate)
    t3 = time.perf_counter()
    height["cost"] = _height_cost(camera, final, (w, h), height, config)
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
        statistics={
            "fit": chosen.fit.to_dict(),
            "cross_validated": chosen.cv.to_dict(),
            "why": why,
            "camera_height": height,
            **({"raised_plate": raised_height.to_dict()} if raised_height is not None else {}),
        },
    )
    timings = {
        "detect_number_ms": 1e3 * (t1 - t0),
        "fit_cv_ms": 1e3 * (t2 - t1),
        "checks_ms": 1e3 * (t3 - t2),
        "total_ms": 1e3 * (t3 - t0),
    }
    return CalibrationResult(
        cal, pts, final(pts.pixel), scores, chosen, why, timings, pitch_ratio, plate_height, plate_sd, raised_height
    )


def _height_cost(camera: CameraModel, final, size, height: dict[str, Any], config: CellConfig) -> dict[str, Any]:
    """What the height's doubt costs the tallest configured part (Calibration.height_cost_mm), for
    the report and the warning: {"worst_mm", "at_table_mm", "part_height_mm", "height_error_mm", "max_mm"}."""
    part = config.parts.tallest_centre_height_mm
    sd = height.get("sd_mm")
    error = HEIGHT_DOUBT_SDS * float(sd) if isinstance(sd, int | float) else None
    cost: dict[str, Any] = {
        "part_height_mm": round(part, 3),
        "height_error_mm": None if error is None else round(error, 3),
        "max_mm": config.calibration.max_height_cost_mm,
    }
    if error is not None:
        worst, at = Calibration("camera", final, size, camera).height_cost_mm(part, error)
        cost |= {"worst_mm": round(worst, 4), "at_table_mm": [round(at[0], 1), round(at[1], 1)]}
    return cost


def _with_known_height(
    camera, plate_sd: float, pts: PlatePoints, size, limits, raised: RaisedHeight | None = None
) -> tuple[CameraModel, dict[str, Any]]:
    """The camera pose at the height the plate, the raised plate and the configured height agree on,
    each weighed by how well it is known; the plate's own pose where neither of the others is given.
    And that height: {"height_mm", "sd_mm", "from"} (what knew it).

    The plate fixes the scale (height over focal length) well even where it cannot fix the
    height: so the focal length is moved with the height, and the pose refitted around it.
    """
    fitted = float(camera.center_table_mm[2])
    known = [("the plate", fitted, plate_sd)] if np.isfinite(plate_sd) else []
    if raised is not None:
        known.append((f"the plate raised on a {raised.spacer_mm:g} mm spacer", raised.height_mm, raised.sd_mm))
    if limits.camera_height_mm is not None:
        known.append(("calibration.camera_height_mm", limits.camera_height_mm, limits.camera_height_sd_mm))
    if raised is None and limits.camera_height_mm is None:
        sd = plate_sd if np.isfinite(plate_sd) else None  # JSON has no infinity: None is "not known at all"
        return camera, {
            "height_mm": round(fitted, 2),
            "sd_mm": None if sd is None else round(sd, 3),
            "from": "the plate alone",
        }
    weights = [1.0 / max(sd, 1e-6) ** 2 for _, _, sd in known]
    height = sum(wt * z for wt, (_, z, _) in zip(weights, known, strict=True)) / sum(weights)
    focal = float(camera.camera_matrix[0, 0]) * height / fitted
    used = {
        "height_mm": round(height, 2),
        "sd_mm": round(1.0 / math.sqrt(sum(weights)), 3),
        "from": " and ".join(k[0] for k in known),
    }
    return fit_camera_pose(pts.pixel, pts.table_mm, size, focal_px=focal)[0], used

"""Looking through the camera before calibrating: is it sharp, well exposed, and does the
plate fill the view squarely? What `run-cell camera` prints, and what the screen can show.

- Focus: the variance of the Laplacian of the grey frame. It has no absolute scale (it
  depends on what is in view), so it is compared with the best seen while the focus ring
  is turned (`FocusTracker`).
- Exposure: the grey histogram, the share of pixels clipped dark (<= 2) and bright (>= 253),
  and the backlight's level (the 95th percentile: most of a backlit table is backlight).
- Plate: found with the calibration's own detection (cell.calibration.pipeline.find_points);
  how much of the view its circle field covers, whether it is wholly in view, how far the
  camera is from square to it (a camera model fitted to the circles) and which side is
  nearer, and how far it is turned in the image.

Every reading turns into words saying what to adjust (`advice`); no CLI here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from cell.calibration.detect import find_candidates, to_gray
from cell.calibration.models import fit_camera
from cell.calibration.pipeline import PlatePoints, find_points
from cell.config import CellConfig
from cell.errors import PlateNotFound
from cell.wording import plural

HIST_BINS = 16
_SHADES = " .:-=+*#%@"  # the histogram in plain ASCII, emptiest to fullest


@dataclass(frozen=True)
class Limits:
    """When a reading deserves a word of advice."""

    bright_clipped_pct: float = 0.5  # white pixels lose the rim of a circle or part
    dark_clipped_pct: float = 20.0  # a backlit table is mostly bright: this much black is underexposed
    backlight_min: float = 120.0  # the backlight (95th percentile) below this: too dark
    focus_fraction: float = 0.85  # below this share of the best focus seen: turn back
    coverage_min_pct: float = 25.0  # the plate's circle field in the view
    centre_offset_pct: float = 15.0  # plate centre from the image centre, per axis
    tilt_deg: float = 5.0  # camera from square to the plate
    turned_deg: float = 10.0  # plate rows against the image rows


@dataclass(frozen=True)
class Exposure:
    mean: float  # grey level 0-255
    backlight: float  # 95th percentile of grey
    dark_clipped_pct: float
    bright_clipped_pct: float
    histogram: tuple[float, ...]  # HIST_BINS shares of the pixels, summing to 1


@dataclass(frozen=True)
class PlateView:
    circles_found: int
    circles_expected: int
    missing: list[int]  # plate point numbers not measured (cut by the border, covered, no contrast)
    coverage_pct: float  # the circle field's share of the image (the part inside it)
    in_view: bool  # the whole circle field inside the image, no circle missing
    centre_offset_pct: tuple[float, float]  # field centre from image centre, % of width / height (right, down +)
    tilt_deg: float  # the fitted camera's optical axis from the plate's normal
    nearer: str  # which side of the plate is nearer the camera ("left", "top-right", ...; "" if square)
    turned_deg: float  # the plate's X axis against the image's rows, -180..180


@dataclass(frozen=True)
class PartialPlate:
    """Where no whole plate is found: a crowd of like dots (the plate, likely) and the image
    edges it runs into."""

    dots: int
    cut_at: tuple[str, ...]  # image edges: "left", "right", "top", "bottom"


@dataclass
class CameraView:
    """One frame's readings."""

    size: tuple[int, int]
    focus: float
    exposure: Exposure
    plate: PlateView | None
    plate_note: str = ""  # why no plate was found
    partial: PartialPlate | None = None  # no plate found, but what looks like part of one
    advice: list[str] = field(default_factory=list)


class FocusTracker:
    """The best focus score seen so far, and the frame it came from."""

    def __init__(self) -> None:
        self.best = 0.0
        self.best_frame = 0
        self.frames = 0

    def update(self, score: float) -> float:
        """Record a frame's score; its share of the best so far (1.0 for a new best)."""
        self.frames += 1
        if score >= self.best:
            self.best, self.best_frame = score, self.frames
        return score / self.best if self.best > 0 else 1.0


def focus_score(gray: np.ndarray) -> float:
    """Variance of the Laplacian: higher is sharper, for the same scene."""
    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


def measure_exposure(gray: np.ndarray) -> Exposure:
    counts = cv2.calcHist([gray], [0], None, [256], [0, 256]).ravel()
    total = max(float(counts.sum()), 1.0)
    cumulative = np.cumsum(counts) / total
    return Exposure(
        mean=float(np.dot(np.arange(256), counts) / total),
        backlight=float(np.searchsorted(cumulative, 0.95)),
        dark_clipped_pct=100.0 * float(counts[:3].sum()) / total,
        bright_clipped_pct=100.0 * float(counts[253:].sum()) / total,
        histogram=tuple(float(x) for x in counts.reshape(HIST_BINS, -1).sum(axis=1) / total),
    )


def find_plate(image: np.ndarray, config: CellConfig) -> PlateView:
    """The plate as the camera sees it; PlateNotFound (saying what was seen) when it is not in view."""
    pts = find_points(image, config)
    h, w = image.shape[:2]
    plate = config.plate
    if len(pts.pixel) < 6:
        raise PlateNotFound(f"only {len(pts.pixel)} plate circles measured")
    H, _ = cv2.findHomography(pts.table_mm.astype(np.float64), pts.pixel.astype(np.float64), 0)
    if H is None:
        raise PlateNotFound("the plate's circles fit no plane")
    r = plate.diameter_mm / 2
    x1, y1 = (plate.columns - 1) * plate.pitch_x_mm + r, (plate.rows - 1) * plate.pitch_y_mm + r
    field_mm = np.array([[-r, -r], [x1, -r], [x1, y1], [-r, y1]], np.float64)
    corners = _apply(H, field_mm)
    frame = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float32)
    inside, _ = cv2.intersectConvexConvex(_convex(corners), frame)
    centre = _apply(H, np.array([[(x1 - r) / 2, (y1 - r) / 2]]))[0]
    axis = _apply(H, np.array([[(x1 - r) / 2 + plate.pitch_x_mm, (y1 - r) / 2]]))[0] - centre
    all_in = bool(np.all((corners >= 0) & (corners <= (w - 1, h - 1))))
    return PlateView(
        circles_found=len(pts.pixel),
        circles_expected=plate.count,
        missing=list(pts.missing),
        coverage_pct=100.0 * float(inside) / (w * h),
        in_view=all_in and not pts.missing,
        centre_offset_pct=(100.0 * (centre[0] - w / 2) / w, 100.0 * (centre[1] - h / 2) / h),
        tilt_deg=_tilt_deg(pts, (w, h)),
        nearer=_nearer_side(H, field_mm),
        turned_deg=math.degrees(math.atan2(axis[1], axis[0])),
    )


def partial_plate(gray: np.ndarray, min_dots: int, max_dots: int) -> PartialPlate | None:
    """The largest crowd of `min_dots` to `max_dots` dark dots of one size spaced as a lattice is
    (most nearest neighbours at one distance), and which image edges it reaches (within two
    dot diameters): a plate cut by the border. None where there is no such crowd (loose parts
    are neither that many nor that regular)."""
    cands = find_candidates(gray)
    if len(cands) < min_dots:
        return None
    d = cands.diameter_px
    counts = [int(np.count_nonzero(np.abs(np.log(d / x)) < np.log(1.4))) for x in d]
    like = np.abs(np.log(d / d[int(np.argmax(counts))])) < np.log(1.4)
    if not min_dots <= np.count_nonzero(like) <= max_dots:  # more: clutter, not a plate
        return None
    xy, margin = cands.centre_px[like], 2.0 * float(np.median(d[like]))
    gaps = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(gaps, np.inf)
    nearest = gaps.min(axis=1)
    if np.mean(np.abs(nearest / np.median(nearest) - 1) < 0.25) < 0.8:
        return None
    h, w = gray.shape[:2]
    near = {
        "left": xy[:, 0].min() < margin,
        "right": xy[:, 0].max() > w - 1 - margin,
        "top": xy[:, 1].min() < margin,
        "bottom": xy[:, 1].max() > h - 1 - margin,
    }
    return PartialPlate(int(np.count_nonzero(like)), tuple(k for k, v in near.items() if v))


def assess(
    image: np.ndarray, config: CellConfig, tracker: FocusTracker | None = None, limits: Limits = Limits()
) -> CameraView:
    """All the readings of one frame and what to adjust; `tracker` (updated here) gives focus its reference."""
    gray = to_gray(image)
    h, w = gray.shape[:2]
    view = CameraView((w, h), focus_score(gray), measure_exposure(gray), None)
    try:
        view.plate = find_plate(image, config)
    except PlateNotFound as e:
        view.plate_note = str(e)
        view.partial = partial_plate(gray, max(8, config.plate.count // 4), 2 * config.plate.count)
    share = tracker.update(view.focus) if tracker is not None else None
    genicam = config.camera.source.strip().startswith("genicam:")
    view.advice = advice(view, share, limits, "camera.genicam.exposure_us" if genicam else "camera.exposure")
    return view


def advice(
    view: CameraView, focus_share: float | None, limits: Limits = Limits(), exposure_key: str = "camera.exposure"
) -> list[str]:
    """What to adjust, in words, most urgent first; empty when nothing needs it. `exposure_key`: the
    config key that sets this camera's exposure."""
    out: list[str] = []
    if focus_share is not None and focus_share < limits.focus_fraction:
        out.append(
            f"focus: {100 * focus_share:.0f} % of the best seen: turn the focus ring (or camera.focus) back towards it"
        )
    e = view.exposure
    if e.bright_clipped_pct > limits.bright_clipped_pct:
        out.append(
            f"exposure: {e.bright_clipped_pct:.1f} % of the pixels are white: lower {exposure_key} "
            "(or dim the backlight) until none are"
        )
    elif e.backlight < limits.backlight_min or e.dark_clipped_pct > limits.dark_clipped_pct:
        out.append(
            f"exposure: too dark (the backlight reads {e.backlight:.0f} of 255, {e.dark_clipped_pct:.1f} % black): "
            f"raise {exposure_key} or the backlight, short of white"
        )
    p = view.plate
    if p is None and view.partial is not None and view.partial.cut_at:
        out.append(_cut_advice(view.partial))
        return out
    if p is None:
        out.append("plate: not in view: lay the calibration plate under the camera to see its coverage and tilt")
        return out
    if not p.in_view:
        cut = f"{plural(len(p.missing), 'circle')} not seen" if p.missing else "its edge is outside the image"
        out.append(f"plate: not wholly in view ({cut}): move it towards the centre {_towards(p)}".rstrip())
    elif max(abs(v) for v in p.centre_offset_pct) > limits.centre_offset_pct:
        out.append(f"plate: off centre: move it {_towards(p)}")
    if p.coverage_pct < limits.coverage_min_pct:
        out.append(
            f"plate: fills {p.coverage_pct:.0f} % of the view: bring the camera closer or zoom in "
            "so the plate covers the area where parts lie"
        )
    if p.tilt_deg > limits.tilt_deg:
        out.append(
            f"camera: {p.tilt_deg:.1f} deg from square to the plate (the {p.nearer} side is nearer): "
            "level the camera over the table"
        )
    if abs(p.turned_deg) > limits.turned_deg:
        out.append(f"plate: turned {p.turned_deg:+.1f} deg in the image: square it with the image's edges")
    return out


def report_text(view: CameraView, source: str, tracker: FocusTracker | None = None) -> str:
    """Several lines for one frame: every reading, then what to adjust."""
    w, h = view.size
    e = view.exposure
    focus = f"focus: {view.focus:.1f} (variance of the Laplacian; higher is sharper"
    if tracker is not None and tracker.frames > 1:
        focus += f"; best {tracker.best:.1f} at frame {tracker.best_frame})"
    else:
        focus += "; watch it peak with --live while turning the focus)"
    lines = [
        f"camera {source}: {w} x {h} px",
        focus,
        f"exposure: mean {e.mean:.0f} of 255, backlight {e.backlight:.0f}; "
        f"{e.dark_clipped_pct:.1f} % black, {e.bright_clipped_pct:.1f} % white",
        f"histogram 0..255: [{histogram_text(e.histogram)}]",
        plate_text(view),
    ]
    lines += [f"adjust: {a}" for a in view.advice] or ["adjust: nothing"]
    return "\n".join(lines)


def live_line(n: int, view: CameraView, tracker: FocusTracker) -> str:
    """One line per frame for --live."""
    e = view.exposure
    share = 100.0 * view.focus / tracker.best if tracker.best > 0 else 100.0
    p = view.plate
    plate = (
        f"plate {p.circles_found}/{p.circles_expected}, {p.coverage_pct:.0f} % of view, tilt {p.tilt_deg:.1f} deg"
        if p is not None
        else "no plate"
    )
    todo = "; ".join(a.split(":")[0] for a in view.advice) or "nothing"
    return (
        f"frame {n}: focus {view.focus:.1f} (best {tracker.best:.1f}, {share:.0f} %) | "
        f"mean {e.mean:.0f}, black {e.dark_clipped_pct:.1f} %, white {e.bright_clipped_pct:.1f} % | "
        f"{plate} | adjust: {todo}"
    )


def plate_text(view: CameraView) -> str:
    p = view.plate
    if p is None and view.partial is not None and view.partial.cut_at:
        return (
            f"plate: not found whole ({view.plate_note}); {plural(view.partial.dots, 'dot')} of one size "
            f"reach the image's {' and '.join(view.partial.cut_at)} edge"
        )
    if p is None:
        return f"plate: not in view ({view.plate_note})"
    dx, dy = p.centre_offset_pct
    missing = f", missing {_numbers(p.missing)}" if p.missing else ""
    centre = (
        "centred"
        if max(abs(dx), abs(dy)) < 0.5
        else f"centre {abs(dx):.1f} % {'right' if dx >= 0 else 'left'}, {abs(dy):.1f} % {'down' if dy >= 0 else 'up'}"
    )
    return (
        f"plate: {p.circles_found} of {p.circles_expected} circles{missing}; fills {p.coverage_pct:.1f} % of the view"
        f"{'' if p.in_view else ' (not wholly in view)'}; {centre}; camera {p.tilt_deg:.1f} deg from square"
        f"{f' ({p.nearer} side nearer)' if p.nearer else ''}; turned {p.turned_deg:+.1f} deg"
    )


def histogram_text(shares: tuple[float, ...]) -> str:
    """One character per bin, its height relative to the fullest bin."""
    top = max(shares) or 1.0
    return "".join(_SHADES[min(len(_SHADES) - 1, math.ceil(s / top * (len(_SHADES) - 1)))] for s in shares)


def _apply(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return cv2.perspectiveTransform(xy.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)


def _convex(points: np.ndarray) -> np.ndarray:
    return cv2.convexHull(points.astype(np.float32))


def _tilt_deg(pts: PlatePoints, size: tuple[int, int]) -> float:
    """Angle between the fitted camera's optical axis and the plate's normal."""
    camera = fit_camera(pts.pixel, pts.table_mm, size)
    rotation, _ = cv2.Rodrigues(np.asarray(camera.rvec, np.float64))
    return math.degrees(math.acos(min(1.0, abs(float(rotation[2, 2])))))


def _nearer_side(H: np.ndarray, field_mm: np.ndarray, threshold: float = 0.01) -> str:
    """The side of the plate the camera sees larger (pixels per mm): the nearer one."""
    (x0, y0), (x1, y1) = field_mm[0], field_mm[2]
    xm, ym = (x0 + x1) / 2, (y0 + y1) / 2

    def scale(x: float, y: float) -> float:  # pixels per mm at (x, y), from a 1 mm square
        quad = _apply(H, np.array([[x, y], [x + 1, y], [x + 1, y + 1], [x, y + 1]]))
        return math.sqrt(abs(cv2.contourArea(quad.astype(np.float32))))

    pts = {"left": (x0, ym), "right": (x1, ym), "top": (xm, y0), "bottom": (xm, y1)}
    s = {k: scale(*v) for k, v in pts.items()}
    # name the sides by where they appear in the image, not in plate coordinates
    where = {k: _apply(H, np.array([v]))[0] for k, v in pts.items()}
    horizontal = sorted(("left", "right"), key=lambda k: where[k][0])
    vertical = sorted(("top", "bottom"), key=lambda k: where[k][1])
    words = []
    for (a, b), names in ((vertical, ("top", "bottom")), (horizontal, ("left", "right"))):
        ratio = s[b] / s[a]
        if abs(ratio - 1) > threshold:
            words.append(names[1] if ratio > 1 else names[0])
    return "-".join(words)


def _cut_advice(partial: PartialPlate) -> str:
    cut = partial.cut_at
    seen = f"cut by the image's {' and '.join(cut)} edge, {plural(partial.dots, 'dot')} seen"
    if {"left", "right"} <= set(cut) or {"top", "bottom"} <= set(cut):
        return f"plate: larger than the view ({seen}): raise the camera or zoom out"
    away = {"left": "right", "right": "left", "top": "down", "bottom": "up"}
    return f"plate: not wholly in view ({seen}): move it towards the centre (in the image: " + (
        " and ".join(away[side] for side in cut) + ")"
    )


def _towards(p: PlateView) -> str:
    dx, dy = p.centre_offset_pct
    moves = []
    if abs(dx) > 2:
        moves.append("left" if dx > 0 else "right")
    if abs(dy) > 2:
        moves.append("up" if dy > 0 else "down")
    return f"(in the image: {' and '.join(moves)})" if moves else ""


def _numbers(values: list[int], limit: int = 8) -> str:
    shown = ", ".join(str(v) for v in values[:limit])
    return shown + (f" and {len(values) - limit} more" if len(values) > limit else "")

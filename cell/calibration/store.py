"""The calibration the cell uses: a fitted model plus the camera pose, saved as versioned JSON.

Whatever model maps the points, the file also carries the camera pose (from the camera
model fit), because part-height (parallax) correction needs to know where the camera is.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from cell.atomicfile import write_text_atomic
from cell.calibration.models import PixelMap, model_from_dict
from cell.camera_model import CameraModel
from cell.errors import InputError

SCHEMA = "pick-cell/calibration"
SCHEMA_VERSION = 1
MIN_IMAGE_PX, MAX_IMAGE_PX = 16, 20000  # as camera.width_px / height_px allow
HEIGHT_DOUBT_SDS = 3.0  # the height's doubt is judged at this many standard deviations (99.7 % of cameras;
# at 2, the 5 % of cameras whose height is 2-3 sd off passed silently: scripts/bench_height_doubt.py)
DEFAULT_PART_HEIGHT_MM = 7.8  # parts' default tallest centre plane (PartsConfig.tallest_centre_height_mm)
DEFAULT_MAX_HEIGHT_COST_MM = 0.5  # calibration.max_height_cost_mm's default: the parts goal
FIELD_SAMPLES = 64  # points along each side of the image where the cost is judged


@dataclass
class Calibration:
    """Maps pixels to table millimetres (the plate frame: point 1 at (0, 0))."""

    model_name: str
    model: PixelMap  # pixels (N, 2) -> table mm (N, 2)
    image_size: tuple[int, int]
    camera: CameraModel | None
    pattern: dict = field(default_factory=dict)
    image_sha256: str = ""
    created_utc: str = ""
    statistics: dict = field(default_factory=dict)

    def pixel_to_table_mm(self, pixels, height_mm: float = 0.0) -> np.ndarray:
        """Table (X, Y) of the point seen at each pixel, on the plane `height_mm` above the table.

        The model maps onto the table plane; a point higher up lies on the same ray,
        nearer the camera: scale towards the camera's foot by (H - h) / H.
        """
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        return self.lift_mm(np.asarray(self.model(px)).reshape(-1, 2), height_mm)

    def lift_mm(self, on_table: np.ndarray, height_mm: float) -> np.ndarray:
        """Points the calibration mapped onto the table plane (N, 2) moved along their rays to the
        plane `height_mm` above it: pixel_to_table_mm's second step, for points mapped already."""
        if height_mm == 0.0:
            return on_table
        if self.camera is None:
            raise InputError("height correction needs the camera pose, which this calibration lacks")
        C = self.camera.center_table_mm
        return C[:2] + (on_table - C[:2]) * (1.0 - height_mm / C[2])

    def height_cost_mm(self, part_height_mm: float, height_error_mm: float) -> tuple[float, tuple[float, float]]:
        """The worst error of a part's centre, over the image's field on the table, when the camera's
        true height is `height_error_mm` off the one this calibration uses (either way), for a part
        whose centre is mapped on the plane `part_height_mm` above the table; and where on the table.

        The map onto the table plane is the plate's and does not depend on the height; the height
        enters only where a point seen at table point q is moved along its ray to the part's plane,
        p = C + (q - C) (1 - h / H), with C the camera's foot. A true height H + d puts the part at
        C + (q - C) (1 - h / (H + d)): off by |q - C| h |d| / (H (H + d)), largest for the field
        point farthest from the foot and for d = -|d| (the camera nearer than believed).
        """
        if self.camera is None or part_height_mm <= 0 or height_error_mm <= 0:
            return 0.0, (0.0, 0.0)
        c = self.camera.center_table_mm
        height, d = float(c[2]), min(float(height_error_mm), 0.95 * float(c[2]))
        q = self.model(field_border_px(self.image_size))
        r = np.hypot(*(np.asarray(q).reshape(-1, 2) - c[:2]).T)
        k = int(np.argmax(r))
        worst = float(r[k]) * part_height_mm * d / (height * (height - d))
        return worst, (float(q[k][0]), float(q[k][1]))

    def height_doubt(
        self, part_height_mm: float | None = None, max_cost_mm: float | None = None
    ) -> tuple[str, str] | None:
        """(reason, hint) when the camera's height above the table, which the part-height correction
        needs, is known too poorly for the parts: when a height error of HEIGHT_DOUBT_SDS standard
        deviations would move the tallest part's centre (its centre plane `part_height_mm` above the
        table) more than `max_cost_mm` somewhere in the field (height_cost_mm), or the height is
        not known at all. Both default to what the calibration recorded (calibrate, from the config)
        or else DEFAULT_PART_HEIGHT_MM and DEFAULT_MAX_HEIGHT_COST_MM. None when the height is known
        well enough, or when the file does not say (older calibrations)."""
        known = self.statistics.get("camera_height")
        if not isinstance(known, dict) or not isinstance(known.get("height_mm"), int | float):
            return None
        cost_entry = known.get("cost")
        recorded: dict = cost_entry if isinstance(cost_entry, dict) else {}
        if part_height_mm is None:
            part_height_mm = float(recorded.get("part_height_mm", DEFAULT_PART_HEIGHT_MM))
        if max_cost_mm is None:
            max_cost_mm = float(recorded.get("max_mm", DEFAULT_MAX_HEIGHT_COST_MM))
        height, sd = float(known["height_mm"]), known.get("sd_mm")
        remedy = (
            "measure the height into calibration.camera_height_mm, or recalibrate with an image of the plate "
            "raised on a spacer (run-cell recalibrate --raised-image FILE --spacer-mm MM; docs/calibration.md)"
        )
        source = f"from {known.get('from', '?')}; {height:.0f} mm used"
        if not isinstance(sd, int | float):
            return (
                f"calibration: the camera's height above the table is not known at all ({source}): "
                "parts' centres may be off by a millimetre or more",
                remedy,
            )
        cost, at = self.height_cost_mm(part_height_mm, HEIGHT_DOUBT_SDS * float(sd))
        if cost <= max_cost_mm:
            return None
        return (
            f"calibration: the camera's height above the table is known only to +- {sd:.1f} mm ({source}): "
            f"a {part_height_mm:.1f} mm high part's centre may be off by up to {cost:.2f} mm (at {at[0]:.0f}, "
            f"{at[1]:.0f} mm; {HEIGHT_DOUBT_SDS:g} standard deviations), more than "
            f"calibration.max_height_cost_mm {max_cost_mm:g} mm",
            remedy,
        )

    @property
    def camera_center_table_mm(self) -> np.ndarray | None:
        return None if self.camera is None else self.camera.center_table_mm

    def mm_per_px(self, pixel) -> float:
        """Local scale at a pixel (geometric mean of the two axes), for size limits in mm."""
        p = np.asarray(pixel, dtype=np.float64).reshape(2)
        q = self.pixel_to_table_mm(np.array([p, p + (1, 0), p + (0, 1)]))
        (ax, ay), (bx, by) = q[1] - q[0], q[2] - q[0]
        return float(math.sqrt(abs(ax * by - ay * bx)))

    @property
    def content_id(self) -> str:
        """A short content hash (sha256 of the canonical JSON): which calibration a pick used."""
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"), default=_plain)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]

    def to_dict(self) -> dict:
        return {
            "schema": SCHEMA,
            "version": SCHEMA_VERSION,
            "model": self.model_name,
            "coefficients": self.model.to_dict(),
            "image_size": list(self.image_size),
            "camera": None if self.camera is None else self.camera.to_dict(),
            "camera_center_table_mm": None if self.camera is None else self.camera.center_table_mm.tolist(),
            "pattern": self.pattern,
            "image_sha256": self.image_sha256,
            "created_utc": self.created_utc,
            "statistics": self.statistics,
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "calibration") -> Calibration:
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            raise InputError(f"{source}: not a calibration file (schema is not {SCHEMA!r})")
        if d.get("version") != SCHEMA_VERSION:
            raise InputError(
                f"{source}: calibration schema version {d.get('version')!r} is not supported "
                f"(this program reads version {SCHEMA_VERSION})"
            )
        if bad := _non_finite(d.get("coefficients"), "coefficients") or _non_finite(d.get("camera"), "camera"):
            raise InputError(f"{source}: corrupt calibration ({bad} is not a finite number)")
        try:
            model = model_from_dict(d["model"], d["coefficients"])
            w, h = (int(v) for v in d["image_size"])
            camera = CameraModel.from_dict(d["camera"]) if d.get("camera") else None
        except (KeyError, TypeError, ValueError, cv2.error) as e:
            raise InputError(f"{source}: corrupt calibration ({type(e).__name__}: {e})") from None
        if not (MIN_IMAGE_PX <= w <= MAX_IMAGE_PX and MIN_IMAGE_PX <= h <= MAX_IMAGE_PX):
            raise InputError(
                f"{source}: corrupt calibration (image size {w} x {h} px is outside {MIN_IMAGE_PX}..{MAX_IMAGE_PX} px)"
            )
        if camera is not None:
            _check_camera(camera, (w, h), source)
        corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [w / 2, h / 2]], dtype=np.float64)
        probe = np.asarray(model(corners))
        if not np.all(np.isfinite(probe)):
            raise InputError(f"{source}: corrupt calibration (maps the image's corners and centre to {probe.tolist()})")
        return cls(
            d["model"],
            model,
            (w, h),
            camera,
            d.get("pattern", {}),
            d.get("image_sha256", ""),
            d.get("created_utc", ""),
            d.get("statistics", {}),
        )

    def save(self, path: str | Path) -> None:
        write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise InputError(
                f"{path}: calibration file not found",
                hint="make one with run-cell recalibrate (the plate under the camera)",
            ) from None
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(f"{path}: cannot read calibration: {e}") from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise InputError(f"{path}: corrupt calibration (not JSON: {e})") from None
        return cls.from_dict(data, str(path))


def field_border_px(image_size: tuple[int, int]) -> np.ndarray:
    """Pixels along the image's four edges (FIELD_SAMPLES each): where the field's farthest points lie."""
    w, h = image_size
    t = np.linspace(0.0, 1.0, FIELD_SAMPLES)
    xs, ys = t * (w - 1), t * (h - 1)
    zeros = np.zeros_like(t)
    return np.concatenate(
        [
            np.column_stack([xs, zeros]),
            np.column_stack([xs, zeros + h - 1]),
            np.column_stack([zeros, ys]),
            np.column_stack([zeros + w - 1, ys]),
        ]
    )


def _non_finite(value, where: str) -> str | None:
    """The path of the first number in a JSON tree that is NaN or infinite (None: all finite)."""
    if isinstance(value, dict):
        return next((bad for k, v in value.items() if (bad := _non_finite(v, f"{where}.{k}"))), None)
    if isinstance(value, list):
        return next((bad for i, v in enumerate(value) if (bad := _non_finite(v, f"{where}[{i}]"))), None)
    if isinstance(value, float) and not math.isfinite(value):
        return where
    return None


def _check_camera(camera: CameraModel, image_size: tuple[int, int], source: str) -> None:
    """The pose must put the camera above the table, looking at it, with the image's size."""
    if (camera.width_px, camera.height_px) != tuple(image_size):
        raise InputError(
            f"{source}: corrupt calibration (camera model is {camera.width_px} x {camera.height_px} px, "
            f"the calibration {image_size[0]} x {image_size[1]} px)"
        )
    centre = camera.center_table_mm
    if not np.all(np.isfinite(centre)) or centre[2] <= 0 or camera.tvec[2] <= 0:
        raise InputError(
            f"{source}: corrupt calibration (camera at {np.round(centre, 1).tolist()} mm with the "
            f"table {camera.tvec[2]:.1f} mm in front of it: not above the table, looking at it)"
        )
    f = camera.camera_matrix[0, 0], camera.camera_matrix[1, 1]
    if min(f) <= 0:
        raise InputError(f"{source}: corrupt calibration (focal length {f} px is not positive)")


def _plain(value):
    """numpy scalars and arrays as the JSON numbers and lists they hold (json cannot write them)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


def write_json_atomic(path: str | Path, data: dict) -> None:
    """JSON (no NaN or inf: a strict reader must be able to load it) written whole or not at all."""
    write_text_atomic(path, json.dumps(data, indent=2, allow_nan=False, default=_plain) + "\n")

"""The calibration the cell uses: a fitted model plus the camera pose, saved as versioned JSON.

Whatever model maps the points, the file also carries the camera pose (from the camera
model fit), because part-height (parallax) correction needs to know where the camera is.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cell.calibration.models import model_from_dict
from cell.camera_model import CameraModel
from cell.errors import InputError

SCHEMA = "pick-cell/calibration"
SCHEMA_VERSION = 1


@dataclass
class Calibration:
    """Maps pixels to table millimetres (the plate frame: point 1 at (0, 0))."""

    model_name: str
    model: object  # a callable pixels (N, 2) -> table mm (N, 2); see models.py
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
        on_table = np.asarray(self.model(px)).reshape(-1, 2)
        if height_mm == 0.0:
            return on_table
        if self.camera is None:
            raise InputError("height correction needs the camera pose, which this calibration lacks")
        C = self.camera.center_table_mm
        return C[:2] + (on_table - C[:2]) * (1.0 - height_mm / C[2])

    @property
    def camera_center_table_mm(self) -> np.ndarray | None:
        return None if self.camera is None else self.camera.center_table_mm

    def mm_per_px(self, pixel) -> float:
        """Local scale at a pixel (geometric mean of the two axes), for size limits in mm."""
        p = np.asarray(pixel, dtype=np.float64).reshape(2)
        q = self.pixel_to_table_mm(np.array([p, p + (1, 0), p + (0, 1)]))
        (ax, ay), (bx, by) = q[1] - q[0], q[2] - q[0]
        return float(math.sqrt(abs(ax * by - ay * bx)))

    def to_dict(self) -> dict:
        return {
            "schema": SCHEMA,
            "version": SCHEMA_VERSION,
            "model": self.model_name,
            "coefficients": self.model.to_dict(),
            "image_size": list(self.image_size),
            "camera": None if self.camera is None else self.camera.to_dict(),
            "camera_center_table_mm": None
            if self.camera is None
            else self.camera.center_table_mm.tolist(),
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
        try:
            model = model_from_dict(d["model"], d["coefficients"])
            w, h = (int(v) for v in d["image_size"])
            camera = CameraModel.from_dict(d["camera"]) if d.get("camera") else None
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"{source}: corrupt calibration ({type(e).__name__}: {e})") from None
        probe = model(np.array([[w / 2, h / 2]], dtype=np.float64))
        if not np.all(np.isfinite(probe)):
            raise InputError(f"{source}: corrupt calibration (maps the image centre to {probe.tolist()})")
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
            raise InputError(f"{path}: calibration file not found", hint="run scripts/recalibrate.py") from None
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(f"{path}: cannot read calibration: {e}") from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise InputError(f"{path}: corrupt calibration (not JSON: {e})") from None
        return cls.from_dict(data, str(path))


def write_json_atomic(path: str | Path, data: dict) -> None:
    """Write to a temporary file beside `path`, fsync, then rename: never a half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=2, allow_nan=False)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise

"""Watching the camera while the cell works: reference marks that stay in view (printed dots at
the table's edge, a few plate circles) are measured on every frame and mapped through the
calibration in use. They lie still; if they seem to move, the camera has, and every pick from
that frame on would miss by as much. The cell stops before the next pick instead.

Each mark is found near where the calibration's camera pose puts it (within `search_mm`),
its centre measured to a fraction of a pixel as the plate's circles are (refine.py), and the
drift is the largest distance between a mark's mapped centre and its place. A mark that
cannot be measured (covered, out of view) is itself a reason to stop: the watch is blind.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from cell.calibration.detect import to_gray
from cell.calibration.refine import refine_centres
from cell.calibration.store import Calibration
from cell.config import DriftConfig
from cell.errors import CameraMoved, InputError

log = logging.getLogger(__name__)


@dataclass
class DriftReading:
    mapped_mm: np.ndarray  # (M, 2) each mark's centre mapped through the calibration
    shift_mm: np.ndarray  # (M, 2) mapped - place
    seen: np.ndarray  # (M,) bool

    @property
    def drift_mm(self) -> float:
        return float(np.hypot(*self.shift_mm[self.seen].T).max(initial=0.0))


class DriftWatch:
    """Call with each captured frame; raises CameraMoved when the marks have moved."""

    def __init__(self, calibration: Calibration, config: DriftConfig):
        if calibration.camera is None:
            raise InputError(
                "the drift watch needs the camera pose, which this calibration lacks",
                hint="recalibrate with run-cell recalibrate",
            )
        self.calibration, self.config = calibration, config
        self.marks_mm = np.asarray(config.marks_mm, dtype=np.float64).reshape(-1, 2)
        self.expected_px = calibration.camera.project(self.marks_mm)
        scale = np.array([calibration.mm_per_px(p) for p in self.expected_px])
        self.diameter_px = config.mark_diameter_mm / scale
        self.search_px = config.search_mm / scale
        self.frames = 0

    def measure(self, frame: np.ndarray) -> DriftReading:
        gray = to_gray(frame)
        centres, diameter, ok = refine_centres(gray, self.expected_px, self.diameter_px, self.search_px)
        ok &= np.abs(diameter / self.diameter_px - 1.0) < 0.5  # a part's edge is not the mark
        mapped = self.calibration.pixel_to_table_mm(np.where(ok[:, None], centres, self.expected_px))
        return DriftReading(mapped, mapped - self.marks_mm, ok)

    def __call__(self, frame: np.ndarray) -> DriftReading:
        reading = self.measure(frame)
        self.frames += 1
        log.debug("frame %d: reference marks drift %.3f mm", self.frames, reading.drift_mm)
        if not reading.seen.all():
            lost = [tuple(m) for m in self.marks_mm[~reading.seen].round(1).tolist()]
            raise CameraMoved(
                f"reference marks at table {lost} mm not found where the calibration puts them: "
                "camera moved or marks covered; check or recalibrate",
                hint="uncover the marks, or run-cell check-calibration with the plate in its fixture",
            )
        if reading.drift_mm > self.config.limit_mm:
            mean = reading.shift_mm.mean(axis=0)
            raise CameraMoved(
                f"camera moved {reading.drift_mm:.2f} mm since calibration (reference marks seen shifted by "
                f"{mean[0]:+.2f}, {mean[1]:+.2f} mm, limit drift.limit_mm {self.config.limit_mm} mm); "
                "check or recalibrate",
                hint="run-cell check-calibration with the plate in its fixture, or run-cell recalibrate",
            )
        return reading

"""Shared test helpers: where ../shared is, and truth-based error measures."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
PAPER = SHARED / "paper"
DATA = SHARED / "data"


def need(path: Path) -> Path:
    """Skip the test, saying why, where ../shared is absent (a user's fresh clone has none)."""
    if not path.exists():
        pytest.skip(f"{path} is absent: the paper's data and real photos live in ../shared, outside the repo")
    return path


def dense_error_mm(camera, calibration, plate, step_mm: float = 2.0) -> tuple[float, float]:
    """RMS and max mapping error over the plate field, at points not used in the fit."""
    X, Y = np.meshgrid(
        np.arange(0.0, (plate.columns - 1) * plate.pitch_x_mm + 1e-9, step_mm),
        np.arange(0.0, (plate.rows - 1) * plate.pitch_y_mm + 1e-9, step_mm),
    )
    table = np.column_stack([X.ravel(), Y.ravel()])
    err = np.hypot(*(calibration.pixel_to_table_mm(camera.project(table)) - table).T)
    return float(np.sqrt(np.mean(err**2))), float(err.max())

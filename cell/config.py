"""The cell's configuration: TOML files validated by pydantic models.

Every key carries its unit; every model forbids unknown keys so a typo is an error that
names the key, not a silently ignored setting.
"""
from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, model_validator

from cell.errors import ConfigError
from cell.run_config import PlanningConfig, RunConfig, SimConfig
from cell.service.config import ServiceConfig
from cell.vision.config import PartsConfig, Preset
from drivers.arm.config import ArmConfig
from drivers.cameras.config import CameraConfig
from drivers.config import Strict

Corner = Literal["top-left", "top-right", "bottom-left", "bottom-right"]
ModelName = Literal["auto", "quadratic", "homography", "polynomial", "camera"]


class PlateConfig(Strict):
    """The printed calibration plate; the paper's plate by default."""

    columns: int = Field(13, ge=3, le=200)
    rows: int = Field(12, ge=3, le=200)
    pitch_x_mm: float = Field(22.0, gt=0, le=1000)
    pitch_y_mm: float = Field(16.0, gt=0, le=1000)
    diameter_mm: float = Field(10.0, gt=0, le=500)
    first_point: Corner = Field(
        "top-left", description="image corner where point 1 lies, for a plate seen unrotated"
    )

    @model_validator(mode="after")
    def _circles_do_not_touch(self) -> PlateConfig:
        if self.diameter_mm >= min(self.pitch_x_mm, self.pitch_y_mm):
            raise ValueError(
                f"plate.diameter_mm ({self.diameter_mm} mm) must be smaller than both pitches "
                f"(pitch_x_mm {self.pitch_x_mm} mm, pitch_y_mm {self.pitch_y_mm} mm)"
            )
        return self

    @property
    def count(self) -> int:
        return self.columns * self.rows


class PaperDetectionConfig(Strict):
    """The paper's thresholds, exactly as published (section III-D)."""

    hsv_lower: tuple[int, int, int] = (10, 0, 100)
    hsv_upper: tuple[int, int, int] = (250, 250, 250)
    min_area_px: float = Field(500, ge=0)
    max_area_px: float = Field(2000, gt=0)

    @model_validator(mode="after")
    def _area_order(self) -> PaperDetectionConfig:
        if self.min_area_px >= self.max_area_px:
            raise ValueError(
                f"detection.paper.min_area_px ({self.min_area_px} px) must be below "
                f"max_area_px ({self.max_area_px} px)"
            )
        return self


class DetectionConfig(Strict):
    """How circle centres are found on the plate image."""

    preset: Preset = "default"
    paper: PaperDetectionConfig = PaperDetectionConfig()
    min_diameter_ratio: float = Field(
        0.6, gt=0, lt=1, description="smallest blob accepted, as a fraction of the lattice's circle diameter"
    )
    max_diameter_ratio: float = Field(1.5, gt=1, le=3)
    max_roundness_error: float = Field(
        0.25, gt=0, le=1, description="1 - (4 pi area / perimeter^2) allowed for a circle blob"
    )
    lattice_tolerance: float = Field(
        0.25, gt=0, lt=0.5, description="largest distance of a blob from its lattice node, in pitches"
    )
    max_missing: int = Field(10, ge=0, description="circles that may be missing or covered")


class CalibrationConfig(Strict):
    """Which model maps pixels to table mm, and when a new fit is refused."""

    model: ModelName = "auto"
    max_cv_rms_mm: float = Field(
        0.25, gt=0, description="recalibration is refused above this cross-validated RMS error"
    )
    max_cv_error_mm: float = Field(
        1.0, gt=0, description="recalibration is refused above this cross-validated max error"
    )
    cv_folds: int = Field(5, ge=2, le=1000, description="k of k-fold cross-validation")
    active_path: Path = Field(Path("calibration/active.json"), description="the calibration run-cell uses")
    backup_dir: Path = Field(Path("calibration/backups"))


class CellConfig(Strict):
    """The whole cell."""

    plate: PlateConfig = PlateConfig()
    detection: DetectionConfig = DetectionConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    camera: CameraConfig = CameraConfig()
    arm: ArmConfig = ArmConfig()
    planning: PlanningConfig = PlanningConfig()
    run: RunConfig = RunConfig()
    sim: SimConfig = SimConfig()
    parts: PartsConfig = PartsConfig()
    service: ServiceConfig = ServiceConfig()


def _format_errors(path: Path | str, err: ValidationError) -> str:
    parts = []
    for e in err.errors():
        loc = ".".join(str(x) for x in e["loc"]) or "(top level)"
        msg = e["msg"].removeprefix("Value error, ")
        parts.append(f"{loc}: {msg}")
    return f"{path}: invalid config: " + "; ".join(parts)


def load_config(path: str | Path | None) -> CellConfig:
    """Read and validate a TOML config; None gives the built-in defaults."""
    if path is None:
        return CellConfig()
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read config: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    try:
        return CellConfig.model_validate(data)
    except ValidationError as e:
        raise ConfigError(_format_errors(path, e)) from None

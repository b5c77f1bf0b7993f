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
from cell.history.config import HistoryConfig
from cell.logretention import LogsConfig
from cell.run_config import PlanningConfig, RunConfig, SimConfig
from cell.service.config import ServiceConfig
from cell.shifts import ShiftsConfig
from cell.telemetry.config import TelemetryConfig
from cell.vision.config import PartsConfig, Preset
from drivers.arm.config import ArmConfig, RobotServerConfig
from drivers.cameras.config import CameraConfig
from drivers.config import Strict

Corner = Literal["top-left", "top-right", "bottom-left", "bottom-right"]
ModelName = Literal["auto", "quadratic", "homography", "polynomial", "camera"]


class PlateConfig(Strict):
    """The printed calibration plate; the paper's plate by default."""

    columns: int = Field(
        13, ge=3, le=200, description="circles in each row, along table X; point numbers run row by row from point 1"
    )
    rows: int = Field(12, ge=3, le=200, description="rows of circles, along table Y")
    pitch_x_mm: float = Field(
        22.0, gt=0, le=1000, description="centre-to-centre distance of neighbouring circles along table X (in a row)"
    )
    pitch_y_mm: float = Field(
        16.0, gt=0, le=1000, description="centre-to-centre distance of neighbouring circles along table Y (in a column)"
    )
    diameter_mm: float = Field(
        10.0,
        gt=0,
        le=500,
        description="printed circles' diameter (below both pitches); each found circle's size is checked against it",
    )
    first_point: Corner = Field("top-left", description="image corner where point 1 lies, for a plate seen unrotated")

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

    hsv_lower: tuple[int, int, int] = Field(
        (10, 0, 100),
        description="preset paper: lowest H, S, V (OpenCV scales) of the plate's paper; pixels outside the range are circles",
    )
    hsv_upper: tuple[int, int, int] = Field(
        (250, 250, 250),
        description="preset paper: highest H, S, V (OpenCV scales) of the plate's paper; pixels outside the range are circles",
    )
    min_area_px: float = Field(
        500, ge=0, description="preset paper: a circle's contour must enclose more than this area, image px"
    )
    max_area_px: float = Field(
        2000, gt=0, description="preset paper: a circle's contour must enclose less than this area, image px"
    )

    @model_validator(mode="after")
    def _area_order(self) -> PaperDetectionConfig:
        if self.min_area_px >= self.max_area_px:
            raise ValueError(
                f"detection.paper.min_area_px ({self.min_area_px} px) must be below max_area_px ({self.max_area_px} px)"
            )
        return self


class DetectionConfig(Strict):
    """How circle centres are found on the plate image."""

    preset: Preset = Field(
        "default",
        description="default: dark blobs on an image pyramid, numbered by lattice growth, centres refined to "
        "sub-pixel; paper: the published threshold and areas ([detection.paper]), whole-pixel centres, none missing",
    )
    paper: PaperDetectionConfig = PaperDetectionConfig()
    min_diameter_ratio: float = Field(
        0.6, gt=0, lt=1, description="smallest blob accepted, as a fraction of the lattice's circle diameter"
    )
    max_diameter_ratio: float = Field(
        1.5, gt=1, le=3, description="largest blob accepted, as a multiple of the lattice's circle diameter"
    )
    max_roundness_error: float = Field(
        0.25, gt=0, le=1, description="1 - (4 pi area / perimeter^2) allowed for a circle blob"
    )
    lattice_tolerance: float = Field(
        0.25, gt=0, lt=0.5, description="largest distance of a blob from its lattice node, in pitches"
    )
    max_missing: int = Field(10, ge=0, description="circles that may be missing or covered")


class CalibrationConfig(Strict):
    """Which model maps pixels to table mm, and when a new fit is refused."""

    model: ModelName = Field(
        "auto",
        description="pixel -> table mm map to fit: auto fits every one and keeps the lowest cross-validated RMS; "
        "quadratic (the paper's Eq. 3), homography, polynomial (degree 3 or 4), camera (lens model, ray onto the table)",
    )
    max_cv_rms_mm: float = Field(
        0.25, gt=0, description="recalibration is refused above this cross-validated RMS error"
    )
    max_cv_error_mm: float = Field(
        1.0, gt=0, description="recalibration is refused above this cross-validated max error"
    )
    cv_folds: int = Field(5, ge=2, le=1000, description="k of k-fold cross-validation")
    active_path: Path = Field(Path("calibration/active.json"), description="the calibration run-cell uses")
    backup_dir: Path = Field(
        Path("calibration/backups"),
        description="where a recalibration copies the active_path file it replaces (name + date and time)",
    )
    max_pitch_ratio_error_pct: float = Field(
        2.0,
        gt=0,
        le=50,
        description="the smallest pitch-ratio error refused: the plate's circles, mapped back through the "
        "configured pitches, wider than tall (or taller than wide) by more than this and by more than "
        "pitch_ratio_refuse_sd standard errors of the measurement on that image (pitch_x_mm / pitch_y_mm is not "
        "the plate's: a wrong pitch, X and Y swapped)",
    )
    pitch_ratio_refuse_sd: float = Field(
        4.0,
        gt=0,
        le=20,
        description="a pitch ratio is refused only when it is off by more than this many standard errors of the "
        "circles' own measurement (their spread over the plate), and more than max_pitch_ratio_error_pct",
    )
    camera_height_min_mm: float = Field(
        50.0, gt=0, description="a fitted camera surely closer to the table (3 standard deviations) is refused"
    )
    camera_height_max_mm: float = Field(
        3000.0, gt=0, description="a fitted camera surely farther from the table (3 standard deviations) is refused"
    )
    camera_height_mm: float | None = Field(
        None,
        gt=0,
        description="the camera's height above the table as installed (the lens's centre, measured), or None: "
        "the plate's fit alone. Seen nearly straight on, one plate image cannot tell a near camera with a short "
        "lens from a far one with a long lens; the part-height correction needs the height",
    )
    camera_height_sd_mm: float = Field(
        5.0, gt=0, description="how well camera_height_mm is known (one standard deviation)"
    )
    max_height_cost_mm: float = Field(
        0.5,
        gt=0,
        description="a warning when the camera's height is known so poorly (3 standard deviations) that the "
        "tallest part's centre could be this far off somewhere in the field (the parts goal: 0.5 mm); the remedy "
        "is a measured camera_height_mm or a raised plate image",
    )
    max_scale_change_pct: float = Field(
        2.0,
        gt=0,
        le=100,
        description="a new calibration whose scale (mm per px at the image centre) differs more "
        "from the active one's needs --accept-change",
    )
    max_origin_change_mm: float = Field(
        5.0, gt=0, description="a new calibration that maps the image centre this much elsewhere needs --accept-change"
    )
    lock_wait_s: float = Field(120.0, ge=0, le=3600, description="how long a recalibration waits for another to finish")
    check_max_mm: float = Field(
        0.3, gt=0, description="check-calibration fails when a plate point maps further than this from where it lies"
    )

    @model_validator(mode="after")
    def _heights_ordered(self) -> CalibrationConfig:
        if self.camera_height_min_mm >= self.camera_height_max_mm:
            raise ValueError(
                f"calibration.camera_height_min_mm ({self.camera_height_min_mm}) must be below "
                f"camera_height_max_mm ({self.camera_height_max_mm})"
            )
        return self


class DriftConfig(Strict):
    """Reference marks that stay in view while the cell works (printed dots at the table's edge,
    a few plate circles): each frame they are measured and mapped through the calibration; when
    they have moved the cell stops before the next pick. No marks: no watch."""

    marks_mm: list[tuple[float, float]] = Field(
        default_factory=list, description="centres of the dark round marks, table mm (the plate frame)"
    )
    mark_diameter_mm: float = Field(
        1.5, gt=0, le=100, description="small enough (under parts.segment.noise_area_mm2) that locate ignores the marks"
    )
    limit_mm: float = Field(
        0.25,
        gt=0,
        le=50,
        description="stop when a mark maps further than this from its place: below 0.3 mm by more than the "
        "measurement noise, so that a 0.3 mm bump is caught",
    )
    search_mm: float = Field(3.0, gt=0, le=50, description="how far from its place a mark is looked for")


class CellConfig(Strict):
    """The whole cell."""

    plate: PlateConfig = PlateConfig()
    detection: DetectionConfig = DetectionConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    drift: DriftConfig = DriftConfig()
    camera: CameraConfig = CameraConfig()
    arm: ArmConfig = ArmConfig()
    robot_server: RobotServerConfig = RobotServerConfig()
    planning: PlanningConfig = PlanningConfig()
    run: RunConfig = RunConfig()
    logs: LogsConfig = LogsConfig()
    sim: SimConfig = SimConfig()
    parts: PartsConfig = PartsConfig()
    service: ServiceConfig = ServiceConfig()
    history: HistoryConfig = HistoryConfig()
    shifts: ShiftsConfig = ShiftsConfig()
    telemetry: TelemetryConfig = TelemetryConfig()


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

"""Settings for finding and classifying parts. Sizes are table millimetres, never pixels:
the calibration's local scale converts them, so one config fits any camera distance."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from drivers.config import Strict

Preset = Literal["default", "paper"]  # "paper": the published thresholds (section III-D)


def _ordered(name: str, pair: tuple[float, float]) -> None:
    if pair[0] >= pair[1]:
        raise ValueError(f"{name} must be (low, high) with low < high, got {pair}")


class PaperPartsConfig(Strict):
    """The paper's segmentation (section III-D), reused for parts as the paper did."""

    hsv_lower: tuple[int, int, int] = (10, 0, 100)
    hsv_upper: tuple[int, int, int] = (250, 250, 250)
    min_elongation_bolt: float = Field(
        1.6, gt=1, description="bounding-box long/short side above which a blob is a bolt"
    )


class SegmentConfig(Strict):
    """The default segmentation: a threshold that follows the local backlight level."""

    threshold_fraction: float = Field(
        0.5, gt=0.05, lt=0.95, description="a pixel is part when darker than this fraction of the local backlight"
    )
    min_background_level: float = Field(
        40.0, ge=0, le=255, description="grey level below which the backlight is too dark to see parts"
    )
    noise_area_mm2: float = Field(2.0, ge=0, description="blobs and holes smaller than this are ignored")


class NutConfig(Strict):
    """Hex nuts lying flat (M5 to M10)."""

    across_flats_mm: tuple[float, float] = (6.5, 19.0)
    hole_ratio: tuple[float, float] = Field(
        (0.25, 0.8), description="hole diameter / across flats (ISO nuts: about 0.5; less seen off-axis)"
    )
    max_hole_offset: float = Field(0.15, gt=0, description="hole centre offset / across flats")
    min_hexagonality: float = Field(0.45, ge=0, le=2)
    max_elongation: float = Field(1.35, gt=1)
    thickness_per_across_flats: float = Field(
        0.5, gt=0, le=2, description="thickness estimate from size (ISO 4032: about 0.5)"
    )
    reference_height_mm: float | None = Field(
        None, ge=0, description="plane the centroid is mapped on; None: half the estimated thickness"
    )

    @model_validator(mode="after")
    def _pairs(self) -> NutConfig:
        _ordered("parts.nut.across_flats_mm", self.across_flats_mm)
        _ordered("parts.nut.hole_ratio", self.hole_ratio)
        return self


class BoltConfig(Strict):
    """Hex-head bolts lying on their side (M5 to M8, 12 to 40 mm under the head)."""

    shaft_mm: tuple[float, float] = (3.8, 10.0)
    head_width_mm: tuple[float, float] = (7.0, 18.0)
    length_mm: tuple[float, float] = Field(
        (13.0, 56.0), description="overall, head included, as seen (perspective adds up to ~10 %)"
    )
    min_head_to_shaft: float = Field(1.25, gt=1, description="head width / shaft width")
    max_profile_misfit: float = Field(
        0.15, gt=0, le=1, description="fraction of the length whose width fits neither head nor shaft"
    )
    head_across_flats_per_width: float = Field(
        0.866, gt=0, le=1, description="head across flats / its top-view width (a hexagon on a flat: cos 30)"
    )
    reference_height_mm: float | None = Field(
        None, ge=0, description="plane the centroid is mapped on; None: half the head's across flats"
    )

    @model_validator(mode="after")
    def _pairs(self) -> BoltConfig:
        for name in ("shaft_mm", "head_width_mm", "length_mm"):
            _ordered(f"parts.bolt.{name}", getattr(self, name))
        return self


class PartsConfig(Strict):
    """How parts are found, told apart and located."""

    preset: Preset = "default"
    height_correction: bool | None = Field(
        None, description="map centroids at the part's reference height; None: on, except in the paper preset"
    )
    paper: PaperPartsConfig = PaperPartsConfig()
    segment: SegmentConfig = SegmentConfig()
    nut: NutConfig = NutConfig()
    bolt: BoltConfig = BoltConfig()
    min_part_area_mm2: float = Field(15.0, ge=0, description="smaller blobs are debris (unknown)")
    max_part_width_mm: float = Field(
        25.0, gt=0, description="widest part expected (its narrow way); sizes the backlight estimate"
    )
    jaw_clearance_mm: float = Field(3.0, ge=0, description="added to the part's width for the jaw opening")
    jaw_max_opening_mm: float = Field(
        30.0,
        gt=0,
        le=500,
        description="the gripper's widest opening: a taught part wider where it is gripped is refused",
    )
    jaw_face_width_mm: float = Field(
        8.0, gt=0, le=200, description="how wide the jaw faces are (a taught part is gripped across that band)"
    )
    jaw_thickness_mm: float = Field(
        5.0, gt=0, le=100, description="how deep each jaw is: a taught part whose jaws would touch a neighbour waits"
    )

    @property
    def tallest_centre_height_mm(self) -> float:
        """The highest plane a configured part's centre is mapped on (cell.vision.locate's
        reference_height_mm at the largest sizes allowed): where a wrong camera height costs most.
        Nuts: half their thickness; bolts lying: their axis, half the head's across flats."""
        nut = self.nut.reference_height_mm
        if nut is None:
            nut = 0.5 * self.nut.thickness_per_across_flats * self.nut.across_flats_mm[1]
        bolt = self.bolt.reference_height_mm
        if bolt is None:
            bolt = 0.5 * self.bolt.head_across_flats_per_width * self.bolt.head_width_mm[1]
        return float(max(nut, bolt))

    @property
    def use_height_correction(self) -> bool:
        if self.height_correction is None:
            return self.preset == "default"
        return self.height_correction

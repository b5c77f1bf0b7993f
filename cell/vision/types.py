"""What the vision step hands to planning: one record per blob on the table."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

PartClass = Literal["bolt", "nut", "unknown"]


@dataclass
class LocatedPart:
    """A part found in one frame. Table coordinates are in the calibration's plate frame, mm."""

    id: int
    cls: str  # bolt, nut, a taught type's name, or unknown
    reason: str  # why this class (and, for unknown, why it is not picked)
    pixel: tuple[float, float]  # sub-pixel centroid of the outline, image px
    table_mm: tuple[float, float]  # footprint centre on the table (height-corrected), table mm
    angle_deg: float | None  # bolts: axis angle in table coordinates, 0-180; else None
    pick: bool
    grasp_mm: tuple[float, float] | None = None  # where the jaws close, table mm
    jaw_opening_mm: float | None = None  # jaw opening needed to close on the part
    head_mm: tuple[float, float] | None = None  # bolts: head end, table mm
    features: dict = field(default_factory=dict)  # area_mm2, elongation, hexagonality, holes...
    score: float | None = None  # taught types: how well the outline fits the model (0-1)
    outline_px: np.ndarray | None = field(default=None, repr=False, compare=False)  # (N, 1, 2) int32, for drawing


@dataclass
class LocateResult:
    objects: list[LocatedPart]
    image_size: tuple[int, int]
    elapsed_ms: float
    warnings: list[str] = field(default_factory=list)  # e.g. frame too dark: why nothing was found

"""Bolt, nut or unknown, from a blob's shape in millimetres, with the reason why.

Only a clear match is a bolt or a nut: anything else (washers, coins, touching parts,
parts cut by the border, debris, parts in an unexpected pose) is unknown and never picked.
A nut lies flat: a hexagon with one centred round hole. A bolt lies on its side: a
straight shaft of constant width with a clearly wider head at one end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cell.vision.config import PartsConfig
from cell.vision.features import Features, Profile, width_profile
from cell.vision.smallstats import median, percentile
from cell.vision.types import PartClass

UNKNOWN: PartClass = "unknown"
NUT: PartClass = "nut"
BOLT: PartClass = "bolt"
# Area / minimum enclosing circle: a disc about 0.95 (blur, noise), a regular hexagon 0.83.
_ROUND = 0.9
_ROUND_WITH_HOLE = 0.85  # a ring's inner edge lets blur and glare eat more of it
_HEXAGON_ROUNDNESS = 0.75


@dataclass
class Verdict:
    cls: PartClass
    reason: str
    size_mm: dict[str, float] = field(default_factory=dict)
    profile: Profile | None = None  # bolts: width along the axis, head first
    head_width_px: float | None = None  # bolts
    shaft_width_px: float | None = None  # bolts


def classify(
    feat: Features, outline: np.ndarray, mm_per_px: float, config: PartsConfig, view_slope: float = 0.0
) -> Verdict:
    """`mm_per_px` is the calibration's local table-plane scale at the blob; `view_slope`
    the tangent of the angle between the camera's ray to it and the vertical (0 unknown)."""
    area_mm2 = feat.outer_area_px * mm_per_px**2
    if feat.touches_border:
        return Verdict(UNKNOWN, "cut by the image border")
    if area_mm2 < config.min_part_area_mm2:
        return Verdict(UNKNOWN, f"too small ({area_mm2:.1f} mm2): debris")
    if config.preset == "paper":
        return _classify_paper(feat, outline, config)
    if len(feat.holes) >= 2:
        return Verdict(UNKNOWN, f"{len(feat.holes)} holes: parts touching or overlapping")
    if len(feat.holes) == 1:
        return _classify_holed(feat, mm_per_px, config, view_slope)
    if feat.elongation >= config.nut.max_elongation:
        return _classify_elongated(feat, outline, mm_per_px, config, view_slope)
    if feat.roundness >= _ROUND:
        return Verdict(UNKNOWN, "round without a hole (a coin or a plug?)")
    if feat.hexagonality >= config.nut.min_hexagonality and feat.roundness >= _HEXAGON_ROUNDNESS:
        return Verdict(UNKNOWN, "hexagon without a hole (a bolt standing on its head?)")
    if feat.solidity >= 0.85:
        return Verdict(UNKNOWN, "compact, no hole, not hexagonal (a nut on its side?)")
    return Verdict(UNKNOWN, f"matches no part (solidity {feat.solidity:.2f}: touching parts or debris?)")


_ISO_HOLE_RATIO = 0.5  # an ISO nut's hole / across flats, about


def _seen_through(offset_per_hole: float) -> float:
    """How much of a hole one sees through a nut at a slope, as a fraction of its diameter (equal
    areas): its top and bottom openings, shifted by thickness x slope (here per hole diameter),
    overlap only in a lens; 1 straight down, 0 once the shift reaches the hole's width."""
    u = min(max(offset_per_hole, 0.0), 1.0)
    lens = 0.5 * math.acos(u) - 0.5 * u * math.sqrt(1.0 - u * u)  # two circles of diameter 1, u apart
    return math.sqrt(lens / (math.pi / 4.0))


def _classify_holed(feat: Features, mm_per_px: float, config: PartsConfig, view_slope: float) -> Verdict:
    """Seen at a slope, a nut's flanks widen its silhouette by thickness x slope along the
    ray: area grows by about that times the across-flats width, elongation likewise."""
    cfg = config.nut
    flank = cfg.thickness_per_across_flats * view_slope
    across_flats_mm = math.sqrt(feat.outer_area_px / (math.sqrt(3) / 2 + flank)) * mm_per_px
    hole = feat.holes[0]
    hole_mm = math.sqrt(4 * hole.area_px / math.pi) * mm_per_px
    offset_mm = math.dist(hole.centroid_px, feat.outer_centroid_px) * mm_per_px
    size = {"across_flats_mm": across_flats_mm, "hole_mm": hole_mm}
    if feat.hexagonality < cfg.min_hexagonality and feat.roundness >= _ROUND_WITH_HOLE:
        return Verdict(UNKNOWN, "round with a hole: a washer (not picked)", size)
    checks = [
        (feat.hexagonality >= cfg.min_hexagonality, f"outline not hexagonal ({feat.hexagonality:.2f})"),
        (feat.elongation <= cfg.max_elongation + flank, f"elongated ({feat.elongation:.2f}): parts touching?"),
        (
            cfg.across_flats_mm[0] <= across_flats_mm <= cfg.across_flats_mm[1],
            f"across flats {across_flats_mm:.1f} mm outside {cfg.across_flats_mm[0]:g}-{cfg.across_flats_mm[1]:g} mm",
        ),
        (
            cfg.hole_ratio[0] * _seen_through(cfg.thickness_per_across_flats * view_slope / _ISO_HOLE_RATIO)
            <= hole_mm / across_flats_mm
            <= cfg.hole_ratio[1],
            f"hole {hole_mm:.1f} mm does not fit a nut of {across_flats_mm:.1f} mm",
        ),
        (offset_mm <= cfg.max_hole_offset * across_flats_mm, f"hole off centre by {offset_mm:.1f} mm"),
    ]
    for ok, why in checks:
        if not ok:
            return Verdict(UNKNOWN, f"a hole, but not a nut: {why}", size)
    return Verdict(NUT, f"hexagon with a round hole, {across_flats_mm:.1f} mm across flats", size)


def _classify_elongated(
    feat: Features, outline: np.ndarray, mm_per_px: float, config: PartsConfig, view_slope: float = 0.0
) -> Verdict:
    """Seen at a slope, a lying bolt's head (about as tall as it is wide) throws its top edge over
    the shaft by its height x slope, and the shaft its own over its end: those stretches are
    neither head nor shaft wide, and are left out of the shaft's evenness check."""
    cfg = config.bolt
    prof = width_profile(outline, feat.centroid_px, feat.axis_px)
    w = prof.widths_px
    n = len(w)
    head_px = percentile(w[: max(3, n // 4)], 90)
    shaft_px = median(w[int(0.45 * n) : max(int(0.9 * n), int(0.45 * n) + 1)])
    peak = int(np.argmax(w[: max(3, n // 3)]))
    below = np.flatnonzero(w[peak:] < (head_px + shaft_px) / 2)
    head_len = peak + int(below[0]) if below.size else n
    size = {
        "length_mm": n * mm_per_px,
        "head_width_mm": head_px * mm_per_px,
        "shaft_mm": shaft_px * mm_per_px,
    }
    ratio = head_px / max(shaft_px, 1e-9)
    if ratio < cfg.min_head_to_shaft:
        return Verdict(UNKNOWN, f"elongated without a head (a nut on its side?): head/shaft {ratio:.2f}", size)
    # px along the axis, at the table's scale: the head's top edge over the shaft, the shaft's over its end
    start, end = head_len + int(math.ceil(head_px * view_slope)), n - 2 - int(math.ceil(shaft_px * view_slope))
    if end - start < 3:
        start, end = head_len, n - 2
    shaft = w[start : max(start, end)]
    misfit = float(np.mean(np.abs(shaft - shaft_px) > max(0.2 * shaft_px, 1.5))) if shaft.size else 1.0
    checks = [
        (cfg.length_mm[0] <= size["length_mm"] <= cfg.length_mm[1], f"length {size['length_mm']:.1f} mm out of range"),
        (cfg.shaft_mm[0] <= size["shaft_mm"] <= cfg.shaft_mm[1], f"shaft {size['shaft_mm']:.1f} mm out of range"),
        (
            cfg.head_width_mm[0] <= size["head_width_mm"] <= cfg.head_width_mm[1],
            f"head {size['head_width_mm']:.1f} mm out of range",
        ),
        (2 <= head_len <= 0.45 * n, "no distinct head at one end"),
        (misfit <= cfg.max_profile_misfit, f"uneven shaft ({misfit:.0%} misfit): parts touching?"),
    ]
    for ok, why in checks:
        if not ok:
            return Verdict(UNKNOWN, f"elongated, but not a bolt: {why}", size)
    return Verdict(
        BOLT,
        f"hex head and shaft, {size['shaft_mm']:.1f} mm x {size['length_mm']:.0f} mm",
        size,
        prof,
        head_px,
        shaft_px,
    )


def _classify_paper(feat: Features, outline: np.ndarray, config: PartsConfig) -> Verdict:
    """The paper's rule as far as it is described: a long bounding box is a bolt."""
    if feat.elongation >= config.paper.min_elongation_bolt:
        prof = width_profile(outline, feat.centroid_px, feat.axis_px)
        return Verdict(BOLT, f"bounding box elongation {feat.elongation:.2f} (paper preset)", {}, prof)
    return Verdict(NUT, f"bounding box elongation {feat.elongation:.2f} (paper preset)")

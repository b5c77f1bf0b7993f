"""Where a bolt lying on its side really is: its top-view footprint from a perspective silhouette.

A bolt's silhouette is not its footprint: seen off-axis, the end faces of the head and
the tip disc tilt into view and stretch the outline along the axis, and the head (taller,
wider) gains more than the shaft, so the silhouette centroid creeps towards the head by
up to about 1 mm. Instead, measure features that perspective leaves in place and rebuild
the footprint from them, all on the plane of the bolt's axis:

- the head's silhouette is centrally symmetric about the head's centre (a hex prism
  lying on a flat), so the midpoint of its two crossings of one width level is the
  head centre; its length there exceeds the head height by a known amount;
- the tip disc adds (shaft diameter / 2) x the view slope along the axis to the length.

The view slope comes from the camera pose the calibration stores; without one it is
taken as zero (a camera straight above).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cell.vision.features import Profile


@dataclass
class BoltPose:
    centre_mm: np.ndarray  # footprint centre (area centroid seen from straight above)
    head_mm: np.ndarray  # centre of the head
    grasp_mm: np.ndarray  # middle of the shaft
    angle_deg: float  # axis direction, 0-180, table frame
    shaft_mm: float
    length_mm: float  # overall, head included
    head_length_mm: float  # along the axis
    head_across_flats_mm: float


def _crossing(pos: np.ndarray, w: np.ndarray, level: float, i: int, j: int) -> float:
    """Position where the width passes `level` between bins i and j (linear)."""
    if w[j] == w[i]:
        return float((pos[i] + pos[j]) / 2)
    t = (level - w[i]) / (w[j] - w[i])
    return float(pos[i] + np.clip(t, 0.0, 1.0) * (pos[j] - pos[i]))


def bolt_pose(
    prof: Profile,
    head_width_px: float,
    shaft_width_px: float,
    mapper,
    axis_height_mm: float,
    table_mm_per_px: float,
    head_across_flats_per_width: float,
) -> BoltPose:
    """Footprint, head, grasp point and axis angle of a bolt lying on its side.

    `mapper` is a Calibration (or PixelScale); `axis_height_mm` the plane of the axis
    (0 maps on the table and ignores parallax).
    """
    w, pos = prof.widths_px, prof.positions_px
    level = (head_width_px + shaft_width_px) / 2
    above = np.flatnonzero(w >= level)
    first = int(above[0]) if above.size else 0
    last = first
    while last + 1 < len(w) and w[last + 1] >= level:
        last += 1
    u_in = _crossing(pos, w, level, first - 1, first) if first > 0 else 0.0
    u_out = _crossing(pos, w, level, last, last + 1) if last + 1 < len(w) else float(pos[last])
    # The axis is the shaft's midline: the head's outline is skewed by perspective, which
    # tilts the blob's principal axis on short bolts by up to a degree or so.
    shaft = slice(last + 2, len(w) - 2)
    if len(pos[shaft]) >= 5:
        slope, offset = np.polyfit(pos[shaft], prof.centres_px[shaft], 1)
    else:
        slope, offset = 0.0, float(np.median(prof.centres_px))
    a = prof.axis_px
    n = np.array([-a[1], a[0]])
    pts = np.array([prof.origin_px + u * a + (offset + slope * u) * n for u in (u_in, u_out, prof.length_px)])
    head_in, head_out, tip = mapper.pixel_to_table_mm(pts, height_mm=axis_height_mm)
    axis = tip - head_in
    axis /= max(float(np.hypot(*axis)), 1e-9)
    head = (head_in + head_out) / 2
    camera = getattr(mapper, "camera", None)
    scale = table_mm_per_px
    slope = across = 0.0
    if camera is not None and axis_height_mm > 0:
        c = camera.center_table_mm
        scale *= 1.0 - axis_height_mm / c[2]
        view = (head - c[:2]) / (c[2] - axis_height_mm)
        slope = abs(float(np.dot(view, axis)))
        across = abs(float(view[0] * axis[1] - view[1] * axis[0]))
    # Seen at a slant across its axis the shaft's silhouette is wider by 1 / cos(slant): the rays
    # graze the cylinder. The head's is not (a hexagon on a flat, slants under 30 degrees).
    e, d = head_width_px * scale, shaft_width_px * scale / math.hypot(1.0, across)
    across_flats = head_across_flats_per_width * e
    stretch = across_flats / 2 * slope  # how far each end face tilts out along the axis
    k = max(float(np.dot(head_out - head_in, axis)) - 2 * stretch * (e - d) / e, 0.1)
    tip_true = tip - d / 2 * slope * axis
    junction = head + k / 2 * axis
    L = max(float(np.dot(tip_true - junction, axis)), 0.1)
    u_c = (k * e * (-k / 2) + L * d * (L / 2)) / (k * e + L * d)
    return BoltPose(
        centre_mm=junction + u_c * axis,
        head_mm=head,
        grasp_mm=junction + L / 2 * axis,
        angle_deg=math.degrees(math.atan2(axis[1], axis[0])) % 180.0,
        shaft_mm=d,
        length_mm=k + L,
        head_length_mm=k,
        head_across_flats_mm=across_flats,
    )

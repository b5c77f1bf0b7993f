"""Where a bolt lying on its side really is: its top-view footprint from a perspective silhouette.

A bolt's silhouette is not its footprint: seen off-axis, the end faces of the head and
the tip disc tilt into view and stretch the outline along the axis, and the head (taller,
wider) gains more than the shaft, so the silhouette centroid creeps towards the head by
up to about 1 mm. Instead, measure features that perspective leaves in place and rebuild
the footprint from them, all on the plane of the bolt's axis:

- the head's two crossings of one width level (halfway between the head's and the shaft's) and
  the tip's (half the shaft's width), measured on the sub-pixel outline mapped onto the plane of
  the axis, in millimetres (issue 29: at 0.3-0.45 mm/px a pixel is a tenth of the head);
- each less its offset from its end face on the shadow of the bolt as first estimated (a hex
  prism on a flat and a cylinder, seen from the camera centre): the end faces tilt into view and
  shear across, the tip's disc reaches out by about (shaft diameter / 2) x the view slope.

The view slope comes from the camera pose the calibration stores; without one it is
taken as zero (a camera straight above), and the first estimate stands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from cell.vision.features import Profile
from cell.vision.smallstats import line_fit, median


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


Sides = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # (u, v) of each side, u rising


def _sides(poly: np.ndarray) -> Sides:
    """A closed polygon ((N, 2): u along the axis, v across) as its two sides from its lowest u to its
    highest, each with u made non-decreasing (a side that turns back on itself, as the outline's noise
    does by a fraction of a pixel, keeps its farthest reach)."""
    i0, i1 = int(np.argmin(poly[:, 0])), int(np.argmax(poly[:, 0]))
    if i0 <= i1:
        one, other = poly[i0 : i1 + 1], np.concatenate((poly[i1:], poly[: i0 + 1]))[::-1]
    else:
        one, other = np.concatenate((poly[i0:], poly[: i1 + 1])), poly[i1 : i0 + 1][::-1]
    return (np.maximum.accumulate(one[:, 0]), one[:, 1], np.maximum.accumulate(other[:, 0]), other[:, 1])


def _widths(polygons: list[Sides], q: np.ndarray) -> np.ndarray:
    """The width across the axis of the union of polygons (each as its two sides) at each u of `q`,
    linear between their vertices; 0 outside them."""
    a, b = (np.interp(q, u, v, left=np.nan, right=np.nan) for u, v in (polygons[0][:2], polygons[0][2:]))
    top, bottom = np.fmax(a, b), np.fmin(a, b)
    for u1, v1, u2, v2 in polygons[1:]:  # NaN where a polygon does not reach: fmax and fmin pass it by
        a, b = np.interp(q, u1, v1, left=np.nan, right=np.nan), np.interp(q, u2, v2, left=np.nan, right=np.nan)
        top, bottom = np.fmax(top, np.fmax(a, b)), np.fmin(bottom, np.fmin(a, b))
    w = top - bottom
    w[np.isnan(w)] = 0.0
    return w


_GRID = np.linspace(-1.0, 1.0, 41)  # where the widths are taken about a crossing, in windows
_SHAFT_STEPS = np.linspace(0.3, 0.8, 6)  # where along the shaft its width is taken (a fraction of it)


def _crossing_at(q: np.ndarray, w: np.ndarray, level: float, guess: float, rising: bool) -> float:
    """Where the widths `w` at the sorted `q` pass `level` nearest `guess`, linear between them
    (`rising`: growing through it in the +u direction); `guess` where they do not."""
    w = w - level
    sign = w >= 0 if rising else w < 0
    i = (~sign[:-1] & sign[1:]).nonzero()[0]
    if not i.size:
        return guess
    j = int(i[np.argmin(np.abs(q[i] - guess))]) if i.size > 1 else int(i[0])
    # in Python floats (the same arithmetic as numpy's scalars, without their overhead)
    a, b, q0, q1 = float(w[j]), float(w[j + 1]), float(q[j]), float(q[j + 1])
    f = a / (a - b) if a != b else 0.5
    return q0 + f * (q1 - q0)


def axis_points_px(prof: Profile, head_width_px: float, shaft_width_px: float) -> np.ndarray:
    """(3, 2) image pixels on the shaft's midline where the profile's width crosses halfway between
    the head's and the shaft's (the head's back, its front) and at the profile's far end (the tip):
    bolt_pose's first estimate of the bolt's axis, before the outline measures it."""
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
        slope, offset = line_fit(pos[shaft], prof.centres_px[shaft])
    else:
        slope, offset = 0.0, median(prof.centres_px)
    a = prof.axis_px
    n = np.array([-a[1], a[0]])
    return np.array([prof.origin_px + u * a + (offset + slope * u) * n for u in (u_in, u_out, prof.length_px)])


def bolt_pose(
    prof: Profile,
    head_width_px: float,
    shaft_width_px: float,
    mapper,
    axis_height_mm: float,
    table_mm_per_px: float,
    head_across_flats_per_width: float,
    outline_mm: np.ndarray | None = None,
    edge_px: float = 0.5,
    axis_on_table_mm: np.ndarray | None = None,
) -> BoltPose:
    """Footprint, head, grasp point and axis angle of a bolt lying on its side.

    `mapper` is a Calibration (or PixelScale); `axis_height_mm` the plane of the axis
    (0 maps on the table and ignores parallax). `outline_mm`: the (sub-pixel) outline the profile
    was taken from, mapped onto the table plane, `edge_px` how far the true edge lies outside it.
    With it the widths and ends are measured in millimetres on the plane of the axis, exactly on
    the outline: not in the image's pixels, which a wide lens stretches unevenly (a bolt near the
    corner of a -12 % barrel lens read up to 1 mm long in the head), nor in the profile's 1-px bins
    (whose widest point stands for the whole bin: the head read 0.4 px long on average).
    `axis_on_table_mm`: axis_points_px(prof, head_width_px, shaft_width_px) mapped onto the table
    plane already (locate maps every part's in one call with the outlines); the mapper must then
    lift points (lift_mm), as pixel_to_table_mm does after its mapping.
    """
    if axis_on_table_mm is None:
        pts = axis_points_px(prof, head_width_px, shaft_width_px)
        head_in, head_out, tip = mapper.pixel_to_table_mm(pts, height_mm=axis_height_mm)
    else:
        head_in, head_out, tip = mapper.lift_mm(np.asarray(axis_on_table_mm, dtype=np.float64), axis_height_mm)
    axis = tip - head_in
    axis /= max(float(np.hypot(*axis)), 1e-9)
    camera = getattr(mapper, "camera", None)
    scale = table_mm_per_px
    if camera is not None and axis_height_mm > 0:
        scale *= 1.0 - axis_height_mm / camera.center_table_mm[2]
    e, d = head_width_px * scale, shaft_width_px * scale
    measured = None
    if outline_mm is not None and len(outline_mm) >= 3 and hasattr(mapper, "lift_mm"):
        ring = mapper.lift_mm(np.asarray(outline_mm, dtype=np.float64), axis_height_mm) - head_in
        edge = edge_px * scale
        uv = np.column_stack((ring @ axis, ring @ np.array([-axis[1], axis[0]])))
        outline = [_sides(uv)]
        u_out = float(np.dot(head_out - head_in, axis))
        u_tip = float(uv[:, 0].max()) + edge
        # The widths about both crossings of the 1-px profile (a wide lens's corner stretches it by up
        # to 2 px), in the head's middle and along the shaft's.
        window = 4.0 * scale
        q_in, q_out = window * _GRID, u_out + window * _GRID
        q_head = u_out / 2 + np.array([-0.2, 0.0, 0.2]) * u_out
        q_shaft = u_out + _SHAFT_STEPS * (u_tip - u_out)
        q_tip = u_tip + window * _GRID
        g = len(_GRID)
        w = _widths(outline, np.concatenate((q_in, q_out, q_tip, q_head, q_shaft))) + 2 * edge
        w_in, w_out, w_tip = w[:g], w[g : 2 * g], w[2 * g : 3 * g]
        e, d = median(w[3 * g : 3 * g + 3]), median(w[3 * g + 3 :])
        # the tip where the shaft's width falls to half (its farthest point is the outline's noise's)
        u_tip = _crossing_at(q_tip, w_tip, d / 2, u_tip, False)
        level = (e + d) / 2  # the silhouette's widths: the model's crossings are taken at the same
        u_in = _crossing_at(q_in, w_in, level, 0.0, True)
        u_out = _crossing_at(q_out, w_out, level, u_out, False)
        measured = (head_in, u_in, u_out, u_tip)
        shaft_level = d / 2
        head_in, head_out, tip = (head_in + t * axis for t in (u_in, u_out, u_tip))
    head = (head_in + head_out) / 2
    slope = across = 0.0
    if camera is not None and axis_height_mm > 0:
        c = camera.center_table_mm
        view = (head - c[:2]) / (c[2] - axis_height_mm)
        slope = abs(float(np.dot(view, axis)))
        across = abs(float(view[0] * axis[1] - view[1] * axis[0]))
    # Seen at a slant across its axis the shaft's silhouette is wider by 1 / cos(slant): the rays
    # graze the cylinder. The head's (a hexagon on a flat) only beyond a slope of tan(30 deg), where
    # its top edge passes its side corner: by 1/2 + sqrt(3)/2 x the slope (4.6 % at 0.63).
    d /= math.hypot(1.0, across)
    e /= max(1.0, 0.5 + math.sqrt(3) / 2 * across)
    across_flats = head_across_flats_per_width * e
    stretch = across_flats / 2 * slope  # how far each end face tilts out along the axis
    k = max(float(np.dot(head_out - head_in, axis)) - 2 * stretch * (e - d) / e, 0.1)
    # The tip disc's top or bottom edge reaches out along the axis by d / 2 x the slope of the view
    # at the tip (on a long bolt not the head's: 0.1 further across 40 mm at 400 mm).
    tip_slope = 0.0
    if camera is not None and axis_height_mm > 0:
        tip_slope = abs(float(np.dot((tip - c[:2]) / (c[2] - axis_height_mm), axis)))
    # (measured at half its width, the tip's disc reaches sqrt(3)/2 of that)
    tip_true = tip - (math.sqrt(3) / 2 if measured is not None else 1.0) * d / 2 * tip_slope * axis
    junction = head + k / 2 * axis
    L = max(float(np.dot(tip_true - junction, axis)), 0.1)
    if measured is not None and camera is not None and axis_height_mm > 0:
        # The same edges on the bolt's own shadow as this pose has it: how far each crossing lies from
        # its end face there (the head's end faces seen at a slant, sheared across as well, the tip
        # disc) is how far the measured ones lie from theirs.
        k, L, junction = _faces_from_model(
            measured, (level, shaft_level), axis, k, L, junction, d, across_flats, c, axis_height_mm
        )
        head = junction - k / 2 * axis
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


# A head's corners about its axis seen end on, a shaft's rim (32 points: its sides within 0.005 r).
_HEX = np.column_stack((np.cos(np.deg2rad(60.0 * np.arange(6))), np.sin(np.deg2rad(60.0 * np.arange(6)))))
_RIM = np.column_stack(
    (np.cos(np.linspace(0.0, 2 * np.pi, 32, endpoint=False)), np.sin(np.linspace(0.0, 2 * np.pi, 32, endpoint=False)))
)


def _shadow_sides(
    rings: list[tuple[np.ndarray, np.ndarray, tuple[float, float]]], camera_uvz: np.ndarray, plane_mm: float
) -> list[Sides]:
    """Each prism's shadow seen on the plane `plane_mm` above the table, in the axis's frame: a prism is
    a ring (v across the axis, height z) swept between two u; the camera at (u, v, height)."""
    cu, cv, h = camera_uvz
    out = []
    for v, z, ends in rings:
        f = (h - plane_mm) / np.maximum(h - z, 1e-9)  # a point at height z seen on the plane
        faces = np.empty((len(ends), len(v), 2))  # each end's ring, one after the other
        faces[:, :, 0] = cu + (np.array(ends, dtype=np.float64).reshape(-1, 1) - cu) * f
        faces[:, :, 1] = cv + (v - cv) * f
        pts = faces.reshape(-1, 2)
        hull = cv2.convexHull(pts.astype(np.float32), clockwise=False, returnPoints=False).reshape(-1)
        out.append(_sides(pts[hull]))
    return out


def _faces_from_model(
    measured: tuple[np.ndarray, float, float, float],
    levels: tuple[float, float],
    axis: np.ndarray,
    k: float,
    L: float,
    junction: np.ndarray,
    d: float,
    across_flats: float,
    camera_centre: np.ndarray,
    axis_height_mm: float,
) -> tuple[float, float, np.ndarray]:
    """The head's length, the shaft's and the junction from the measured crossings (origin, back,
    front, tip along `axis` on the plane of the axis), each less its offset from its end face on the
    shadow of the bolt as first estimated (its head a hexagonal prism on a flat, its shaft a cylinder,
    as silhouette.Bolt: the end faces seen at a slant and sheared across, the tip's disc)."""
    origin, u_in, u_out, u_tip = measured
    level, shaft_level = levels  # the head's crossings', the tip's
    r, z = across_flats / math.sqrt(3), across_flats / 2  # the head's corner radius, the axis's height
    front = float(np.dot(junction - origin, axis))
    back = front - k
    c = np.asarray(camera_centre, dtype=np.float64)
    rel = c[:2] - origin
    camera = np.array([rel @ axis, rel[1] * axis[0] - rel[0] * axis[1], c[2]])
    polygons = _shadow_sides(
        [
            (r * _HEX[:, 0], z + r * _HEX[:, 1], (back, front)),
            (d / 2 * _RIM[:, 0], z + d / 2 * _RIM[:, 1], (front, front + L)),
        ],
        camera,
        axis_height_mm,
    )
    window = max(k / 2, 1.0)
    q_in, q_out, q_tip = back + window * _GRID, front + window * _GRID, front + L + window * _GRID
    w = _widths(polygons, np.concatenate((q_in, q_out, q_tip)))
    g = len(_GRID)
    m_in = _crossing_at(q_in, w[:g], level, back, True)
    m_out = _crossing_at(q_out, w[g : 2 * g], level, front, False)
    m_tip = _crossing_at(q_tip, w[2 * g :], shaft_level, front + L, False)
    back, front, tip = u_in - (m_in - back), u_out - (m_out - front), u_tip - (m_tip - front - L)
    k, L = max(front - back, 0.1), max(tip - front, 0.1)
    return k, L, origin + front * axis

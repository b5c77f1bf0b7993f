"""The previous implementation of part location, kept verbatim as the reference the faster code in
cell/vision is pinned against (tests/test_locate_speed.py) and timed beside (scripts/bench_parts.py
--speed): as of commit ecf563f, the shadow model of cell/vision/silhouette.py (pure-Python polygon
geometry per part), the sub-pixel outline of cell/vision/subpixel.py, the body of
cell/vision/locate.py (one mapping call per outline and per centroid), features.hexagonality and
footprint.bolt_pose (a lying bolt's ends from its 1-px width profile; issue 29 measures them on the
outline itself). Segmentation, measurement and classification are the current ones (unchanged, but
for hexagonality).

`locate(image, calibration, config)` runs it.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np

from cell.errors import InputError
from cell.vision import features
from cell.vision.classify import BOLT, NUT, Verdict, classify
from cell.vision.config import PartsConfig
from cell.vision.features import Features, Profile, measure, resample, width_profile
from cell.vision.footprint import BoltPose
from cell.vision.segment import segment, to_gray
from cell.vision.subpixel import EDGE_PX
from cell.vision.types import LocatedPart, LocateResult

_SWEEP_DEG = 12.0  # edges this close to the sweep's direction are the sweep's, not a side's
_RING = 96  # points on a shaft's rim (as the renderer draws it)


def shadow(points_xyz: np.ndarray, camera_centre: np.ndarray) -> np.ndarray:
    """(N, 2) where each point (X, Y, height) is seen on the table plane from the camera centre."""
    p = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(camera_centre, dtype=np.float64)
    k = c[2] / np.maximum(c[2] - p[:, 2], 1e-9)
    return c[:2] + (p[:, :2] - c[:2]) * k[:, None]


def polygon_moments(poly: np.ndarray) -> tuple[float, np.ndarray]:
    """Area (positive) and area centroid of a simple polygon (N, 2)."""
    x, y = poly[:, 0], poly[:, 1]
    xs, ys = np.concatenate((x[1:], x[:1])), np.concatenate((y[1:], y[:1]))
    cross = x * ys - xs * y
    a = cross.sum() / 2
    if abs(a) < 1e-12:
        return 0.0, poly.mean(axis=0)
    return abs(a), np.array([((x + xs) * cross).sum(), ((y + ys) * cross).sum()]) / (6 * a)


def _hull(points: np.ndarray) -> np.ndarray:
    origin = points.mean(axis=0)
    hull = cv2.convexHull((points - origin).astype(np.float32)).reshape(-1, 2)
    return hull.astype(np.float64) + origin


def _union_moments(hulls: list[np.ndarray]) -> tuple[float, np.ndarray]:
    """Area and area centroid of the union of two convex polygons (or of one)."""
    moments = [polygon_moments(h) for h in hulls]
    if len(hulls) == 1:
        return moments[0]
    (a1, c1), (a2, c2) = moments
    inter = _intersection(hulls[0], hulls[1])
    a12, c12 = (0.0, c1) if len(inter) < 3 else polygon_moments(inter)
    area = a1 + a2 - a12
    return area, (a1 * c1 + a2 * c2 - a12 * c12) / max(area, 1e-12)


def _intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The intersection of two convex polygons: `a` clipped by each edge of `b` in turn
    (Sutherland-Hodgman, float64). OpenCV's intersectConvexConvex returns the wrong polygon for
    the head's and the shaft's shadows, which share an edge where they join."""
    if len(b) > len(a):
        a, b = b, a  # the work grows with the clipping polygon's edges
    x, y = b[:, 0], b[:, 1]
    if float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) < 0:
        b = b[::-1]  # counter-clockwise: inside is to the left of every edge
    out = a
    for p, q in zip(b, np.roll(b, -1, axis=0), strict=True):
        if len(out) < 3:
            return np.zeros((0, 2))
        nxt = np.roll(out, -1, axis=0)
        side = (q[0] - p[0]) * (out[:, 1] - p[1]) - (q[1] - p[1]) * (out[:, 0] - p[0])
        side_nxt = np.roll(side, -1)
        inside = side >= 0
        crossing = inside != (side_nxt >= 0)
        t = side / np.where(crossing, side - side_nxt, 1.0)
        cut = out + (nxt - out) * t[:, None]
        out = np.stack([out, cut], axis=1).reshape(-1, 2)[np.stack([inside, crossing], axis=1).reshape(-1)]
    return out


@dataclass(frozen=True)
class Nut:
    """A hexagonal prism lying flat: across flats, thickness, corner direction (table degrees)."""

    across_flats_mm: float
    thickness_mm: float
    corner_deg: float

    def solids(self, centre: np.ndarray) -> list[np.ndarray]:
        r = self.across_flats_mm / math.sqrt(3)
        a = np.deg2rad(self.corner_deg + 60.0 * np.arange(6))
        hexagon = centre + r * np.column_stack([np.cos(a), np.sin(a)])
        z = np.repeat([0.0, self.thickness_mm], 6)
        return [np.column_stack([np.vstack([hexagon, hexagon]), z])]


@dataclass(frozen=True)
class Bolt:
    """A hex-head bolt on its side, head on a flat: head across flats and length, shaft diameter
    and length, axis direction head -> tip (table degrees). Its footprint centre (the top view's
    area centroid) is the origin of its own frame."""

    head_across_flats_mm: float
    head_length_mm: float
    shaft_mm: float
    shaft_length_mm: float
    axis_deg: float

    def solids(self, centre: np.ndarray) -> list[np.ndarray]:
        s, k, d, L = self.head_across_flats_mm, self.head_length_mm, self.shaft_mm, self.shaft_length_mm
        e = 2 * s / math.sqrt(3)  # the head's width seen from above (across corners)
        u0 = -(k * e * (-k / 2) + L * d * (L / 2)) / (k * e + L * d)  # head-shaft junction
        a = math.radians(self.axis_deg)
        axis, side = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
        corners = np.deg2rad(60.0 * np.arange(6))
        ring = np.linspace(0.0, 2 * np.pi, _RING, endpoint=False)
        head_vz = np.column_stack([e / 2 * np.cos(corners), s / 2 + e / 2 * np.sin(corners)])
        shaft_vz = np.column_stack([d / 2 * np.cos(ring), s / 2 + d / 2 * np.sin(ring)])

        def prism(vz: np.ndarray, u_from: float, u_to: float) -> np.ndarray:
            ends = [centre + u * axis + vz[:, :1] * side for u in (u_from, u_to)]
            return np.column_stack([np.vstack(ends), np.concatenate([vz[:, 1], vz[:, 1]])])

        return [prism(head_vz, u0 - k, u0), prism(shaft_vz, u0, u0 + L)]


Shape = Nut | Bolt


def shadow_moments(shape: Shape, centre: np.ndarray, camera_centre: np.ndarray) -> tuple[float, np.ndarray]:
    """Area and area centroid of the shadow `shape` casts on the table plane from the camera centre."""
    return _union_moments([_hull(shadow(s, camera_centre)) for s in shape.solids(np.asarray(centre, float))])


def footprint_centre(
    shape: Shape, measured_mm: np.ndarray, camera_centre: np.ndarray, start_mm: np.ndarray | None = None, steps: int = 2
) -> np.ndarray:
    """The footprint centre whose shadow's centroid is `measured_mm` (the outline's centroid on
    the table plane); `start_mm` a first guess (default: the measured centroid)."""
    measured = np.asarray(measured_mm, dtype=np.float64)
    c = measured.copy() if start_mm is None else np.asarray(start_mm, dtype=np.float64).copy()
    for _ in range(steps):
        c = c + (measured - shadow_moments(shape, c, camera_centre)[1])
    return c


def nut_from_outline(outline_mm: np.ndarray, across_flats_mm: float, thickness_ratio: float, camera_centre) -> Nut:
    """The nut whose shadow has this outline (on the table plane): the corner direction from the
    outline's edges, the across flats from its area (which grows as the square), the thickness
    `thickness_ratio` times that.

    The shadow is the bottom hexagon swept to the top one: its edges run along the hexagon's six
    sides, and two along the sweep (towards the camera's foot), which are left out. So the sides'
    direction is the sixth harmonic of the edge directions weighed by length, the sweep's excepted.
    """
    area, centre = polygon_moments(outline_mm)
    edges = np.diff(np.vstack([outline_mm, outline_mm[:1]]), axis=0)
    length = np.hypot(edges[:, 0], edges[:, 1])
    direction = np.arctan2(edges[:, 1], edges[:, 0])
    sweep = math.atan2(centre[1] - camera_centre[1], centre[0] - camera_centre[0])
    off_sweep = np.abs(np.angle(np.exp(2j * (direction - sweep)))) > np.deg2rad(2 * _SWEEP_DEG)
    # A side runs at 120 degrees to the corner it leaves: modulo 60 the sides' and corners'
    # directions are the same.
    corner = math.degrees(float(np.angle(np.sum(length * off_sweep * np.exp(6j * direction))))) / 6
    af = across_flats_mm
    for _ in range(2):
        model, _ = shadow_moments(Nut(af, thickness_ratio * af, corner), centre, camera_centre)
        af *= math.sqrt(area / max(model, 1e-9))
    return Nut(af, thickness_ratio * af, corner)


# ---- cell/vision/subpixel.py -------------------------------------------------------------------
UPSAMPLE = 4
_MARGIN_PX = 4


def subpixel_outline(gray: np.ndarray, outline: np.ndarray, fraction: float) -> np.ndarray | None:
    """(N, 2) float outline in image pixels, or None where no paper is seen around the part."""
    H, W = gray.shape
    x, y, w, h = cv2.boundingRect(outline)
    x0, y0 = max(x - _MARGIN_PX, 0), max(y - _MARGIN_PX, 0)
    x1, y1 = min(x + w + _MARGIN_PX, W), min(y + h + _MARGIN_PX, H)
    roi = gray[y0:y1, x0:x1].astype(np.float32)
    part = np.zeros(roi.shape, np.uint8)
    cv2.drawContours(part, [outline], -1, 255, -1, offset=(-x0, -y0))
    paper = roi[cv2.dilate(part, np.ones((5, 5), np.uint8)) == 0]
    if paper.size < 16:
        return None
    up = cv2.resize(roi, None, fx=UPSAMPLE, fy=UPSAMPLE, interpolation=cv2.INTER_LINEAR)
    dark = (up < fraction * float(np.median(paper))).astype(np.uint8)
    contours, _ = cv2.findContours(dark, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    pts = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
    return (pts + 0.5) / UPSAMPLE - 0.5 + (x0, y0)


# ---- cell/vision/features.py: hexagonality ------------------------------------------------------
def hexagonality(outline: np.ndarray, centre: tuple[float, float]) -> float:
    """Sixth angular harmonic of the outline's radius, relative to a regular hexagon's."""
    d = resample(outline, features._OUTLINE_SAMPLES) - centre
    z = d[:, 0] + 1j * d[:, 1]
    theta = np.angle(z)
    r = np.abs(z)
    dtheta = np.angle(np.roll(z, -1) * np.conj(z))  # turn from each sample to the next
    mean_r = np.sum(r * dtheta) / (2 * np.pi)
    if abs(mean_r) < 1e-9:
        return 0.0
    c6 = np.sum(r * np.exp(-6j * theta) * dtheta) / np.pi
    return float(abs(c6) / abs(mean_r) / features._HEXAGON_RATIO)


# ---- cell/vision/locate.py ----------------------------------------------------------------------
log = logging.getLogger(__name__)


class PixelScale:
    """A plain scale for an uncalibrated image: X right, Y down, origin at pixel (0, 0).

    It knows no camera pose, so it cannot correct for part height.
    """

    camera = None
    image_size = None

    def __init__(self, mm_per_px: float):
        if not (mm_per_px > 0 and math.isfinite(mm_per_px)):
            raise InputError(f"mm per pixel must be a positive number, got {mm_per_px}")
        self.scale = float(mm_per_px)

    def pixel_to_table_mm(self, pixels, height_mm: float = 0.0) -> np.ndarray:
        if height_mm:
            raise InputError("a plain pixel scale cannot correct for part height")
        return np.asarray(pixels, dtype=np.float64).reshape(-1, 2) * self.scale

    def mm_per_px(self, pixel) -> float:
        return self.scale


def _parts_config(config) -> PartsConfig:
    if config is None:
        return PartsConfig()
    return config if isinstance(config, PartsConfig) else config.parts


def _locate(image_bgr: np.ndarray, calibration_or_scale, config=None) -> LocateResult:
    """Find, classify and locate the parts in one frame.

    calibration_or_scale: a Calibration (table mm in its plate frame, height correction
    possible) or a plain mm-per-pixel number. config: PartsConfig or CellConfig (its
    .parts); None for the defaults.
    """
    cfg = _parts_config(config)
    mapper = (
        PixelScale(calibration_or_scale) if isinstance(calibration_or_scale, (int, float)) else calibration_or_scale
    )
    image = np.asarray(image_bgr)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or image.size == 0:
        raise InputError(f"expected an 8-bit grey or BGR image, got {image.dtype} with shape {image.shape}")
    h, w = image.shape[:2]
    if mapper.image_size is not None and tuple(mapper.image_size) != (w, h):
        cw, ch = mapper.image_size
        raise InputError(f"frame is {w}x{h} px but the calibration was made at {cw}x{ch} px")
    t0 = time.perf_counter()
    scale = mapper.mm_per_px((w / 2, h / 2))
    gray = to_gray(image)
    seg = segment(
        image,
        cfg,
        part_width_px=cfg.max_part_width_mm / scale,
        noise_area_px=cfg.segment.noise_area_mm2 / scale**2,
        gray=gray,
    )
    warnings = list(seg.warnings)
    correct = cfg.use_height_correction and mapper.camera is not None
    if cfg.use_height_correction and mapper.camera is None and not isinstance(mapper, PixelScale):
        warnings.append("the calibration has no camera pose: no part-height correction")
    feats = [measure(blob, seg.mask) for blob in seg.blobs]
    scales, slopes = _local_geometry(mapper, np.array([f.centroid_px for f in feats]).reshape(-1, 2))
    found = []
    for blob, feat, local_scale, slope in zip(seg.blobs, feats, scales, slopes, strict=True):
        verdict = classify(feat, blob.outer, local_scale, cfg, slope)
        part = _place(feat, verdict, local_scale, mapper, cfg, correct, (gray, blob.outer))
        part.outline_px = blob.outer
        found.append(_refuse_non_finite(part))
    found.sort(key=lambda p: (p.pixel[1], p.pixel[0]))
    for i, part in enumerate(found, start=1):
        part.id = i
    elapsed_ms = (time.perf_counter() - t0) * 1e3
    log.debug("located %d blobs in %.1f ms", len(found), elapsed_ms)
    return LocateResult(found, (w, h), elapsed_ms, warnings)


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


def _refuse_non_finite(part: LocatedPart) -> LocatedPart:
    """A part whose position or angle is not a finite number is never picked (and says why)."""
    numbers = [*part.table_mm, *(part.grasp_mm or ()), *(part.head_mm or ())]
    numbers += [v for v in (part.angle_deg, part.jaw_opening_mm) if v is not None]
    if part.pick and not np.all(np.isfinite(np.asarray(numbers, dtype=np.float64))):
        part.pick = False
        part.reason = f"{part.cls} with no finite table position (calibration?): not picked"
        part.cls = "unknown"
    return part


def _local_geometry(mapper, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: the table-plane scale (mm/px, as Calibration.mm_per_px) and the view slope
    (tangent of the angle between the camera's ray and the vertical; 0 without a pose).

    One mapping call for all parts: a calibration's mapping is the costly step per part.
    """
    n = len(pixels)
    if n == 0:
        return np.zeros(0), np.zeros(0)
    probes = np.concatenate([pixels, pixels + (1.0, 0.0), pixels + (0.0, 1.0)])
    q = mapper.pixel_to_table_mm(probes).reshape(3, n, 2)
    du, dv = q[1] - q[0], q[2] - q[0]
    scales = np.sqrt(np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]))
    if mapper.camera is None:
        return scales, np.zeros(n)
    c = mapper.camera.center_table_mm
    return scales, np.hypot(*(q[0] - c[:2]).T) / c[2]


def reference_height_mm(verdict: Verdict, config: PartsConfig) -> float:
    """Height above the table of the plane a part's centroid is mapped on."""
    if verdict.cls == NUT:
        if config.nut.reference_height_mm is not None:
            return config.nut.reference_height_mm
        return 0.5 * config.nut.thickness_per_across_flats * verdict.size_mm["across_flats_mm"]
    if verdict.cls == BOLT:
        if config.bolt.reference_height_mm is not None:
            return config.bolt.reference_height_mm
        head_mm = verdict.size_mm.get("head_width_mm")
        return 0.5 * config.bolt.head_across_flats_per_width * head_mm if head_mm else 0.0
    return 0.0


def _place(
    feat: Features,
    verdict: Verdict,
    scale: float,
    mapper,
    cfg: PartsConfig,
    correct: bool,
    seen: tuple[np.ndarray, np.ndarray],
) -> LocatedPart:
    """`seen`: the grey frame and the blob's outline (a bolt's pose is measured on a sub-pixel outline)."""
    height = reference_height_mm(verdict, cfg) if correct else 0.0
    centre = np.asarray(feat.centroid_px, dtype=np.float64)
    world = mapper.pixel_to_table_mm(centre, height_mm=height)[0]
    angle = head = grasp = jaw = None
    prof, head_px, shaft_px = verdict.profile, verdict.head_width_px, verdict.shaft_width_px
    bolt_on_side = verdict.cls == BOLT and head_px is not None
    needs_outline = bolt_on_side or (verdict.cls == NUT and correct)
    fine = subpixel_outline(*seen, cfg.segment.threshold_fraction) if needs_outline else None
    if bolt_on_side and prof is not None and head_px is not None and shaft_px is not None:
        if fine is not None:
            prof = width_profile(fine, feat.centroid_px, feat.axis_px, edge_px=EDGE_PX)
        pose = bolt_pose(
            prof,
            head_px,
            shaft_px,
            mapper,
            height,
            scale,
            cfg.bolt.head_across_flats_per_width,
        )
        world, head, grasp, angle = pose.centre_mm, pose.head_mm, pose.grasp_mm, pose.angle_deg
        if correct and fine is not None:
            # The shadow's centroid places the bolt; its head and grasp point move with it.
            outline_mm = mapper.pixel_to_table_mm(_thinned(fine))
            shift = _from_shadow(_bolt_shape(pose), outline_mm, mapper, world) - world
            world, head, grasp = world + shift, head + shift, grasp + shift
        jaw = pose.shaft_mm + cfg.jaw_clearance_mm
    elif verdict.cls == BOLT and prof is not None:  # paper preset: the centroid, and the axis end to end
        ends_px = np.array([prof.origin_px, prof.origin_px + prof.length_px * prof.axis_px])
        ends = mapper.pixel_to_table_mm(ends_px, height_mm=height)
        d = ends[1] - ends[0]
        angle = math.degrees(math.atan2(d[1], d[0])) % 180.0
        head = ends[0]
    elif verdict.cls == NUT:
        if correct and fine is not None:
            outline_mm = mapper.pixel_to_table_mm(_thinned(fine))
            nut = nut_from_outline(
                outline_mm,
                verdict.size_mm["across_flats_mm"],
                cfg.nut.thickness_per_across_flats,
                mapper.camera.center_table_mm,
            )
            world = _from_shadow(nut, outline_mm, mapper, world)
        grasp = world
        jaw = feat.enclosing_diameter_px * scale + cfg.jaw_clearance_mm
    features = {
        "area_mm2": feat.area_px * scale**2,
        "holes": len(feat.holes),
        "elongation": feat.elongation,
        "hexagonality": feat.hexagonality,
        "roundness": feat.roundness,
        "solidity": feat.solidity,
        "reference_height_mm": height,
        **verdict.size_mm,
    }
    return LocatedPart(
        id=0,
        cls=verdict.cls,
        reason=verdict.reason,
        pixel=(float(centre[0]), float(centre[1])),
        table_mm=(float(world[0]), float(world[1])),
        angle_deg=angle,
        pick=verdict.cls in (BOLT, NUT),
        grasp_mm=None if grasp is None else (float(grasp[0]), float(grasp[1])),
        jaw_opening_mm=jaw,
        head_mm=None if head is None else (float(head[0]), float(head[1])),
        features=features,
    )


def _from_shadow(shape: Nut | Bolt, outline_mm: np.ndarray, mapper, start_mm: np.ndarray) -> np.ndarray:
    """The footprint centre whose shadow (silhouette.py) has the centroid of the outline on the table plane."""
    _, measured = polygon_moments(outline_mm)
    return footprint_centre(shape, measured, mapper.camera.center_table_mm, start_mm)


def _thinned(outline_px: np.ndarray) -> np.ndarray:
    """The sub-pixel outline with the points that lie within 0.02 px of a straight run dropped (a
    polygon's area and centroid barely move; mapping it through a calibration costs per point)."""
    poly = cv2.approxPolyDP(np.asarray(outline_px, dtype=np.float32).reshape(-1, 1, 2), 0.02, True)
    return poly.reshape(-1, 2).astype(np.float64) if len(poly) >= 3 else np.asarray(outline_px, dtype=np.float64)


def _bolt_shape(pose: BoltPose) -> Bolt:
    return Bolt(
        pose.head_across_flats_mm,
        pose.head_length_mm,
        pose.shaft_mm,
        max(pose.length_mm - pose.head_length_mm, 0.1),
        pose.angle_deg if np.dot(pose.grasp_mm - pose.head_mm, _unit(pose.angle_deg)) >= 0 else pose.angle_deg + 180,
    )


def _unit(angle_deg: float) -> np.ndarray:
    a = math.radians(angle_deg)
    return np.array([math.cos(a), math.sin(a)])


def locate(image_bgr: np.ndarray, calibration_or_scale, config=None) -> LocateResult:
    """The previous locate(), with the previous hexagonality in measure() (one thread at a time)."""
    current = features.hexagonality
    features.hexagonality = hexagonality
    try:
        return _locate(image_bgr, calibration_or_scale, config)
    finally:
        features.hexagonality = current

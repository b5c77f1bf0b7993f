"""One frame in, parts out: segment, measure, classify, then map each centre to the table.

Height correction: the calibration holds on the table plane, but a part's outline comes
from faces up to its full height, which a camera off to one side sees displaced outwards.
So each centroid is mapped on the plane at the part's reference height (half its height
by default), which needs the class first and the camera pose the calibration stores.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence

import cv2
import numpy as np

from cell.errors import InputError
from cell.vision.classify import BOLT, NUT, Verdict, classify
from cell.vision.config import PartsConfig
from cell.vision.features import Features, Profile, measure, part_centroid_px, width_profile
from cell.vision.footprint import BoltPose, axis_points_px, bolt_pose
from cell.vision.segment import Blob, segment, to_gray
from cell.vision.shapes import ShapeModel, best_match, footprint_of_blob, footprints_of_blobs
from cell.vision.silhouette import Bolt, Nut, footprint_centre, nut_from_outline, polygon_moments
from cell.vision.subpixel import EDGE_PX, subpixel_outline
from cell.vision.types import LocatedPart, LocateResult

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
        return self.lift_mm(np.asarray(pixels, dtype=np.float64).reshape(-1, 2) * self.scale, height_mm)

    def lift_mm(self, on_table: np.ndarray, height_mm: float) -> np.ndarray:
        if height_mm:
            raise InputError("a plain pixel scale cannot correct for part height")
        return on_table

    def mm_per_px(self, pixel) -> float:
        return self.scale


def _parts_config(config) -> PartsConfig:
    if config is None:
        return PartsConfig()
    return config if isinstance(config, PartsConfig) else config.parts


def locate(image_bgr: np.ndarray, calibration_or_scale, config=None, shapes: Sequence[ShapeModel] = ()) -> LocateResult:
    """Find, classify and locate the parts in one frame.

    calibration_or_scale: a Calibration (table mm in its plate frame, height correction
    possible) or a plain mm-per-pixel number. config: PartsConfig or CellConfig (its
    .parts); None for the defaults. shapes: the recipe's taught part types (cell.vision.shapes),
    tried on each blob before the built-in bolt and nut; none: bolts and nuts only, as always.
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
    # Taught types first (each blob's silhouette, all mapped in one call); the built-in rules'
    # measurements and outlines only for the blobs no taught type takes.
    feats = {} if shapes else {i: measure(blob, seg.mask) for i, blob in enumerate(seg.blobs)}
    centroids = np.array(
        [feats[i].centroid_px if i in feats else part_centroid_px(blob, seg.mask) for i, blob in enumerate(seg.blobs)]
    ).reshape(-1, 2)
    scales, slopes, centres_mm = _local_geometry(mapper, centroids)
    taught: list[tuple[LocatedPart | None, str]] = (
        _taught_all(seg.blobs, centroids, gray, mapper, cfg, shapes, scales, correct)
        if shapes
        else [(None, "")] * len(seg.blobs)
    )
    rest = [i for i, (part, _) in enumerate(taught) if part is None]
    feats.update({i: measure(seg.blobs[i], seg.mask) for i in rest if i not in feats})
    verdicts = {i: classify(feats[i], seg.blobs[i].outer, scales[i], cfg, slopes[i]) for i in rest}
    fines = {i: _fine_outline(verdicts[i], correct, cfg, gray, seg.blobs[i].outer) for i in rest}
    shadows = [
        (f if f is not None and ((correct and _shadow_placed(verdicts[i])) or _posed(verdicts[i])) else None)
        for i, f in fines.items()
    ]
    # A posed bolt's profile on its fine outline, and its axis's first estimate (footprint.py): those
    # points are mapped in the same call as the outlines (where the mapper lifts mapped points).
    profiles = {i: _pose_profile(feats[i], verdicts[i], fines[i]) for i in rest if _posed(verdicts[i])}
    axes_px = {i: _axis_px(verdicts[i], p) for i, p in profiles.items()} if hasattr(mapper, "lift_mm") else {}
    mapped = _outlines_on_table(
        mapper, [None if f is None else _thinned(f) for f in shadows] + [axes_px.get(i) for i in rest]
    )
    outlines_mm = dict(zip(rest, mapped[: len(rest)], strict=True))
    axes_mm = dict(zip(rest, mapped[len(rest) :], strict=True))
    found = []
    for i, (blob, (part, why)) in enumerate(zip(seg.blobs, taught, strict=True)):
        if part is None:
            verdict = verdicts[i]
            if why and verdict.cls not in (BOLT, NUT):
                verdict = Verdict(verdict.cls, f"{verdict.reason}; {why}", verdict.size_mm)
            part = _place(
                feats[i],
                verdict,
                scales[i],
                mapper,
                cfg,
                correct,
                centres_mm[i],
                outlines_mm[i],
                profiles.get(i),
                axes_mm[i],
            )
        part.outline_px = blob.outer
        found.append(_refuse_non_finite(part))
    found.sort(key=lambda p: (p.pixel[1], p.pixel[0]))
    for i, part in enumerate(found, start=1):
        part.id = i
    if shapes:
        _leave_crowded(found, mapper, cfg)
    elapsed_ms = (time.perf_counter() - t0) * 1e3
    log.debug("located %d blobs in %.1f ms", len(found), elapsed_ms)
    return LocateResult(found, (w, h), elapsed_ms, warnings)


def silhouettes(image_bgr: np.ndarray, mapper, config: PartsConfig) -> list[tuple[tuple, bool, float]]:
    """Every blob large enough to be a part, as (its silhouette on the table plane (outer, holes;
    table mm), whether it touches the image's edge, its area in mm2): what teaching learns from."""
    image = np.asarray(image_bgr)
    h, w = image.shape[:2]
    scale = mapper.mm_per_px((w / 2, h / 2))
    gray = to_gray(image)
    seg = segment(
        image,
        config,
        part_width_px=config.max_part_width_mm / scale,
        noise_area_px=config.segment.noise_area_mm2 / scale**2,
        gray=gray,
    )
    out = []
    for blob in seg.blobs:
        feat = measure(blob, seg.mask)
        area = feat.outer_area_px * scale**2
        if area < config.min_part_area_mm2:
            continue
        sil = footprint_of_blob(
            gray, blob.outer, mapper, config.segment.threshold_fraction, config.segment.noise_area_mm2 / scale**2
        )
        if sil is not None:
            out.append((sil, blob.touches_border, area))
    return out


def _taught_all(
    blobs: Sequence[Blob],
    centroids_px: np.ndarray,
    gray: np.ndarray,
    mapper,
    cfg: PartsConfig,
    shapes: Sequence[ShapeModel],
    scales: np.ndarray,
    correct: bool,
) -> list[tuple[LocatedPart | None, str]]:
    """Each blob as a taught part type, or (None, why not; empty when the built-in rules should say)."""
    out: list[tuple[LocatedPart | None, str]] = [(None, "")] * len(blobs)
    inside = [i for i, b in enumerate(blobs) if not b.touches_border]
    silhouettes = footprints_of_blobs(
        gray,
        [blobs[i].outer for i in inside],
        mapper,
        cfg.segment.threshold_fraction,
        [cfg.segment.noise_area_mm2 / scales[i] ** 2 for i in inside],
    )
    camera_centre = mapper.camera.center_table_mm if correct else None
    for i, silhouette in zip(inside, silhouettes, strict=True):
        if silhouette is not None:
            out[i] = _taught(silhouette, centroids_px[i], shapes, camera_centre, correct)
    return out


def _taught(
    silhouette: tuple[np.ndarray, list[np.ndarray]],
    centroid_px: np.ndarray,
    shapes: Sequence[ShapeModel],
    camera_centre: np.ndarray | None,
    correct: bool,
) -> tuple[LocatedPart | None, str]:
    """A blob's silhouette (table plane) as a taught part type, or (None, why not)."""
    match, fp, why = best_match(silhouette, shapes, camera_centre)
    if match is None or not match.accepted or fp is None:
        return None, why
    model = next(m for m in shapes if m.name == match.name)
    grasp, jaw_deg = model.grip_on_table(match.centre_mm, match.angle_deg)
    centre = match.centre_mm
    return LocatedPart(
        id=0,
        cls=match.name,
        reason=f"taught type {match.name}: fits its model (score {match.score:.3f}, "
        f"differs by {match.misfit_mm2:.1f} mm2)",
        pixel=(float(centroid_px[0]), float(centroid_px[1])),
        table_mm=(float(centre[0]), float(centre[1])),
        angle_deg=None if model.symmetry == 0 else float(match.angle_deg),
        pick=True,
        grasp_mm=(float(grasp[0]), float(grasp[1])),
        jaw_opening_mm=model.grip.opening_mm,
        features={
            "area_mm2": fp.area_mm2,
            "holes": len(fp.holes),
            "symmetry": model.symmetry,
            "jaw_angle_deg": jaw_deg,
            "misfit_mm2": match.misfit_mm2,
            "reference_height_mm": model.height_mm if correct else 0.0,
        },
        score=match.score,
    ), ""


def _leave_crowded(found: list[LocatedPart], mapper, cfg: PartsConfig) -> None:
    """A taught part whose jaws would touch a neighbour is left for later, saying which: each jaw a
    rectangle `jaw_thickness_mm` deep and `jaw_face_width_mm` wide just outside the opening, on
    either side of the grasp point along the direction the jaws close, against every other part's
    silhouette on the table plane."""
    taught = [p for p in found if p.pick and p.score is not None and p.grasp_mm is not None]
    if not taught or len(found) < 2:
        return
    # Outlines within half a pixel (the jaws' reach is millimetres), mapped in one call.
    outlines = [
        cv2.approxPolyDP(np.asarray(p.outline_px, dtype=np.int32).reshape(-1, 1, 2), 0.5, True).reshape(-1, 2)
        for p in found
    ]
    mapped = mapper.pixel_to_table_mm(np.vstack(outlines).astype(np.float64))
    cuts = np.cumsum([len(o) for o in outlines])[:-1]
    polys = [q.astype(np.float32) for q in np.split(mapped, cuts)]
    centres = np.array([q.mean(axis=0) for q in polys])
    radii = np.array([float(np.max(np.hypot(*(q - c).T))) for q, c in zip(polys, centres, strict=True)])
    index = {id(p): i for i, p in enumerate(found)}
    for part in taught:
        a = math.radians(part.features["jaw_angle_deg"])
        d, side = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
        g = np.asarray(part.grasp_mm)
        half = (part.jaw_opening_mm or 0.0) / 2
        t, w = cfg.jaw_thickness_mm, cfg.jaw_face_width_mm / 2
        jaws = []
        for sign in (1.0, -1.0):
            near, far = g + sign * half * d, g + sign * (half + t) * d
            jaws.append(np.array([near - w * side, far - w * side, far + w * side, near + w * side], np.float32))
        spans = [(jaw, jaw.mean(axis=0), math.hypot(*(jaw[2] - jaw[0])) / 2) for jaw in jaws]
        reach = half + t + w + 1.0  # the farthest a jaw's corner lies from the grasp point, and a margin
        close = np.flatnonzero(np.hypot(*(centres - g).T) <= reach + radii)
        for j in close:
            other = found[j]
            if j == index[id(part)]:
                continue
            poly = polys[j]
            # A jaw wholly further from the outline's centre than its radius cannot touch it (the
            # margin covers float32 rounding): most neighbours are left out before the full test.
            if any(_near(c, hd, centres[j], radii[j]) and _overlap(jaw, poly) for jaw, c, hd in spans):
                part.pick = False
                part.reason = f"{part.cls}: the jaws would touch part {other.id}: left for later"
                break


def _near(jaw_centre: np.ndarray, half_diagonal: float, centre: np.ndarray, radius: float) -> bool:
    """Whether a jaw's rectangle (its centre and half diagonal) comes within `radius` (and 1 um) of
    `centre`."""
    d = math.hypot(float(jaw_centre[0] - centre[0]), float(jaw_centre[1] - centre[1]))
    return d <= radius + half_diagonal + 1e-3


def _overlap(jaw: np.ndarray, poly: np.ndarray) -> bool:
    """Whether a jaw's rectangle (4 corners in order) and a part's outline overlap: a point of the
    outline inside the rectangle, or a corner of the rectangle inside the outline."""
    c = jaw.mean(axis=0)
    u, v = jaw[1] - jaw[0], jaw[3] - jaw[0]
    p = poly - c
    inside = (np.abs(p @ u) <= 0.5 * float(u @ u)) & (np.abs(p @ v) <= 0.5 * float(v @ v))
    if inside.any():
        return True
    return any(cv2.pointPolygonTest(poly, (float(x), float(y)), False) >= 0 for x, y in jaw)


def _refuse_non_finite(part: LocatedPart) -> LocatedPart:
    """A part whose position or angle is not a finite number is never picked (and says why)."""
    numbers = [*part.table_mm, *(part.grasp_mm or ()), *(part.head_mm or ())]
    numbers += [v for v in (part.angle_deg, part.jaw_opening_mm) if v is not None]
    if part.pick and not np.all(np.isfinite(np.asarray(numbers, dtype=np.float64))):
        part.pick = False
        part.reason = f"{part.cls} with no finite table position (calibration?): not picked"
        part.cls = "unknown"
    return part


def _local_geometry(mapper, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel: the table-plane scale (mm/px, as Calibration.mm_per_px), the view slope
    (tangent of the angle between the camera's ray and the vertical; 0 without a pose) and the
    point on the table plane (N, 2).

    One mapping call for all parts: a calibration's mapping is the costly step per part.
    """
    n = len(pixels)
    if n == 0:
        return np.zeros(0), np.zeros(0), np.zeros((0, 2))
    probes = np.concatenate([pixels, pixels + (1.0, 0.0), pixels + (0.0, 1.0)])
    q = mapper.pixel_to_table_mm(probes).reshape(3, n, 2)
    du, dv = q[1] - q[0], q[2] - q[0]
    scales = np.sqrt(np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]))
    if mapper.camera is None:
        return scales, np.zeros(n), q[0]
    c = mapper.camera.center_table_mm
    return scales, np.hypot(*(q[0] - c[:2]).T) / c[2], q[0]


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


def _posed(verdict: Verdict) -> bool:
    """A bolt on its side with a width profile: its pose places it (footprint.py)."""
    return (
        verdict.cls == BOLT
        and verdict.profile is not None
        and verdict.head_width_px is not None
        and verdict.shaft_width_px is not None
    )


def _shadow_placed(verdict: Verdict) -> bool:
    """Placed by its shadow (with height correction): a nut, or a posed bolt."""
    return verdict.cls == NUT or _posed(verdict)


def _fine_outline(
    verdict: Verdict, correct: bool, cfg: PartsConfig, gray: np.ndarray, outline: np.ndarray
) -> np.ndarray | None:
    """The sub-pixel outline where it is used: a bolt on its side (its pose), a nut with height correction."""
    bolt_on_side = verdict.cls == BOLT and verdict.head_width_px is not None
    if bolt_on_side:  # its ends are measured on it: halfway between the paper's level and the bolt's
        return subpixel_outline(gray, outline, cfg.segment.threshold_fraction, mid_level=True)
    if verdict.cls == NUT and correct:
        return subpixel_outline(gray, outline, cfg.segment.threshold_fraction)
    return None


def _pose_profile(feat: Features, verdict: Verdict, fine: np.ndarray | None) -> Profile:
    """The width profile a posed bolt's pose is measured on: its sub-pixel outline's where it has one."""
    if fine is None:
        assert verdict.profile is not None  # _posed
        return verdict.profile
    return width_profile(fine, feat.centroid_px, feat.axis_px, edge_px=EDGE_PX)


def _axis_px(verdict: Verdict, profile: Profile) -> np.ndarray:
    """A posed bolt's axis's first estimate in pixels (footprint.axis_points_px)."""
    assert verdict.head_width_px is not None and verdict.shaft_width_px is not None  # _posed
    return axis_points_px(profile, verdict.head_width_px, verdict.shaft_width_px)


def _outlines_on_table(mapper, outlines_px: list[np.ndarray | None]) -> list[np.ndarray | None]:
    """Each outline mapped onto the table plane, all in one mapping call (its cost is mostly per call)."""
    given = [o for o in outlines_px if o is not None]
    if not given:
        return [None] * len(outlines_px)
    mapped = iter(np.split(mapper.pixel_to_table_mm(np.concatenate(given)), np.cumsum([len(o) for o in given])[:-1]))
    return [None if o is None else next(mapped) for o in outlines_px]


def _place(
    feat: Features,
    verdict: Verdict,
    scale: float,
    mapper,
    cfg: PartsConfig,
    correct: bool,
    centre_mm: np.ndarray,
    outline_mm: np.ndarray | None,
    pose_profile: Profile | None = None,
    axis_mm: np.ndarray | None = None,
) -> LocatedPart:
    """`centre_mm`: the centroid mapped onto the table plane; `outline_mm`: the blob's sub-pixel
    outline, thinned, on the table plane where the shadow places the part or a bolt's pose is
    measured; `pose_profile`: a posed bolt's width profile on that outline (_pose_profile),
    `axis_mm`: its axis's first estimate mapped onto the table plane (footprint.axis_points_px)."""
    height = reference_height_mm(verdict, cfg) if correct else 0.0
    centre = np.asarray(feat.centroid_px, dtype=np.float64)
    angle = head = grasp = jaw = None
    prof, head_px, shaft_px = verdict.profile, verdict.head_width_px, verdict.shaft_width_px
    posed = _posed(verdict)
    # The centroid at the part's reference height (a posed bolt's place comes from its pose): moved
    # up from the table plane where the mapper can, else mapped again (a mapping call per part).
    if posed:
        world = np.zeros(2)
    elif hasattr(mapper, "lift_mm"):
        world = mapper.lift_mm(centre_mm.reshape(1, 2), height)[0]
    else:
        world = mapper.pixel_to_table_mm(centre, height_mm=height)[0]
    if posed and prof is not None and head_px is not None and shaft_px is not None:
        pose = bolt_pose(
            prof if pose_profile is None else pose_profile,
            head_px,
            shaft_px,
            mapper,
            height,
            scale,
            cfg.bolt.head_across_flats_per_width,
            outline_mm,
            EDGE_PX,
            axis_mm,
        )
        world, head, grasp, angle = pose.centre_mm, pose.head_mm, pose.grasp_mm, pose.angle_deg
        if correct and outline_mm is not None:
            # The shadow's centroid places the bolt; its head and grasp point move with it across the
            # axis. Along it they keep their place from the bolt's ends: the centroid's shift there
            # mostly answers the widths' error (0.03 mm towards the head on average, at 0.3-0.4 mm/px).
            shift = _from_shadow(_bolt_shape(pose), outline_mm, mapper, world) - world
            side = _unit(pose.angle_deg + 90.0)
            world, head, grasp = world + shift, head + (shift @ side) * side, grasp + (shift @ side) * side
        jaw = pose.shaft_mm + cfg.jaw_clearance_mm
    elif verdict.cls == BOLT and prof is not None:  # paper preset: the centroid, and the axis end to end
        ends_px = np.array([prof.origin_px, prof.origin_px + prof.length_px * prof.axis_px])
        ends = mapper.pixel_to_table_mm(ends_px, height_mm=height)
        d = ends[1] - ends[0]
        angle = math.degrees(math.atan2(d[1], d[0])) % 180.0
        head = ends[0]
    elif verdict.cls == NUT:
        if correct and outline_mm is not None:
            moments = polygon_moments(outline_mm)
            nut = nut_from_outline(
                outline_mm,
                verdict.size_mm["across_flats_mm"],
                cfg.nut.thickness_per_across_flats,
                mapper.camera.center_table_mm,
                moments,
            )
            world = _from_shadow(nut, outline_mm, mapper, world, moments[1])
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


def _from_shadow(
    shape: Nut | Bolt, outline_mm: np.ndarray, mapper, start_mm: np.ndarray, centroid_mm: np.ndarray | None = None
) -> np.ndarray:
    """The footprint centre whose shadow (silhouette.py) has the centroid of the outline on the table plane
    (`centroid_mm`, where the caller has it)."""
    measured = polygon_moments(outline_mm)[1] if centroid_mm is None else centroid_mm
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

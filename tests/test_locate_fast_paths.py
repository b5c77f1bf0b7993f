"""locate's shortcuts of issue 29's speed item 5(a) give what the plain forms give, to the bit: a
posed bolt's axis points mapped in the frame's one mapping call then lifted (bolt_pose's
`axis_on_table_mm`) against bolt_pose mapping them itself; the convex overlap with its side tests
laid out along the longer polygon; the outline resampled without np.diff / vstack / column_stack; a
nut's outline moments handed over against taken again; the shadow model's end faces stacked and its
union's moments in Python floats against face by face and numpy's 2-vectors; the camera centre kept
against computed. No timing is asserted here: scripts/bench_parts.py --speed measures it."""

from __future__ import annotations

import cv2
import numpy as np

from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.sim.cameras import FAMILY, random_camera
from cell.sim.parts import random_scene, render_scene
from cell.vision import features, footprint, locate, silhouette
from cell.vision.classify import BOLT, NUT, classify
from cell.vision.config import PartsConfig
from cell.vision.footprint import axis_points_px, bolt_pose
from cell.vision.segment import segment, to_gray
from cell.vision.silhouette import nut_from_outline, polygon_moments
from cell.vision.subpixel import EDGE_PX, subpixel_outline


def _frame(seed: int):
    sim = random_camera(FAMILY["1920 x 1080"], seed)
    cam = sim.camera
    parts = random_scene(seed=seed, n_parts=(17, 19), area_mm=sim.scene_area_mm)
    frame = render_scene(cam, parts, sim.optics, seed=seed)
    return frame, Calibration("camera", CameraMap(cam), (cam.width_px, cam.height_px), cam)


def _parts(seed: int):
    """(blob, features, verdict, sub-pixel outline, calibration) of each bolt and nut of a frame."""
    config = PartsConfig()
    frame, cal = _frame(seed)
    gray = to_gray(frame)
    scale = cal.mm_per_px((960, 540))
    seg = segment(frame, config, config.max_part_width_mm / scale, config.segment.noise_area_mm2 / scale**2, gray=gray)
    for blob in seg.blobs:
        feat = features.measure(blob, seg.mask)
        verdict = classify(feat, blob.outer, scale, config)
        if verdict.cls in (BOLT, NUT):
            mid = verdict.cls == BOLT
            fine = subpixel_outline(gray, blob.outer, config.segment.threshold_fraction, mid_level=mid)
            yield blob, feat, verdict, fine, cal


def _previous_resample(outline: np.ndarray, count: int | None = None, step_px: float = 0.5) -> np.ndarray:
    """features.resample as it was before issue 29's speed item 5(a)."""
    pts = outline.reshape(-1, 2).astype(np.float64)
    closed = np.vstack([pts, pts[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(closed, axis=0).T))])
    if s[-1] <= 0:
        return pts[:1]
    n = count or max(3, int(s[-1] / step_px))
    t = np.arange(n) * (s[-1] / n)
    return np.column_stack([np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])])


def test_bolt_pose_on_axis_points_mapped_with_the_outlines_is_the_same():
    config = PartsConfig()
    bolts = 0
    for seed in (29_100, 29_101):
        for _blob, feat, verdict, fine, cal in _parts(seed):
            if verdict.cls != BOLT or fine is None or verdict.head_width_px is None:
                continue
            assert verdict.shaft_width_px is not None
            prof = features.width_profile(fine, feat.centroid_px, feat.axis_px, edge_px=EDGE_PX)
            axis_px = axis_points_px(prof, verdict.head_width_px, verdict.shaft_width_px)
            outline = locate._thinned(fine)
            # as locate maps them: after the frame's outlines, in one call
            mapped = cal.pixel_to_table_mm(np.concatenate((outline, axis_px)))
            outline_mm, axis_mm = mapped[: len(outline)], mapped[len(outline) :]
            height = locate.reference_height_mm(verdict, config)
            args = (prof, verdict.head_width_px, verdict.shaft_width_px, cal, height, 0.3, 1.0, outline_mm, EDGE_PX)
            plain, batched = bolt_pose(*args), bolt_pose(*args, axis_on_table_mm=axis_mm)
            for name in ("centre_mm", "head_mm", "grasp_mm"):
                np.testing.assert_array_equal(getattr(batched, name), getattr(plain, name))
            assert (batched.angle_deg, batched.shaft_mm, batched.length_mm, batched.head_length_mm) == (
                plain.angle_deg,
                plain.shaft_mm,
                plain.length_mm,
                plain.head_length_mm,
            )
            bolts += 1
    assert bolts >= 6


def test_resample_is_the_previous_form():
    rng = np.random.default_rng(5)
    outlines = [blob.outer for blob, *_ in _parts(29_100)]
    outlines += [fine for *_, fine, _cal in _parts(29_100) if fine is not None]
    outlines += [rng.normal(0, 30, (int(rng.integers(1, 60)), 1, 2)) for _ in range(200)]
    outlines += [np.zeros((5, 1, 2), np.int32)]  # no length: its first point
    for outline in outlines:
        for count in (None, 180):
            np.testing.assert_array_equal(features.resample(outline, count), _previous_resample(outline, count))


def test_nut_from_outline_with_its_moments_handed_over_is_the_same():
    nuts = 0
    for _blob, _feat, verdict, fine, cal in _parts(29_100):
        if verdict.cls != NUT or fine is None:
            continue
        outline_mm = cal.pixel_to_table_mm(locate._thinned(fine))
        camera = cal.camera.center_table_mm
        af = verdict.size_mm["across_flats_mm"]
        plain = nut_from_outline(outline_mm, af, 0.8, camera)
        handed = nut_from_outline(outline_mm, af, 0.8, camera, polygon_moments(outline_mm))
        assert handed == plain
        nuts += 1
    assert nuts >= 3


def test_the_kept_camera_centre_is_the_computed_one():
    _, cal = _frame(29_100)
    cam = cal.camera
    C = -cam.rotation.T @ cam.tvec
    first = cam.center_table_mm
    np.testing.assert_array_equal(first, [C[0], C[1], abs(C[2])])
    first[:] = 0.0  # a caller's copy: the kept one is not changed
    np.testing.assert_array_equal(cam.center_table_mm, [C[0], C[1], abs(C[2])])


def _previous_intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """silhouette._intersection as it was before issue 29's speed item 5(a)."""
    a_next = np.concatenate((a[1:], a[:1]))
    b_next = np.concatenate((b[1:], b[:1]))
    ea, eb = a_next - a, b_next - b
    side_a = eb[:, 0] * (a[:, 1:2] - b[:, 1]) - eb[:, 1] * (a[:, 0:1] - b[:, 0])
    side_b = ea[:, 0] * (b[:, 1:2] - a[:, 1]) - ea[:, 1] * (b[:, 0:1] - a[:, 0])
    hair = 1e-12
    kept = [a[(side_a >= -hair).all(axis=1)], b[(side_b >= -hair).all(axis=1)]]
    sa_next = np.concatenate((side_a[1:], side_a[:1]))
    sb_next = np.concatenate((side_b[1:], side_b[:1]))
    crosses = ((side_a >= 0) != (sa_next >= 0)) & ((side_b >= 0) != (sb_next >= 0)).T
    i, j = np.nonzero(crosses)
    if len(i):
        t = side_a[i, j] / (side_a[i, j] - sa_next[i, j])
        kept.append(a[i] + ea[i] * t[:, None])
    pts = np.concatenate(kept)
    if len(pts) < 3:
        return np.zeros((0, 2))
    d = pts - pts.mean(axis=0)
    return pts[np.argsort(np.arctan2(d[:, 1], d[:, 0]), kind="stable")]


def test_the_convex_overlap_is_the_previous_form():
    """Random hulls that overlap, nest, share an edge or miss, each way round, and a bolt's head and
    shaft shadows (a hexagon's hull against a 96-point rim's)."""
    rng = np.random.default_rng(11)
    pairs = []
    for k in range(3000):
        a = silhouette._hull(rng.normal(0, 1, (int(rng.integers(3, 12)), 2)))
        if k % 3 == 0:  # sharing an edge of a
            b = silhouette._hull(np.vstack([a[:2], rng.normal(rng.uniform(-1, 1), 1, (int(rng.integers(1, 60)), 2))]))
        else:
            b = silhouette._hull(rng.normal(rng.uniform(-1, 1), 1, (int(rng.integers(3, 60)), 2)))
        pairs += [(a, b), (b, a)]
    camera = np.array([120.0, 80.0, 400.0])
    for axis_deg in range(0, 360, 15):
        caster = silhouette._Caster(silhouette.Bolt(13.0, 5.3, 8.0, 30.0, axis_deg), camera)
        hulls = [silhouette._hull(base + k1 * np.array([60.0, 40.0])) for base, k1 in caster.solids]
        pairs.append((hulls[0], hulls[1]))
    for a, b in pairs:
        np.testing.assert_array_equal(silhouette._intersection(a, b), _previous_intersection(a, b))


def test_the_shadow_casters_points_and_union_are_the_plain_forms():
    """A bolt's end faces stacked in one step against face by face, and the union's moments in Python
    floats against numpy's 2-vectors; the pose's model shadow likewise."""
    rng = np.random.default_rng(13)
    for _ in range(300):
        camera = np.array([rng.uniform(-50, 310), rng.uniform(-50, 230), rng.uniform(100, 900)])
        centre = np.array([rng.uniform(0, 260), rng.uniform(0, 180)])
        bolt = silhouette.Bolt(
            rng.uniform(7, 14), rng.uniform(3, 6), rng.uniform(4, 9), rng.uniform(8, 45), 360 * rng.random()
        )
        caster = silhouette._Caster(bolt, camera)
        head_vz, head_u, shaft_vz, shaft_u, axis, side = bolt.frame()
        c = camera
        for (base, _k1), (vz, ends) in zip(caster.solids, ((head_vz, head_u), (shaft_vz, shaft_u)), strict=True):
            k = c[2] / np.maximum(c[2] - vz[:, 1:], 1e-9)
            local = vz[:, :1] * side
            np.testing.assert_array_equal(base, np.concatenate([c[:2] + (u * axis + local - c[:2]) * k for u in ends]))
        hulls = [cv2.convexHull((b + k1 * centre).astype(np.float32), clockwise=False) for b, k1 in caster.solids]
        (a1, c1), (a2, c2) = silhouette._hull_moments(hulls[0]), silhouette._hull_moments(hulls[1])
        overlap = silhouette._intersection(*(h.reshape(-1, 2).astype(np.float64) for h in hulls))
        a12, c12 = (0.0, c1) if len(overlap) < 3 else polygon_moments(overlap)
        union = a1 + a2 - a12
        area, centroid = caster.moments(centre)
        assert area == union
        np.testing.assert_array_equal(centroid, centre + (a1 * c1 + a2 * c2 - a12 * c12) / max(union, 1e-12))
        # the pose's model shadow: each end's ring seen on the plane, face by face
        rings = [(r * np.cos(np.linspace(0, 6, 9)), 4 + r * np.sin(np.linspace(0, 6, 9)), (-3.0, 9.5)) for r in (2, 3)]
        uvz = np.array([rng.uniform(-100, 100), rng.uniform(-100, 100), rng.uniform(200, 800)])
        for (v, z, ends), got in zip(rings, footprint._shadow_sides(rings, uvz, 4.0), strict=True):
            f = (uvz[2] - 4.0) / np.maximum(uvz[2] - z, 1e-9)
            pts = np.concatenate(
                [np.column_stack((uvz[0] + (u - uvz[0]) * f, uvz[1] + (v - uvz[1]) * f)) for u in ends]
            )
            hull = cv2.convexHull(pts.astype(np.float32), clockwise=False, returnPoints=False).reshape(-1)
            for a, b in zip(got, footprint._sides(pts[hull]), strict=True):
                np.testing.assert_array_equal(a, b)

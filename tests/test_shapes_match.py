"""Taught types found in one rendered 1920 x 1080 frame of 20 parts of 5 types (the frame the locate
speed is measured on, issue 30), and the matching's pieces against their plain forms.

The results are pinned against the renderer's truth with the tolerances test_teach_parts.py uses
(centre within 0.2 mm, angle within 1 degree modulo the symmetry found), so that a faster matcher
cannot drift; the pieces made faster (the harmonics from the grid's powers, the fit's opening on
the differences' box, every polygon's moments and facing in one pass) are compared with the
straightforward computation they replace. No timing is asserted.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.camera_model import CameraModel
from cell.sim.cameras import FAMILY, random_camera
from cell.sim.flatparts import circle, layout, random_types, rect
from cell.sim.parts import PartSpec, render_scene
from cell.vision.config import PartsConfig
from cell.vision.locate import locate, silhouettes
from cell.vision.segment import segment
from cell.vision.shapes import (
    FIT_OPENING_MM,
    HARMONICS,
    RINGS,
    Example,
    Footprint,
    far_sides,
    fine_outlines,
    fit_tolerance_mm2,
    misfit_mm2,
    net_moments,
    perimeter_mm,
    predicted_silhouette,
    teach,
)

W, H = 1920, 1080
FIVE = ("l-bracket", "t-bracket", "plate-4h", "clip", "gear")
TYPES = random_types(seed=11)
CFG = PartsConfig(jaw_max_opening_mm=40.0)


@pytest.fixture(scope="module")
def cal() -> Calibration:
    cam = CameraModel.looking_down(W, H, 0.15, (144.0, 81.0), tilt_deg=5.0, k1=-0.05)
    return Calibration("camera", CameraMap(cam), (W, H), cam)


@pytest.fixture(scope="module")
def models(cal):
    """The five types, each taught from two rendered images of one example (the bench's way)."""
    centre = cal.camera.center_table_mm
    out = []
    for name in FIVE:
        part = TYPES[name]
        examples = []
        for k, pose in enumerate(((70.0, 50.0, 25.0), (210.0, 110.0, 230.0))):
            frame = render_scene(cal.camera, [part.placed(*pose)], seed=k)
            for sil, border, _ in silhouettes(frame, cal, CFG):
                examples.append(Example.of(sil, part.height_mm, centre, f"image {k}", border))
        model = teach(name, examples, part.height_mm, max_opening_mm=40.0, jaw_face_mm=8.0, clearance_mm=3.0).model
        out.append(model)
    return out


def test_twenty_parts_of_five_types_classes_places_and_angles(cal, models):
    rng = np.random.default_rng(5)
    # 20 parts of the 5 taught types, the L bracket's mirror image (not taught) and a washer.
    parts = layout(
        [*(TYPES[n] for n in FIVE for _ in range(4)), TYPES["l-bracket-mirror"]], rng, (10, 8, 260, 154), 4.0
    )
    assert len(parts) == 21
    scene = [*parts, PartSpec("washer", "M8", 276.0, 80.0)]
    frame = render_scene(cal.camera, scene, seed=9)
    found = locate(frame, cal, CFG, models).objects
    assert len(found) == len(scene)
    by_name = {m.name: m for m in models}
    offsets = {
        n: m.match(Footprint(TYPES[n].outline_mm, list(TYPES[n].holes_mm))).angle_deg for n, m in by_name.items()
    }
    for part in scene:
        truth = np.array(part.footprint_centre_mm)
        o = min(found, key=lambda o: float(np.hypot(*(np.array(o.table_mm) - truth))))
        error = float(np.hypot(*(np.array(o.table_mm) - truth)))
        if isinstance(part, PartSpec) or part.name not in by_name:
            assert o.cls == "unknown" and not o.pick, o.reason
            continue
        assert o.cls == part.name, o.reason
        assert error < 0.2, (part.name, error)
        model = by_name[part.name]
        if model.symmetry:
            period = 360.0 / model.symmetry
            miss = (o.angle_deg - part.angle_deg - offsets[part.name] + period / 2) % period - period / 2
            assert abs(miss) < 1.0, (part.name, miss)
        assert 0.95 < o.score <= 1.0


def _harmonics_plain(grid, mask: np.ndarray) -> np.ndarray:
    """Per ring, the sum over the mask's pixels (weighed by it) of e^{-i k phi}: written out."""
    out = np.zeros((RINGS, HARMONICS), np.complex128)
    w, ring, z = mask.ravel().astype(float), grid.ring.ravel(), grid.rotor.ravel()
    for r in range(RINGS):
        sel = (ring == r) & (w > 0)
        for k in range(1, HARMONICS + 1):
            out[r, k - 1] = np.sum(w[sel] * z[sel] ** k)
    return out


def test_the_matchings_pieces_are_their_plain_forms(models):
    rng = np.random.default_rng(2)
    for model in models:
        grid = model._coarse
        mask = grid.draw(model.outline_mm + rng.normal(0, 0.3, 2), model.holes_mm, soft=True)
        want = _harmonics_plain(grid, mask)
        assert grid.tabled
        for got in (grid.harmonics(mask), grid._harmonics_direct(mask)):
            assert np.abs(got - want).max() <= 1e-9 * np.abs(want).max()

        # The fit's opening over the differences' box counts what it counts over the whole grid.
        fine = model._grid
        a = fine.draw(model.outline_mm, model.holes_mm)
        b = fine.draw(model.outline_mm + (0.5, -0.2), model.holes_mm[1:])
        r = max(1, round(FIT_OPENING_MM / fine.step_mm))
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        whole = np.count_nonzero(cv2.morphologyEx(cv2.bitwise_xor(a, b), cv2.MORPH_OPEN, kernel)) * fine.step_mm**2
        assert misfit_mm2(a, b, fine.step_mm) == whole > 0
        assert misfit_mm2(a, a, fine.step_mm) == 0.0

        # The footprint about its centroid without the turn by 0 is the same, to the bit.
        fp = Footprint(model.outline_mm + (3.0, -2.0), [h + (3.0, -2.0) for h in model.holes_mm])
        turned = fp.in_frame(fp.centroid_mm, 0.0)
        assert np.array_equal(turned[0], fp.outer - fp.centroid_mm)
        assert all(np.array_equal(a, b - fp.centroid_mm) for a, b in zip(turned[1], fp.holes, strict=True))

        # Every polygon's moments and facing at once, against one polygon at a time.
        polys = [model.outline_mm, *(h[::-1] for h in model.holes_mm)]  # holes either way round
        plain = net_moments(polys[:1]) - sum((net_moments([h]) for h in polys[1:]), np.zeros(6))
        assert np.allclose(net_moments(polys), plain, rtol=1e-12, atol=1e-9)
        foot = np.array([300.0, -50.0])
        for k, (poly, facing) in enumerate(zip(polys, far_sides(polys, foot), strict=True)):
            nxt, prv = np.roll(poly, -1, axis=0), np.roll(poly, 1, axis=0)
            d = nxt - prv
            n = np.column_stack([d[:, 1], -d[:, 0]])
            if (poly[:, 0] * nxt[:, 1] - nxt[:, 0] * poly[:, 1]).sum() < 0:
                n = -n
            want_far = np.einsum("ij,ij->i", n * (1.0 if k == 0 else -1.0), foot - poly) < 0
            assert np.array_equal(facing, want_far)


def _predicted_plain(grid, outer, holes, centre_mm, angle_deg, height_mm, camera_centre):
    """The shadow of a prism: its bottom face swept to its top face in layers, then each hole's
    light (where its bottom and top openings overlap) taken out, one hole at a time."""
    a = np.radians(angle_deg)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    placed, placed_holes = outer @ rot.T, [h @ rot.T for h in holes]
    foot = np.asarray(camera_centre[:2], float) - centre_mm
    grow = float(camera_centre[2]) / (float(camera_centre[2]) - height_mm)
    top = foot + (placed - foot) * grow
    sweep = float(np.max(np.hypot(*(top - placed).T)))
    layers = int(min(6, max(2, np.ceil(sweep / 0.4) + 1)))
    mask = np.zeros((grid.size, grid.size), np.uint8)
    for t in np.linspace(0.0, 1.0, layers):
        grid.fill(mask, placed + t * (top - placed))
    for h in placed_holes:
        light = grid.draw(h, []) & grid.draw(foot + (h - foot) * grow, [])
        mask &= 1 - light
    return mask


def test_the_predicted_silhouette_takes_out_each_holes_own_light(models):
    # The taught models, and a plate whose holes lie closer together than its sweep (tall, seen
    # from far to the side): there a hole's bottom meets its neighbour's top, which lets no light through.
    close = [circle(-4.0, 0.0, 1.8, 36), circle(0.0, 0.0, 1.8, 36), circle(4.2, 0.5, 1.6, 36)]
    cases = [(m.outline_mm, m.holes_mm, m.height_mm, m._grid) for m in models]
    cases.append((rect(-12.0, -8.0, 12.0, 8.0), close, 9.0, models[2]._grid))
    camera = np.array([144.0, 81.0, 300.0])
    for outer, holes, height, grid in cases:
        for centre, angle in (((30.0, 20.0), 15.0), ((250.0, 150.0), 200.0), ((144.0, 81.0), 90.0)):
            got = predicted_silhouette(grid, outer, holes, np.array(centre), angle, height, camera)
            want = _predicted_plain(grid, outer, holes, np.array(centre), angle, height, camera)
            assert np.array_equal(got, want), (len(holes), centre, angle)


def _fine_outlines_plain(gray, outline, fraction, min_hole_px):
    """fine_outlines written out: the upsampled threshold always masked by the blob's grown outline
    upsampled; and whether the mask took out any dark pixel (a neighbour's edge in the box)."""
    x, y, w, h = cv2.boundingRect(outline)
    x0, y0 = max(x - 4, 0), max(y - 4, 0)
    roi = gray[y0 : min(y + h + 4, gray.shape[0]), x0 : min(x + w + 4, gray.shape[1])]
    part = np.zeros(roi.shape, np.uint8)
    cv2.drawContours(part, [outline], -1, 255, -1, offset=(-x0, -y0))
    level = fraction * float(np.median(roi[cv2.dilate(part, np.ones((5, 5), np.uint8)) == 0]))
    k = int(np.clip(round(400 / max(w, h, 1)), 1, 4))
    up = cv2.resize(roi, None, fx=k, fy=k, interpolation=cv2.INTER_LINEAR)
    dark = (up < np.ceil(level)).astype(np.uint8)
    keep = cv2.resize(cv2.dilate(part, np.ones((3, 3), np.uint8)), None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST)
    masked = dark & (keep > 0)
    contours, hier = cv2.findContours(masked, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    best = max((i for i in range(len(contours)) if hier[0][i][3] == -1), key=lambda i: cv2.contourArea(contours[i]))
    holes = [c for i, c in enumerate(contours) if hier[0][i][3] == best and cv2.contourArea(c) >= min_hole_px * k**2]
    polys = [(c.reshape(-1, 2) + 0.5) / k - 0.5 + (x0, y0) for c in (contours[best], *holes)]
    return polys, not np.array_equal(masked, dark)


def test_the_fine_outlines_are_their_plain_form_with_neighbours_close(cal):
    """The blob's mask on the upsampled threshold is left out only where it changes nothing: parts
    laid 1 mm apart (a neighbour's edge inside the box) and further, against the plain form."""
    rng = np.random.default_rng(8)
    parts = layout([TYPES[n] for n in FIVE for _ in range(3)], rng, (10, 8, 260, 154), 1.0)
    frame = render_scene(cal.camera, parts, seed=4)
    gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    seg = segment(frame, CFG, part_width_px=CFG.max_part_width_mm / 0.15, noise_area_px=20.0, gray=gray)
    masked = 0
    for blob in seg.blobs:
        outer, holes = fine_outlines(gray, blob.outer, CFG.segment.threshold_fraction, 20.0)
        want, mattered = _fine_outlines_plain(gray, blob.outer, CFG.segment.threshold_fraction, 20.0)
        assert len(holes) == len(want) - 1
        for got, plain in zip((outer, *holes), want, strict=True):
            assert np.array_equal(got, plain)
        masked += mattered
    assert len(seg.blobs) >= 12 and 1 <= masked < len(seg.blobs)


def test_the_fine_outline_keeps_out_a_neighbour_joined_by_a_dim_gap():
    """Two dark parts whose one-pixel gap is dimmer than the level: upsampled, they join; the blob's
    own mask keeps its neighbour out, as the plain form does."""
    gray = np.full((120, 160), 200, np.uint8)
    gray[30:90, 20:70] = 20  # the blob
    gray[30:90, 71:110] = 20  # its neighbour...
    gray[30:90, 70] = 90  # ...a pixel away, the gap below the level (100)
    mask = np.zeros_like(gray)
    mask[30:90, 20:70] = 1
    outline = max(cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0], key=len)
    outer, holes = fine_outlines(gray, outline, 0.5, 20.0)
    (want,), mattered = _fine_outlines_plain(gray, outline, 0.5, 20.0)
    assert mattered and holes == [] and np.array_equal(outer, want)
    assert outer[:, 0].max() < 71  # not the neighbour's


def test_a_gear_taught_at_a_coarse_scale_takes_its_tolerance_from_its_examples():
    """The examples are judged against the finished model (its symmetry decides how its angle is
    found: a many-toothed part's less closely), and the tolerance a found part must meet is twice
    their worst misfit where that is more than the shape's own, at most twice the shape's own. Before,
    the consistency came from a trial model without symmetry (this camera's gear examples read 0.0
    mm2 there, 2.1 mm2 against the model used) and one found gear was left unknown at 2.8 mm2
    (scripts/bench_teach.py --seed-base 81000, camera 83004 at 0.28 mm/px)."""
    sim = random_camera(FAMILY["1920 x 1080"], 83004)
    cam = sim.camera
    exact = Calibration("camera", CameraMap(cam), (cam.width_px, cam.height_px), cam)
    gear = random_types(sim.seed)["gear"]
    rng = np.random.default_rng(7)
    examples = []
    for k in range(5):
        frame = render_scene(cam, layout([gear], rng, sim.scene_area_mm), sim.optics, seed=sim.seed * 100 + k)
        for sil, border, _ in silhouettes(frame, exact, CFG):
            examples.append(Example.of(sil, gear.height_mm, cam.center_table_mm, f"image {k}", border))
    model = teach("gear", examples, gear.height_mm, max_opening_mm=40.0, jaw_face_mm=8.0, clearance_mm=3.0).model
    assert model.symmetry > 1  # the gear's teeth
    ref = model.consistency  # the examples against the finished model
    misfits = [model.match(e.footprint, e.silhouette, e.camera_centre).misfit_mm2 for e in examples]
    assert ref["worst_misfit_mm2"] == pytest.approx(max(misfits)) and max(misfits) > 0.0
    shape_own = fit_tolerance_mm2(model.area_mm2, perimeter_mm([model.outline_mm, *model.holes_mm]))
    want = min(max(shape_own, 2.0 * max(misfits)), 2.0 * shape_own)
    assert model.tolerance_mm2 == pytest.approx(want, rel=0.02)  # (the reference example's area, not the median)
    assert all(m <= model.tolerance_mm2 for m in misfits)

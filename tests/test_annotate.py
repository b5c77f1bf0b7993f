"""Frames an operator can read: one number per part, short labels, and labels that overlap
neither each other, the legend nor another part's outline box, inside the image, at any size."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.sim.parts import random_scene, render_scene
from cell.sim.rig import default_camera
from cell.vision.annotate import COLOURS_BGR, Layout, annotate, layout, short_reason
from cell.vision.locate import locate
from cell.vision.types import LocatedPart, LocateResult
from tests.helpers import DATA

PHOTOS = DATA / "parts-photos"
SIZES = [(1920, 1080), (1280, 720), (640, 480), (320, 240)]

pytestmark = pytest.mark.timeout(120)


def _overlap(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def assert_readable(plan: Layout) -> None:
    """Every label and the legend inside the image; no two of them overlap; no label
    overlaps the outline box of a part other than its own."""
    w, h = plan.image_size
    boxes = [label.box_px for label in plan.labels] + ([plan.legend_box] if plan.legend_box else [])
    for b in boxes:
        assert 0 <= b[0] < b[2] <= w and 0 <= b[1] < b[3] <= h, (b, plan.image_size)
    for i, a in enumerate(boxes):
        for b in boxes[i + 1 :]:
            assert not _overlap(a, b), (a, b)
    for label in plan.labels:
        for part_id, box in plan.part_boxes.items():
            if part_id != label.part_id:
                assert not _overlap(label.box_px, box), (label, part_id, box)


def assert_one_number_each(plan: Layout, result: LocateResult, order) -> None:
    numbers = {label.part_id: re.findall(r"\d+", label.text) for label in plan.labels}
    assert all(len(n) <= 1 for n in numbers.values()), numbers
    for p in result.objects:
        if order is None:
            assert numbers.get(p.id, [str(p.id)]) == [str(p.id)]
        elif p.id in order:
            assert numbers[p.id] == [str(list(order).index(p.id) + 1)]
        else:
            assert numbers.get(p.id, []) == []


def _photos() -> list:
    if not PHOTOS.exists():
        return [pytest.param(None, marks=pytest.mark.skip(reason=f"{PHOTOS} is absent (../shared, outside the repo)"))]
    return sorted(PHOTOS.glob("*.png"))


@pytest.mark.parametrize("path", _photos(), ids=lambda p: getattr(p, "name", "absent"))
def test_labels_on_the_real_photos(path):
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    result = locate(image, 0.3)
    h, w = image.shape[:2]
    for order in (None, [p.id for p in result.objects if p.pick]):
        plan = layout(result, (w, h), order)
        assert_readable(plan)
        assert_one_number_each(plan, result, order)
        assert plan.unplaced == []
        wanted = [p for p in result.objects if p.cls == "unknown" or order is None or p.id in order]
        assert sorted(label.part_id for label in plan.labels) == sorted(p.id for p in wanted)


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_labels_on_rendered_scenes(size):
    w, h = size
    camera = default_camera(w, h)
    calibration = Calibration("camera", CameraMap(camera), (w, h), camera)
    for seed in (0, 1):
        image = render_scene(camera, random_scene(seed), seed=seed)
        result = locate(image, calibration)
        assert len(result.objects) >= 15
        pickable = [p.id for p in result.objects if p.pick]
        for order in (None, pickable, pickable[::-1][:5]):
            plan = layout(result, (w, h), order)
            assert_readable(plan)
            assert_one_number_each(plan, result, order)
            assert plan.unplaced == []
        drawn = annotate(image, result, pickable)
        for label in layout(result, (w, h), pickable).labels:  # what annotate drew is what layout placed
            x0, y0, _, _ = label.box_px
            assert tuple(int(v) for v in drawn[y0, x0]) == COLOURS_BGR[label.cls]


def test_text_grows_with_the_image():
    heights = {}
    for w, h in [(320, 240), (640, 480), (1280, 720), (1920, 1080), (3840, 2160)]:
        part = LocatedPart(1, "nut", "hexagon", (w / 2, h / 2), (0.0, 0.0), None, True)
        (label,) = layout(LocateResult([part], (w, h), 1.0), (w, h), [1]).labels
        heights[w] = label.box_px[3] - label.box_px[1]
    assert list(heights.values()) == sorted(heights.values())
    assert 1.8 < heights[3840] / heights[1920] < 2.2  # in proportion to the image
    assert heights[320] >= 14  # 10 px text and its padding: readable on a 320 x 240 photo


def test_crowded_and_edge_parts_keep_the_rules():
    """Parts packed close and against every border: labels still never overlap nor leave the
    image; any that find no free place are reported, not drawn over another part."""
    rng = np.random.default_rng(7)
    w, h = 640, 480
    parts = []
    centres = [(5, 5), (w - 5, 5), (5, h - 5), (w - 5, h - 5), (w / 2, 2), (w - 2, h / 2)]
    centres += [tuple(rng.uniform((0, 0), (w, h))) for _ in range(60)]
    for i, (x, y) in enumerate(centres, start=1):
        r = int(rng.integers(6, 25))
        outline = cv2.ellipse2Poly((int(x), int(y)), (r, r // 2 + 3), int(rng.integers(0, 180)), 0, 360, 20)
        cls = ["bolt", "nut", "unknown"][i % 3]
        parts.append(LocatedPart(i, cls, "round with a hole: a washer", (x, y), (0.0, 0.0), None, cls != "unknown"))
        parts[-1].outline_px = outline.reshape(-1, 1, 2)
    result = LocateResult(parts, (w, h), 1.0)
    plan = layout(result, (w, h), [p.id for p in parts if p.pick])
    assert_readable(plan)
    assert len(plan.labels) + len(plan.unplaced) == len(parts) and len(plan.labels) > len(parts) // 2
    annotate(np.full((h, w, 3), 200, np.uint8), result, [p.id for p in parts if p.pick])  # draws what it placed


def test_the_pick_order_numbers_only_the_ordered_parts():
    image = np.full((540, 960, 3), 200, np.uint8)
    parts = [LocatedPart(i, "nut", "hexagon", (200.0 * i, 300.0), (0.0, 0.0), None, True) for i in (1, 2, 3)]
    result = LocateResult(parts, (960, 540), 1.0)
    plan = layout(result, (960, 540), [3, 1])
    assert {label.part_id: label.text for label in plan.labels} == {3: "1", 1: "2"}
    assert not np.array_equal(annotate(image, result, [3, 1]), annotate(image, result, [1, 3]))
    assert {label.text for label in layout(result, (960, 540), None).labels} == {"1", "2", "3"}  # ids


@pytest.mark.parametrize(
    "reason, short",
    [
        ("round with a hole: a washer (not picked)", "washer?"),
        ("cut by the image border", "at edge"),
        ("too small (1.2 mm2): debris", "debris?"),
        ("2 holes: parts touching or overlapping", "touching?"),
        ("hexagon without a hole (a bolt standing on its head?)", "standing?"),
        ("compact, no hole, not hexagonal (a nut on its side?)", "on side?"),
        ("matches no part (solidity 0.61: touching parts or debris?)", "debris?"),
        ("something new", "unknown"),
    ],
)
def test_unknown_parts_get_a_short_label(reason, short):
    assert short_reason(reason) == short

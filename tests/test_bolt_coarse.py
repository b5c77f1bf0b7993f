"""Lying bolts at coarse scales (issue 29): at 0.3-0.45 mm per pixel a bolt's place along its own axis
within the parts goal (mean <= 0.15 mm, max <= 0.5 mm), for its footprint centre (`world_mm`) and for
the grasp point the pick plan targets (the middle of the shaft), with no bias towards head or tip.

Its ends are found on the sub-pixel outline itself, halfway between the paper's level and the bolt's
(a blurred edge's contour at the segmentation's threshold lies inside the edge by about 0.18 blur
sigmas), in millimetres on the plane of the axis, each end less its offset on the bolt's own
shadow. Before, over the coarse bench's cameras, the grasp point lay 0.09 mm towards the tip on
average (the head read 0.14 mm long), and on the -12 % barrel lens here up to 0.38 mm. The wide
sweep is scripts/bench_parts.py --min-mm-per-px 0.3 --previous (docs/parts.md).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.camera_model import CameraModel
from cell.sim.cameras import FAMILY, random_camera
from cell.sim.parts import BOLTS_MM, PartSpec, render_scene
from cell.sim.render import Optics
from cell.vision.config import PartsConfig
from cell.vision.locate import locate

GOAL_MEAN_MM, GOAL_MAX_MM = 0.15, 0.5


def _cameras() -> list[tuple[str, CameraModel, Optics]]:
    """Two of the bench's coarse families' cameras (other seeds than the bench's) and a 0.45 mm/px one."""
    out = []
    for family, seed in (("640 x 480", 2901), ("1280 x 720", 2904)):
        sim = random_camera(FAMILY[family], seed)
        assert 0.3 <= sim.mm_per_px <= 0.45, sim.describe()
        out.append((sim.describe(), sim.camera, sim.optics))
    coarse = CameraModel.looking_down(640, 480, 0.45, (100.0, 75.0), hfov_deg=70.0, tilt_deg=5.0, k1=-0.05)
    out.append(("640x480 0.45 mm/px, blur 1.2 px", coarse, Optics(blur_sigma_px=1.2, noise_sigma=3.0)))
    return out


def _bolts(camera: CameraModel, seed: int) -> list[PartSpec]:
    """Eight bolts of every size, lengths 16-35 mm, at random angles, spread over the view."""
    rng = np.random.default_rng(seed)
    corners = camera.pixel_to_table(np.array([[0.0, 0.0], [camera.width_px - 1.0, camera.height_px - 1.0]]))
    (x0, y0), (x1, y1) = corners.min(axis=0), corners.max(axis=0)
    cells = [(i, j) for i in range(4) for j in range(2)]
    parts = []
    for n, (i, j) in enumerate(cells):
        x = x0 + (x1 - x0) * (0.16 + 0.225 * i)
        y = y0 + (y1 - y0) * (0.3 + 0.4 * j)
        size = list(BOLTS_MM)[n % 3]
        length = float(rng.choice([16, 20, 25, 30, 35]))
        parts.append(PartSpec("bolt", size, float(x), float(y), float(rng.uniform(0, 360)), length))
    return parts


def _errors(camera: CameraModel, optics: Optics, parts: list[PartSpec], seed: int):
    """Per bolt found: (its centre's, its grasp point's) error along its true axis, mm."""
    cal = Calibration("camera", CameraMap(camera), (camera.width_px, camera.height_px), camera)
    result = locate(render_scene(camera, parts, optics, seed=seed), cal, PartsConfig())
    truth = np.array([p.footprint_centre_mm for p in parts])
    out = []
    for obj in result.objects:
        part = parts[int(np.hypot(*(truth - np.array(obj.table_mm)).T).argmin())]
        assert obj.cls == "bolt", obj.reason
        a = math.radians(part.angle_deg)
        axis = np.array([math.cos(a), math.sin(a)])
        centre = np.array(obj.table_mm) - part.footprint_centre_mm
        grasp = np.array(obj.grasp_mm) - part.footprint_centre_mm - part.shaft_middle_offset_mm * axis
        out.append((float(centre @ axis), float(grasp @ axis)))
    assert len(out) == len(parts)
    return out


@pytest.mark.parametrize("index", range(3))
def test_lying_bolts_at_coarse_scales_along_their_axis(index):
    name, camera, optics = _cameras()[index]
    errors = []
    for seed in (1, 2):
        errors += _errors(camera, optics, _bolts(camera, 29 * index + seed), seed)
    centre, grasp = np.array(errors).T
    for what, e in (("centre", centre), ("grasp point", grasp)):
        assert np.abs(e).mean() <= GOAL_MEAN_MM and np.abs(e).max() <= GOAL_MAX_MM, (name, what, np.round(e, 3))
    # no lean towards the head or the tip (the 1-px profile put the grasp point 0.09 mm tipwards)
    assert abs(grasp.mean()) <= 0.05 and abs(centre.mean()) <= 0.05, (name, grasp.mean(), centre.mean())


def test_the_grasp_point_holds_whatever_the_blur():
    """A bolt below a 0.37 mm/px camera, blurred 0.5-1.3 px, at three angles: its head and grasp point
    along the axis within 0.1 mm. At the segmentation's threshold the head read 0.12-0.25 mm short,
    more with more blur, and the grasp point moved with it."""
    camera = CameraModel.looking_down(640, 480, 0.37, (100.0, 75.0), hfov_deg=70.0)
    cal = Calibration("camera", CameraMap(camera), (camera.width_px, camera.height_px), camera)
    for blur in (0.5, 1.3):
        for angle in (10.0, 100.0, 235.0):
            part = PartSpec("bolt", "M8", 100.0, 75.0, angle, 25.0)
            frame = render_scene(camera, [part], replace(Optics(), blur_sigma_px=blur, noise_sigma=0.0), seed=1)
            (obj,) = locate(frame, cal, PartsConfig()).objects
            a = math.radians(angle)
            axis = np.array([math.cos(a), math.sin(a)])
            head = (np.array(obj.head_mm) - part.head_centre_mm) @ axis
            grasp = (np.array(obj.grasp_mm) - part.footprint_centre_mm) @ axis - part.shaft_middle_offset_mm
            assert abs(head) <= 0.1 and abs(grasp) <= 0.1, (blur, angle, head, grasp)

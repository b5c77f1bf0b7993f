"""The simulated world, arm and camera: grips succeed or miss by geometry alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.sim.cell import outline_gap_mm, paper_layout
from cell.sim.parts import PartSpec
from cell.sim.rig import default_camera
from cell.sim.sim_arm import SimArm
from cell.sim.sim_camera import SimCamera
from cell.sim.world import Bin, Truth, World
from drivers.arm.config import Workspace
from drivers.arm.errors import HardwareFault, OutOfReach

TRUTH = Truth(0.0, -132.0, 40.0, 0.0)
BINS = [Bin("nut", (200.0, 60.0), 40.0), Bin("bolt", (-200.0, 60.0), 40.0)]
NUT = PartSpec("nut", "M8", 100.0, 50.0, 0.0)
BOLT = PartSpec("bolt", "M6", 100.0, 50.0, 30.0, 20.0)  # axis at 30 deg


def world(*parts):
    return World(list(parts), TRUTH, BINS)


def robot(x, y):
    return x + TRUTH.tx_mm, y + TRUTH.ty_mm


@pytest.mark.parametrize("dx,dy,held", [(0, 0, True), (1.4, 0, True), (1.6, 0, False), (0, 0.9, True), (0, 1.2, False)])
def test_nut_grip_tolerance_across_and_along_the_jaws(dx, dy, held):
    w = world(NUT)
    got = w.grip((*robot(100 + dx, 50 + dy), 2.0), 0.0)  # jaws close along X
    assert (got.part is not None) == held
    assert (w.held() is not None) == held


def test_jaws_above_the_part_miss_it():
    assert world(NUT).grip((*robot(100, 50), 7.0), 0.0).part is None


def test_bolt_needs_the_jaws_across_its_axis_and_on_its_body():
    across = 30.0 + 90.0
    assert world(BOLT).grip((*robot(100, 50), 3.5), across + 4.0).part is not None
    assert "deg off" in world(BOLT).grip((*robot(100, 50), 3.5), across + 8.0).reason
    a = math.radians(30.0)
    u = BOLT._bolt_axis_offset_mm() + 20.0 - 1.0  # 1 mm from the tip: the jaws would slip off
    tip = (100 + u * math.cos(a), 50 + u * math.sin(a))
    assert "off the body" in world(BOLT).grip((*robot(*tip), 3.5), across).reason
    side = (100 - 2 * math.sin(a), 50 + 2 * math.cos(a))  # 2 mm off the axis
    assert "off the axis" in world(BOLT).grip((*robot(*side), 3.5), across).reason


def test_release_drops_into_the_bin_below_or_back_onto_the_table():
    w = world(NUT, PartSpec("nut", "M5", 20.0, 20.0))
    w.grip((*robot(100, 50), 2.0), 0.0)
    assert "bin nut" in w.release((210.0, 70.0, 60.0))
    assert [p.spec.kind for p in w.in_bin("nut")] == ["nut"]
    w.grip((*robot(20, 20), 2.0), 0.0)
    assert "on the table" in w.release((*robot(50.0, 60.0), 30.0))
    assert [(p.spec.x_mm, p.spec.y_mm) for p in w.on_table()] == [pytest.approx((50.0, 60.0))]


def test_sim_arm_refuses_out_of_workspace_and_faults_into_the_table():
    arm = SimArm(
        world(NUT), Workspace(x_min_mm=-300, x_max_mm=300, y_min_mm=-300, y_max_mm=300, z_min_mm=-10, z_max_mm=200)
    )
    with arm:
        with pytest.raises(OutOfReach):
            arm.move_to(400.0, 0.0, 10.0)
        arm.move_to(0.0, 100.0, 50.0)
        t = arm.motion_time_s
        arm.move_to(0.0, 100.0, 20.0)
        assert arm.motion_time_s - t == pytest.approx(30.0 / arm.speed_mm_s)
        with pytest.raises(HardwareFault, match="into the table"):
            arm.move_to(0.0, 100.0, -3.0)
        assert arm.status().state == "fault"
        arm.unlock()  # no controller restarted: a torque released by a fault stays released
        with pytest.raises(HardwareFault, match="torque is off"):
            arm.move_to(0.0, 100.0, 20.0)
        assert arm.commands[-1] == ("unlock",)


def test_paper_layout_has_the_papers_parts_and_a_washer_none_touching():
    parts = paper_layout()
    kinds = [p.kind for p in parts]
    assert kinds.count("bolt") == 9 and kinds.count("nut") == 8 and kinds.count("washer") == 1
    gaps = [outline_gap_mm(a, b) for i, a in enumerate(parts) for b in parts[i + 1 :]]
    assert min(gaps) > 3.0


@pytest.mark.slow
def test_square_to_base_layout_lays_every_bolt_across_the_line_from_the_base_none_touching():
    base = (144.0, -40.0)  # an arm's base axis in the table frame
    parts = paper_layout(base_table_mm=base)
    bolts = [p for p in parts if p.kind == "bolt"]
    assert len(bolts) == 9 and sum(p.kind == "nut" for p in parts) == 8
    for b in bolts:  # the shaft's middle, where the jaws close, is where the base's line meets the axis square
        d = np.array([math.cos(math.radians(b.angle_deg)), math.sin(math.radians(b.angle_deg))])
        middle = np.array([b.x_mm, b.y_mm]) + b.shaft_middle_offset_mm * d
        assert abs(np.dot(middle - base, d)) < 1e-9
    gaps = [outline_gap_mm(a, b) for i, a in enumerate(parts) for b in parts[i + 1 :]]
    assert min(gaps) > 3.0


def test_sim_camera_renders_only_what_is_on_the_table():
    cam_model = default_camera(640, 360)
    w = world(NUT)
    with SimCamera(w, cam_model) as cam:
        with_part = cam.capture().astype(float)
        w.grip((*robot(100, 50), 2.0), 0.0)
        without = cam.capture().astype(float)
    px = cam_model.project(np.array([[105.0, 50.0]]), 3.0)[0].round().astype(int)  # on the nut, off its hole
    assert with_part[px[1], px[0]].mean() < 100 < without[px[1], px[0]].mean()
    assert cam.frames == 2 and cam.render_s > 0

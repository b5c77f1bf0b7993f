"""Table -> robot mapping, the taught fit, per-class targets, reach checks and pick order."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cell.errors import InputError
from cell.planning import Planner, TableToRobot, Unreachable, fit_table_to_robot, load_taught, save_taught
from cell.run_config import PlanningConfig
from cell.vision.types import LocatedPart

CFG = PlanningConfig()


def part(cls="nut", xy=(100.0, 50.0), angle=None, pid=1, grasp=None):
    return LocatedPart(pid, cls, "test", (0.0, 0.0), xy, angle, cls != "unknown", grasp)


def test_offset_frame_adds_the_configured_offset_and_table_height():
    frame = TableToRobot.from_offset(PlanningConfig(offset_x_mm=150.0, offset_y_mm=-100.0, table_z_mm=-20.0))
    assert frame.to_robot([10.0, 20.0]).tolist() == [[160.0, -80.0]]
    t = Planner(
        PlanningConfig(offset_x_mm=150.0, offset_y_mm=-100.0, table_z_mm=-20.0, workspace={"z_min_mm": -50}), frame
    ).target(part(xy=(10.0, 20.0)))
    assert t.robot_mm == (160.0, -80.0, -20.0 + CFG.nut.pick_above_table_mm)
    assert t.approach_z_mm == -20.0 + CFG.nut.approach_above_table_mm


@settings(max_examples=50, deadline=None)
@given(st.floats(-180, 180), st.floats(-300, 300), st.floats(-300, 300), st.floats(0.9, 1.1), st.booleans())
def test_fit_recovers_a_rigid_or_similar_transform(rot, tx, ty, scale, with_scale):
    truth = TableToRobot(rot, tx, ty, 5.0, scale if with_scale else 1.0)
    table = np.array([[0.0, 0.0], [264.0, 0.0], [0.0, 176.0], [264.0, 176.0]])
    fit, res = fit_table_to_robot(table, truth.to_robot(table), 5.0, with_scale)
    assert res.max() < 1e-6
    assert np.allclose(fit.to_robot([[50.0, 70.0]]), truth.to_robot([[50.0, 70.0]]), atol=1e-6)
    assert np.allclose(fit.to_table(fit.to_robot([[3.0, 4.0]])), [[3.0, 4.0]], atol=1e-9)


def test_fit_reports_residuals_of_a_badly_jogged_point():
    truth = TableToRobot(10.0, 20.0, 30.0, 0.0)
    table = np.array([[0.0, 0.0], [264.0, 0.0], [0.0, 176.0], [264.0, 176.0]])
    robot = truth.to_robot(table)
    robot[3] += (4.0, 0.0)
    _, res = fit_table_to_robot(table, robot, 0.0)
    assert res.max() > 1.0


def test_fit_needs_three_points():
    with pytest.raises(InputError, match="3 or more"):
        fit_table_to_robot(np.zeros((2, 2)), np.zeros((2, 2)), 0.0)


def test_taught_frame_round_trips_and_bad_files_are_one_line_errors(tmp_path):
    fit = TableToRobot(12.5, -10.0, 40.0, 3.0, 1.001)
    save_taught(tmp_path / "f.json", fit, [], np.zeros(0))
    assert load_taught(tmp_path / "f.json") == fit
    with pytest.raises(InputError, match="not found"):
        load_taught(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(InputError, match="not a taught robot frame"):
        load_taught(tmp_path / "bad.json")


def test_bolt_jaws_close_across_the_axis_in_the_robot_frame():
    frame = TableToRobot(30.0, -132.0, 40.0, 0.0)
    t = Planner(CFG, frame).target(part("bolt", (132.0, 100.0), angle=20.0))
    assert t.jaw_angle_deg == pytest.approx(20.0 + 90.0 + 30.0 - 180.0)
    assert Planner(CFG, frame).target(part("nut")).jaw_angle_deg is None


def test_grasp_point_is_used_when_vision_gives_one():
    t = Planner(CFG, TableToRobot.from_offset(CFG)).target(part("bolt", (100.0, 50.0), 0.0, grasp=(103.0, 50.0)))
    assert t.table_mm == (103.0, 50.0)


@pytest.mark.parametrize("xy,why", [((900.0, 50.0), "outside the workspace"), ((132.0, -10.0), "reach")])
def test_targets_outside_workspace_or_reach_are_refused(xy, why):
    with pytest.raises(Unreachable, match=why):
        Planner(CFG, TableToRobot.from_offset(CFG)).target(part(xy=xy))


def test_unknown_parts_are_never_targets():
    with pytest.raises(Unreachable, match="not picked"):
        Planner(CFG, TableToRobot.from_offset(CFG)).target(part("unknown"))


def test_pick_order_nearest_rows_and_as_found():
    parts = [part(xy=(200.0, 10.0), pid=1), part(xy=(10.0, 100.0), pid=2), part(xy=(120.0, 10.0), pid=3)]
    frame = TableToRobot.from_offset(CFG)
    here = tuple(frame.to_robot([12.0, 98.0])[0])
    assert [p.id for p in Planner(CFG, frame).order(parts, here)] == [2, 3, 1]
    rows = PlanningConfig(pick_order="rows")
    assert [p.id for p in Planner(rows, frame).order(parts, here)] == [3, 1, 2]
    found = PlanningConfig(pick_order="as-found")
    assert [p.id for p in Planner(found, frame).order(parts, here)] == [1, 2, 3]


def test_workspace_must_be_ordered():
    with pytest.raises(ValueError, match="x_min_mm"):
        PlanningConfig(workspace={"x_min_mm": 10, "x_max_mm": 0})


def test_angle_wraps_into_half_turn():
    frame = TableToRobot(170.0, 0.0, 0.0, 0.0)
    assert frame.angle_to_robot(100.0) == pytest.approx(-90.0)
    assert frame.angle_to_robot(-100.0) == pytest.approx(70.0)


@pytest.mark.parametrize(
    "xy,angle", [((float("nan"), 50.0), None), ((100.0, float("inf")), None), ((100.0, 50.0), float("nan"))]
)
def test_a_target_that_is_not_a_finite_number_never_reaches_the_arm(xy, angle):
    cls = "nut" if angle is None else "bolt"
    with pytest.raises(Unreachable, match="not a finite number"):
        Planner(CFG, TableToRobot.from_offset(CFG)).target(part(cls, xy, angle))

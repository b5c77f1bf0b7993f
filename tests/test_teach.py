"""Teaching by jogging: the pose at 'ok' is recorded for each circle, then fitted and checked."""

from __future__ import annotations

import pytest

from cell.config import CellConfig
from cell.planning import TeachRejected
from cell.teach import TaughtPoint, check_fit, circle_table_mm, fit_points, jog_session
from drivers.arm.config import ArmConfig
from drivers.arm.mock import MockArm

CONFIG = CellConfig()


def scripted(lines):
    it = iter(lines)
    return lambda prompt: next(it)


def test_jogging_onto_three_circles_records_their_poses():
    arm = MockArm(ArmConfig(kind="mock"))
    told = []
    script = [
        "x 10",
        "y 20",
        "z 5",
        "ok",  # circle 1 -> (10, 20)
        "to 100 50 5",
        "x",
        "x abc",
        "ok",  # circle 13 -> (100, 50); bad commands only explain
        "skip",  # circle 144 skipped
        "to 30 120 5",
        "ok",
    ]  # circle 156 -> (30, 120)
    with arm:
        points = jog_session(arm, [1, 13, 144, 156], CONFIG, scripted(script), told.append)
    assert [(p.circle, p.robot_mm) for p in points] == [(1, (10.0, 20.0)), (13, (100.0, 50.0)), (156, (30.0, 120.0))]
    assert any("not a number" in t for t in told) and any("commands:" in t for t in told)


def test_quit_ends_the_session_with_what_was_recorded():
    with MockArm(ArmConfig(kind="mock")) as arm:
        points = jog_session(arm, [1, 13], CONFIG, scripted(["ok", "quit"]), lambda line: None)
    assert [p.circle for p in points] == [1]


def test_circle_numbers_are_row_by_row_and_checked():
    assert circle_table_mm(1, CONFIG) == (0.0, 0.0)
    assert circle_table_mm(14, CONFIG) == (0.0, 16.0)
    assert circle_table_mm(156, CONFIG) == (264.0, 176.0)
    with pytest.raises(Exception, match="does not exist"):
        circle_table_mm(157, CONFIG)


def test_a_bad_point_is_refused_with_its_circle():
    points = [
        TaughtPoint(1, (0.0, 0.0), (10.0, 10.0)),
        TaughtPoint(13, (264.0, 0.0), (274.0, 10.0)),
        TaughtPoint(144, (0.0, 176.0), (10.0, 186.0)),
        TaughtPoint(156, (264.0, 176.0), (279.0, 186.0)),
    ]
    fit, residuals = fit_points(points, CONFIG)
    with pytest.raises(TeachRejected, match="exceeds"):
        check_fit(points, residuals, CONFIG)
    fit, residuals = fit_points(points[:3], CONFIG)
    check_fit(points[:3], residuals, CONFIG)
    assert fit.to_robot([[0.0, 0.0]])[0].tolist() == pytest.approx([10.0, 10.0])

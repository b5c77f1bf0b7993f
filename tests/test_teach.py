"""Teaching by jogging: the pose at 'ok' is recorded for each circle, then fitted and checked."""

from __future__ import annotations

from pathlib import Path

import pytest

from cell.cli import main
from cell.config import CellConfig
from cell.errors import InputError
from cell.planning import TeachRejected, save_taught
from cell.teach import TaughtPoint, check_circles_reachable, check_fit, circle_table_mm, fit_points, jog_session
from drivers.arm.config import ArmConfig
from drivers.arm.mock import MockArm
from tests.helpers import REPO

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


def stock_grbl_line(tmp_path: Path) -> Path:
    """configs/arm-grbl.toml (a stock GRBL: 200 x 200 x 100 mm) with plate circle 1 at the machine's origin."""
    cfg = tmp_path / "line.toml"
    cfg.write_text(
        (REPO / "configs" / "arm-grbl.toml").read_text()
        + f'\n[planning]\nframe = "offset"\noffset_x_mm = 0.0\noffset_y_mm = 0.0\ntaught_path = "{tmp_path / "frame.json"}"\n'
    )
    return cfg


@pytest.mark.timeout(60)  # opens a pty with the emulated GRBL
def test_teach_refuses_circles_outside_the_workspace_before_any_motion(grbl, tmp_path, capsys, monkeypatch):
    """Circle 13 lies at x = 264 mm, beyond a stock GRBL's 200 mm: refused before connecting,
    where it once failed half-way through the session and left the arm in feed hold."""
    emu, path = grbl
    monkeypatch.setattr("builtins.input", lambda prompt: pytest.fail(f"the session started: {prompt}"))
    code = main(["teach", "--config", str(stock_grbl_line(tmp_path)), "--port", path, "--circles", "1", "13", "144"])
    assert code == 2  # bad input before anything ran (docs/running-the-cell.md, exit codes)
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "circle 13 lies outside the arm's reach by planning.offset_x_mm 0 mm, offset_y_mm 0 mm" in err
    assert "circle 13 at robot (264.0, 0.0) mm: target (264.0, 0.0, 0.0) mm: x = 264 mm is outside the workspace" in err
    assert "[0, 200] mm (arm.serial.workspace)" in err
    assert "e.g. --circles 1 10 144 153" in err  # the plate's corners inside the machine
    assert emu.lines_received == []  # not a move, not even the setup lines
    assert not (tmp_path / "frame.json").exists()


@pytest.mark.timeout(60)
def test_teach_jogs_onto_circles_the_stock_machine_reaches(grbl, tmp_path, capsys, monkeypatch):
    emu, path = grbl
    answers = iter(["to 0 0 0", "ok", "to 176 0 0", "ok", "to 0 176 0", "ok"])
    monkeypatch.setattr("builtins.input", lambda prompt: next(answers))
    cfg = stock_grbl_line(tmp_path)
    assert main(["teach", "--config", str(cfg), "--port", path, "--circles", "1", "9", "144"]) == 0
    assert "residual 0.000 mm" in capsys.readouterr().out
    assert emu.tool_pose()[:3] == (0.0, 176.0, 0.0)
    assert (tmp_path / "frame.json").exists()


def test_reachability_uses_the_taught_frame_when_teaching_again(tmp_path):
    config = CellConfig.model_validate({"planning": {"frame": "taught", "taught_path": str(tmp_path / "f.json")}})
    arm = MockArm(ArmConfig(kind="mock"))  # a GRBL's default 200 x 200 mm
    with pytest.raises(InputError, match=r"circle 1 lies outside .* by planning.offset_x_mm -132 mm"):
        check_circles_reachable(arm, [1, 9], config)  # no taught frame yet: the offset's -132 mm
    points = [
        TaughtPoint(n, circle_table_mm(n, CONFIG), (x, y)) for n, x, y in [(1, 10, 10), (9, 186, 10), (144, 10, 186)]
    ]
    fit, residuals = fit_points(points, CONFIG)
    save_taught(tmp_path / "f.json", fit, [p.to_dict() for p in points], residuals)
    check_circles_reachable(arm, [1, 9, 144], config)
    with pytest.raises(InputError, match=r"circles 13, 156 lie outside .* by the taught frame"):
        check_circles_reachable(arm, [1, 13, 156], config)

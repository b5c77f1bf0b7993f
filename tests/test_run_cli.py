"""`run-cell --dry-run` end to end on the built-in simulated cell, and the CLI's errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from cell.cli import main
from cell.summary import counts_from_log
from tests.helpers import REPO, audit_of, ctrl_c_after_first_pick

pytestmark = pytest.mark.timeout(240)  # whole runs; the Ctrl-C test runs run-cell as a subprocess


@pytest.mark.slow
def test_dry_run_clears_the_papers_table_and_agrees_with_its_log(tmp_path, capsys):
    assert main(["--dry-run", "--log-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "DONE" in out and "picked 9 bolts, 8 nuts; 0 misses" in out
    assert out.count("pick ") >= 17 and "software" in out
    events = audit_of(tmp_path)
    summary = next(e for e in events if e["kind"] == "summary")
    assert {k: summary[k] for k in counts_from_log(events)} == counts_from_log(events)
    assert summary["picked"] == {"bolt": 9, "nut": 8} and summary["unknown_left"] == 1
    truth = next(e for e in events if e["kind"] == "sim_truth")["where"]
    assert truth == {"bin:bolt": {"bolt": 9}, "bin:nut": {"nut": 8}, "table": {"washer": 1}}
    assert events[-1]["kind"] == "run_end" and events[-1]["exit_code"] == 0
    assert len((tmp_path).glob("run-*.log").__next__().read_text()) > 0


@pytest.mark.slow
def test_a_wrong_offset_misses_retries_and_fails(tmp_path, capsys):
    cfg = tmp_path / "one-retry.toml"
    # one retry shows it as well as two, in fewer frames; a 960 x 540 camera, a quarter of the pixels to render
    # and search (without the drift watch's marks, which it does not find, and with the plate's height doubt,
    # a warning these runs are not about, let through)
    cfg.write_text(f"[run]\nmax_retries = 1\n{SMALL_CAMERA}")
    code = main(["--dry-run", "--config", str(cfg), "--offset-x-mm", "3", "--log-dir", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 1
    events = audit_of(tmp_path)
    c = counts_from_log(events)
    assert c["misses"] > 0 and c["retries"] > 0 and c["failed"] > 0
    assert sum(c["picked"].values()) < 17
    assert f"{c['failed']} failed" in out


SMALL_CAMERA = (
    "[camera]\nwidth_px = 960\nheight_px = 540\n[sim]\nreference_marks_mm = []\n"
    "[calibration]\nmax_height_cost_mm = 5.0\n"
)


def test_a_missing_config_is_a_one_line_error_and_a_fault_in_the_log(tmp_path, capsys):
    assert main(["--config", "/nonexistent/cell.toml", "--log-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "config file not found" in err and err.count("\n") == 1
    events = audit_of(tmp_path)
    assert events[0]["kind"] == "fault" and "config file not found" in events[0]["reason"]
    assert events[-1]["kind"] == "run_end" and events[-1]["exit_code"] == 2


def test_no_config_and_no_dry_run_is_refused(capsys):
    import argparse

    from cell.commands.run import run_cell
    from cell.errors import ConfigError

    try:
        run_cell(argparse.Namespace(run_config=None, dry_run=False))
    except ConfigError as e:
        assert "--dry-run" in str(e)
    else:
        raise AssertionError("ran without a config")


def test_a_wrong_config_value_names_the_key(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[run]\nmax_retries = -1\n")
    assert main(["--config", str(bad), "--dry-run", "--log-dir", str(tmp_path / "logs")]) == 2
    assert "run.max_retries" in capsys.readouterr().err
    assert "run.max_retries" in audit_of(tmp_path / "logs")[0]["reason"]


def test_a_missing_camera_is_a_fault_in_the_log(tmp_path, capsys):
    cal = tmp_path / "cal.json"
    from cell.calibration.models import CameraMap
    from cell.calibration.store import Calibration
    from cell.sim.rig import default_camera

    cam = default_camera(64, 48)
    Calibration("camera", CameraMap(cam), (64, 48), cam).save(cal)
    cfg = tmp_path / "cell.toml"
    cfg.write_text(
        f'[camera]\nsource = "{tmp_path / "no-such-folder"}"\nwidth_px = 64\nheight_px = 48\n'
        f'[calibration]\nactive_path = "{cal}"\n[run]\nlog_dir = "{tmp_path / "logs"}"\n'
    )
    assert main(["--config", str(cfg), "--dry-run"]) == 2
    assert "no such device" in capsys.readouterr().err
    events = audit_of(tmp_path / "logs")
    assert events[-2]["kind"] == "fault" and "no such device" in events[-2]["reason"]
    assert events[-1]["kind"] == "run_end"


def test_an_empty_camera_folder_faults_in_idle_and_exits_non_zero(tmp_path, capsys):
    from cell.calibration.models import CameraMap
    from cell.calibration.store import Calibration
    from cell.sim.rig import default_camera

    cam = default_camera(64, 48)
    Calibration("camera", CameraMap(cam), (64, 48), cam).save(tmp_path / "cal.json")
    (tmp_path / "frames").mkdir()
    cfg = tmp_path / "cell.toml"
    cfg.write_text(
        f'[camera]\nsource = "{tmp_path / "frames"}"\nwidth_px = 64\nheight_px = 48\n'
        f'[calibration]\nactive_path = "{tmp_path / "cal.json"}"\n[run]\nlog_dir = "{tmp_path / "logs"}"\n'
    )
    assert main(["--config", str(cfg), "--dry-run"]) == 3
    out = capsys.readouterr().out
    assert "FAULT" in out and "no images" in out
    events = audit_of(tmp_path / "logs")
    assert any(e["kind"] == "fault" and e["state"] == "idle" for e in events)


def test_bare_run_cell_prints_the_short_usage(capsys):
    assert main([]) == 2
    assert "run-cell --dry-run" in capsys.readouterr().err  # more in tests/test_cli_wording.py


def test_teach_fits_prints_residuals_and_writes(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[planning]\ntaught_path = "{tmp_path / "frame.json"}"\n')
    # Circles 1, 13, 144, 156 (the plate's corners) at robot = table + (-132, 40), rotated 0.
    points = ["1", "-132", "40", "13", "132", "40", "144", "-132", "216", "156", "132", "216"]
    args = ["teach", "--config", str(cfg)]
    for i in range(0, len(points), 3):
        args += ["--point", *points[i : i + 3]]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "residual 0.000 mm" in out and (tmp_path / "frame.json").exists()


def test_teach_refuses_a_fit_with_a_large_residual(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[planning]\ntaught_path = "{tmp_path / "frame.json"}"\n')
    args = [
        "teach",
        "--config",
        str(cfg),
        "--point",
        "1",
        "-132",
        "40",
        "--point",
        "13",
        "132",
        "40",
        "--point",
        "144",
        "-132",
        "216",
        "--point",
        "156",
        "137",
        "216",
    ]
    assert main(args) == 2
    assert "exceeds planning.teach_max_residual_mm" in capsys.readouterr().err
    assert not (tmp_path / "frame.json").exists()


def test_diagram_prints_mermaid(capsys):
    assert main(["diagram"]) == 0
    assert capsys.readouterr().out.startswith("stateDiagram-v2")


def test_example_configs_load():
    from cell.config import load_config

    for name in ("sim.toml", "example-line.toml"):
        load_config(REPO / "configs" / name)


def line_config(tmp_path: Path, nut_bin=(250.0, 250.0, 60.0)) -> Path:
    """A line-like config: stills of the paper's table in a folder, a serial arm (mocked in the dry run)."""
    import cv2

    from cell.calibration.models import CameraMap
    from cell.calibration.store import Calibration
    from cell.sim.cell import paper_layout
    from cell.sim.parts import render_scene
    from cell.sim.rig import default_camera

    cam = default_camera(960, 540)
    (tmp_path / "frames").mkdir()
    cv2.imwrite(str(tmp_path / "frames" / "000.png"), render_scene(cam, paper_layout()))
    Calibration("camera", CameraMap(cam), (960, 540), cam).save(tmp_path / "cal.json")
    cfg = tmp_path / "line.toml"
    cfg.write_text(f"""
[camera]
source = "{tmp_path / "frames"}"
width_px = 960
height_px = 540
loop = true
[calibration]
active_path = "{tmp_path / "cal.json"}"
[arm]
kind = "serial"
port = "/dev/ttyUSB0"
[arm.serial.workspace]
x_max_mm = 300.0
y_max_mm = 300.0
[arm.serial.commands]
rotate = "G0 A{{angle_deg:.2f}}"
[planning]
offset_x_mm = 20.0
offset_y_mm = 20.0
[planning.workspace]
x_min_mm = 0.0
y_min_mm = 0.0
z_min_mm = 0.0
reach_min_mm = 0.0
[planning.bolt]
pick_above_table_mm = 3.5
jaw_across_axis = true
bin_robot_mm = [290.0, 20.0, 60.0]
[planning.nut]
pick_above_table_mm = 2.0
bin_robot_mm = {list(nut_bin)}
[run]
log_dir = "{tmp_path / "logs"}"
""")
    return cfg


@pytest.mark.slow
def test_dry_run_of_a_line_config_rehearses_every_pick_with_the_mock_arm(tmp_path, capsys):
    assert main(["--config", str(line_config(tmp_path)), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "rehearsed 17 picks" in out
    events = audit_of(tmp_path / "logs")
    assert counts_from_log(events)["rehearsed"] == 17
    assert next(e for e in events if e["kind"] == "run_start")["arm"] == "MockArm"


def test_a_bin_out_of_reach_is_a_fault_before_anything_moves(tmp_path, capsys):
    assert main(["--config", str(line_config(tmp_path, (290.0, 280.0, 60.0))), "--dry-run"]) == 3
    assert "bins out of reach: planning.nut.bin_robot_mm" in capsys.readouterr().out
    events = audit_of(tmp_path / "logs")
    assert [e["command"] for e in events if e["kind"] == "arm"] == ["connect"]


@pytest.mark.slow
def test_ctrl_c_stops_safely_and_the_log_says_where(tmp_path):

    cfg = tmp_path / "rt.toml"
    cfg.write_text(
        f"[sim]\nrealtime = true\nperfect_calibration = true\nspeed_mm_s = 500.0\n"
        f'[run]\nlog_dir = "{tmp_path / "logs"}"\n'
    )
    code, rest = ctrl_c_after_first_pick("--config", str(cfg))
    assert code == 130
    assert "STOPPED: Ctrl-C" in rest
    events = audit_of(tmp_path / "logs")
    steps = [e["step"] for e in events if e["kind"] == "safe_step" and e["ok"]]
    assert steps[-2:] == ["home", "release torque"]
    assert events[-1]["kind"] == "run_end" and events[-1]["state"] == "stopped"


@pytest.mark.slow
def test_a_stale_calibration_camera_moved_shows_as_misses(tmp_path, capsys):
    """Without reference marks (no drift watch) a moved camera shows only as misses; with
    them the cell stops before the first pick (tests/test_drift_watch.py)."""
    cfg = tmp_path / "bumped.toml"
    cfg.write_text(
        f"[sim]\nperfect_calibration = true\ncamera_bumped_mm = [0.0, 2.5]\nreference_marks_mm = []\n"
        f'[run]\nmax_retries = 1\nlog_dir = "{tmp_path / "logs"}"\n'
        "[camera]\nwidth_px = 960\nheight_px = 540\n"
    )
    assert main(["--config", str(cfg)]) == 1
    c = counts_from_log(audit_of(tmp_path / "logs"))
    assert c["misses"] > 0 and c["failed"] > 0


@pytest.mark.slow
def test_a_rotated_robot_frame_needs_teach_and_then_clears_the_table(tmp_path, capsys):
    """The table sits 2 degrees rotated in the robot frame: the paper's fixed offset misses
    the far parts; a frame taught from four jogged circles picks everything."""
    import math

    truth = (2.0, -132.0, 40.0)
    base = (
        f"[sim]\nperfect_calibration = true\ntruth_rotation_deg = {truth[0]}\nreference_marks_mm = []\n"
        f'[run]\nmax_retries = 0\nlog_dir = "{tmp_path / "logs"}"\n'
        "[camera]\nwidth_px = 960\nheight_px = 540\n"
    )
    offset_cfg = tmp_path / "offset.toml"
    offset_cfg.write_text(base)
    assert main(["--config", str(offset_cfg)]) == 1

    taught_cfg = tmp_path / "taught.toml"
    taught_cfg.write_text(base + f'[planning]\nframe = "taught"\ntaught_path = "{tmp_path / "frame.json"}"\n')
    a = math.radians(truth[0])
    args = ["teach", "--config", str(taught_cfg)]
    for circle, (x, y) in {1: (0, 0), 13: (264, 0), 144: (0, 176), 156: (264, 176)}.items():
        rx = math.cos(a) * x - math.sin(a) * y + truth[1]
        ry = math.sin(a) * x + math.cos(a) * y + truth[2]
        args += ["--point", str(circle), f"{rx:.3f}", f"{ry:.3f}"]
    assert main(args) == 0
    assert "rotation +2.000 deg" in capsys.readouterr().out
    assert main(["--config", str(taught_cfg)]) == 0

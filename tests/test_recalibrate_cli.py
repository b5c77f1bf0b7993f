"""scripts/recalibrate.py, `run-cell recalibrate` and `run-cell map`, driven as operators and other tools call them."""

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cell.calibration.recalibrate import build_parser as script_parser
from cell.camera_model import CameraModel
from cell.cli import build_parser as cli_parser
from cell.config import CellConfig
from cell.sim.render import render_plate

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]  # the CLIs run as subprocesses, end to end

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "recalibrate.py"
CAMERA = CameraModel.looking_down(1280, 720, 0.30, (132, 88), tilt_deg=3, k1=-0.06)


def run(*args, cwd=None):
    return subprocess.run([sys.executable, *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=120)


def run_cell(*args):
    return run("-m", "cell.cli", *args, cwd=ROOT)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("recal")
    cv2.imwrite(str(d / "plate.png"), render_plate(CAMERA, CellConfig().plate, seed=1))
    (d / "cell.toml").write_text("[camera]\nwidth_px = 1280\nheight_px = 720\n")
    return d


def recalibrate(work, out, *extra):
    return run(
        SCRIPT,
        "--image",
        work / "plate.png",
        "--out",
        out,
        "--config",
        work / "cell.toml",
        "--log",
        work / "cell.log",
        *extra,
    )


def test_recalibrate_writes_report_and_keeps_a_backup(work, tmp_path):
    out = tmp_path / "active.json"
    r = recalibrate(work, out, "--report-dir", tmp_path / "report")
    assert r.returncode == 0, r.stderr
    assert "cross-validated" in r.stdout and "Table III" in r.stdout
    data = json.loads(out.read_text())
    assert data["schema"] == "pick-cell/calibration" and data["version"] == 1
    assert data["camera"] and data["camera_center_table_mm"][2] > 100
    assert len(data["image_sha256"]) == 64
    for name in ("table3.csv", "plate_numbered.png", "deviation.png", "report.txt"):
        assert (tmp_path / "report" / name).stat().st_size > 0
    rows = (tmp_path / "report" / "table3.csv").read_text().splitlines()
    assert rows[0] == "point,x_px,y_px,X_cal_mm,Y_cal_mm,X_mm,Y_mm,dX_mm,dY_mm" and len(rows) == 157
    first = out.read_bytes()
    r = recalibrate(work, out, "--model", "polynomial")
    assert r.returncode == 0, r.stderr
    backups = list((tmp_path / "backups").glob("active.*.json"))
    assert len(backups) == 1 and backups[0].read_bytes() == first
    assert json.loads(out.read_text())["model"] == "polynomial"
    assert "recalibrated" in (work / "cell.log").read_text()


def _untouched_after(work, tmp_path, *args, image=None, code=2):
    out = tmp_path / "active.json"
    out.write_text('{"keep": "me"}')
    cmd = [SCRIPT, "--image", image or work / "plate.png", "--out", out, "--log", work / "cell.log", *args]
    if "--config" not in args:
        cmd += ["--config", work / "cell.toml"]
    r = run(*cmd)
    assert r.returncode == code, r.stdout + r.stderr
    assert out.read_text() == '{"keep": "me"}'
    assert "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    return r.stderr


def test_missing_image(work, tmp_path):
    assert "not found" in _untouched_after(work, tmp_path, image=tmp_path / "nope.png")


def test_unreadable_image(work, tmp_path):
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG garbage")
    assert "cannot decode image" in _untouched_after(work, tmp_path, image=bad)


def test_no_plate(work, tmp_path):
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((720, 1280, 3), 220, np.uint8))
    assert "no plate" in _untouched_after(work, tmp_path, image=blank)


def test_part_of_a_plate(work, tmp_path):
    part = tmp_path / "part.png"
    image = cv2.imread(str(work / "plate.png"))
    image[:, 700:] = image[5, 5]  # cover the right half with backlight
    cv2.imwrite(str(part), image)
    assert "column(s) missing" in _untouched_after(work, tmp_path, image=part)


def test_grid_mismatch(work, tmp_path):
    cfg = tmp_path / "grid.toml"
    cfg.write_text("[camera]\nwidth_px = 1280\nheight_px = 720\n[plate]\ncolumns = 12\n")
    assert "expected 12 x 12" in _untouched_after(work, tmp_path, "--config", cfg)


def test_image_size_mismatch(work, tmp_path):
    cfg = tmp_path / "size.toml"
    cfg.write_text("[camera]\nwidth_px = 1920\nheight_px = 1080\n")
    err = _untouched_after(work, tmp_path, "--config", cfg)
    assert "1280 x 720" in err and "1920 x 1080" in err


def test_bad_config_value(work, tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[plate]\npitch_x_mm = -22\n")
    assert "plate.pitch_x_mm" in _untouched_after(work, tmp_path, "--config", cfg)


def test_a_missing_camera_is_one_line_and_the_active_file_stays(work, tmp_path):
    cfg = tmp_path / "camera.toml"
    cfg.write_text(f'[camera]\nsource = "{tmp_path / "no-camera"}"\n')
    out = tmp_path / "active.json"
    out.write_text('{"keep": "me"}')
    r = run(SCRIPT, "--out", out, "--config", cfg, "--log", work / "cell.log")
    assert r.returncode == 2 and out.read_text() == '{"keep": "me"}', r.stdout + r.stderr
    assert r.stderr.startswith("recalibrate: error: camera ") and "no such device" in r.stderr
    assert r.stderr.count("\n") == 1 and "(hint: camera.source is 'sim'" in r.stderr


def test_fit_over_the_limit_is_refused(work, tmp_path):
    cfg = tmp_path / "strict.toml"
    cfg.write_text("[camera]\nwidth_px = 1280\nheight_px = 720\n[calibration]\nmax_cv_rms_mm = 0.05\n")
    err = _untouched_after(work, tmp_path, "--config", cfg, "--model", "quadratic", code=3)
    assert "max_cv_rms_mm" in err and "left unchanged" in err


@pytest.fixture(scope="module")
def calibration(work):
    out = work / "cal.json"
    assert recalibrate(work, out).returncode == 0
    return out


def test_map_csv_in_input_order(calibration, tmp_path):
    truth = np.array([[0.0, 0.0], [264.0, 176.0], [100.0, 50.0]])
    px = CAMERA.project(truth)
    csv = tmp_path / "points.csv"
    csv.write_text("x_px,y_px\n" + "".join(f"{x},{y}\n" for x, y in px))
    r = run_cell("map", "--calibration", calibration, "--pixels", csv, "--json")
    assert r.returncode == 0, r.stderr
    rows = json.loads(r.stdout)
    assert [list(r) for r in rows] == [["x_px", "y_px", "X_mm", "Y_mm"]] * 3
    got = np.array([[r["X_mm"], r["Y_mm"]] for r in rows])
    assert np.abs(got - truth).max() < 0.03
    one = run_cell("map", "--calibration", calibration, str(px[2, 0]), str(px[2, 1]), "--json")
    assert json.loads(one.stdout)[0]["X_mm"] == pytest.approx(rows[2]["X_mm"])


@pytest.mark.parametrize(
    "content,message",
    [
        ("x_px,y_px\n10,20\nnan,5\n", "line 3: not a finite number"),
        ("x_px,y_px\n10,twenty\n", "line 2: not a number"),
        ("x,y\n10,20\n", "line 1: header must be 'x_px,y_px'"),
    ],
)
def test_map_rejects_bad_pixels(calibration, tmp_path, content, message):
    csv = tmp_path / "points.csv"
    csv.write_text(content)
    r = run_cell("map", "--calibration", calibration, "--pixels", csv, "--json")
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize(
    "content,message",
    [
        ("{not json", "not JSON"),
        (
            '{"schema": "pick-cell/calibration", "version": 1, "model": "quadratic", "coefficients": {}}',
            "corrupt calibration",
        ),
        ('{"schema": "other"}', "not a calibration file"),
    ],
)
def test_map_rejects_a_corrupt_calibration(tmp_path, content, message):
    cal = tmp_path / "cal.json"
    cal.write_text(content)
    r = run_cell("map", "--calibration", cal, "1", "2")
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr


def test_capture_from_the_configured_camera(work, tmp_path):
    """Without --image the plate comes from camera.source (here a folder of images)."""
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "0001.png").write_bytes((work / "plate.png").read_bytes())
    cfg = tmp_path / "folder.toml"
    cfg.write_text(f"[camera]\nsource = '{frames}'\nwidth_px = 1280\nheight_px = 720\n")
    out = tmp_path / "active.json"
    r = run(SCRIPT, "--out", out, "--config", cfg, "--log", work / "cell.log", "--quiet")
    assert r.returncode == 0, r.stderr
    assert json.loads(out.read_text())["image_size"] == [1280, 720]


def test_camera_giving_the_wrong_size_is_refused(work, tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "0001.png").write_bytes((work / "plate.png").read_bytes())
    cfg = tmp_path / "folder.toml"
    cfg.write_text(f"[camera]\nsource = '{frames}'\nwidth_px = 1920\nheight_px = 1080\n")
    out = tmp_path / "active.json"
    out.write_text("{}")
    r = run(SCRIPT, "--out", out, "--config", cfg, "--log", work / "cell.log")
    assert r.returncode == 2 and "1280x720" in r.stderr and "Traceback" not in r.stderr
    assert out.read_text() == "{}"


def test_capture_from_the_simulated_camera(work, tmp_path):
    out = tmp_path / "active.json"
    r = run(SCRIPT, "--out", out, "--log", work / "cell.log", "--quiet")
    assert r.returncode == 0, r.stderr
    assert json.loads(out.read_text())["statistics"]["cross_validated"]["rms_mm"] < 0.015


def test_run_cell_recalibrate_is_the_script_s_command(work, tmp_path):
    out = tmp_path / "active.json"
    args = ("--image", work / "plate.png", "--out", out, "--config", work / "cell.toml", "--log", work / "cell.log")
    r = run_cell("recalibrate", *args, "--quiet")
    assert r.returncode == 0, r.stderr
    assert "cross-validated" in r.stdout and f"active calibration replaced: {out}" in r.stdout
    assert json.loads(out.read_text())["schema"] == "pick-cell/calibration"
    strict = tmp_path / "strict.toml"
    strict.write_text("[camera]\nwidth_px = 1280\nheight_px = 720\n[calibration]\nmax_cv_rms_mm = 0.05\n")
    before = out.read_bytes()
    r = run_cell("recalibrate", *args[:4], "--config", strict, "--model", "quadratic", "--log", work / "cell.log")
    assert r.returncode == 3 and out.read_bytes() == before, r.stdout + r.stderr
    assert r.stderr.startswith("run-cell recalibrate: error: ") and r.stderr.count("\n") == 1
    assert "max_cv_rms_mm" in r.stderr and "left unchanged" in r.stderr


def test_the_script_and_the_sub_command_take_the_same_options():
    def options(parser):
        return sorted((a.dest, tuple(a.option_strings), a.choices, a.default) for a in parser._actions)

    sub = next(a for a in cli_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["recalibrate"]
    assert options(script_parser()) == options(sub)
    assert "--report-dir" in sub.format_help() and "--quiet" in sub.format_help()


def run_into_a_closed_pipe(*args, cwd=ROOT):
    """As `cmd | head -0`: every write to stdout meets a pipe whose reader is gone."""
    read, write = os.pipe()
    os.close(read)
    try:
        return subprocess.run(
            [sys.executable, *map(str, args)], stdout=write, stderr=subprocess.PIPE, text=True, cwd=cwd, timeout=120
        )
    finally:
        os.close(write)


@pytest.mark.parametrize("how", ["script", "run-cell"])
def test_a_closed_stdout_pipe_does_not_stop_the_recalibration(work, tmp_path, how):
    """`... | head -3`: the calibration is replaced exactly as when not piped; stderr says the
    output was cut short; exit 0."""
    out = tmp_path / "active.json"
    out.write_text(json.dumps({"previous": True}))
    args = ["--image", work / "plate.png", "--out", out, "--config", work / "cell.toml", "--log", work / "cell.log"]
    command = [SCRIPT, *args] if how == "script" else ["-m", "cell.cli", "recalibrate", *args]
    r = run_into_a_closed_pipe(*command)
    assert r.returncode == 0, r.stderr
    assert json.loads(out.read_text())["schema"] == "pick-cell/calibration"
    (backup,) = (tmp_path / "backups").glob("active.*.json")
    assert json.loads(backup.read_text()) == {"previous": True}
    prefix = "recalibrate" if how == "script" else "run-cell recalibrate"
    assert r.stderr.startswith(f"{prefix}: note: standard output was closed early (Broken pipe)")
    assert "ran to its end (exit 0)" in r.stderr and r.stderr.count("\n") == 1

"""A plate with circles that cannot be seen: every output of a recalibration still comes out,
saying which points are missing (report, Table III CSV, numbered plate, JSON calibration)."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cell.calibration.pipeline import calibrate
from cell.calibration.report import annotate_plate
from cell.calibration.store import Calibration
from cell.camera_model import CameraModel
from cell.config import CellConfig
from cell.sim.render import render_plate
from tests.helpers import DATA

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]  # recalibrate.py runs as a subprocess, end to end

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "recalibrate.py"
CAMERA = CameraModel.looking_down(1280, 720, 0.30, (132, 88), tilt_deg=3, k1=-0.06)
OMIT = {(0, 0), (5, 4), (12, 11)}  # points 1, 58, 156: two corners and one inside
MISSING = sorted(r * 13 + c + 1 for c, r in OMIT)


def recalibrate(image: Path, out: Path, config: Path, report: Path):
    return subprocess.run(
        [
            sys.executable,
            SCRIPT,
            "--image",
            image,
            "--out",
            out,
            "--config",
            config,
            "--report-dir",
            report,
            "--log",
            out.parent / "cell.log",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )


def check_outputs(r, out: Path, report: Path, missing: list[int], total: int):
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Traceback" not in r.stderr
    data = json.loads(out.read_text())
    assert data["pattern"]["points_missing"] == missing
    assert data["pattern"]["points_used"] == total - len(missing)
    Calibration.load(out)  # and it reads back
    with open(report / "table3.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(row["point"]) for row in rows] == list(range(1, total + 1))
    for row in rows:
        measured = row["x_px"] != ""
        assert measured == (int(row["point"]) not in missing), row
    text = (report / "report.txt").read_text()
    assert f"missing: {missing}" in text and text.count("not found") == len(missing)
    assert cv2.imread(str(report / "plate_numbered.png")) is not None
    assert (report / "deviation.png").stat().st_size > 0


def test_rendered_plate_with_missing_circles(tmp_path):
    image = tmp_path / "plate.png"
    cv2.imwrite(str(image), render_plate(CAMERA, CellConfig().plate, omit=OMIT, seed=2))
    config = tmp_path / "cell.toml"
    config.write_text("[camera]\nwidth_px = 1280\nheight_px = 720\n")
    out, report = tmp_path / "active.json", tmp_path / "report"
    check_outputs(recalibrate(image, out, config, report), out, report, MISSING, 156)


def test_numbered_plate_rings_a_missing_point_where_the_camera_puts_it():
    config = CellConfig(camera={"width_px": 1280, "height_px": 720})
    image = render_plate(CAMERA, config.plate, omit=OMIT, seed=2)
    result = calibrate(image, config)
    drawn = annotate_plate(image, result)
    red = (drawn[:, :, 2] > 200) & (drawn[:, :, 1] < 80) & (drawn[:, :, 0] < 80)
    for c, r in OMIT:
        x, y = np.round(CAMERA.project(np.array([[22.0 * c, 16.0 * r]]))[0]).astype(int)
        assert red[y - 10 : y + 11, x - 10 : x + 11].any(), (c, r)


def test_real_photo_with_a_dot_painted_out(tmp_path):
    photo = DATA / "circles-opencv" / "opencv_circles03.png"
    if not photo.exists():
        pytest.skip(f"{photo} is absent: the real photos live in ../shared/data, outside the repo")
    gray = cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE)
    found, centres = cv2.findCirclesGrid(gray, (7, 7), flags=cv2.CALIB_CB_SYMMETRIC_GRID)
    assert found
    x, y = centres.reshape(-1, 2)[24]  # the middle dot, covered with the paper's grey
    paper = int(np.median(gray[int(y) - 14 : int(y) + 15, int(x) + 9 : int(x) + 13]))
    cv2.circle(gray, (int(round(x)), int(round(y))), 9, paper, -1)
    image = tmp_path / "photo.png"
    cv2.imwrite(str(image), gray)
    config = tmp_path / "cell.toml"
    config.write_text(
        "[camera]\nwidth_px = 640\nheight_px = 480\n[plate]\ncolumns = 7\nrows = 7\npitch_x_mm = 10\n"
        "pitch_y_mm = 10\ndiameter_mm = 5\n[calibration]\nmax_cv_rms_mm = 1.0\nmax_cv_error_mm = 5.0\n"
    )
    out, report = tmp_path / "active.json", tmp_path / "report"
    check_outputs(recalibrate(image, out, config, report), out, report, [25], 49)

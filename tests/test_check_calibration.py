"""`run-cell check-calibration`: a fresh plate image through the calibration in use."""

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cell.calibration.check import check_calibration
from cell.calibration.pipeline import calibrate
from cell.camera_model import CameraModel
from cell.config import CellConfig
from cell.sim.render import render_plate

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]  # run-cell runs as a subprocess

ROOT = Path(__file__).resolve().parents[1]
CONFIG = CellConfig(camera={"width_px": 1280, "height_px": 720})


def camera(shift_mm=(0.0, 0.0), roll_deg=3.0) -> CameraModel:
    centre = (132.0 + shift_mm[0], 88.0 + shift_mm[1])
    return CameraModel.looking_down(1280, 720, 0.30, centre, tilt_deg=4, roll_deg=roll_deg, k1=-0.08, k2=0.03)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("check")
    calibrate(render_plate(camera(), CONFIG.plate, seed=1), CONFIG).calibration.save(d / "cal.json")
    (d / "cell.toml").write_text("[camera]\nwidth_px = 1280\nheight_px = 720\n")
    for name, cam, seed in (
        ("fresh", camera(), 2),
        ("bumped", camera((0.5, 0.0)), 3),
        ("turned", camera(roll_deg=3.2), 4),
    ):
        cv2.imwrite(str(d / f"{name}.png"), render_plate(cam, CONFIG.plate, seed=seed))
    return d


def run_check(work, image, *extra):
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "cell.cli",
            "check-calibration",
            "--image",
            work / image,
            "--calibration",
            work / "cal.json",
            "--config",
            work / "cell.toml",
            "--log",
            work / "cell.log",
            *extra,
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )


def test_a_fresh_image_of_the_plate_passes_with_every_point_listed(work):
    r = run_check(work, "fresh.png")
    assert r.returncode == 0, r.stdout + r.stderr
    lines = r.stdout.splitlines()
    assert sum(1 for line in lines if line[:5].strip().isdigit()) == 156
    assert "PASS" in r.stdout
    assert "calibration check" in (work / "cell.log").read_text()
    assert r.stderr == ""  # the INFO line goes to the log file, not the terminal (without -v)


def test_the_errors_are_the_detection_noise_only():
    cal = calibrate(render_plate(camera(), CONFIG.plate, seed=1), CONFIG).calibration
    result = check_calibration(render_plate(camera(), CONFIG.plate, seed=2), cal, CONFIG)
    assert result.rms_mm < 0.02 and result.max_mm < 0.06


@pytest.mark.parametrize("image", ["bumped.png", "turned.png"])
def test_a_moved_camera_fails_with_exit_3(work, image):
    r = run_check(work, image)
    assert r.returncode == 3, r.stdout + r.stderr
    assert "FAIL" in r.stdout and "recalibrate" in r.stdout


def test_a_bump_is_measured_as_its_size():
    cal = calibrate(render_plate(camera(), CONFIG.plate, seed=1), CONFIG).calibration
    result = check_calibration(render_plate(camera((0.5, 0.0)), CONFIG.plate, seed=3), cal, CONFIG)
    # The camera moved +0.5 mm in X: the plate appears 0.5 mm further in -X.
    assert abs(result.error_mm[:, 0].mean() - 0.5) < 0.03 and abs(result.error_mm[:, 1].mean()) < 0.03
    assert np.max(result.rigid_error_mm) < 0.06  # the mapping still holds: the camera moved as a whole


def test_limit_comes_from_the_config(work, tmp_path):
    cfg = tmp_path / "lax.toml"
    cfg.write_text("[camera]\nwidth_px = 1280\nheight_px = 720\n[calibration]\ncheck_max_mm = 1.0\n")
    r = run_check(work, "bumped.png", "--config", cfg)
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.parametrize(
    "case, message",
    [
        ("missing image", "not found"),
        ("missing calibration", "calibration file not found"),
        ("wrong size", "1280 x 720"),
        ("other plate", "plate.columns"),
        ("huge image", "more than camera.max_image_px"),
    ],
)
def test_bad_input_is_one_line_exit_2(work, tmp_path, case, message):
    args = []
    image = "fresh.png"
    if case == "missing image":
        image = "nope.png"
    elif case == "missing calibration":
        args = ["--calibration", tmp_path / "none.json"]
    elif case == "wrong size":
        cv2.imwrite(str(work / "small.png"), np.full((480, 640, 3), 200, np.uint8))
        image = "small.png"
    elif case == "huge image":  # 20000 x 20000 in its header: refused before it is decoded
        cv2.imwrite(str(work / "huge.png"), np.zeros((20000, 20000), np.uint8))
        image = "huge.png"
    else:
        cfg = tmp_path / "plate.toml"
        cfg.write_text("[camera]\nwidth_px = 1280\nheight_px = 720\n[plate]\ncolumns = 12\n")
        args = ["--config", cfg]
    r = run_check(work, image, *args)
    assert r.returncode == 2, r.stdout + r.stderr
    assert message in r.stderr and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1

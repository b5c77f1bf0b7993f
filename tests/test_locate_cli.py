"""`run-cell locate`: JSON contract, readable table, annotation, one-line errors."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.camera_model import CameraModel
from cell.cli import main
from cell.sim.parts import PartSpec, render_scene

W, H = 960, 540
PARTS = [
    PartSpec("nut", "M8", 80.0, 60.0, 10.0),
    PartSpec("bolt", "M6", 170.0, 110.0, 120.0, 25.0),
    PartSpec("washer", "M8", 60.0, 130.0),
]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("locate")
    cam = CameraModel.looking_down(W, H, 0.4, (132.0, 88.0), tilt_deg=3.0, k1=-0.04)
    Calibration("camera", CameraMap(cam), (W, H), cam).save(d / "cal.json")
    cv2.imwrite(str(d / "scene.png"), render_scene(cam, PARTS))
    return d


def run(capsys, *argv):
    code = main(["locate", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_json_output(files, capsys):
    code, out, err = run(capsys, "--image", files / "scene.png", "--calibration", files / "cal.json", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["image_size"] == [W, H] and data["elapsed_ms"] > 0
    objs = data["objects"]
    assert [o["id"] for o in objs] == [1, 2, 3]
    for o in objs:
        assert {"id", "class", "reason", "pixel", "world_mm", "angle_deg", "pick"} <= set(o)
    by_class = {o["class"]: o for o in objs}
    assert set(by_class) == {"nut", "bolt", "unknown"}
    assert by_class["unknown"]["pick"] is False and by_class["unknown"]["angle_deg"] is None
    assert by_class["nut"]["angle_deg"] is None
    assert abs((by_class["bolt"]["angle_deg"] - 120.0 + 90) % 180 - 90) < 1.5
    for part in PARTS[:2]:
        got = by_class[part.kind]["world_mm"]
        assert np.hypot(got[0] - part.x_mm, got[1] - part.y_mm) < 0.7


def test_table_and_annotation(files, capsys):
    out_png = files / "annotated.png"
    code, out, _ = run(
        capsys, "--image", files / "scene.png", "--calibration", files / "cal.json", "--annotate", out_png
    )
    assert code == 0
    assert "X (mm)" in out and "Nut" in out and "Bolt" in out and "washer" in out
    annotated = cv2.imread(str(out_png))
    assert annotated.shape == (H, W, 3)
    assert not np.array_equal(annotated, cv2.imread(str(files / "scene.png")))


def test_plain_scale_and_paper_preset(files, capsys):
    code, out, _ = run(capsys, "--image", files / "scene.png", "--mm-per-px", "0.4", "--preset", "paper", "--json")
    assert code == 0
    assert len(json.loads(out)["objects"]) == 3


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda d: d / "missing.png", "image file not found"),
        (lambda d: (d / "text.png").write_text("not an image") and d / "text.png", "cannot decode image"),
        (
            lambda d: cv2.imwrite(str(d / "small.png"), np.zeros((100, 100, 3), np.uint8)) and d / "small.png",
            "100 x 100 px",
        ),
    ],
)
def test_bad_images_give_one_line_errors(files, capsys, make, message):
    path = make(files)
    code, out, err = run(capsys, "--image", path, "--calibration", files / "cal.json")
    assert code != 0 and out == ""
    assert err.count("\n") == 1 and message in err and str(path) in err


def test_bad_calibration_gives_one_line_error(files, capsys):
    bad = files / "corrupt.json"
    bad.write_text("{not json")
    code, _, err = run(capsys, "--image", files / "scene.png", "--calibration", bad)
    assert code != 0 and err.count("\n") == 1 and "corrupt" in err and str(bad) in err


def test_bad_config_names_the_key(files, capsys):
    cfg = files / "cell.toml"
    cfg.write_text("[parts.nut]\nacross_flats_mm = [20.0, 10.0]\n")
    code, _, err = run(capsys, "--image", files / "scene.png", "--mm-per-px", "0.4", "--config", cfg)
    assert code != 0 and "parts.nut.across_flats_mm" in err

"""The camera's height from a second image of the plate raised on a spacer (cell.calibration.raised):
where one flat plate seen straight down cannot tell the height, the raised plate measures it."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cell.calibration.pipeline import RaisedPlate, calibrate
from cell.calibration.raised import similarity_fit
from cell.camera_model import CameraModel
from cell.config import CellConfig
from cell.errors import CalibrationRejected
from cell.sim.render import render_plate

SPACER_MM = 20.0


def straight_down(tilt_deg: float = 0.3) -> CameraModel:
    """A 1280 x 720 camera nearly straight above the plate, a little barrel distortion."""
    return CameraModel.looking_down(
        1280, 720, mm_per_px=0.3, look_at_table_mm=(132.0, 88.0), hfov_deg=62.0, tilt_deg=tilt_deg, k1=-0.05
    )


@pytest.fixture(scope="module")
def images():
    camera = straight_down()
    config = CellConfig()
    config.camera.width_px, config.camera.height_px = 1280, 720
    flat = render_plate(camera, config.plate, seed=3)
    raised = render_plate(camera, config.plate, seed=4, height_mm=SPACER_MM, offset_mm=(6.0, -4.0))
    return camera, config, flat, raised


def test_similarity_fit_recovers_scale_turn_and_shift():
    rng = np.random.default_rng(5)
    src = rng.uniform(-100, 100, (40, 2))
    a = math.radians(17.0)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    dst = 1.0537 * src @ rot.T + (12.0, -3.0)
    scale, scale_sd, residuals = similarity_fit(src, dst)
    assert scale == pytest.approx(1.0537, abs=1e-12)
    assert scale_sd < 1e-12 and np.abs(residuals).max() < 1e-9


def test_the_raised_plate_measures_the_height_one_flat_plate_cannot(images):
    camera, config, flat, raised = images
    truth_mm = float(camera.center_table_mm[2])
    alone = calibrate(flat, config)
    with_raised = calibrate(flat, config, raised=RaisedPlate(raised, SPACER_MM))
    r = with_raised.raised
    assert r is not None
    # the flat plate alone: either far off or unsure (the camera sees the plate straight on)
    assert alone.plate_height_sd_mm > 0.05 * truth_mm or abs(alone.plate_height_mm - truth_mm) > 0.05 * truth_mm
    # the raised plate: within 1 %, and it knows it
    assert abs(r.height_mm - truth_mm) < 0.01 * truth_mm, (r.height_mm, truth_mm)
    assert r.sd_mm < 0.01 * truth_mm
    used = float(with_raised.calibration.camera.center_table_mm[2])
    assert abs(used - truth_mm) < 0.01 * truth_mm, (used, truth_mm)
    assert with_raised.calibration.statistics["raised_plate"]["spacer_mm"] == SPACER_MM


def test_a_plate_that_was_not_raised_is_refused(images):
    _, config, flat, _ = images
    with pytest.raises(CalibrationRejected, match="it was not raised"):
        calibrate(flat, config, raised=RaisedPlate(flat, SPACER_MM, "raised.png"))


def test_a_raised_image_of_another_size_is_refused(images):
    _, config, flat, raised = images
    small = cv2.resize(raised, (640, 360))
    with pytest.raises(CalibrationRejected, match=r"raised.png: 640 x 360 px, the plate image 1280 x 720"):
        calibrate(flat, config, raised=RaisedPlate(small, SPACER_MM, "raised.png"))


def test_recalibrate_takes_the_raised_image(images, tmp_path, capsys):
    from cell.commands.recalibrate import main

    camera, _, flat, raised = images
    cv2.imwrite(str(tmp_path / "flat.png"), flat)
    cv2.imwrite(str(tmp_path / "raised.png"), raised)
    (tmp_path / "cell.toml").write_text("[camera]\nwidth_px = 1280\nheight_px = 720\n")
    common = ["--config", str(tmp_path / "cell.toml"), "--image", str(tmp_path / "flat.png"), "--quiet"]
    common += ["--out", str(tmp_path / "active.json"), "--log", str(tmp_path / "cell.log")]
    code = main([*common, "--raised-image", str(tmp_path / "raised.png"), "--spacer-mm", "20"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "camera height from the plate raised on the 20 mm spacer" in out
    assert (tmp_path / "active.json").exists()

    code = main([*common, "--raised-image", str(tmp_path / "raised.png")])  # no thickness
    assert code == 2
    assert "--raised-image and --spacer-mm go together" in capsys.readouterr().err

    with pytest.raises(SystemExit) as e:
        main([*common, "--raised-image", str(tmp_path / "raised.png"), "--spacer-mm", "-3"])
    assert e.value.code == 2
    assert "must be above 0 mm" in capsys.readouterr().err


def test_a_spacer_of_another_thickness_than_told_is_refused_against_the_measured_height(images):
    """The raised plate and the installer's measured height disagree when the spacer was not the
    thickness given (here 25 mm told, 20 mm under the plate): the recalibration is refused."""
    from cell.calibration.gates import plausibility_problems

    camera, config, flat, raised = images
    c = config.model_copy(deep=True)
    c.calibration.camera_height_mm = float(camera.center_table_mm[2]) + 3.0  # measured 3 mm high
    right = calibrate(flat, c, raised=RaisedPlate(raised, SPACER_MM))
    assert plausibility_problems(right, c.calibration, c.plate) == []
    wrong = calibrate(flat, c, raised=RaisedPlate(raised, 25.0))
    problems = plausibility_problems(wrong, c.calibration, c.plate)
    assert len(problems) == 1, problems
    assert "raised on the 25 mm spacer" in problems[0] and "calibration.camera_height_mm" in problems[0]


def test_the_calibration_says_how_well_it_knows_the_height(images):
    """Stored with the calibration: the height used, how well it is known and from what. A height
    whose doubt would cost the tallest part more than calibration.max_height_cost_mm is a doubt the
    cell reports (run-cell's notes, the service's warning; tests/test_height_cost.py)."""
    _, config, flat, raised = images
    alone = calibrate(flat, config).calibration
    known = alone.statistics["camera_height"]
    assert known["from"] == "the plate alone"
    assert known["sd_mm"] is None or known["sd_mm"] > 0.05 * known["height_mm"]
    doubt = alone.height_doubt()
    assert doubt is not None and "camera's height above the table" in doubt[0] and "--raised-image" in doubt[1]

    with_raised = calibrate(flat, config, raised=RaisedPlate(raised, SPACER_MM)).calibration
    known = with_raised.statistics["camera_height"]
    assert "raised on a 20 mm spacer" in known["from"] and known["sd_mm"] < 0.01 * known["height_mm"]
    assert with_raised.height_doubt() is None


def test_a_calibration_that_does_not_say_raises_no_doubt(images):
    """Calibrations written before the height was recorded: nothing to report, nothing invented."""
    _, config, flat, _ = images
    cal = calibrate(flat, config).calibration
    del cal.statistics["camera_height"]
    assert cal.height_doubt() is None

"""What the camera height's doubt costs the parts (Calibration.height_cost_mm, height_doubt): the
predicted worst part-centre error over the field, checked against the camera model itself, and
the warning judged by that cost against calibration.max_height_cost_mm."""

from __future__ import annotations

import numpy as np
import pytest

from cell.calibration.models import fit_camera_pose
from cell.calibration.pipeline import calibrate
from cell.calibration.report import summary_text
from cell.calibration.store import HEIGHT_DOUBT_SDS, field_border_px
from cell.config import CellConfig
from cell.sim.cameras import FAMILY, random_camera
from cell.sim.render import render_plate

# Two 640 x 480 cameras of the height-doubt bench (scripts/bench_height_doubt.py, seeds 90000 up):
# the plate alone pins 90003's height to about 2 mm (costs ~0.18 mm), 90002's only to about 25 mm.
WELL_KNOWN_SEED, POORLY_KNOWN_SEED = 90_003, 90_002


def _calibrated(seed: int, **calibration):
    sim = random_camera(FAMILY["640 x 480"], seed)
    config = CellConfig(plate=sim.plate)
    for key, value in calibration.items():
        setattr(config.calibration, key, value)
    return sim, config, calibrate(render_plate(sim.camera, sim.plate, sim.optics, seed=sim.seed), config)


@pytest.fixture(scope="module")
def poorly_known():
    return _calibrated(POORLY_KNOWN_SEED)


def test_the_cost_formula_is_the_camera_models(poorly_known):
    """The closed form (|q - C| h d / (H (H - d)), worst over the field) against the camera model
    directly: the pose the plate gives at the height H - d (as a measured height would refit it),
    a part h high seen at the image's border located by both, the difference at h minus the one
    on the table (the height's share)."""
    _, config, result = poorly_known
    cal, pts = result.calibration, result.points
    part = config.parts.tallest_centre_height_mm
    height = float(cal.camera.center_table_mm[2])
    px = field_border_px(cal.image_size)
    for d in (5.0, 20.0, -20.0):
        focal = float(cal.camera.camera_matrix[0, 0]) * (height - d) / height
        other = fit_camera_pose(pts.pixel, pts.table_mm, cal.image_size, focal_px=focal)[0]
        assert float(other.center_table_mm[2]) == pytest.approx(height - d, rel=0.01)
        shift = (cal.pixel_to_table_mm(px, part) - other.pixel_to_table(px, part)) - (
            cal.pixel_to_table_mm(px) - other.pixel_to_table(px)
        )
        direct = float(np.max(np.hypot(*shift.T)))
        predicted = cal.height_cost_mm(part, abs(d))[0]
        # the formula takes the worse sign (the camera nearer than believed) and the foot as fixed
        assert direct == pytest.approx(predicted, rel=0.1) or (d < 0 and direct < predicted), (d, direct, predicted)
        assert direct > 0.5 * predicted


def test_the_cost_is_recorded_and_printed(poorly_known):
    _, config, result = poorly_known
    cal = result.calibration
    known = cal.statistics["camera_height"]
    cost = known["cost"]
    part = config.parts.tallest_centre_height_mm
    assert cost["part_height_mm"] == pytest.approx(part, abs=1e-3) and cost["max_mm"] == 0.5
    assert cost["height_error_mm"] == pytest.approx(HEIGHT_DOUBT_SDS * known["sd_mm"], abs=1e-3)
    assert cost["worst_mm"] == pytest.approx(cal.height_cost_mm(part, cost["height_error_mm"])[0], rel=1e-3)
    text = summary_text(result, table=False)
    assert f"part's centre off by up to {cost['worst_mm']:.3f} mm" in text


def test_the_tallest_part_is_the_configured_one():
    """Bolts lying on their axis (half the largest head's across flats), nuts at half their thickness."""
    config = CellConfig()
    assert config.parts.tallest_centre_height_mm == pytest.approx(0.5 * 0.866 * 18.0)
    config.parts.bolt.reference_height_mm = 2.0
    assert config.parts.tallest_centre_height_mm == pytest.approx(0.5 * 0.5 * 19.0)


def test_the_warning_fires_where_the_cost_passes_the_tolerance(poorly_known):
    _, _, result = poorly_known
    cost = result.calibration.statistics["camera_height"]["cost"]["worst_mm"]
    assert cost > 0.5
    doubt = result.calibration.height_doubt()
    assert doubt is not None
    assert f"off by up to {cost:.2f} mm" in doubt[0] and "calibration.max_height_cost_mm 0.5" in doubt[0]
    assert "calibration.camera_height_mm" in doubt[1] and "--raised-image" in doubt[1]
    # a tolerance above the cost (configured, or given by the caller) silences it
    assert result.calibration.height_doubt(max_cost_mm=1.01 * cost) is None
    assert result.calibration.height_doubt(max_cost_mm=0.99 * cost) is not None
    loose = _calibrated(POORLY_KNOWN_SEED, max_height_cost_mm=1.01 * cost)[2].calibration
    assert loose.height_doubt() is None


def test_no_warning_where_the_height_is_known_well_enough():
    _, _, result = _calibrated(WELL_KNOWN_SEED)
    cost = result.calibration.statistics["camera_height"]["cost"]["worst_mm"]
    assert 0 < cost < 0.5
    assert result.calibration.height_doubt() is None
    assert result.calibration.height_doubt(max_cost_mm=0.9 * cost) is not None

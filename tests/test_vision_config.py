"""Parts settings: part of the cell config, validated with the key named."""

from __future__ import annotations

import numpy as np
import pytest

from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.camera_model import CameraModel
from cell.config import CellConfig, load_config
from cell.errors import ConfigError
from cell.sim.parts import PartSpec, render_scene
from cell.vision.config import PartsConfig
from cell.vision.locate import locate


def test_cell_config_carries_parts_defaults():
    cfg = CellConfig()
    assert cfg.parts.preset == "default" and cfg.parts.use_height_correction
    assert PartsConfig(preset="paper").use_height_correction is False
    assert PartsConfig(preset="paper", height_correction=True).use_height_correction is True


def test_parts_table_in_toml(tmp_path):
    path = tmp_path / "cell.toml"
    path.write_text('[parts]\npreset = "paper"\njaw_clearance_mm = 4.5\n[parts.bolt]\nreference_height_mm = 5.0\n')
    cfg = load_config(path)
    assert cfg.parts.preset == "paper" and cfg.parts.jaw_clearance_mm == 4.5
    assert cfg.parts.bolt.reference_height_mm == 5.0


@pytest.mark.parametrize(
    "text, key",
    [
        ("[parts]\npreset = 'fast'\n", "parts.preset"),
        ("[parts.nut]\nhole_ratio = [0.9, 0.2]\n", "parts.nut.hole_ratio"),
        ("[parts.bolt]\nlength_mm = [40, 10]\n", "parts.bolt.length_mm"),
        ("[parts]\nmin_part_area = 3\n", "parts.min_part_area"),
    ],
)
def test_bad_parts_settings_name_the_key(tmp_path, text, key):
    path = tmp_path / "cell.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(path)


def test_fixed_reference_height_and_missing_camera_pose():
    cam = CameraModel.looking_down(640, 480, 0.4, (60.0, 40.0), tilt_deg=3.0)
    frame = render_scene(cam, [PartSpec("nut", "M10", 90.0, 60.0)])
    with_pose = Calibration("camera", CameraMap(cam), (640, 480), cam)
    cfg = PartsConfig()
    cfg.nut.reference_height_mm = 2.0
    obj = locate(frame, with_pose, cfg).objects[0]
    assert obj.cls == "nut" and obj.features["reference_height_mm"] == 2.0
    no_pose = Calibration("camera", CameraMap(cam), (640, 480), None)
    result = locate(frame, no_pose, PartsConfig())
    assert result.objects[0].features["reference_height_mm"] == 0.0
    assert any("no camera pose" in w for w in result.warnings)
    # Mapped on the table plane, the nut lands farther from the camera's foot.
    foot = cam.center_table_mm[:2]
    assert np.hypot(*(np.array(result.objects[0].table_mm) - foot)) > np.hypot(*(np.array(obj.table_mm) - foot))

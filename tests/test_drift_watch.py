"""The drift watch: reference marks measured on every frame; a moved camera stops the cell
before the next pick."""

from __future__ import annotations

import numpy as np
import pytest

from cell.audit import read_events
from cell.calibration.drift import DriftWatch
from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.cli import main
from cell.config import DriftConfig
from cell.errors import CameraMoved, InputError
from cell.sim.cell import bumped
from cell.sim.rig import default_camera
from cell.sim.sim_camera import SimCamera
from cell.sim.world import Truth, World

MARKS = [(-6.0, -6.0), (270.0, -6.0), (-6.0, 182.0), (270.0, 182.0)]


@pytest.fixture(scope="module")
def setup():
    model = default_camera(1280, 720)
    cal = Calibration("camera", CameraMap(model), (1280, 720), model)
    return model, cal, DriftWatch(cal, DriftConfig(marks_mm=MARKS))


def frame(model, marks=MARKS, seed=0):
    world = World([], Truth(0.0, -132.0, 40.0, 0.0), [])
    camera = SimCamera(world, model, seed=seed, marks_mm=np.array(marks))
    camera.connect()
    return camera.capture()


def test_a_still_camera_reads_almost_no_drift(setup):
    model, _, watch = setup
    for seed in range(3):
        assert watch(frame(model, seed=seed)).drift_mm < 0.05


@pytest.mark.parametrize("shift", [(0.3, 0.0), (0.0, -0.3), (0.22, 0.22)])
def test_a_bump_of_0_3_mm_is_caught_and_measured(setup, shift):
    model, _, watch = setup
    moved = frame(bumped(model, shift))
    assert watch.measure(moved).drift_mm == pytest.approx(0.3, abs=0.03)
    with pytest.raises(CameraMoved, match=r"camera moved 0\.[23]\d mm since calibration.*check or recalibrate"):
        watch(moved)


def test_a_mark_that_cannot_be_seen_stops_the_cell(setup):
    model, _, watch = setup
    with pytest.raises(CameraMoved, match=r"reference marks at table \[\(270\.0, 182\.0\)\] mm not found"):
        watch(frame(model, marks=MARKS[:3]))


def test_a_calibration_without_camera_pose_cannot_watch(setup):
    _, cal, _ = setup
    bare = Calibration("camera", cal.model, (1280, 720), None)
    with pytest.raises(InputError, match="camera pose"):
        DriftWatch(bare, DriftConfig(marks_mm=MARKS))


@pytest.mark.slow
@pytest.mark.timeout(240)  # a whole run of the simulated cell
def test_the_simulated_cell_stops_before_the_first_pick_from_a_moved_camera(tmp_path):
    cfg = tmp_path / "bump.toml"
    cfg.write_text("[sim]\ncamera_bumped_mm = [0.3, 0.0]\ncamera_bumped_at_pick = 4\n")
    assert main(["--config", str(cfg), "--dry-run", "--log-dir", str(tmp_path)]) == 3
    events = read_events(next(tmp_path.glob("run-*.jsonl")))
    targets = [e for e in events if e["kind"] == "target"]
    assert len(targets) == 3  # picks 1-3 from frames 1-3; frame 4 was the moved camera's
    fault = [e for e in events if e["kind"] == "fault"][0]
    assert "camera moved 0.3" in fault["reason"] and "check or recalibrate" in fault["reason"]

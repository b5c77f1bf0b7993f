"""The simulated cell seen through a GenICam camera: Aravis's in-process Fake camera fed the
rendered frames (cell/sim/genicam_feed.py), so a job's every frame comes through Aravis's stream
and buffers and the GenICam driver; a dry-run job with the simulated arm clears the table with it."""

from __future__ import annotations

import numpy as np
import pytest

from cell.cli import main
from cell.errors import ConfigError
from drivers.cameras.base import Camera
from tests.helpers import audit_of
from tests.test_genicam import genicam_camera, needs_aravis

pytestmark = pytest.mark.timeout(120)


class Pattern(Camera):
    """A frame source of known pixels (what the simulated camera would render): a ramp with a red,
    a green and a blue square, changed at each capture."""

    def __init__(self, width_px: int, height_px: int):
        self.source, self.width_px, self.height_px = "pattern", width_px, height_px
        self.frames: list[np.ndarray] = []
        self._connected = False

    def connect(self) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def _grab(self) -> np.ndarray:
        h, w, n = self.height_px, self.width_px, len(self.frames)
        ramp = ((np.arange(w)[None, :] + 3 * np.arange(h)[:, None] + n) % 200).astype(np.uint8)
        frame = np.repeat(ramp[:, :, None], 3, axis=2)
        for channel, x in ((2, 20), (1, 100), (0, 180)):  # red, green, blue squares
            frame[40:100, x : x + 60] = 0
            frame[40:100, x : x + 60, channel] = 250
        self.frames.append(frame)
        return frame


@needs_aravis
@pytest.mark.parametrize("pixel_format", ["Mono8", "BayerRG8"])
def test_the_fake_camera_gives_back_each_fed_frame_through_aravis(pixel_format):
    import cv2

    from cell.sim.genicam_feed import FedGenICamCamera

    render = Pattern(320, 240)
    camera = FedGenICamCamera(render, genicam_camera("Fake_1", 320, 240, pixel_format=pixel_format, features={}))
    with camera:
        frames, ids = [], []
        for _ in range(3):
            frames.append(camera.capture())
            ids.append(camera.genicam.last_frame.frame_id)
    assert camera.refused is None and camera.fed >= 3 and camera.genicam.stats.frames == 3
    assert camera.genicam.device.interface == "Fake" and ids == [ids[0], ids[0] + 1, ids[0] + 2]
    for got, sent in zip(frames, render.frames, strict=True):
        assert got.shape == (240, 320, 3)
        if pixel_format == "Mono8":
            assert np.array_equal(got, np.repeat(cv2.cvtColor(sent, cv2.COLOR_BGR2GRAY)[:, :, None], 3, axis=2))
        else:  # each colour square reads as its colour after the driver's demosaic (the tile the right way round)
            for channel, x in ((2, 20), (1, 100), (0, 180)):
                inside = got[50:90, x + 10 : x + 50].reshape(-1, 3).mean(axis=0)
                assert inside[channel] > 200 and np.delete(inside, channel).max() < 50, (channel, inside)
            assert np.abs(got[120:, :].astype(int) - sent[120:, :]).mean() < 3  # the grey ramp comes back grey


@needs_aravis
def test_a_dry_run_job_whose_camera_is_the_fed_genicam_fake_clears_the_table(tmp_path, capsys, monkeypatch):
    from cell.sim import genicam_feed

    opened: list[genicam_feed.FedGenICamCamera] = []
    build = genicam_feed.fed_genicam
    monkeypatch.setattr(genicam_feed, "fed_genicam", lambda *a: opened.append(build(*a)) or opened[-1])
    config = tmp_path / "cell.toml"
    config.write_text(  # 1280 x 960: the smallest the simulated cell's reference marks are found at
        "[camera]\nwidth_px = 1280\nheight_px = 960\n"
        '[sim]\nperfect_calibration = true\ncamera_source = "genicam:Fake_1"\n'
        f'[run]\nlog_dir = "{tmp_path / "logs"}"\n'
    )
    assert main(["--config", str(config), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "connecting the camera genicam:Fake_1" in out and "picked 9 bolts, 8 nuts; 0 misses" in out
    events = audit_of(tmp_path / "logs")
    assert next(e for e in events if e["kind"] == "summary")["picked"] == {"bolt": 9, "nut": 8}
    truth = next(e for e in events if e["kind"] == "sim_truth")["where"]
    assert truth == {"bin:bolt": {"bolt": 9}, "bin:nut": {"nut": 8}, "table": {"washer": 1}}
    [camera] = opened
    stats = camera.genicam.stats
    assert camera.genicam.device is not None and camera.genicam.device.interface == "Fake"
    assert camera.refused is None and stats.incomplete == 0 and stats.timeouts == 0
    # every frame the job used came out of an Aravis buffer the Fake camera filled with a rendered frame
    assert stats.frames > 17 and camera.fed >= stats.frames and camera.rendered == stats.frames


def test_the_simulated_camera_is_fed_only_to_a_fake_genicam_camera(tmp_path):
    from cell.config import load_config

    config = tmp_path / "cell.toml"
    config.write_text('[sim]\ncamera_source = "genicam:24312345"\n')
    with pytest.raises(ConfigError, match=r"sim\.camera_source"):
        load_config(config)

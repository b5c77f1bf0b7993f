"""`run-cell camera`: one frame or a live line per frame, from the simulated camera and from a
video file; the snapshot written whole; bad input and a missing camera as one line of ours."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cell.cli import main
from cell.config import CellConfig
from cell.sim.render import render_plate
from cell.sim.rig import default_camera

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[1]
W, H = 960, 540
BLUR_SIGMAS = [3.0, 2.0, 0.0, 1.5, 2.5]  # the third frame is the sharpest


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("camera")
    (d / "sim.toml").write_text(f"[camera]\nwidth_px = {W}\nheight_px = {H}\n")
    plate = render_plate(default_camera(W, H), CellConfig().plate, seed=3)
    video = d / "focus.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 5, (W, H))
    assert writer.isOpened()
    for sigma in BLUR_SIGMAS:
        writer.write(cv2.GaussianBlur(plate, (0, 0), sigma) if sigma else plate)
    writer.release()
    (d / "video.toml").write_text(f'[camera]\nsource = "{video}"\nwidth_px = {W}\nheight_px = {H}\n')
    return d


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main(["camera", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_one_frame_from_the_simulated_camera_with_a_snapshot(work, tmp_path, capsys):
    snap = tmp_path / "snap.png"
    code, out, err = run(capsys, "--config", work / "sim.toml", "--snapshot", snap)
    assert code == 0 and err == "", err
    assert out.startswith(f"camera sim: {W} x {H} px\nfocus: ")
    assert "plate: 156 of 156 circles" in out and "adjust: nothing" in out
    assert f"snapshot: {snap}" in out
    assert cv2.imread(str(snap)).shape == (H, W, 3)
    assert not list(tmp_path.glob("*.tmp*"))


def test_live_from_the_simulated_camera(work, capsys):
    code, out, err = run(capsys, "--config", work / "sim.toml", "--live", "--frames", "3")
    assert code == 0, err
    lines = out.splitlines()
    assert [line.split(":")[0] for line in lines[:3]] == ["frame 1", "frame 2", "frame 3"]
    assert all("plate 156/156" in line for line in lines[:3])
    assert lines[3].startswith("after 3 frames; best focus ")


def test_live_from_a_video_file_finds_the_sharpest_frame(work, tmp_path, capsys):
    snap = tmp_path / "last.jpg"
    frames = len(BLUR_SIGMAS)
    code, out, err = run(capsys, "--config", work / "video.toml", "--live", "--frames", frames, "--snapshot", snap)
    assert code == 0, err
    lines = out.splitlines()
    assert len([line for line in lines if line.startswith("frame ")]) == frames
    assert re.fullmatch(rf"after {frames} frames; best focus [0-9.]+ at frame 3", lines[frames])
    assert "adjust: focus" in lines[frames - 1]  # the last frame is blurred again: turn back
    assert cv2.imread(str(snap)).shape == (H, W, 3)


def test_one_frame_from_a_video_file(work, capsys):
    code, out, err = run(capsys, "--config", work / "video.toml")
    assert code == 0, err
    assert out.startswith(f"camera {work / 'focus.avi'}: {W} x {H} px")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--frames", "2"], "run-cell camera: error: --frames N goes with --live"),
        (["--snapshot", "snap.txt"], "run-cell camera: error: snap.txt: cannot write an image as '.txt'"),
    ],
)
def test_bad_input_is_refused_before_the_camera_opens(work, capsys, argv, message):
    code, out, err = run(capsys, "--config", work / "sim.toml", *argv)
    assert code == 2 and out == "" and err.startswith(message) and err.count("\n") == 1


def test_a_missing_camera_is_one_line_without_opencv_s_own(tmp_path, capfd):
    cfg = tmp_path / "cam.toml"
    cfg.write_text('[camera]\nsource = "7"\n')
    assert main(["camera", "--config", str(cfg)]) == 2
    out, err = capfd.readouterr()
    assert out == "" and err.count("\n") == 1 and "WARN" not in err, err
    assert err.startswith("run-cell camera: error: camera 7: cannot open: no such device /dev/video7")


@pytest.mark.slow
@pytest.mark.timeout(90)
def test_ctrl_c_ends_the_live_view_and_writes_the_snapshot(work, tmp_path):
    snap = tmp_path / "snap.png"
    argv = ["-m", "cell.cli", "camera", "--config", str(work / "sim.toml"), "--live", "--snapshot", str(snap)]
    proc = subprocess.Popen([sys.executable, *argv], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        for line in proc.stdout:
            if line.startswith("frame 2:"):
                break
        proc.send_signal(signal.SIGINT)
        rest = proc.stdout.read()
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "stopped by Ctrl-C after" in rest and f"snapshot: {snap}" in rest
    assert np.asarray(cv2.imread(str(snap))).shape == (H, W, 3)

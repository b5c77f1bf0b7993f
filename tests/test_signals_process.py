"""Signals delivered to a real run-cell process: the terminal hangs up mid-run (SIGHUP with
its output gone), and two recalibrations of one file race. Nothing may be left behind."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from cell.audit import read_events
from cell.camera_model import CameraModel
from cell.config import CellConfig
from cell.sim.render import render_plate
from tests.faults import fast_config

# Whole runs of the cell or of recalibrations (slow); ptys and subprocesses must never hang the suite.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

REPO = Path(__file__).resolve().parents[1]
RUN_CELL = Path(sys.executable).parent / "run-cell"


def test_a_hang_up_mid_run_stops_safely_even_with_the_terminal_gone(tmp_path):
    """SSH drops: SIGHUP arrives and stdout is a closed pipe; the safe stop and the log still happen."""
    cfg = fast_config(tmp_path, "dynamixel", speed_scale=50.0)
    proc = subprocess.Popen(
        [str(RUN_CELL), "--config", str(cfg), "--log-dir", str(tmp_path / "logs")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        for line in proc.stdout:
            if line.startswith("pick  1:"):
                break
        proc.stdout.close()  # the terminal is gone: every later print fails
        proc.send_signal(signal.SIGHUP)
        err = proc.stderr.read()
        assert proc.wait(timeout=60) == 130, err
    finally:
        proc.kill()
        proc.wait()
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].endswith("SIGHUP (terminal closed) (arm made safe; exit 130)")
    (log,) = (tmp_path / "logs").glob("run-*.jsonl")
    events = read_events(log)
    steps = [(e["step"], e["ok"]) for e in events if e["kind"] == "safe_step"]
    assert steps[-2:] == [("home", True), ("release torque", True)]
    assert events[-1]["kind"] == "run_end" and events[-1]["outcome"] == "stopped"
    assert next(e for e in events if e["kind"] == "sim_truth")["where"].get("gripper") is None
    port = Path(next(e["arm_port"] for e in events if e["kind"] == "run_start"))
    assert not port.parent.exists()  # the emulator's pty folder is gone


def test_concurrent_recalibrations_are_serialised_and_keep_every_backup(tmp_path):
    camera = CameraModel.looking_down(1280, 720, 0.30, (132, 88), tilt_deg=3, k1=-0.06)
    cv2.imwrite(str(tmp_path / "plate.png"), render_plate(camera, CellConfig().plate, seed=1))
    (tmp_path / "cell.toml").write_text("[camera]\nwidth_px = 1280\nheight_px = 720\n")
    out = tmp_path / "cal" / "active.json"
    out.parent.mkdir()
    out.write_text('{"original": true}')  # not a calibration: it cannot be compared, only kept
    runs = [
        subprocess.Popen(
            [
                sys.executable,
                str(REPO / "scripts" / "recalibrate.py"),
                "--image",
                str(tmp_path / "plate.png"),
                "--out",
                str(out),
                "--config",
                str(tmp_path / "cell.toml"),
                "--log",
                str(tmp_path / "cell.log"),
                "--quiet",
                "--model",
                model,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for model in ("camera", "polynomial", "camera", "polynomial")
    ]
    results = [(p.wait(timeout=120), p.stderr.read()) for p in runs]
    for p in runs:
        p.stdout.close()
        p.stderr.close()
    assert [code for code, _ in results] == [0, 0, 0, 0], results
    backups = sorted((out.parent / "backups").iterdir())
    assert len(backups) == 4  # four replacements, four backups: none overwrote another
    contents = [b.read_text() for b in backups]
    assert contents.count('{"original": true}') == 1  # the original is kept
    assert all(json.loads(c)["schema"] == "pick-cell/calibration" for c in contents if "original" not in c)
    assert json.loads(out.read_text())["model"] in ("camera", "polynomial")
    assert not [p for p in out.parent.rglob("*") if p.name.endswith(".tmp")]


def test_a_pause_in_the_first_second_never_kills_the_job_and_holds_it_before_any_motion(tmp_path):
    """SIGUSR1 as soon as the process has said it started (still importing numpy, OpenCV...): the
    job pauses before its first motion, and a second SIGUSR1 lets it run to the end."""
    proc = subprocess.Popen(
        [str(RUN_CELL), "--dry-run", "--log-dir", str(tmp_path / "logs")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        first = proc.stdout.readline()
        assert first.startswith("run-cell: starting a job"), first
        proc.send_signal(signal.SIGUSR1)
        for line in proc.stdout:
            assert not line.startswith("pick "), "it moved while paused"
            if line.startswith("paused at a safe point"):
                break
        proc.send_signal(signal.SIGUSR1)
        rest = proc.stdout.read()
        assert proc.wait(timeout=120) == 0, proc.stderr.read()
    finally:
        proc.kill()
        proc.wait()
    assert "pick 17:" in rest
    (log,) = (tmp_path / "logs").glob("run-*.jsonl")
    states = [e["target"] for e in read_events(log) if e["kind"] == "state"]
    assert states[:3] == ["home", "paused", "home"]  # paused before the first motion


def test_a_stop_in_the_first_second_ends_with_one_line_and_no_traceback(tmp_path):
    proc = subprocess.Popen(
        [str(RUN_CELL), "--dry-run", "--log-dir", str(tmp_path / "logs")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().startswith("run-cell: starting a job")
        proc.send_signal(signal.SIGTERM)
        err = proc.stderr.read()
        assert proc.wait(timeout=120) == 130, err
    finally:
        proc.kill()
        proc.wait()
    assert "Traceback" not in err and "SIGTERM" in err.strip().splitlines()[-1]

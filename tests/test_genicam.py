"""GenICam cameras through Aravis: against Aravis's fake GigE Vision camera (`arv-fake-gv-camera-0.8`,
started here on loopback, with packet loss where asked), and against Aravis's in-process Fake
interface: discovery and the config line, settings checked and read back, software trigger, frames
lost and retried, the camera killed and back; and the driver imported only for a genicam source.

The fake GigE camera listens on GVCP's fixed port (3956) of 127.0.0.1, so two at once would answer
for each other: each is started under one lock shared by every process (xdist's workers, other
checkouts' runs) and stopped before the next starts.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from cell.cli import main
from drivers.cameras.config import CameraConfig
from drivers.cameras.errors import CameraError
from drivers.cameras.factory import make_camera
from drivers.cameras.genicam import GenICamCamera

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[1]
FAKE_GV = shutil.which("arv-fake-gv-camera-0.8")
GVCP_PORT = 3956


def _aravis_missing() -> str | None:
    try:
        from drivers.cameras.genicam import aravis

        aravis()
    except CameraError as e:
        return f"no GenICam here ({e}); .ci/run installs Aravis and PyGObject"
    return None


MISSING = _aravis_missing()
needs_aravis = pytest.mark.skipif(MISSING is not None, reason=MISSING or "")
needs_fake_gv = pytest.mark.skipif(
    MISSING is not None or FAKE_GV is None,
    reason=MISSING or "no arv-fake-gv-camera-0.8 (Debian aravis-tools; .ci/run installs it)",
)


def _port_bound() -> bool:
    """Whether something holds GVCP's port on 127.0.0.1 (the fake camera binds it with SO_REUSEADDR)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", GVCP_PORT))
        except OSError:
            return True
        return False


@contextlib.contextmanager
def _one_fake_at_a_time() -> Iterator[None]:
    path = Path(tempfile.gettempdir()) / "pick-cell-arv-fake-gv.lock"
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # blocks while another test's fake camera runs
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


class FakeGV:
    """arv-fake-gv-camera-0.8 on 127.0.0.1 with a serial of its own; start() and kill() may repeat."""

    def __init__(self, loss_per_thousand: int = 0):
        self.serial = f"T{uuid.uuid4().hex[:8].upper()}"
        self.loss = loss_per_thousand
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        argv = [str(FAKE_GV), "-i", "127.0.0.1", "-s", self.serial]
        if self.loss:
            argv += ["-r", str(self.loss)]
        self.proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 20
        while not _port_bound():
            if self.proc.poll() is not None:
                pytest.fail(
                    f"arv-fake-gv-camera-0.8 ended: {self.proc.stderr.read().decode() if self.proc.stderr else ''}"
                )
            assert time.monotonic() < deadline, "the fake camera did not bind GVCP's port in 20 s"
            time.sleep(0.02)

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)
            if self.proc.stderr is not None:
                self.proc.stderr.close()
        self.proc = None


@pytest.fixture
def fake_gv(request) -> Iterator[FakeGV]:
    loss = getattr(request, "param", 0)
    with _one_fake_at_a_time():
        fake = FakeGV(loss)
        fake.start()
        try:
            yield fake
        finally:
            fake.kill()


def genicam_config(wanted: str, w: int = 320, h: int = 240, **genicam: object) -> CameraConfig:
    genicam.setdefault("features", {"AcquisitionFrameRate": 200.0})  # the fake answers a trigger at its frame rate
    genicam.setdefault("acquisition_timeout_s", 10.0)  # generous for a loaded machine; a passing test waits none of it
    return CameraConfig.model_validate(
        {"source": f"genicam:{wanted}", "width_px": w, "height_px": h, "timeout_s": 10, "genicam": genicam}
    )


def genicam_camera(wanted: str, w: int = 320, h: int = 240, **genicam: object) -> GenICamCamera:
    """The camera make_camera builds for a genicam source (as the cell gets it), not yet connected."""
    camera = make_camera(genicam_config(wanted, w, h, **genicam))
    assert isinstance(camera, GenICamCamera)
    return camera


def test_the_driver_is_imported_only_for_a_genicam_source():
    code = (
        "import sys, drivers.cameras.factory, cell.cli, cell.assembly\n"
        "print(sorted(m for m in sys.modules if m.startswith('gi') or m == 'drivers.cameras.genicam'))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert out.stdout.strip() == "[]"


def test_a_genicam_source_must_name_a_camera():
    with pytest.raises(CameraError, match=r"no camera named.*run-cell cameras"):
        make_camera(CameraConfig(source="genicam: "))


def _without_pygobject(monkeypatch):
    """This process as on a machine without PyGObject: importing gi fails as it would there."""
    import importlib

    real = importlib.import_module

    def import_module(name, package=None):
        if name == "gi" or name.startswith("gi."):
            raise ModuleNotFoundError("No module named 'gi'")
        return real(name, package)

    monkeypatch.setattr(importlib, "import_module", import_module)


def test_without_aravis_a_genicam_source_says_what_to_install(monkeypatch):
    _without_pygobject(monkeypatch)
    camera = genicam_camera("24312345")
    with pytest.raises(
        CameraError, match=r"no GenICam support here: No module named 'gi' \(hint: .*gir1\.2-aravis-0\.8.*genicam"
    ):
        camera.connect()
    assert not camera.is_connected


def test_without_aravis_run_cell_cameras_lists_the_rest_and_says_why(monkeypatch, capsys):
    _without_pygobject(monkeypatch)
    assert main(["cameras"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("OpenCV video devices: ")
    assert "GenICam cameras: none listed: no GenICam support here: No module named 'gi'" in out


@needs_fake_gv
def test_discovery_lists_the_fake_gige_camera_with_its_config_line(fake_gv, capsys):
    assert main(["cameras"]) == 0
    out = capsys.readouterr().out
    assert f"Aravis Fake, serial {fake_gv.serial}, address 127.0.0.1, GigEVision" in out
    assert f'[camera] source = "genicam:Aravis-Fake-{fake_gv.serial}"' in out


@needs_fake_gv
def test_settings_read_back_and_software_trigger_gives_one_new_frame_per_capture(fake_gv):
    camera = genicam_camera("127.0.0.1", exposure_us=1500.0, gain_db=4.0)  # by address: no discovery
    with camera:
        settings = camera.settings()
        assert settings["exposure_us"] == 1500.0 and settings["gain_db"] == 4.0
        assert settings["pixel_format"] == "Mono8" and settings["region_px"] == (0, 0, 320, 240)
        assert (settings["trigger_mode"], settings["trigger_source"]) == ("On", "Software")
        ids = []
        for _ in range(3):
            before = time.time_ns()
            frame = camera.capture()
            info = camera.last_frame
            assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8
            assert info.system_timestamp_ns >= before  # begun after the request, never a queued one
            ids.append(info.frame_id)
        assert ids == [ids[0], ids[0] + 1, ids[0] + 2]  # one trigger, one frame: none skipped, none stale
        assert camera.stats.frames == 3 and camera.stats.incomplete == 0
        assert camera.device.serial == fake_gv.serial


@needs_fake_gv
@pytest.mark.parametrize(
    ("genicam", "words"),
    [
        ({"exposure_us": 5e7}, r"exposure_us 5e\+07 out of range 10 to 1e\+07 µs"),
        ({"features": {"BalanceWhiteAuto": "Off"}}, r"has no feature 'BalanceWhiteAuto'"),
        ({"features": {"AcquisitionFrameRate": 5000.0}}, r"feature AcquisitionFrameRate = 5000 out of range"),
        (
            {"features": {"GainAuto": "Sometimes"}},
            r"feature GainAuto = 'Sometimes' is not one of Off, Once, Continuous",
        ),
        ({"trigger": "line", "trigger_line": "Line7"}, r"trigger source Line7 not offered \(it has Line0, Software\)"),
    ],
)
def test_a_setting_the_camera_does_not_have_is_refused_naming_it(fake_gv, genicam, words):
    camera = genicam_camera("127.0.0.1", **genicam)
    with pytest.raises(CameraError, match=words):
        camera.connect()
    assert not camera.is_connected


@needs_fake_gv
@pytest.mark.parametrize("fake_gv", [200], indirect=True)  # 20 % of the stream's packets lost: 2 in 3 frames
def test_lost_packets_are_counted_retried_and_raise_the_loss_warning(fake_gv):
    camera = genicam_camera(
        "127.0.0.1", 64, 48, acquisition_timeout_s=30.0, loss_alarm_percent=1.0, loss_window_frames=10
    )
    warnings: list[tuple[str, str, str]] = []
    camera.on_warning = lambda *w: warnings.append(w)
    with camera:
        deadline = time.monotonic() + 60
        while not warnings:  # every capture still returns a complete frame
            assert time.monotonic() < deadline, f"no loss warning: {camera.stats}"
            assert camera.capture().shape == (48, 64, 3)
        stats = camera.stats
    assert stats.incomplete >= 1 and stats.frames >= 1
    key, reason, hint = warnings[0]
    assert key == "camera-frame-loss" and f"camera {fake_gv.serial}: " in reason and "came incomplete" in reason
    assert "packet_size_bytes" in hint


@needs_fake_gv
def test_the_camera_killed_is_lost_in_words_and_taken_back_when_it_returns(fake_gv):
    camera = genicam_camera(fake_gv.serial)
    with camera:
        camera.capture()
        fake_gv.kill()
        with pytest.raises(
            CameraError, match=rf"^camera {fake_gv.serial} lost: .*timeout.*\(hint: check the camera at 127\.0\.0\.1"
        ):
            camera.capture()
        with pytest.raises(CameraError, match=rf"^camera {fake_gv.serial} lost: .*; not back yet: "):
            camera.capture()
        fake_gv.start()
        deadline = time.monotonic() + 30
        while True:
            try:
                frame = camera.capture()
                break
            except CameraError as e:
                assert "not back yet" in str(e) and time.monotonic() < deadline, e
        assert frame.shape == (240, 320, 3)
        assert camera.stats.lost == 1 and camera.stats.reconnects == 1


@needs_fake_gv
def test_run_cell_camera_snapshot_from_a_genicam_camera(fake_gv, tmp_path, capsys):
    config = tmp_path / "cell.toml"
    config.write_text(
        f'[camera]\nsource = "genicam:{fake_gv.serial}"\nwidth_px = 640\nheight_px = 480\n'
        "[camera.genicam]\nexposure_us = 2000\nfeatures = { AcquisitionFrameRate = 200.0 }\n"
    )
    snap = tmp_path / "snap.png"
    assert main(["camera", "--config", str(config), "--snapshot", str(snap)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"camera genicam:{fake_gv.serial}: 640 x 480 px\n") and f"snapshot: {snap}" in out
    assert "raise camera.genicam.exposure_us or the backlight" in out  # the fake's ramp reads dark
    import cv2

    assert cv2.imread(str(snap)).shape == (480, 640, 3)


@needs_aravis
def test_the_in_process_fake_camera_gives_bayer_frames_converted_to_colour():
    camera = genicam_camera("Fake_1", 320, 240, pixel_format="BayerRG8", features={})
    with camera:
        frames, ids = [], []
        for _ in range(2):
            frames.append(camera.capture())
            ids.append(camera.last_frame.frame_id)
        assert camera.settings()["pixel_format"] == "BayerRG8"
    assert all(f.shape == (240, 320, 3) and f.dtype == np.uint8 for f in frames)
    assert frames[0].std() > 0  # the fake's ramp, not a blank
    assert camera.device.interface == "Fake"
    assert ids[1] == ids[0] + 1

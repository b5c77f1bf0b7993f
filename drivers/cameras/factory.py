"""Which frame source a camera config names: a device index, a URL, a folder, a video file or a
GenICam camera (whose driver, and Aravis with it, is imported only then)."""

from __future__ import annotations

from pathlib import Path

from drivers.cameras.base import Camera
from drivers.cameras.config import GENICAM_PREFIX, CameraConfig
from drivers.cameras.errors import CameraError
from drivers.cameras.folder import FolderCamera
from drivers.cameras.opencv import OpenCVCamera
from drivers.cameras.video import VideoFileCamera


def make_camera(cfg: CameraConfig) -> Camera:
    """A Camera for the config; 'sim' is built by the simulated cell, not here."""
    source = cfg.source.strip()
    if source == "sim":
        raise CameraError("the simulated camera comes with the simulated cell", source=source)
    if source.startswith(GENICAM_PREFIX):
        wanted = source.removeprefix(GENICAM_PREFIX).strip()
        if not wanted:
            raise CameraError(
                "no camera named", source=source, hint="camera.source is 'genicam:<id>' as `run-cell cameras` prints it"
            )
        from drivers.cameras.genicam import GenICamCamera

        return GenICamCamera(wanted, cfg.width_px, cfg.height_px, cfg.timeout_s, cfg.genicam)
    if source.isdigit():
        return OpenCVCamera(
            int(source), cfg.width_px, cfg.height_px, cfg.timeout_s, cfg.focus, cfg.exposure, cfg.warmup_frames
        )
    if "://" in source:
        return OpenCVCamera(
            source, cfg.width_px, cfg.height_px, cfg.timeout_s, cfg.focus, cfg.exposure, cfg.warmup_frames
        )
    path = Path(source)
    if path.is_dir():
        return FolderCamera(path, cfg.width_px, cfg.height_px, cfg.loop)
    if path.is_file():
        return VideoFileCamera(path, cfg.width_px, cfg.height_px, cfg.loop)
    raise CameraError(
        "no such device, URL, folder or video file",
        source=source,
        hint="camera.source is 'sim', a device index (0), a URL (rtsp://...), a folder, a video file "
        "or genicam:<id> (`run-cell cameras` lists the cameras)",
    )

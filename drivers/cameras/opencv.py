"""A camera device (index) or stream URL through cv2.VideoCapture.

The paper's webcam (Logitech C525) has autofocus and auto-exposure: either may drift
between the calibration and the job and move every located part, so both are locked
where the backend allows it; what the camera would not accept is logged, not hidden.
"""

from __future__ import annotations

import contextlib
import glob
import logging
import os
import socket
from collections.abc import Iterator
from urllib.parse import urlsplit

import cv2
import numpy as np

from drivers.cameras.base import Camera
from drivers.cameras.errors import CameraError

log = logging.getLogger(__name__)

# OpenCV's and FFmpeg's own lines ("[ WARN:0@0.01] global cap_v4l.cpp ...", "[tcp @ 0x...]
# Connection refused") would reach the operator's terminal beside our one-line error, which
# says the same in words (why_not_open). FFmpeg reads its level once, at its first use, from
# this variable (-8: quiet); either variable set by the user is left alone.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
_DEFAULT_PORTS = {"rtsp": 554, "http": 80, "https": 443, "rtmp": 1935}


@contextlib.contextmanager
def opencv_quiet() -> Iterator[None]:
    """OpenCV's own logging silenced for a block (unless OPENCV_LOG_LEVEL asks for it)."""
    if "OPENCV_LOG_LEVEL" in os.environ:
        yield
        return
    before = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(before)


def why_not_open(target: int | str, timeout_s: float) -> tuple[str, str]:
    """(reason, hint) in words for a source cv2.VideoCapture could not open."""
    text = str(target)
    if isinstance(target, int) or text.isdigit() or text.startswith("/dev/"):
        device = f"/dev/video{text}" if text.isdigit() else text
        present = sorted(glob.glob("/dev/video*"))
        if not os.path.exists(device):
            listed = ", ".join(present) if present else "none"
            return f"no such device {device}", f"video devices here: {listed}; set camera.source to its number"
        if not os.access(device, os.R_OK | os.W_OK):
            return f"{device}: permission denied", "add the user to the 'video' group, then log in again"
        return (
            f"{device} gives no video",
            "another program may hold it, or it is not a capture node (a webcam often has two: try the other)",
        )
    url = urlsplit(text)
    if url.hostname:
        try:
            port = url.port or _DEFAULT_PORTS.get(url.scheme, 80)
        except ValueError:
            return f"bad port in {text}", "camera.source is a URL like rtsp://host:554/path"
        try:
            with socket.create_connection((url.hostname, port), timeout=min(timeout_s, 3.0)):
                pass
        except OSError as e:
            return (
                f"cannot connect to {url.hostname}:{port}: {e.strerror or e}",
                "check the camera's address and network",
            )
        return f"{url.hostname}:{port} answers but sends no video", "check the URL's path, user and password"
    return "cannot open", "check camera.source: a device number, a URL, a video file or an image folder"


class CaptureCamera(Camera):
    """A source read through one cv2.VideoCapture (a device, a stream or a video file)."""

    _cap: cv2.VideoCapture | None = None

    def disconnect(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    @property
    def is_connected(self) -> bool:
        return self._cap is not None

    def _opened(self) -> cv2.VideoCapture:
        """The open capture; CameraError before connect or after disconnect."""
        if self._cap is None:
            raise CameraError("capture before connect", source=self.source)
        return self._cap


class OpenCVCamera(CaptureCamera):
    def __init__(
        self,
        source: int | str,
        width_px: int,
        height_px: int,
        timeout_s: float = 5.0,
        focus: float | None = None,
        exposure: float | None = None,
        warmup_frames: int = 5,
    ):
        self.source = str(source)
        self._target = source
        self.width_px = width_px
        self.height_px = height_px
        self.timeout_s = timeout_s
        self.focus = focus
        self.exposure = exposure
        self.warmup_frames = warmup_frames

    def connect(self) -> None:
        params = [
            cv2.CAP_PROP_OPEN_TIMEOUT_MSEC,
            int(self.timeout_s * 1000),
            cv2.CAP_PROP_READ_TIMEOUT_MSEC,
            int(self.timeout_s * 1000),
        ]
        with opencv_quiet():
            cap = cv2.VideoCapture(self._target, cv2.CAP_ANY, params)
            opened = cap.isOpened()
        if not opened:
            cap.release()
            reason, hint = why_not_open(self._target, self.timeout_s)
            raise CameraError(f"cannot open: {reason}", source=self.source, hint=hint)
        self._cap = cap
        self._set(cv2.CAP_PROP_FRAME_WIDTH, self.width_px, "width")
        self._set(cv2.CAP_PROP_FRAME_HEIGHT, self.height_px, "height")
        self._set(cv2.CAP_PROP_BUFFERSIZE, 1, "buffer size")
        self._set(cv2.CAP_PROP_AUTOFOCUS, 0, "autofocus off")
        if self.focus is not None:
            self._set(cv2.CAP_PROP_FOCUS, self.focus, "focus")
        if self.exposure is not None:
            self._set(cv2.CAP_PROP_AUTO_EXPOSURE, 1, "manual exposure")  # V4L2: 1 manual, 3 auto
            self._set(cv2.CAP_PROP_EXPOSURE, self.exposure, "exposure")
        with opencv_quiet():
            for _ in range(self.warmup_frames):  # let exposure settle, drop stale buffered frames
                cap.grab()

    def _set(self, prop: int, value: float, what: str) -> None:
        if not self._opened().set(prop, value):
            log.warning("camera %s: could not set %s to %s", self.source, what, value)

    def _grab(self) -> np.ndarray | None:
        with opencv_quiet():
            cap = self._opened()
            cap.grab()  # the buffered frame may be old: drop it, keep the next
            ok, frame = cap.read()
        return frame if ok else None


def video_devices() -> list[tuple[int, str]]:
    """The V4L2 capture devices here, as (index for camera.source, the device's own name), by index."""
    found = []
    for path in glob.glob("/dev/video*"):
        number = path.removeprefix("/dev/video")
        if not number.isdigit():
            continue
        try:
            with open(f"/sys/class/video4linux/video{number}/name", encoding="utf-8", errors="replace") as f:
                name = f.read().strip()
        except OSError:
            name = ""
        found.append((int(number), name))
    return sorted(found)

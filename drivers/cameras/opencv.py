"""A camera device (index) or stream URL through cv2.VideoCapture.

The paper's webcam (Logitech C525) has autofocus and auto-exposure: either may drift
between the calibration and the job and move every located part, so both are locked
where the backend allows it; what the camera would not accept is logged, not hidden.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from drivers.cameras.base import Camera
from drivers.cameras.errors import CameraError

log = logging.getLogger(__name__)


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
        cap = cv2.VideoCapture(self._target, cv2.CAP_ANY, params)
        if not cap.isOpened():
            cap.release()
            raise CameraError(
                "cannot open",
                source=self.source,
                hint="check the device index (ls /dev/video*) or the URL, and that no other program holds it",
            )
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
        for _ in range(self.warmup_frames):  # let exposure settle, drop stale buffered frames
            cap.grab()

    def _set(self, prop: int, value: float, what: str) -> None:
        if not self._cap.set(prop, value):
            log.warning("camera %s: could not set %s to %s", self.source, what, value)

    def _grab(self) -> np.ndarray | None:
        self._cap.grab()  # the buffered frame may be old: drop it, keep the next
        ok, frame = self._cap.read()
        return frame if ok else None

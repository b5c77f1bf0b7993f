"""Frames from a video file, in order: a recorded job replayed through the cell."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from drivers.cameras.errors import CameraError
from drivers.cameras.opencv import CaptureCamera, opencv_quiet


class VideoFileCamera(CaptureCamera):
    def __init__(self, path: str | Path, width_px: int, height_px: int, loop: bool = False):
        self.path = Path(path)
        self.source = str(path)
        self.width_px = width_px
        self.height_px = height_px
        self.loop = loop

    def connect(self) -> None:
        if not self.path.is_file():
            raise CameraError("video file not found", source=self.source)
        with opencv_quiet():
            cap = cv2.VideoCapture(str(self.path))
            opened = cap.isOpened()
        if not opened:
            cap.release()
            raise CameraError("cannot decode the video file", source=self.source)
        self._cap = cap

    def _grab(self) -> np.ndarray | None:
        with opencv_quiet():
            cap = self._opened()
            ok, frame = cap.read()
            if not ok and self.loop:
                cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                ok, frame = cap.read()
        if not ok:
            raise CameraError("the video has no more frames", source=self.source)
        return frame

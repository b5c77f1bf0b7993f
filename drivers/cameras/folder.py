"""Frames from a folder of images, in name order: stills replayed through the cell."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from drivers.cameras.base import Camera
from drivers.cameras.errors import CameraError
from drivers.cameras.imageheader import UnknownFormat, image_size

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


class FolderCamera(Camera):
    def __init__(self, folder: str | Path, width_px: int, height_px: int, loop: bool = False):
        self.folder = Path(folder)
        self.source = str(folder)
        self.width_px = width_px
        self.height_px = height_px
        self.loop = loop
        self._files: list[Path] | None = None
        self._next = 0

    def connect(self) -> None:
        if not self.folder.is_dir():
            raise CameraError("image folder not found", source=self.source)
        files = sorted(p for p in self.folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise CameraError(f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in the folder", source=self.source)
        self._files = files
        self._next = 0

    def disconnect(self) -> None:
        self._files = None

    @property
    def is_connected(self) -> bool:
        return self._files is not None

    def _grab(self) -> np.ndarray | None:
        files = self._files
        if files is None:
            raise CameraError("capture before connect", source=self.source)
        if self._next >= len(files):
            if not self.loop:
                raise CameraError(f"no more images after {len(files)}", source=self.source)
            self._next = 0
        path = files[self._next]
        self._next += 1
        try:
            size = image_size(path)
        except (UnknownFormat, OSError) as e:
            raise CameraError(f"{path.name}: not a readable image ({e})", source=self.source) from None
        if size != (self.width_px, self.height_px):  # refused from the header: a huge file is never decoded
            raise CameraError(
                f"{path.name}: frame is {size[0]}x{size[1]} px, expected {self.width_px}x{self.height_px} "
                "px; not decoded",
                source=self.source,
            )
        frame = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if frame is None:
            raise CameraError(f"{path.name}: not a readable image", source=self.source)
        return frame

"""The camera interface the cell programs against: connect, capture one BGR frame, disconnect.

Every frame is checked here, once for all sources: a missing frame or one of the wrong
size is a CameraError with the reason, never an exception from deep inside OpenCV.
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Callable

import numpy as np

from drivers.cameras.errors import CameraError
from drivers.device import Device

log = logging.getLogger(__name__)


class Camera(Device):
    """One frame source of a fixed size; `with camera:` connects and always disconnects."""

    source: str
    width_px: int
    height_px: int
    # Where a camera reports a condition worth a warning alarm that is not a failure (a GenICam camera's
    # share of incomplete frames): (key, reason, hint), and the key when it is over. The line service sets
    # them to its warnings; left None, the driver only logs.
    on_warning: Callable[[str, str, str], None] | None = None
    on_clear: Callable[[str], None] | None = None

    @abc.abstractmethod
    def _grab(self) -> np.ndarray | None:
        """The next raw frame, or None if the source gave none."""

    def capture(self) -> np.ndarray:
        """The next frame as a BGR uint8 array of the configured size."""
        if not self.is_connected:
            raise CameraError("capture before connect", source=self.source)
        frame = self._grab()
        if frame is None or not isinstance(frame, np.ndarray) or frame.size == 0:
            raise CameraError(
                "returned no frame",
                source=self.source,
                hint="check the cable, the device index or URL, and that no other program holds the camera",
            )
        if frame.ndim == 2:
            frame = np.repeat(frame[:, :, None], 3, axis=2)
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            raise CameraError(
                f"frame is {frame.dtype} with shape {frame.shape}, expected 8-bit BGR", source=self.source
            )
        h, w = frame.shape[:2]
        if (w, h) != (self.width_px, self.height_px):
            raise CameraError(
                f"frame is {w}x{h} px, expected {self.width_px}x{self.height_px} px",
                source=self.source,
                hint="set camera.width_px/height_px to a mode the camera supports",
            )
        return frame

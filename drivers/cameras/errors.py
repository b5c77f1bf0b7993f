"""Camera failures the operator sees as one line: which source, what went wrong."""

from __future__ import annotations

from drivers.errors import DeviceError


class CameraError(DeviceError):
    """A frame source failed: cannot open, no frame, wrong size, ran out of frames."""

    def __init__(self, message: str, *, source: str | None = None, hint: str | None = None):
        super().__init__(f"camera {source}: {message}" if source else message, hint=hint)
        self.source = source

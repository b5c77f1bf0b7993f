"""Camera failures the operator sees as one line: which source, what went wrong."""
from __future__ import annotations

from cell.errors import CellError


class CameraError(CellError):
    """A frame source failed: cannot open, no frame, wrong size, ran out of frames."""

    def __init__(self, message: str, *, source: str | None = None, hint: str | None = None):
        super().__init__(f"camera {source}: {message}" if source else message, hint)
        self.source = source

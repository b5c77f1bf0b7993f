"""The camera check on the screen: what `run-cell camera --live` prints, on the live view.

Switched on from the screen (any user who may control the cell), each live frame is assessed
by cell.vision.commissioning: focus (variance of the Laplacian) against the best seen since
the check was switched on, exposure (histogram, % clipped black and white), the plate's share
of the view and the camera's tilt to it, and what to adjust, in words. It runs in the screen's
live-view thread, only between jobs (about 75 ms of CPU per 1920 x 1080 frame), and switches
itself off after CHECK_FOR_S so a check left on costs nothing for long.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from cell.config import CellConfig
from cell.vision.commissioning import CameraView, FocusTracker, assess

CHECK_FOR_S = 900.0


class CameraCheck:
    def __init__(self, config: CellConfig, check_for_s: float = CHECK_FOR_S):
        self.config, self.check_for_s = config, check_for_s
        self._lock = threading.Lock()
        self._since: float | None = None  # time.monotonic() when switched on; None: off
        self._tracker = FocusTracker()

    @property
    def on(self) -> bool:
        since = self._since
        return since is not None and time.monotonic() - since < self.check_for_s

    def switch(self, on: bool) -> None:
        """On: a fresh best focus (the operator is about to turn the ring); off: nothing more is assessed."""
        with self._lock:
            self._since = time.monotonic() if on else None
            if on:
                self._tracker = FocusTracker()

    def read(self, image: np.ndarray) -> dict[str, Any] | None:
        """The frame's readings as the page shows them, or None when the check is off."""
        if not self.on:
            return None
        with self._lock:
            tracker = self._tracker
            view = assess(image, self.config, tracker)
            return check_json(view, tracker)


def check_json(view: CameraView, tracker: FocusTracker) -> dict[str, Any]:
    e, p = view.exposure, view.plate
    return {
        "focus": round(view.focus, 1),
        "focus_best": round(tracker.best, 1),
        "focus_pct": round(100.0 * view.focus / tracker.best, 0) if tracker.best > 0 else 100.0,
        "exposure": {
            "mean": round(e.mean, 0),
            "backlight": round(e.backlight, 0),
            "black_pct": round(e.dark_clipped_pct, 1),
            "white_pct": round(e.bright_clipped_pct, 1),
            "histogram": [round(x, 4) for x in e.histogram],
        },
        "plate": None
        if p is None
        else {
            "found": p.circles_found,
            "expected": p.circles_expected,
            "coverage_pct": round(p.coverage_pct, 0),
            "in_view": p.in_view,
            "tilt_deg": round(p.tilt_deg, 1),
            "nearer": p.nearer,
            "turned_deg": round(p.turned_deg, 1),
        },
        "plate_note": view.plate_note,
        "advice": list(view.advice),
    }

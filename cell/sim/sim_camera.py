"""The simulated camera: the world's table rendered through the camera model at each capture.

Each part's silhouette is rendered once and kept while the part stays put; a capture
composes the kept silhouettes and exposes them (light fall-off, blur, fresh noise), so a
frame costs one exposure, not a re-render of every part. `render_s` adds up the time
spent, which the cell reports apart from its own software time.

The table may carry printed reference marks (dark dots that never move), and the camera
may be bumped: from a chosen frame on, it sees through a moved camera model.
"""

from __future__ import annotations

import time

import numpy as np

from cell.camera_model import CameraModel
from cell.sim.parts import part_coverage
from cell.sim.render import Optics, circles_coverage, expose
from cell.sim.world import World
from drivers.cameras.base import Camera


class SimCamera(Camera):
    def __init__(
        self,
        world: World,
        model: CameraModel,
        optics: Optics = Optics(),
        seed: int = 0,
        marks_mm: np.ndarray | None = None,
        mark_diameter_mm: float = 1.5,
        bump: tuple[int, CameraModel] | None = None,
    ):
        """`marks_mm`: printed reference marks' centres (table mm); `bump`: (frame number from
        which on, the moved camera model)."""
        self.source = "sim"
        self.world = world
        self.model = model
        self.width_px = model.width_px
        self.height_px = model.height_px
        self.optics = optics
        self.rng = np.random.default_rng(seed)
        self.render_s = 0.0
        self.frames = 0
        self._silhouettes: dict = {}
        self._connected = False
        self.marks_mm = np.zeros((0, 2)) if marks_mm is None else np.asarray(marks_mm, dtype=np.float64).reshape(-1, 2)
        self.mark_radius_mm = mark_diameter_mm / 2
        self.bump = bump
        self._marks: np.ndarray | None = None

    def connect(self) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def _grab(self) -> np.ndarray:
        t0 = time.perf_counter()
        if self.bump is not None and self.frames + 1 >= self.bump[0]:
            self.model, self.bump = self.bump[1], None
            self._silhouettes, self._marks = {}, None  # everything is seen from elsewhere now
        if self._marks is None:
            self._marks = circles_coverage(self.model, self.marks_mm, self.mark_radius_mm)
        opacity = self._marks.copy()
        keep = {}
        for part_id, spec in self.world.table_specs():
            key = (part_id, spec)
            got = self._silhouettes[key] if key in self._silhouettes else part_coverage(self.model, spec)
            keep[key] = got
            if got is None:
                continue
            (x0, y0), cov = got
            sl = (slice(y0, y0 + cov.shape[0]), slice(x0, x0 + cov.shape[1]))
            np.maximum(opacity[sl], cov, out=opacity[sl])
        self._silhouettes = keep
        frame = expose(self.model, opacity, self.optics, self.rng)
        self.render_s += time.perf_counter() - t0
        self.frames += 1
        return frame

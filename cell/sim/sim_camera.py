"""The simulated camera: the world's table rendered through the camera model at each capture.

Each part's silhouette is rendered once and kept while the part stays put; a capture
composes the kept silhouettes and exposes them (light fall-off, blur, noise from its pool), so a
frame costs one exposure, not a re-render of every part. The silhouettes and the marks are
kept as small windows and exposed band by band (render.Scene): a capture allocates its frame
and a few MB, never a frame-sized float image. `render_s` adds up the time spent, which the
cell reports apart from its own software time.

The table may carry printed reference marks (dark dots that never move), and the camera
may be bumped: from a chosen frame on, it sees through a moved camera model.
"""

from __future__ import annotations

import time

import numpy as np

from cell.camera_model import CameraModel
from cell.sim.parts import part_coverage
from cell.sim.render import Optics, Scene, SensorNoise, Window, circles_windows, expose
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
        self._marks: list[Window] | None = None
        self._noise: SensorNoise | None = None

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
            self._marks = circles_windows(self.model, self.marks_mm, self.mark_radius_mm)
        if self._noise is None or self._noise.width_px != self.model.width_px:
            self._noise = SensorNoise(self.model.width_px, self.optics.noise_sigma, self.rng)
        frame = expose(self.model, self._scene(), self.optics, self.rng, noise_pool=self._noise)
        self.render_s += time.perf_counter() - t0
        self.frames += 1
        return frame

    def _scene(self) -> Scene:
        """The marks and every part on the table (each part's silhouette rendered once, while it stays put)."""
        keep = {}
        windows = list(self._marks or [])
        for part_id, spec in self.world.table_specs():
            key = (part_id, spec)
            got = self._silhouettes[key] if key in self._silhouettes else part_coverage(self.model, spec)
            keep[key] = got
            if got is not None:
                windows.append(got)
        self._silhouettes = keep
        return Scene(self.model.height_px, self.model.width_px, windows)

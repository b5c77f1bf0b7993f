"""The simulated camera: the world's table rendered through the camera model at each capture.

Each part's silhouette is rendered once and kept while the part stays put; a capture
composes the kept silhouettes and exposes them (light fall-off, blur, fresh noise), so a
frame costs one exposure, not a re-render of every part. `render_s` adds up the time
spent, which the cell reports apart from its own software time.
"""
from __future__ import annotations

import time

import numpy as np

from cell.camera_model import CameraModel
from cell.sim.parts import part_coverage
from cell.sim.render import Optics, expose
from cell.sim.world import World
from drivers.cameras.base import Camera


class SimCamera(Camera):
    def __init__(self, world: World, model: CameraModel, optics: Optics = Optics(), seed: int = 0):
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

    def connect(self) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def _grab(self) -> np.ndarray:
        t0 = time.perf_counter()
        opacity = np.zeros((self.height_px, self.width_px), np.float64)
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

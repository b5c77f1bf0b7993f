"""The dry run's parts supply: bolts, nuts and washers dropped onto free spots of the simulated
table at a set rate of simulated time, so continuous mode has a shift to work through.

Parts arrive only when the camera takes a frame (the feeder is ticked from the capture),
so nothing changes between the frame a pick was planned on and the pick itself. A part
lands where its outline keeps MIN_GAP_MM from every other part's, never where a part has
just been taken away (the next frame verifies that pick), and inside the configured area.
Parts that reach a bin, and parts left on the table past `clear_after_s` (the washers the
cell leaves), are taken out of the world and tallied, so a long shift holds no more than
what lies on the table.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import numpy as np

from cell.run_config import FeederConfig
from cell.sim.cell import MIN_GAP_MM, outline_gap_mm
from cell.sim.parts import BOLTS_MM, NUTS_MM, WASHERS_MM, ExtrudedPart, PartSpec
from cell.sim.world import SimPart, World
from drivers.cameras.base import Camera

log = logging.getLogger(__name__)

_BOLT_LENGTHS_MM = (12.0, 16.0, 20.0, 25.0, 30.0)
_VACATED_CLEARANCE_MM = 12.0  # from where a part was just taken: the verify radius plus a part's extent
_TRIES = 60


class Feeder:
    def __init__(self, world: World, cfg: FeederConfig, sim_time_s: Callable[[], float]):
        self.world, self.cfg, self.sim_time_s = world, cfg, sim_time_s
        self.rng = np.random.default_rng(cfg.seed)
        shares = np.array([cfg.bolt_share, cfg.nut_share, cfg.washer_share], float)
        self.p = shares / shares.sum()
        self.t_start = sim_time_s()
        self.due = 0  # parts that have arrived so far, dropped or not
        self.dropped = 0
        self.skipped = 0  # due with the table full or no free spot
        self.binned: dict[str, int] = {}
        self.cleared = 0
        self._next_id = max((p.id for p in world.parts), default=0) + 1
        self._landed: dict[int, float] = {p.id: self.t_start for p in world.parts}
        self._last_seen = self._positions()

    def _positions(self) -> dict[int, tuple[float, float]]:
        return {p.id: (p.spec.x_mm, p.spec.y_mm) for p in self.world.on_table()}

    def tick(self) -> None:
        """Before a frame: tidy the world, then drop every part that has arrived since the last tick."""
        now = self.sim_time_s()
        here = self._positions()
        vacated = [xy for pid, xy in self._last_seen.items() if pid not in here]
        self._tidy(now)
        arrived = int(self.cfg.parts_per_minute * (now - self.t_start) / 60.0)
        for _ in range(arrived - self.due):
            self._drop(now, vacated)
        self.due = max(self.due, arrived)
        self._last_seen = self._positions()

    def _tidy(self, now: float) -> None:
        keep = []
        for p in self.world.parts:
            if p.where.startswith("bin:"):
                self.binned[p.spec.kind] = self.binned.get(p.spec.kind, 0) + 1
            elif p.where == "floor" or (
                p.where == "table"
                and self.cfg.clear_after_s
                and now - self._landed.get(p.id, now) > self.cfg.clear_after_s
            ):
                self.cleared += 1
            else:
                keep.append(p)
                continue
            self._landed.pop(p.id, None)
        if len(keep) != len(self.world.parts):
            self.world.parts = keep
            self.world.version += 1

    def _drop(self, now: float, vacated: list[tuple[float, float]]) -> None:
        on_table = [p.spec for p in self.world.on_table()]
        if len(on_table) >= self.cfg.max_on_table:
            self.skipped += 1
            return
        for _ in range(_TRIES):
            spec = self._random_part()
            if self._fits(spec, on_table, vacated):
                self.world.parts.append(SimPart(self._next_id, spec))
                self._landed[self._next_id] = now
                self._next_id += 1
                self.dropped += 1
                self.world.version += 1
                return
        self.skipped += 1
        log.info("feeder: no free spot for a part (%d on the table)", len(on_table))

    def _random_part(self) -> PartSpec:
        kind = str(self.rng.choice(["bolt", "nut", "washer"], p=self.p))
        x0, y0, x1, y1 = self.cfg.area_mm
        x, y = float(self.rng.uniform(x0, x1)), float(self.rng.uniform(y0, y1))
        angle = float(self.rng.uniform(0, 360))
        sizes = {"bolt": BOLTS_MM, "nut": NUTS_MM, "washer": WASHERS_MM}[kind]
        size = str(self.rng.choice(sorted(sizes)))
        length = float(self.rng.choice(_BOLT_LENGTHS_MM)) if kind == "bolt" else None
        return PartSpec(kind, size, x, y, angle, length)

    def _fits(self, spec: PartSpec, others: list[PartSpec | ExtrudedPart], vacated: list[tuple[float, float]]) -> bool:
        outline = spec.top_view_outline_mm()
        x0, y0, x1, y1 = self.cfg.area_mm
        if outline[:, 0].min() < x0 or outline[:, 0].max() > x1 or outline[:, 1].min() < y0 or outline[:, 1].max() > y1:
            return False
        reach = float(np.hypot(*(outline - (spec.x_mm, spec.y_mm)).T).max())
        if any(math.dist(outline_xy, xy) < _VACATED_CLEARANCE_MM for xy in vacated for outline_xy in outline):
            return False
        for q in others:  # the cheap bound first: most parts are far away
            if math.dist((q.x_mm, q.y_mm), (spec.x_mm, spec.y_mm)) > reach + 40.0 + MIN_GAP_MM:
                continue
            if outline_gap_mm(spec, q) < MIN_GAP_MM:
                return False
        return True

    def account(self) -> dict:
        """What the feeder did, for the log."""
        return {
            "dropped": self.dropped,
            "skipped": self.skipped,
            "binned": dict(self.binned),
            "cleared": self.cleared,
            "on_table": len(self.world.on_table()),
        }


class FedCamera(Camera):
    """The simulated camera with the feeder ticked before each frame."""

    def __init__(self, camera: Camera, feeder: Feeder):
        self.inner, self.feeder = camera, feeder
        self.source, self.width_px, self.height_px = camera.source, camera.width_px, camera.height_px

    def connect(self) -> None:
        self.inner.connect()

    def disconnect(self) -> None:
        self.inner.disconnect()

    @property
    def is_connected(self) -> bool:
        return self.inner.is_connected

    def _grab(self):
        self.feeder.tick()
        return self.inner._grab()


class SimClock:
    """Simulated seconds since start: the wall clock times the speed factor."""

    def __init__(self, speed_factor: float):
        self.speed_factor, self._t0 = speed_factor, time.monotonic()

    def __call__(self) -> float:
        return (time.monotonic() - self._t0) * self.speed_factor

"""Parts followed across frames by position: a detection within a radius of a tracked part
is that part. The runner asks which track a detection is, which tracks are near a place,
and how many tracks ended in each status."""

from __future__ import annotations

import enum
import itertools
from dataclasses import dataclass

import numpy as np

from cell.vision.types import LocatedPart


class PartStatus(enum.Enum):
    """Where a tracked part stands; only PENDING parts are planned."""

    PENDING = "pending"
    PICKED = "picked"  # verified gone from the table
    FAILED = "failed"  # still there after run.max_retries retries
    UNREACHABLE = "unreachable"  # refused by the planner or the arm before any motion
    REHEARSED = "rehearsed"  # dry run over a real table: sent, not verified


@dataclass
class Track:
    """One part followed across frames."""

    id: int
    cls: str
    table_mm: tuple[float, float]
    status: PartStatus = PartStatus.PENDING
    attempts: int = 0


def distance_mm(a: tuple[float, float], b: tuple[float, float]) -> float:
    return float(np.hypot(a[0] - b[0], a[1] - b[1]))


class Tracker:
    """Every part seen this run, matched to detections by position within radius_mm."""

    def __init__(self, radius_mm: float):
        self.radius_mm = radius_mm
        self.tracks: list[Track] = []
        self._ids = itertools.count(1)

    def track_for(self, part: LocatedPart) -> Track:
        """The tracked part this detection is (the nearest not yet picked), or a new track."""
        best, best_d = None, self.radius_mm
        for t in self.tracks:
            if t.status is PartStatus.PICKED:
                continue
            d = distance_mm(part.table_mm, t.table_mm)
            if d <= best_d:
                best, best_d = t, d
        if best is None:
            best = Track(next(self._ids), part.cls, part.table_mm)
            self.tracks.append(best)
        best.table_mm = (part.table_mm[0], part.table_mm[1])
        return best

    def near(self, track: Track, objects: list[LocatedPart]) -> list[LocatedPart]:
        """The detections that are where the track was."""
        return [o for o in objects if distance_mm(o.table_mm, track.table_mm) <= self.radius_mm]

    def keep_only(self, tracks: list[Track]) -> None:
        """Forget every track but these (continuous mode: the parts still on the table)."""
        self.tracks = [t for t in self.tracks if any(t is k for k in tracks)]

    def count(self, status: PartStatus) -> int:
        return sum(t.status is status for t in self.tracks)

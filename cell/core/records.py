"""The records every consumer reads: the service's Snapshot and what it holds (counters, picks,
alarms, calibration), and the frames the screen shows. Immutable; made by the service, read by
OPC UA, the screen, history, telemetry and /metrics alike.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from cell.core.commands import (
    Command,
    VisionState,
)
from cell.core.eventbus import SubscriberStats
from cell.core.events import Event, JobStarted, PartFailed, PickVerified


@dataclass(frozen=True)
class RecipeInfo:
    """A recipe file as listed: its id, content hash and when it was written."""

    recipe_id: str
    path: Path
    sha256: str  # of the file's bytes: OPC 40100-1's recipe Hash
    modified_utc: datetime
    products: tuple[str, ...]
    error: str = ""  # why the file is not a valid recipe; empty when it is


@dataclass(frozen=True)
class Counters:
    """The shift's counters. `picked` counts each part class by name (cell.core.parts: the registry
    decides which classes there are and what each interface calls their counters)."""

    picked: tuple[tuple[str, int], ...] = ()  # (class name, parts picked), classes never picked left out
    misses: int = 0
    retries: int = 0
    failed: int = 0
    unreachable: int = 0
    unknown_left: int = 0

    def picked_of(self, cls: str) -> int:
        return dict(self.picked).get(cls, 0)

    @property
    def picked_total(self) -> int:
        return sum(n for _, n in self.picked)

    def as_json(self) -> dict[str, Any]:
        """The counters as JSON: `picked` a mapping of class name to count."""
        return {
            "picked": dict(self.picked),
            "picked_total": self.picked_total,
            "misses": self.misses,
            "retries": self.retries,
            "failed": self.failed,
            "unreachable": self.unreachable,
            "unknown_left": self.unknown_left,
        }


@dataclass(frozen=True)
class PickRecord:
    """One finished pick attempt, as the screen's table and OPC UA's LastPick* show it."""

    time_utc: datetime
    track_id: int  # the part's number within its job
    cls: str  # the part class's name (cell.core.parts)
    table_mm: tuple[float, float]
    robot_mm: tuple[float, float, float]
    angle_deg: float | None  # jaw angle for bolts, None for nuts
    outcome: str  # picked | missed | failed | rehearsed
    pick_id: str = ""  # unique across jobs and restarts (cell.core.events.pick_id)
    job_id: str = ""


@dataclass(frozen=True)
class Alarm:
    reason: str  # what failed and where
    hint: str  # what the operator can do about it
    time_utc: datetime
    alarm_id: str = ""
    severity: str = "fault"  # fault (needs Reset) | warning (shown until its cause is gone)
    source: str = "job"


@dataclass(frozen=True)
class CalibrationInfo:
    model: str
    cv_rms_mm: float
    cv_max_mm: float
    time_utc: datetime | None  # when it was made
    source_image: str  # which image it was made from (a name for display, never a path to open)
    calibration_id: str = ""  # content hash


@dataclass(frozen=True)
class Snapshot:
    """Everything a client shows, consistent at one instant."""

    vision_state: VisionState
    cell_state: str  # the runner's State name (CAPTURE, PICK, PAUSED ...); between jobs IDLE, STOPPED or FAULT
    paused: bool  # a job paused and at rest (nothing moves)
    waiting_for_parts: bool  # continuous mode with an empty table
    counters: Counters
    parts_per_min: float  # 0 when no job runs
    last_picks: tuple[PickRecord, ...]  # newest last, at most 20
    alarm: Alarm | None  # the fault alarm (needs Reset)
    calibration: CalibrationInfo | None
    heartbeat: int  # +1 a second while the service runs
    allowed: frozenset[Command]  # what the current state accepts (buttons enabled)
    pausing: bool = False  # a pause was asked for; the last motion is finishing (paused once at rest)
    job_id: str = ""
    job_mode: str = ""  # single | continuous while a job runs
    hold: str = ""  # a guard holding starts (e.g. a recalibration awaiting its answer)
    warnings: tuple[Alarm, ...] = ()  # warning alarms (no Reset needed)
    subscribers: tuple[SubscriberStats, ...] = ()  # every subscriber's delivered / dropped / failed
    recipe: str = ""  # the prepared recipe's id
    simulated: bool = False  # a dry run: the simulated cell, or a mock arm over a real table
    shift: str = ""  # the shift the counters count (e.g. 2026-12-01 early)
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class FrameView:
    """A located frame annotated for the screen (made off the control thread)."""

    seq: int  # +1 per captured frame
    capture_monotonic_s: float  # time.monotonic() at capture, for latency measurement
    image_bgr: np.ndarray  # the annotated frame (outlines, class, pick order, jaw direction)
    pick_order: tuple[int, ...] = ()  # the drawn order: part ids as PLAN chose them; empty if not planned


@dataclass(frozen=True)
class LiveFrame:
    """A raw camera frame taken while the cell is at rest, for the screen's live view."""

    image_bgr: np.ndarray
    captured_monotonic_s: float  # time.monotonic() at capture
    time_utc: datetime  # when it was taken


@dataclass(frozen=True)
class PartImage:
    """A camera frame of example parts for teaching a part type, and the calibration in use when it was taken
    (cell.calibration.store.Calibration: pixels to table mm, the camera's pose for the height correction)."""

    image_bgr: np.ndarray
    calibration: Any
    time_utc: datetime


class PickRecords:
    """PickRecords from the event stream: each verdict, and a part given up (its last attempt's place).

    Only the records of parts missed and not yet picked or given up are kept (small records, never
    the events: those carry frames, and a continuous job's parts never end)."""

    def __init__(self) -> None:
        self._missed: dict[tuple[str, int], PickRecord] = {}

    def of(self, event: Event) -> PickRecord | None:
        if isinstance(event, JobStarted):
            self._missed.clear()
        elif isinstance(event, PickVerified):
            record = pick_record(event, event.result)
            key = (event.job_id or "", event.track)
            if event.result == "missed":
                self._missed[key] = record  # it may yet be given up
            else:
                self._missed.pop(key, None)
            return record
        elif isinstance(event, PartFailed):
            last = self._missed.pop((event.job_id or "", event.track), None)
            if last is not None:
                return replace(last, outcome="failed")
        return None


def pick_record(e: PickVerified, outcome: str) -> PickRecord:
    return PickRecord(
        e.time_utc,
        e.track,
        e.cls,
        (float(e.table_mm[0]), float(e.table_mm[1])),
        (float(e.robot_mm[0]), float(e.robot_mm[1]), float(e.robot_mm[2])),
        e.jaw_angle_deg,
        outcome,
        e.pick_id,
        e.job_id or "",
    )

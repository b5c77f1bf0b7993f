"""The shift's counters, the last picks and the pick rate, kept from the event stream.

A subscriber of the bus (its own thread): it never runs on the control thread, and the
service reads it under its own lock. At start it is primed from the day's audit files, so a
restart loses no count.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from datetime import UTC, datetime
from typing import Any

from cell.events import Event, JobEnded, JobStarted, PartFailed, PickVerified
from cell.service.api import Counters, PickRecord
from cell.service.counters import ShiftCounts

PICKS_KEPT = 20
RATE_WINDOW = 20  # picks the parts-per-minute figure is taken over


def _utc_day(t: datetime) -> str:
    return t.astimezone(UTC).date().isoformat()


class PickRecords:
    """PickRecords from the event stream: each verdict, and a part given up (its last attempt's place)."""

    def __init__(self) -> None:
        self._last: dict[tuple[str, int], PickVerified] = {}

    def of(self, event: Event) -> PickRecord | None:
        if isinstance(event, JobStarted):
            self._last.clear()
        elif isinstance(event, PickVerified):
            self._last[(event.job_id or "", event.track)] = event
            return _record(event, event.result)
        elif isinstance(event, PartFailed):
            last = self._last.pop((event.job_id or "", event.track), None)
            if last is not None:
                return _record(last, "failed")
        return None


class Ledger:
    def __init__(self, history: Iterable[dict[str, Any]] = (), on_change: Callable[[str], None] = lambda what: None):
        self._lock = threading.Lock()
        self._counts = ShiftCounts.from_events(history)
        self._day = _utc_day(datetime.now(UTC))
        self._picks: deque[PickRecord] = deque(maxlen=PICKS_KEPT)
        self._pick_times: deque[float] = deque(maxlen=RATE_WINDOW)
        self._records = PickRecords()
        self._on_change = on_change

    # ---- the subscriber ------------------------------------------------------------------
    def handle(self, event: Event) -> None:
        changed = ""
        with self._lock:
            day = _utc_day(event.time_utc)
            if day != self._day:  # 00:00 UTC: the audit files roll to a new day, a new shift
                self._day, self._counts = day, ShiftCounts()
                changed = "counters"
            if event.audited and self._counts.apply({"kind": event.kind, **event.record()}):
                changed = "counters"
            record = self._records.of(event)
            if record is not None:
                self._picks.append(record)
                if record.outcome == "picked":
                    self._pick_times.append(time.monotonic())
                changed = "pick"
            if isinstance(event, JobStarted):
                self._pick_times.clear()
            elif isinstance(event, JobEnded):
                self._pick_times.clear()
                changed = changed or "counters"
        if changed:
            self._on_change(changed)

    # ---- the service's reads ---------------------------------------------------------------
    def counters(self) -> Counters:
        with self._lock:
            return self._counts.counters()

    def as_dict(self) -> dict[str, int]:
        return dict(self.counters().__dict__)

    def last_picks(self) -> tuple[PickRecord, ...]:
        with self._lock:
            return tuple(self._picks)

    def parts_per_min(self) -> float:
        with self._lock:
            times = self._pick_times
            if len(times) >= 2 and times[-1] > times[0]:
                return 60.0 * (len(times) - 1) / (times[-1] - times[0])
            return 0.0

    @property
    def shift(self) -> str:
        return self._day


def _record(e: PickVerified, outcome: str) -> PickRecord:
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

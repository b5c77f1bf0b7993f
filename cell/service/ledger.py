"""The shift's counters, the last picks and the pick rate, kept from the event stream.

A subscriber of the bus (its own thread): it never runs on the control thread, and the
service reads it under its own lock. Shifts are the plant's (`[shifts]`, cell.shifts): the
counters start again when the next shift starts. At start it is restored from the history
store (counters and last picks of the running shift), or, without a store, primed from the
audit files of the shift, so a restart loses no count.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from datetime import datetime
from typing import Any

from cell.core.events import Event, JobEnded, JobStarted
from cell.core.records import Counters, PickRecord, PickRecords
from cell.service.counters import ShiftCounts
from cell.shifts import Shift, ShiftCalendar

PICKS_KEPT = 20
RATE_WINDOW = 20  # picks the parts-per-minute figure is taken over


class Ledger:
    def __init__(
        self,
        history: Iterable[dict[str, Any]] = (),
        on_change: Callable[[str], None] = lambda what: None,
        calendar: ShiftCalendar | None = None,
    ):
        """`history`: audit events of the running shift to count first (the restart without a store)."""
        self._lock = threading.Lock()
        self.calendar = calendar or ShiftCalendar()
        self._shift: Shift = self.calendar.now()
        self._counts = ShiftCounts.from_events(e for e in history if self._in_shift(e))
        self._picks: deque[PickRecord] = deque(maxlen=PICKS_KEPT)
        self._pick_times: deque[float] = deque(maxlen=RATE_WINDOW)
        self._records = PickRecords()
        self._on_change = on_change

    def _in_shift(self, e: dict[str, Any]) -> bool:
        t = e.get("t_utc")
        if not t:
            return True
        try:
            return self._shift.contains(datetime.fromisoformat(t))
        except ValueError:
            return True

    def prime(self, history: Iterable[dict[str, Any]]) -> None:
        """Count the running shift's audit events (a restart without a history store)."""
        with self._lock:
            self._counts = ShiftCounts.from_events(e for e in history if self._in_shift(e))
        self._on_change("counters")

    def restore(self, counters: Counters, picks: Iterable[PickRecord]) -> None:
        """The running shift's counters and the last picks, read back from the history store."""
        with self._lock:
            self._counts = ShiftCounts.from_counters(counters)
            self._picks.clear()
            self._picks.extend(picks)
        self._on_change("counters")

    # ---- the subscriber ------------------------------------------------------------------
    def handle(self, event: Event) -> None:
        changed = ""
        with self._lock:
            if not self._shift.contains(event.time_utc) and event.time_utc >= self._shift.end_utc:
                self._shift, self._counts = self.calendar.at(event.time_utc), ShiftCounts()  # the next shift
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

    def as_dict(self) -> dict[str, Any]:
        return self.counters().as_json()

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
        """The id of the shift the counters count (e.g. 2026-12-01/early)."""
        return self._shift.id

    @property
    def current_shift(self) -> Shift:
        return self._shift

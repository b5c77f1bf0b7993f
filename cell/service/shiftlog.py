"""The service's audit log: the same JSON lines as a run's, in files that roll over at each UTC
day and past a size, so a shift of any length stays readable and no file grows without end.

It is the event stream's synchronous record (cell.core.eventbus): each event is on disk before
the emitter goes on. A roll happens only between two events, so every file holds whole
lines. Files are named `cell-YYYYMMDD-N.jsonl` with N counting up from 000 for as many
files as a day needs. A file that failed (a full disk) is never written again: the next
event opens the day's next file, and if that cannot be written either the event's write
raises AuditWriteFailed, so nothing moves without its record.
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cell.audit import AuditLog, AuditWriteFailed
from cell.core.events import Event

log = logging.getLogger(__name__)

_NAME = re.compile(r"^cell-(\d{8})-(\d{3,})\.jsonl$")


def _today() -> str:
    return datetime.now(UTC).strftime("%Y%m%d")


def shift_files(log_dir: Path, day: str) -> list[Path]:
    """The audit files of one UTC day (YYYYMMDD), oldest first (numbered 000, 001, ... 999, 1000 ...)."""
    found = [(int(m.group(2)), p) for p in Path(log_dir).glob(f"cell-{day}-*.jsonl") if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def _file_number(path: Path) -> int:
    """The count in an audit file's name (cell-YYYYMMDD-NNN.jsonl)."""
    m = _NAME.match(path.name)
    if m is None:
        raise ValueError(f"{path.name} is not an audit file's name")
    return int(m.group(2))


def iter_shift(log_dir: Path, day: str | None = None) -> Iterator[dict[str, Any]]:
    """Every complete event of the day's files, in order, one at a time (a day may hold gigabytes);
    a torn line (a writer killed mid-line) is skipped."""
    for path in shift_files(log_dir, day or _today()):
        with open(path, encoding="utf-8") as f:
            for line in f:
                try:
                    yield json.loads(line)
                except json.JSONDecodeError:
                    log.warning("%s: skipping a torn line: %.60s", path, line)


def iter_since(log_dir: Path, start_utc: datetime) -> Iterator[dict[str, Any]]:
    """Every complete event of the UTC days from `start_utc`'s to today's (a plant shift may span two)."""
    day = start_utc.astimezone(UTC).date()
    today = datetime.now(UTC).date()
    while day <= today:
        yield from iter_shift(log_dir, day.strftime("%Y%m%d"))
        day = day.fromordinal(day.toordinal() + 1)


def read_shift(log_dir: Path, day: str | None = None) -> list[dict[str, Any]]:
    return list(iter_shift(log_dir, day))


class ShiftLog:
    """The service's record over rolling files; thread-safe. `record(event)` is the bus's record."""

    def __init__(self, log_dir: Path, max_bytes: int, day: Callable[[], str] = _today, rehearsal: bool = False):
        self.log_dir, self.max_bytes, self._day = Path(log_dir), max_bytes, day
        self.rehearsal = rehearsal  # a dry run's: every line marked "rehearsal": true (cell.audit)
        self.state = "idle"
        self.best_effort = False  # set by the bus while a job makes safe: a failed write is not raised
        self._lock = threading.Lock()
        self._log: AuditLog | None = None
        self._open_day = ""
        self.on_roll: Callable[[], object] | None = None  # after a new file is opened (log retention)

    @property
    def path(self) -> Path | None:
        return None if self._log is None else self._log.path

    @property
    def failed(self) -> OSError | None:
        return None if self._log is None else self._log.failed

    def _current(self, best_effort: bool = False) -> AuditLog:
        day = self._day()
        current = self._log
        if current is not None and current.failed is not None and (self.best_effort or best_effort):
            return current  # making safe: drop the line rather than create a file per event on a full disk
        if (
            current is not None
            and day == self._open_day
            and current.failed is None
            and current.path.stat().st_size < self.max_bytes
        ):
            return current
        if current is not None:
            current.close()
            self._log = None
        files = shift_files(self.log_dir, day)  # audit logs are created, never reopened: a restart takes the next
        n = _file_number(files[-1]) + 1 if files else 0
        try:
            self._log = AuditLog(self.log_dir / f"cell-{day}-{n:03d}.jsonl", rehearsal=self.rehearsal)
        except OSError as e:
            raise AuditWriteFailed(
                f"audit log in {self.log_dir}: cannot create cell-{day}-{n:03d}.jsonl: {e.strerror or e}",
                hint="free space on its filesystem or set run.log_dir elsewhere",
            ) from None
        self._open_day = day
        log.info("audit log: %s", self._log.path)
        if self.on_roll is not None:
            try:
                self.on_roll()
            except Exception as e:  # the record comes first
                log.warning("after the audit log's roll: %s", e)
        return self._log

    def record(self, event: Event, best_effort: bool = False) -> dict[str, Any] | None:
        """Write one event (raises AuditWriteFailed when it cannot, unless best effort: the log's
        switch or this call's; then a broken file is not replaced for it: no file per event)."""
        if not event.audited:
            return None
        effort = self.best_effort or best_effort
        with self._lock:
            try:
                audit = self._current(effort)
            except AuditWriteFailed:
                if effort:
                    return None
                raise
            audit.state = self.state
            audit.best_effort = self.best_effort
            line = audit.record(event, best_effort=effort)
            self.state = audit.state
            return line

    def ensure_writable(self) -> None:
        """Before a job: a broken file is left for the day's next one now, not at the first motion."""
        with self._lock:
            self._current()

    def close(self) -> None:
        with self._lock:
            if self._log is not None:
                self._log.close()
                self._log = None

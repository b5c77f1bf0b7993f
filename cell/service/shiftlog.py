"""The service's audit log: the same JSON lines as a run's, in files that roll over at each UTC
day and past a size, so a shift of any length stays readable and no file grows without end.

A roll happens only between two events, so every file holds whole lines. The files of a
day are that day's shift: the service reads them back at start to carry its counters over
a restart. Listeners hear every event as it is written (the service's view of the runner).
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path

from cell.audit import AuditLog

log = logging.getLogger(__name__)

_NAME = re.compile(r"^cell-(\d{8})-(\d{3})\.jsonl$")


def _today() -> str:
    return datetime.now(UTC).strftime("%Y%m%d")


def shift_files(log_dir: Path, day: str) -> list[Path]:
    """The audit files of one UTC day (YYYYMMDD), oldest first."""
    found = [(m.group(2), p) for p in Path(log_dir).glob(f"cell-{day}-*.jsonl") if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def iter_shift(log_dir: Path, day: str | None = None) -> Iterator[dict]:
    """Every complete event of the day's shift, in order, one at a time (a day may hold gigabytes);
    a torn line (a writer killed mid-line) is skipped."""
    for path in shift_files(log_dir, day or _today()):
        with open(path, encoding="utf-8") as f:
            for line in f:
                try:
                    yield json.loads(line)
                except json.JSONDecodeError:
                    log.warning("%s: skipping a torn line: %.60s", path, line)


def read_shift(log_dir: Path, day: str | None = None) -> list[dict]:
    return list(iter_shift(log_dir, day))


class ShiftLog:
    """AuditLog's interface (event, state, close) over rolling files; thread-safe."""

    def __init__(self, log_dir: Path, max_bytes: int, day: Callable[[], str] = _today):
        self.log_dir, self.max_bytes, self._day = Path(log_dir), max_bytes, day
        self.state = "idle"
        self.listeners: list[Callable[[dict], None]] = []
        self._lock = threading.Lock()
        self._log: AuditLog | None = None
        self._open_day = ""

    @property
    def path(self) -> Path | None:
        return None if self._log is None else self._log.path

    def _current(self) -> AuditLog:
        day = self._day()
        if self._log is not None and day == self._open_day and self._log.path.stat().st_size < self.max_bytes:
            return self._log
        if self._log is not None:
            self._log.close()
        files = shift_files(self.log_dir, day)  # audit logs are created, never reopened: a restart takes the next
        n = int(_NAME.match(files[-1].name).group(2)) + 1 if files else 0
        self._log = AuditLog(self.log_dir / f"cell-{day}-{n:03d}.jsonl")
        self._open_day = day
        log.info("audit log: %s", self._log.path)
        return self._log

    def event(self, kind: str, **fields) -> dict:
        with self._lock:
            audit = self._current()
            audit.state = self.state
            record = audit.event(kind, **fields)
        for listener in list(self.listeners):
            listener(record)
        return record

    def close(self) -> None:
        with self._lock:
            if self._log is not None:
                self._log.close()
                self._log = None

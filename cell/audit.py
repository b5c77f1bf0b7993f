"""The run's audit log: one JSON object per line, flushed as it is written.

A run killed at any moment leaves a valid file (at worst a last line cut short, which
`read_events` drops) whose last complete line says the state it was in. Each event has
`seq`, `t_utc`, `t_run_s`, `kind` and `state`; the rest depends on the kind. Every line of a
rehearsal's log (`--dry-run`, `make demo`) also carries `"rehearsal": true`: what reads audit
files back to count a shift (the counters after a restart, the history store's read-back)
counts a rehearsal's lines only for a rehearsal, and production's only for production.

The file is created exclusively (never another run's). A write that fails (a full disk)
raises AuditWriteFailed, so the run faults and stops safely, and so does every later one
(nothing runs without its record); once `best_effort` is set (while making safe and ending
the run) events that cannot be written are dropped instead: the record never stands in
the way of the safe stop.
"""

from __future__ import annotations

import json
import logging
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cell.core.events import Event, StateChanged, to_json
from cell.errors import CellError
from cell.recordfile import RecordFile

log = logging.getLogger(__name__)


class AuditWriteFailed(CellError):
    """The audit log cannot be written: the run cannot keep its record, so it stops (a fault)."""

    exit_code = 3


class AuditLog:
    """Append-only JSON-lines writer of the cell's events (cell.core.events); the runner's state is
    stamped on every line (`state`: the state the event happened in).

    It is the event stream's synchronous record (cell.core.eventbus): `record(event)` writes one
    line before the emitter goes on, so what the arm is about to do is on disk first. It can
    stand in for a whole bus (`emit`) where nothing else listens (tests, benches).
    """

    def __init__(self, path: str | Path, rehearsal: bool = False):
        self.path = Path(path)
        self.rehearsal = rehearsal  # every line marked "rehearsal": true (a dry run's)
        self._file = RecordFile(self.path, exclusive=True, what="audit log")
        self._seq = 0
        self._t0 = time.monotonic()
        self.state = "idle"
        self.best_effort = False  # set while making safe and ending: a failed write is never raised

    @property
    def failed(self) -> OSError | None:
        """The write error that broke the log, if any (later events were dropped)."""
        return self._file.failed

    def record(self, event: Event, best_effort: bool = False) -> dict[str, Any] | None:
        """Write one typed event; a StateChanged moves the stamped state on after its own line.
        `best_effort`: this event is dropped, not raised, if it cannot be written."""
        if not event.audited:
            return None
        fields = event.record()
        if event.job_id is not None:
            fields = {"job": event.job_id, **fields}
        if best_effort and not self.best_effort:  # this one event only
            self.best_effort = True
            try:
                line = self.event(event.kind, **fields)
            finally:
                self.best_effort = False
        else:
            line = self.event(event.kind, **fields)
        if isinstance(event, StateChanged):
            self.state = event.target
        return line

    emit = record  # an AuditLog is a bus with one record and no subscribers

    def event(self, kind: str, **fields: Any) -> dict[str, Any]:
        self._seq += 1
        record = {
            "seq": self._seq,
            "t_utc": datetime.now(UTC).isoformat(timespec="milliseconds"),
            "t_run_s": round(time.monotonic() - self._t0, 4),
            "kind": kind,
            "state": self.state,
            **({"rehearsal": True} if self.rehearsal else {}),
            **to_json(fields),
        }
        if not self._file.write_line(json.dumps(record, separators=(",", ":"), allow_nan=False)):
            if not self.best_effort:  # every write, not only the first: nothing runs without its record
                failed = self.failed
                why = "the log is closed" if failed is None else (failed.strerror or str(failed))
                raise AuditWriteFailed(
                    f"audit log {self.path}: cannot write event {self._seq} ({kind}): {why}",
                    hint="free space on its filesystem or set run.log_dir elsewhere",
                )
        return record

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> AuditLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def is_rehearsal(line: dict[str, Any]) -> bool:
    """An audit line written by a rehearsal (a dry run, the demo): never counted as production's."""
    return line.get("rehearsal") is True


def read_events(path: str | Path) -> list[dict[str, Any]]:
    """Every complete event of a log; a torn last line (a killed writer) is skipped."""
    events = []
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        try:
            events.append(json.loads(line))
        except json.JSONDecodeError:
            log.warning("%s: skipping a torn line: %.60s", path, line)
    return events

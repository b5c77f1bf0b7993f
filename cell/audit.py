"""The run's audit log: one JSON object per line, flushed as it is written.

A run killed at any moment leaves a valid file (at worst a last line cut short, which
`read_events` drops) whose last complete line says the state it was in. Each event has
`seq`, `t_utc`, `t_run_s`, `kind` and `state`; the rest depends on the kind.

The file is created exclusively (never another run's). A write that fails (a full disk)
raises AuditWriteFailed once, so the run faults and stops safely; from then on, and
always once `best_effort` is set (while making safe and ending the run), events that
cannot be written are dropped: the record never stands in the way of the safe stop.
"""

from __future__ import annotations

import json
import logging
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from cell.errors import CellError
from cell.recordfile import RecordFile

log = logging.getLogger(__name__)


def _plain(value):
    """JSON-safe copy: numpy scalars and arrays, tuples, enums, paths."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return getattr(value, "value", None) or str(value)


class AuditWriteFailed(CellError):
    """The audit log cannot be written: the run cannot keep its record, so it stops (a fault)."""

    exit_code = 3


class AuditLog:
    """Append-only JSON-lines writer; `state` is stamped on every event by the runner."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._file = RecordFile(self.path, exclusive=True, what="audit log")
        self._seq = 0
        self._t0 = time.monotonic()
        self.state = "idle"
        self.best_effort = False  # set while making safe and ending: a failed write is never raised

    @property
    def failed(self) -> OSError | None:
        """The write error that broke the log, if any (later events were dropped)."""
        return self._file.failed

    def event(self, kind: str, **fields) -> dict:
        self._seq += 1
        record = {
            "seq": self._seq,
            "t_utc": datetime.now(UTC).isoformat(timespec="milliseconds"),
            "t_run_s": round(time.monotonic() - self._t0, 4),
            "kind": kind,
            "state": self.state,
            **_plain(fields),
        }
        broken_before = self.failed is not None
        if not self._file.write_line(json.dumps(record, separators=(",", ":"), allow_nan=False)):
            if not (broken_before or self.best_effort):
                raise AuditWriteFailed(
                    f"audit log {self.path}: cannot write event {self._seq} ({kind}): "
                    f"{self.failed.strerror or self.failed}",
                    hint="free space on its filesystem or set run.log_dir elsewhere",
                )
        return record

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> AuditLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_events(path: str | Path) -> list[dict]:
    """Every complete event of a log; a torn last line (a killed writer) is skipped."""
    events = []
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        try:
            events.append(json.loads(line))
        except json.JSONDecodeError:
            log.warning("%s: skipping a torn line: %.60s", path, line)
    return events

"""The operator's log: everything a command does on the line, in a file to read later.

Written through a RecordFile: a run's log is created exclusively (its own file); the
shared `logs/cell.log` of the other commands is appended to. A failed write (a full
disk) is reported once on stderr and never raised into the code that logged.
"""

from __future__ import annotations

import logging
from pathlib import Path

from cell.logratelimit import LogRateLimiter
from cell.recordfile import RecordFile

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class RecordHandler(logging.Handler):
    """A logging handler over a RecordFile: one line per record, best effort; warnings and errors
    of one kind past 10 a minute are counted, not written (cell.logratelimit)."""

    def __init__(self, path: Path, exclusive: bool):
        super().__init__(logging.INFO)
        self.record_file = RecordFile(path, exclusive=exclusive, what="operator log")
        self.path = self.record_file.path
        self.limiter = LogRateLimiter()

    def emit(self, record: logging.LogRecord) -> None:
        wanted, dropped = self.limiter.check(record)
        if not wanted:
            return
        if dropped:
            note = logging.makeLogRecord(
                {"name": record.name, "levelno": record.levelno, "levelname": record.levelname}
                | {"msg": self.limiter.summary(record, dropped)}
            )
            self.record_file.write_line(self.format(note))
        try:
            text = self.format(record)
        except Exception:  # a bad format string in a log call must not break the caller
            self.handleError(record)
            return
        self.record_file.write_line(text)

    def close(self) -> None:
        self.record_file.close()
        super().close()


def log_to_file(path: str | Path, exclusive: bool = False) -> Path:
    """INFO and above from every module into `path` (created with its folder); with
    `exclusive`, the file must not exist yet (a run's own log)."""
    path = Path(path)
    root = logging.getLogger()
    for h in root.handlers:
        if isinstance(h, RecordHandler) and h.path.resolve() == path.resolve():
            return path
    handler = RecordHandler(path, exclusive)
    handler.setFormatter(logging.Formatter(FORMAT))
    root.addHandler(handler)
    if root.level > logging.INFO or root.level == logging.NOTSET:
        root.setLevel(logging.INFO)
    return path


def stop_logging_to(path: str | Path) -> None:
    """Detach and close the handler of `path` (a run's log, once the run has ended)."""
    root = logging.getLogger()
    for h in list(root.handlers):
        if isinstance(h, RecordHandler) and h.path == Path(path):
            root.removeHandler(h)
            h.close()


def quiet_terminal(level: int) -> None:
    """Raise the terminal's log handlers to `level`: the operator's file keeps every line,
    the terminal only what a command does not already say in its own one-line message."""
    for h in logging.getLogger().handlers:
        if type(h) is logging.StreamHandler:
            h.setLevel(level)

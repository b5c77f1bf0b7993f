"""How long the cell's logs are kept: `[logs] keep_days` and `max_mb` over `run.log_dir`.

The folder holds the service's audit files (`cell-YYYYMMDD-NNN.jsonl`, rolled each UTC day and past
`service.audit_max_bytes`), its operator log (`serve-YYYYMMDD.log`, one per start day), each run's
pair (`run-<UTC time>-<pid>[-n].jsonl` and `.log`) and the calibration commands' `cell.log`. Only
files of those names are counted and removed; anything else in the folder is left alone.

The pruner removes the oldest (by last write) first: every file last written more than `keep_days`
ago, then more until the rest are under `max_mb` together. It never removes a file being written (this
process's open logs, and any file written in the last hour: another command's), nor an audit file of
the running shift: those are what a restart reads back to prime the shift's counters and what crash
recovery reads back after the history store's mark (cell.service.shiftlog.iter_since,
cell.history.store). The service prunes at start (after that reading back) and at each roll of its
audit file.
"""

from __future__ import annotations

import logging
import os
import re
import stat
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

from pydantic import Field

from drivers.config import Strict

log = logging.getLogger(__name__)

MIB = 2**20
DAY_S = 86400.0
RECENT_S = 3600.0  # written this recently: maybe another command's open file, never removed

LOG_NAME = re.compile(
    r"^(?:cell-(?P<day>\d{8})-\d{3,}\.jsonl"
    r"|serve-\d{8}\.log"
    r"|run-\d{8}-\d{6}-\d+(?:-\d+)?\.(?:jsonl|log)"
    r"|cell\.log)$"
)


class LogsConfig(Strict):
    """How long the cell's logs in run.log_dir are kept (audit files, operator logs, each run's pair):
    `serve` removes the oldest first at start and at each roll of its audit file, never a file being
    written nor an audit file of the running shift."""

    keep_days: int = Field(
        365,
        ge=0,
        le=36500,
        description="log files last written longer ago than this are removed; 0: kept whatever their age",
    )
    max_mb: int = Field(
        2048,
        ge=0,
        description="the cell's log files together stay under this, the oldest removed first; 0: no limit",
    )


@dataclass(frozen=True)
class Removed:
    path: Path
    size_bytes: int
    reason: str  # "age" or "size"


@dataclass(frozen=True)
class _Entry:
    path: Path
    size_bytes: int
    mtime_s: float


def shift_days(start_utc: datetime, now: datetime) -> set[str]:
    """The UTC days (YYYYMMDD) from the running shift's start to now: the audit files a restart reads."""
    day = start_utc.astimezone(UTC).date()
    today = now.astimezone(UTC).date()
    days = set()
    while day <= today:
        days.add(day.strftime("%Y%m%d"))
        day += timedelta(days=1)
    return days


def log_files(folder: Path) -> list[_Entry]:
    """The cell's log files in `folder` (regular files of its names only), oldest first."""
    found = []
    try:
        with os.scandir(folder) as it:
            for e in it:
                if not LOG_NAME.match(e.name):
                    continue
                try:
                    st = e.stat(follow_symlinks=False)
                except FileNotFoundError:
                    continue
                if stat.S_ISREG(st.st_mode):
                    found.append(_Entry(Path(e.path), st.st_size, st.st_mtime))
    except FileNotFoundError:
        return []
    return sorted(found, key=lambda f: (f.mtime_s, f.path.name))


def _open_log_paths() -> set[Path]:
    """The files this process's operator-log handlers write (cell.oplog)."""
    from cell.oplog import RecordHandler

    return {h.path for h in logging.getLogger().handlers if isinstance(h, RecordHandler)}


class LogPruner:
    """Keeps `folder` within `config`; `prune()` is safe to call from any thread (one at a time;
    a call while another runs returns at once) and never raises an OSError into its caller."""

    def __init__(
        self,
        config: LogsConfig,
        folder: Path,
        *,
        live: Callable[[], Iterable[Path | None]] = lambda: (),
        shift_start: Callable[[], datetime] | None = None,
        clock: Callable[[], float] = time.time,
    ):
        self.config, self.folder = config, Path(folder)
        self.live, self.shift_start, self.clock = live, shift_start, clock
        self._lock = threading.Lock()

    def protected(self, now_s: float) -> tuple[set[Path], set[str]]:
        """(files being written, days whose audit files belong to the running shift)."""
        live = {Path(p).resolve() for p in (*self.live(), *_open_log_paths()) if p is not None}
        now = datetime.fromtimestamp(now_s, UTC)
        days = shift_days(self.shift_start(), now) if self.shift_start is not None else {now.strftime("%Y%m%d")}
        return live, days

    def prune(self) -> list[Removed]:
        if not self._lock.acquire(blocking=False):
            return []
        try:
            return self._prune()
        except Exception as e:  # retention must never stop the cell or its record
            log.warning("log retention in %s: not applied this time: %s", self.folder, e)
            return []
        finally:
            self._lock.release()

    def _prune(self) -> list[Removed]:
        keep_days, max_mb = self.config.keep_days, self.config.max_mb
        if not keep_days and not max_mb:
            return []
        now_s = self.clock()
        files = log_files(self.folder)
        live, days = self.protected(now_s)
        total = sum(f.size_bytes for f in files)
        limit = max_mb * MIB
        removed: list[Removed] = []
        for f in files:
            too_old = bool(keep_days) and f.mtime_s < now_s - keep_days * DAY_S
            too_big = bool(max_mb) and total > limit
            if not (too_old or too_big):
                break  # files are oldest first: every later one is younger, and the total only fell
            m = LOG_NAME.match(f.path.name)
            if f.path.resolve() in live or f.mtime_s > now_s - RECENT_S or (m is not None and m.group("day") in days):
                continue
            try:
                f.path.unlink()
            except FileNotFoundError:
                pass
            except OSError as e:
                log.warning("log retention: cannot remove %s: %s", f.path, e.strerror or e)
                continue
            total -= f.size_bytes
            removed.append(Removed(f.path, f.size_bytes, "age" if too_old else "size"))
        if removed:
            for reason, key in (("age", f"logs.keep_days = {keep_days}"), ("size", f"logs.max_mb = {max_mb}")):
                mine = [r for r in removed if r.reason == reason]
                if mine:
                    log.info(
                        "log retention (%s): removed %d files, %.1f MiB, from %s: %s",
                        key,
                        len(mine),
                        sum(r.size_bytes for r in mine) / MIB,
                        self.folder,
                        ", ".join(r.path.name for r in mine),
                    )
        if max_mb and total > limit:
            log.warning(
                "log retention: %s holds %.1f MiB of logs, over logs.max_mb = %d: the rest are being written "
                "or are the running shift's audit files",
                self.folder,
                total / MIB,
                max_mb,
            )
        return removed

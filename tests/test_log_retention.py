"""[logs] keep_days and max_mb over run.log_dir: the oldest removed first, never a file being written,
never an audit file of the running shift, only the cell's own log files; a bad value names its key."""

from __future__ import annotations

import logging
import os
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from cell.config import load_config
from cell.core.events import PartFailed, ServiceStarted
from cell.errors import ConfigError
from cell.logretention import MIB, LogPruner, LogsConfig
from cell.oplog import log_to_file, stop_logging_to
from cell.service.shiftlog import ShiftLog
from tests.serve_process import ServeProcess

DAY_S = 86400.0


def make(folder: Path, name: str, age_days: float, size_bytes: int = 100) -> Path:
    path = folder / name
    path.write_bytes(b"x" * size_bytes)
    t = time.time() - age_days * DAY_S
    os.utime(path, (t, t))
    return path


def names(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir()}


def test_files_older_than_keep_days_are_removed_and_only_the_cells_own(tmp_path: Path) -> None:
    make(tmp_path, "cell-20241101-000.jsonl", 400)
    make(tmp_path, "cell-20241101-001.jsonl", 399)
    make(tmp_path, "serve-20241101.log", 401)
    make(tmp_path, "run-20241101-101010-4242.jsonl", 367)
    make(tmp_path, "run-20241101-101010-4242-2.log", 366)
    make(tmp_path, "cell.log", 500)
    make(tmp_path, "cell-20251201-000.jsonl", 364)  # within a year: kept
    make(tmp_path, "run-20251201-101010-4242.log", 2)
    make(tmp_path, "notes.txt", 900)  # not the cell's: never touched
    make(tmp_path, "cell-backup.jsonl", 900)
    removed = LogPruner(LogsConfig(keep_days=365, max_mb=0), tmp_path).prune()
    assert names(tmp_path) == {
        "cell-20251201-000.jsonl",
        "run-20251201-101010-4242.log",
        "notes.txt",
        "cell-backup.jsonl",
    }
    assert [r.path.name for r in removed] == [  # oldest first
        "cell.log",
        "serve-20241101.log",
        "cell-20241101-000.jsonl",
        "cell-20241101-001.jsonl",
        "run-20241101-101010-4242.jsonl",
        "run-20241101-101010-4242-2.log",
    ]
    assert {r.reason for r in removed} == {"age"}


def test_past_max_mb_the_oldest_go_first_until_the_rest_fit(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    for i, day in enumerate(("01", "02", "03", "04", "05")):
        make(tmp_path, f"cell-202611{day}-000.jsonl", 30 - i, MIB)
    caplog.set_level(logging.INFO, logger="cell.logretention")
    removed = LogPruner(LogsConfig(keep_days=0, max_mb=3), tmp_path).prune()
    assert [r.path.name for r in removed] == ["cell-20261101-000.jsonl", "cell-20261102-000.jsonl"]
    assert {r.reason for r in removed} == {"size"}
    assert names(tmp_path) == {f"cell-202611{d}-000.jsonl" for d in ("03", "04", "05")}
    assert "logs.max_mb = 3" in caplog.text and "cell-20261101-000.jsonl" in caplog.text
    assert LogPruner(LogsConfig(keep_days=0, max_mb=3), tmp_path).prune() == []  # within the limit: nothing


def test_zero_is_no_limit(tmp_path: Path) -> None:
    make(tmp_path, "cell-20001101-000.jsonl", 9000, MIB)
    assert LogPruner(LogsConfig(keep_days=0, max_mb=0), tmp_path).prune() == []
    assert names(tmp_path) == {"cell-20001101-000.jsonl"}


def test_the_files_being_written_survive(tmp_path: Path) -> None:
    """The audit file the service writes and the operator log this process writes, however old
    their last write and however far over the limit."""
    record = ShiftLog(tmp_path, max_bytes=10**6, day=lambda: "20200101")  # not the running shift's day
    record.record(PartFailed(track=1, cls="nut", attempts=3))
    operator_log = log_to_file(tmp_path / "serve-20200101.log")
    try:
        logging.getLogger("test").info("a line")
        make(tmp_path, "cell-20191231-000.jsonl", 800, MIB)
        assert record.path is not None
        for live in (record.path, operator_log):
            t = time.time() - 700 * DAY_S
            os.utime(live, (t, t))
        pruner = LogPruner(LogsConfig(keep_days=1, max_mb=1), tmp_path, live=lambda: (record.path,))
        removed = pruner.prune()
        assert [r.path.name for r in removed] == ["cell-20191231-000.jsonl"]
        assert names(tmp_path) == {"cell-20200101-000.jsonl", "serve-20200101.log"}
        record.record(PartFailed(track=2, cls="nut", attempts=3))  # still the same file, still written
        assert record.path.name == "cell-20200101-000.jsonl"
    finally:
        stop_logging_to(operator_log)
        record.close()
    assert len((tmp_path / "cell-20200101-000.jsonl").read_text().splitlines()) == 2


def test_the_running_shifts_audit_files_survive(tmp_path: Path) -> None:
    """A restart primes the shift's counters from them and crash recovery reads them back: a night
    shift that began yesterday keeps yesterday's and today's files, whatever the limits say."""
    now = datetime.now(UTC)
    start = (now - timedelta(days=1)).replace(hour=22, minute=0, second=0, microsecond=0)
    today, yesterday, before = (f"{(now - timedelta(days=d)):%Y%m%d}" for d in (0, 1, 2))
    kept = [make(tmp_path, f"cell-{d}-00{i}.jsonl", 10, MIB) for d in (yesterday, today) for i in (0, 1)]
    make(tmp_path, f"cell-{before}-000.jsonl", 11, MIB)
    make(tmp_path, f"run-{before}-101010-7.log", 12, MIB)
    pruner = LogPruner(LogsConfig(keep_days=1, max_mb=1), tmp_path, shift_start=lambda: start)
    removed = pruner.prune()
    assert sorted(r.path.name for r in removed) == sorted([f"cell-{before}-000.jsonl", f"run-{before}-101010-7.log"])
    assert names(tmp_path) == {p.name for p in kept}


def test_a_file_written_in_the_last_hour_survives(tmp_path: Path) -> None:
    """Another command (a `run` beside the service) may have it open."""
    make(tmp_path, "run-20200101-101010-99.log", 0, 2 * MIB)
    assert LogPruner(LogsConfig(keep_days=1, max_mb=1), tmp_path).prune() == []
    assert names(tmp_path) == {"run-20200101-101010-99.log"}


def test_the_audit_logs_roll_prunes(tmp_path: Path) -> None:
    """The service prunes at each roll of its audit file (each UTC day, past audit_max_bytes)."""
    day = {"d": "20200101"}
    record = ShiftLog(tmp_path, max_bytes=10**6, day=lambda: day["d"])
    make(tmp_path, "cell-20190101-000.jsonl", 800)
    record.on_roll = LogPruner(LogsConfig(keep_days=365, max_mb=0), tmp_path, live=lambda: (record.path,)).prune
    record.record(ServiceStarted(counters={}, calibration="a", capture_interval_s=1.0))
    assert names(tmp_path) == {"cell-20200101-000.jsonl"}
    make(tmp_path, "cell-20190102-000.jsonl", 800)
    record.record(ServiceStarted(counters={}, calibration="b", capture_interval_s=1.0))  # no roll: kept
    assert "cell-20190102-000.jsonl" in names(tmp_path)
    day["d"] = "20200102"
    record.record(ServiceStarted(counters={}, calibration="c", capture_interval_s=1.0))
    record.close()
    assert names(tmp_path) == {"cell-20200101-000.jsonl", "cell-20200102-000.jsonl"}


@pytest.mark.parametrize(
    ("toml", "key"),
    [
        ("[logs]\nkeep_days = -1\n", "logs.keep_days"),
        ("[logs]\nmax_mb = 'lots'\n", "logs.max_mb"),
        ("[logs]\nmax_mb = -5\n", "logs.max_mb"),
        ("[logs]\nmax_gb = 2\n", "logs.max_gb"),
    ],
)
def test_a_bad_value_is_a_config_error_naming_the_key(tmp_path: Path, toml: str, key: str) -> None:
    path = tmp_path / "cell.toml"
    path.write_text(toml)
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(path)


def test_serve_prunes_at_start(tmp_path: Path) -> None:
    """`run-cell serve` as shipped: a year-old run log is gone by its ready line, the rest stays."""
    logs = tmp_path / "logs"
    logs.mkdir()
    make(logs, "run-20201101-101010-4242.log", 400)
    make(logs, "notes.txt", 400)
    config = tmp_path / "cell.toml"
    config.write_text("[logs]\nkeep_days = 30\n")
    serve = ServeProcess(tmp_path, "--config", str(config), "--log-dir", str(logs))
    try:
        assert "run-20201101-101010-4242.log" not in names(logs)
        assert "notes.txt" in names(logs)
    finally:
        assert serve.stop() == 0
    operator_log = next(logs.glob("serve-*.log")).read_text()
    assert "log retention (logs.keep_days = 30): removed 1 files" in operator_log

"""The history store in-process: shifts, rows from events (idempotent, transactional), images and
their retention, the audit read back after a crash, a damaged file, a failed write, the query
API, `run-cell history` and `run-cell report`."""

from __future__ import annotations

import csv
import io
import json
import sqlite3
from datetime import UTC, date, datetime, timedelta
from pathlib import Path

import pytest

from cell.cli import main
from cell.errors import ConfigError
from cell.history.db import HistoryCorrupt, HistoryError, open_sqlite
from cell.history.query import PickFilter, open_reader
from cell.history.report import build_report
from cell.history.schema import VERSION
from cell.history.store import HistoryStore
from cell.service.shiftlog import ShiftLog
from cell.shifts import ShiftCalendar, ShiftsConfig
from tests.history_helpers import JOB, T0, frame, history_config, shift_events, verify

pytestmark = pytest.mark.timeout(60)


class Hooks:
    def __init__(self):
        self.faults, self.warnings, self.cleared = [], {}, []

    def fault(self, reason, hint, source):
        self.faults.append((reason, hint, source))

    def raise_warning(self, key, reason, hint, source):
        self.warnings[key] = reason

    def clear_warning(self, key):
        self.cleared.append(key)
        self.warnings.pop(key, None)


def fill(cfg, events=None, hooks=None) -> HistoryStore:
    store = HistoryStore(cfg.history, cfg.run.log_dir, hooks or Hooks())
    for e in events if events is not None else shift_events():
        store.handle(e)
    assert store.wait_idle(30)
    return store


def db_of(cfg) -> sqlite3.Connection:
    return sqlite3.connect(cfg.history.data_dir / "history.sqlite")


# ---- shifts -------------------------------------------------------------------------------
def test_shift_ids_and_bounds_in_the_plants_time_zone():
    cal = ShiftCalendar(ShiftsConfig(time_zone="Europe/Berlin"))  # UTC+1 in December
    s = cal.at(datetime(2026, 12, 1, 13, 30, tzinfo=UTC))  # 14:30 local
    assert s.id == "2026-12-01/late" and s.start_utc == datetime(2026, 12, 1, 13, 0, tzinfo=UTC)
    night = cal.at(datetime(2026, 12, 2, 3, 0, tzinfo=UTC))  # 04:00 local, started 22:00 on the 1st
    assert night.id == "2026-12-01/night" and night.end_utc == datetime(2026, 12, 2, 5, 0, tzinfo=UTC)
    assert cal.by_id("2026-12-01/night") == night
    start, end = cal.day(date(2026, 12, 1))
    assert (end - start) == timedelta(hours=24) and start == datetime(2026, 12, 1, 5, 0, tzinfo=UTC)
    unnamed = ShiftCalendar(ShiftsConfig(starts=["07:30", "19:30"], names=[]))
    assert unnamed.at(datetime(2026, 12, 1, 20, 0, tzinfo=UTC)).id == "2026-12-01T19:30"
    with pytest.raises(ValueError, match="no shift 'lunch'"):
        cal.by_id("2026-12-01/lunch")


def test_a_daylight_saving_night_shift_is_an_hour_longer():
    cal = ShiftCalendar(ShiftsConfig(time_zone="Europe/Berlin"))
    night = cal.by_id("2026-10-24/night")  # the clocks go back at 03:00 on the 25th
    assert night.end_utc - night.start_utc == timedelta(hours=9)


@pytest.mark.parametrize(
    "shifts, message",
    [
        ({"time_zone": "Mars/Olympus"}, "not an IANA time zone"),
        ({"starts": ["14:00", "06:00"]}, "in day order"),
        ({"starts": ["6:00"], "names": ["day"]}, "not a time HH:MM"),
        ({"names": ["early", "late"]}, "2 names for 3 start times"),
    ],
)
def test_bad_shift_settings_are_refused_saying_what(tmp_path, shifts, message):
    from cell.config import load_config

    body = "[shifts]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in shifts.items())
    (tmp_path / "c.toml").write_text(body)
    with pytest.raises(ConfigError, match=message):
        load_config(tmp_path / "c.toml")


# ---- rows ---------------------------------------------------------------------------------
def test_every_kind_of_row_from_the_events(tmp_path):
    cfg = history_config(tmp_path)
    store = fill(cfg)
    store.close()
    db = db_of(cfg)
    picks = db.execute("SELECT id, outcome, attempt, image_id IS NOT NULL FROM picks ORDER BY time_utc").fetchall()
    assert picks == [
        (f"{JOB}/1", "picked", 1, 0),
        (f"{JOB}/2", "picked", 1, 0),
        (f"{JOB}/3", "missed", 1, 1),
        (f"{JOB}/4", "failed", 2, 1),
        (f"{JOB}/6", "picked", 1, 0),
    ]
    job = db.execute("SELECT mode, interface, user_name, outcome, picked, failed, unreachable FROM jobs").fetchall()
    assert job == [("single", "screen", "anna", "done", 3, 1, 1)]
    alarm = db.execute("SELECT alarm_id, reason, cleared_interface, cleared_user, cleared_address FROM alarms")
    assert alarm.fetchall() == [("A1", "arm stalled", "screen", "anna", "10.0.0.7")]
    commands = db.execute("SELECT command, accepted, refusal FROM commands ORDER BY command").fetchall()
    assert commands == [("Reset", 0, "invalid_state"), ("StartSingleJob", 1, "")]
    cal = db.execute("SELECT id, model, cv_rms_mm, accepted_user FROM calibrations").fetchall()
    assert cal == [("cal0001", "polynomial", 0.01, "anna")]
    assert db.execute("SELECT count(*) FROM unreachable").fetchone() == (1,)
    assert db.execute("SELECT max(version) FROM schema_version").fetchone() == (VERSION,)
    assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
    assert db.execute("PRAGMA journal_mode").fetchone() == ("wal",)


def test_a_row_written_twice_is_there_once(tmp_path):
    cfg = history_config(tmp_path)
    store = fill(cfg)
    store.handle(verify(1))
    store.handle(verify(2, cls="bolt"))
    assert store.wait_idle(10)
    store.close()
    ids = [r[0] for r in db_of(cfg).execute("SELECT id FROM picks")]
    assert len(ids) == len(set(ids)) == 5


def test_a_newer_schema_is_refused_naming_its_version(tmp_path):
    cfg = history_config(tmp_path)
    fill(cfg).close()
    with db_of(cfg) as db:
        db.execute("INSERT INTO schema_version VALUES (99, 'x')")
    with pytest.raises(HistoryError, match="schema version 99; this cell knows up to 1"):
        HistoryStore(cfg.history, cfg.run.log_dir)


# ---- images -------------------------------------------------------------------------------
def test_images_of_misses_and_failures_are_saved_once_and_linked(tmp_path):
    cfg = history_config(tmp_path)
    store = fill(cfg)
    store.close()
    db = db_of(cfg)
    rows = db.execute("SELECT id, kind, frame_file, annotated_file FROM images ORDER BY frame_no").fetchall()
    assert [r[1] for r in rows] == ["miss", "miss"]  # frame 4: the miss and its part's failure, one image
    linked = {r[0] for r in db.execute("SELECT image_id FROM picks WHERE image_id IS NOT NULL")}
    assert linked == {r[0] for r in rows}
    import cv2

    for _, _, frame_file, annotated in rows:
        image = cv2.imread(str(cfg.history.data_dir / "images" / frame_file))
        assert image.shape == (60, 80, 3) and (cfg.history.data_dir / "images" / annotated).is_file()
    png = cv2.imread(str(cfg.history.data_dir / "images" / rows[1][2]))
    assert (png == frame(4).image).all()  # lossless


def test_retention_deletes_the_oldest_images_past_the_size_limit(tmp_path):
    cfg = history_config(tmp_path, images_max_mb=0.005, images_queue=64)  # 5 KB: room for a few small images
    events = [verify(n, "missed", track=n, ref=frame(n), time_utc=T0 + timedelta(seconds=n)) for n in range(1, 40)]
    store = fill(cfg, events)
    store.close()
    folder = cfg.history.data_dir / "images"
    size = sum(p.stat().st_size for p in folder.rglob("*.png"))
    assert 0 < size <= 0.005 * 2**20
    db = db_of(cfg)
    deleted = db.execute("SELECT count(*) FROM images WHERE deleted_utc IS NOT NULL").fetchone()[0]
    kept = db.execute("SELECT frame_no FROM images WHERE deleted_utc IS NULL ORDER BY frame_no").fetchall()
    assert deleted > 0 and kept[-1] == (39,) and kept[0][0] > 1  # the newest kept, the oldest gone


def test_below_the_free_disk_limit_no_image_is_saved_and_a_warning_says_why(tmp_path):
    cfg = history_config(tmp_path, min_free_mb=10**9)  # more free space than any disk has
    hooks = Hooks()
    store = fill(cfg, hooks=hooks)
    store.close()
    assert "under history.min_free_mb" in hooks.warnings["history-disk"]
    assert not list((cfg.history.data_dir / "images").rglob("*.png"))
    assert db_of(cfg).execute("SELECT count(*) FROM picks").fetchone() == (5,)  # the rows are all there


def test_a_full_image_queue_drops_and_counts_never_holds(tmp_path, monkeypatch):
    import threading

    import cell.history.images as images

    gate, stuck, real = threading.Event(), threading.Event(), images.write_bytes_atomic

    def stuck_write(path, data):
        stuck.set()
        gate.wait(30)
        return real(path, data)

    monkeypatch.setattr(images, "write_bytes_atomic", stuck_write)
    cfg = history_config(tmp_path, images_queue=1)
    store = HistoryStore(cfg.history, cfg.run.log_dir, Hooks())
    store.handle(verify(1, "missed", track=1, ref=frame(1)))
    assert stuck.wait(30)  # the saver has taken the first image and is stuck writing it
    for n in range(2, 30):  # one waits in the queue, the rest are dropped
        store.handle(verify(n, "missed", track=n, ref=frame(n)))
    s = store.stats()
    assert s.images_dropped == 27
    gate.set()
    assert store.wait_idle(30)
    s = store.stats()
    assert s.images_saved == 2 and s.images_dropped == 27
    store.close()
    db = db_of(cfg)
    assert db.execute("SELECT count(*) FROM picks").fetchone() == (29,)  # every row, images or not
    assert db.execute("SELECT count(*) FROM picks WHERE image_id IS NOT NULL").fetchone() == (2,)


# ---- integrity -------------------------------------------------------------------------------
def test_after_a_crash_the_audit_gives_back_the_picks_the_store_missed(tmp_path):
    cfg = history_config(tmp_path)
    store = fill(cfg, shift_events()[:8])  # up to pick 2
    store.close()
    audit = ShiftLog(cfg.run.log_dir, 2**20, day=lambda: "20261201")
    for e in shift_events():
        audit.record(e)  # the audit holds the whole job: the store "crashed" after pick 2
    audit.close()
    store = HistoryStore(cfg.history, cfg.run.log_dir, Hooks())
    assert store.reconciled > 0
    store.close()
    rows = db_of(cfg).execute("SELECT id, outcome FROM picks ORDER BY id").fetchall()
    assert [r[0] for r in rows] == [f"{JOB}/{n}" for n in (1, 2, 3, 4, 6)] and rows[3][1] == "failed"
    assert db_of(cfg).execute("SELECT outcome, unreachable FROM jobs").fetchall() == [("done", 1)]


def test_a_malformed_audit_line_is_skipped_and_counted_never_a_reason_not_to_start(tmp_path, caplog):
    """A `verify` line without its pick_id (and one that is not an object) in the audit after a
    crash: the read-back skips them, says so in the log, and gives back every other pick."""
    import json

    cfg = history_config(tmp_path)
    store = fill(cfg, shift_events()[:8])  # up to pick 2
    store.close()
    audit = ShiftLog(cfg.run.log_dir, 2**20, day=lambda: "20261201")
    for e in shift_events():
        audit.record(e)
    path = audit.path
    audit.close()
    lines = path.read_text().splitlines()
    broken = json.loads(next(line for line in lines if '"kind":"verify"' in line and f"{JOB}/3" in line))
    del broken["pick_id"]
    lines += [json.dumps(broken, separators=(",", ":")), '[{"kind":"verify"}]']
    path.write_text("\n".join(lines) + "\n")
    store = HistoryStore(cfg.history, cfg.run.log_dir, Hooks())
    assert store.reconciled > 0 and store.reconcile_skipped == 2
    store.close()
    assert "malformed audit lines skipped" in caplog.text and "no 'pick_id'" in caplog.text
    rows = db_of(cfg).execute("SELECT id FROM picks ORDER BY id").fetchall()
    assert [r[0] for r in rows] == [f"{JOB}/{n}" for n in (1, 2, 3, 4, 6)]


def test_a_damaged_file_is_refused_naming_it_or_moved_aside_when_configured(tmp_path):
    cfg = history_config(tmp_path)
    path = cfg.history.data_dir / "history.sqlite"
    path.parent.mkdir(parents=True)
    path.write_bytes(b"this is not a database, it is garbage" * 200)
    with pytest.raises(HistoryCorrupt, match=f"history database {path} is damaged"):
        HistoryStore(cfg.history, cfg.run.log_dir)
    assert path.read_bytes().startswith(b"this is not")
    cfg.history.on_corrupt = "move-aside"
    fill(cfg).close()
    (aside,) = path.parent.glob("history.sqlite.corrupt-*")
    assert aside.read_bytes().startswith(b"this is not")
    assert db_of(cfg).execute("SELECT count(*) FROM picks").fetchone() == (5,)


def test_a_failed_write_faults_when_required_and_warns_otherwise_keeping_the_rows(tmp_path):
    for required in (True, False):
        cfg = history_config(tmp_path / str(required), required=required, retry_s=0.05)
        hooks = Hooks()
        store = HistoryStore(cfg.history, cfg.run.log_dir, hooks)
        db = store.local
        real = db.conn
        db.conn = sqlite3.connect(":memory:", isolation_level=None)  # has no tables: every batch fails whole
        store.handle(verify(1))
        store.handle(verify(2))
        deadline = datetime.now() + timedelta(seconds=20)
        while not (hooks.faults or hooks.warnings) and datetime.now() < deadline:
            store.wait_idle(0.05)
        if required:
            ((reason, hint, source),) = hooks.faults
            assert reason.startswith("history cannot be written: ") and source == "history"
        else:
            assert hooks.warnings["history"].startswith("history cannot be written: ") and not hooks.faults
        db.conn = real  # the disk is back: the kept rows are written, none half
        assert store.wait_idle(20)
        store.close()
        assert db_of(cfg).execute("SELECT count(*) FROM picks").fetchone() == (2,)
        assert required or "history" in hooks.cleared


def test_closing_while_every_write_fails_ends_the_writer_at_once_and_says_what_was_left(tmp_path, caplog):
    """The writer (a cell.core.worker.QueueWorker) waits retry_s between tries; closing ends that
    wait: no further try, the thread ends, the rows not written are counted and logged."""
    cfg = history_config(tmp_path, retry_s=600)  # a close that waited out a retry would hit the test's timeout
    hooks = Hooks()
    store = HistoryStore(cfg.history, cfg.run.log_dir, hooks)
    real, store.local.conn = store.local.conn, sqlite3.connect(":memory:", isolation_level=None)  # no tables
    store.handle(verify(1))
    store.handle(verify(2))
    deadline = datetime.now() + timedelta(seconds=20)
    while not (hooks.faults or hooks.warnings) and datetime.now() < deadline:
        store.wait_idle(0.05)
    assert hooks.faults or hooks.warnings  # failed once; waiting 600 s for the next try
    pending = store.stats().rows_pending
    assert pending > 0
    with caplog.at_level("ERROR", logger="cell.history.store"):
        store.close(timeout_s=0.2)
    assert not store._writer.is_alive()
    assert store.stats().rows_pending == pending and store.written == 0
    assert any(f"{pending} rows not written at close" in r.getMessage() for r in caplog.records)
    real.close()


# ---- reading ---------------------------------------------------------------------------------
def test_the_query_api_filters_and_gets_by_id(tmp_path):
    cfg = history_config(tmp_path)
    fill(cfg).close()
    reader = open_reader(cfg)
    try:
        assert reader.get_pick(f"{JOB}/2")["class"] == "bolt"
        assert reader.get_pick("nope/1") is None
        assert [p["id"] for p in reader.list_picks(PickFilter(outcome="failed"))] == [f"{JOB}/4"]
        window = PickFilter(since=T0 + timedelta(seconds=2), until=T0 + timedelta(seconds=4))
        assert [p["id"] for p in reader.list_picks(window)] == [f"{JOB}/2", f"{JOB}/3"]
        assert reader.count_picks(PickFilter(job_id=JOB, cls="nut")) == 4
        c = reader.counters(T0, T0 + timedelta(hours=1))
        assert (c.picked_of("bolt"), c.picked_of("nut"), c.misses, c.retries, c.failed, c.unreachable) == (
            1,
            2,
            2,
            1,
            1,
            1,
        )
        last = reader.last_picks(2)
        assert [p.pick_id for p in last] == [f"{JOB}/4", f"{JOB}/6"] and last[0].outcome == "failed"
        report = build_report(reader, "test", T0 - timedelta(minutes=10), T0 + timedelta(minutes=10))
    finally:
        reader.close()
    assert (report.picked, report.misses, report.failed, report.attempts) == (3, 2, 1, 5)
    assert report.faults[0]["reason"] == "arm stalled" and report.faults[0]["cleared_by"] == "anna via screen"
    assert report.down_s == pytest.approx(120.0) and report.running_s == pytest.approx(7.0)
    assert report.mtbf_s == pytest.approx(7.0) and report.top_alarms == [("arm stalled", 1)]


def config_file(tmp_path, cfg) -> str:
    path = tmp_path / "cell.toml"
    path.write_text(
        f'[run]\nlog_dir = "{cfg.run.log_dir}"\n[history]\ndata_dir = "{cfg.history.data_dir}"\ncell_name = "cell-a"\n'
    )
    return str(path)


def test_run_cell_history_json_and_csv(tmp_path, capsys):
    cfg = history_config(tmp_path)
    fill(cfg).close()
    conf = config_file(tmp_path, cfg)
    assert main(["history", "--config", conf, "--shift", "2026-12-01/early", "--json"]) == 0
    picks = json.loads(capsys.readouterr().out)
    assert len(picks) == 5
    keys = {"id", "job_id", "time_utc", "class", "table_mm", "robot_mm", "outcome", "calibration_id"}
    assert keys <= set(picks[0]) and picks[0]["calibration_id"] == "cal0001"
    assert picks[0]["table_mm"] == [11.0, 20.0] and picks[0]["robot_mm"] == [-121.0, 60.0, 2.0]
    assert main(["history", "--config", conf, "--outcome", "missed", "--csv"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["id"] for r in rows] == [f"{JOB}/3"] and rows[0]["table_x_mm"] == "13.0"
    assert main(["history", "--config", conf, "--since", "2026-12-01T06:15:03Z", "--class", "nut"]) == 0
    out = capsys.readouterr().out
    assert f"{JOB}/3" in out and f"{JOB}/2" not in out and out.strip().endswith("3 picks")


def test_run_cell_report_and_its_chart(tmp_path, capsys):
    cfg = history_config(tmp_path)
    fill(cfg).close()
    conf = config_file(tmp_path, cfg)
    png = tmp_path / "chart.png"
    assert main(["report", "--config", conf, "--shift", "2026-12-01/early", "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "report shift 2026-12-01/early" in out and "3 picked (1 bolt, 2 nut) in 5 attempts" in out
    assert "2 misses (40.0 %)" in out and "arm stalled (reset by anna via screen)" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["report", "--config", conf, "--day", "2026-12-01", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["picked"] == 3


def _kolkata(tmp_path, cfg) -> str:
    """A plant at UTC+05:30 all year: its hours split UTC's, and no daylight saving blurs the offset."""
    path = tmp_path / "kolkata.toml"
    path.write_text(Path(config_file(tmp_path, cfg)).read_text() + '[shifts]\ntime_zone = "Asia/Kolkata"\n')
    return str(path)


def test_run_cell_report_speaks_the_shifts_zone_and_says_which(tmp_path, capsys):
    """Issue 33: the report printed UTC (and counted UTC hours) while `history` spoke the plant's zone."""
    cfg = history_config(tmp_path)
    later = verify(7, time_utc=T0 + timedelta(minutes=31))  # 06:46 UTC: the same UTC hour, the next local one
    fill(cfg, [*shift_events(), later]).close()
    conf = _kolkata(tmp_path, cfg)
    assert main(["report", "--config", conf, "--shift", "2026-12-01/early"]) == 0
    lines = capsys.readouterr().out.splitlines()
    # the early shift starts at 06:00 on the plant's clock: 00:30 UTC
    assert lines[0] == "report shift 2026-12-01/early: 2026-12-01 06:00 - 2026-12-01 14:00"
    assert lines[1] == "times in Asia/Kolkata (UTC+05:30)"
    assert "  2026-12-01 11:46:00  arm stalled (reset by anna via screen)" in lines  # raised 06:16:00 UTC
    hours = lines[lines.index("picks per hour (Asia/Kolkata): ") + 1 :]
    assert hours == ["  2026-12-01 11:00      3 picked     2 missed", "  2026-12-01 12:00      1 picked     0 missed"]
    assert main(["report", "--config", conf, "--shift", "2026-12-01/early", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["time_zone"] == "Asia/Kolkata" and report["start"] == "2026-12-01T06:00:00+05:30"
    assert report["start_utc"] == "2026-12-01T00:30:00+00:00"
    assert report["per_hour"] == [
        {"hour": "2026-12-01T11:00+05:30", "picked": 3, "missed": 2},
        {"hour": "2026-12-01T12:00+05:30", "picked": 1, "missed": 0},
    ]


def test_run_cell_history_says_the_zone_its_times_are_in(tmp_path, capsys):
    cfg = history_config(tmp_path)
    fill(cfg).close()
    assert main(["history", "--config", _kolkata(tmp_path, cfg), "--shift", "2026-12-01/early"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "times in Asia/Kolkata (UTC+05:30)"
    (row,) = [line for line in lines if f"{JOB}/2 " in line]
    assert row.startswith(f"2026-12-01 11:45:02.000    {JOB}/2 ")  # picked 06:15:02 UTC


@pytest.mark.parametrize(
    "argv, message",
    [
        (["history", "--shift", "2026-12-01/lunch"], "--shift: shift '2026-12-01/lunch': no shift 'lunch'"),
        (["history", "--since", "yesterday"], "--since 'yesterday': expected an ISO 8601 time"),
        (["report", "--day", "2026-13-01"], "--day:"),
        (["report", "--png", "chart.jpg"], "give a file name ending in .png"),
    ],
)
def test_bad_history_arguments_are_one_line_errors(tmp_path, capsys, argv, message):
    cfg = history_config(tmp_path)
    fill(cfg).close()
    assert main([*argv, "--config", config_file(tmp_path, cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_history_of_a_store_that_does_not_exist_says_so(tmp_path, capsys):
    assert main(["history", "--url", f"sqlite:///{tmp_path}/none.sqlite"]) == 2
    assert f"history database {tmp_path}/none.sqlite does not exist" in capsys.readouterr().err


def test_a_read_only_reader_cannot_write(tmp_path):
    cfg = history_config(tmp_path)
    fill(cfg).close()
    db = open_sqlite(cfg.history.data_dir / "history.sqlite", readonly=True)
    with pytest.raises(sqlite3.OperationalError, match="readonly"):
        db.execute("DELETE FROM picks")
    db.close()


def test_times_sort_as_text_in_sqlite(tmp_path):
    from cell.history.db import sqlite_time

    a, b = datetime(2026, 12, 1, 9, 59, 59, 999999, tzinfo=UTC), datetime(2026, 12, 1, 10, tzinfo=UTC)
    assert sqlite_time(a) < sqlite_time(b) and len(sqlite_time(a)) == len(sqlite_time(b))


@pytest.mark.parametrize(
    "argv, message",
    [
        (["history", "copy"], "both are needed"),
        (["history", "copy", "--to", "sqlite:///x.sqlite"], "give the server as postgresql://"),
        (["history", "copy", "--to", "postgresql://cell@127.0.0.1:9/x", "--shift", "2026-12-01/early"], "--shift"),
        (["history", "copy", "--to", "postgresql://cell@127.0.0.1:9/x", "--simulated"], "--simulated"),
    ],
)
def test_history_copy_arguments_are_one_line_errors(tmp_path, capsys, argv, message):
    cfg = history_config(tmp_path)
    fill(cfg).close()
    assert main([*argv, "--config", config_file(tmp_path, cfg)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err

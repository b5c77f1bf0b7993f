"""The history store on a live PostgreSQL server that these tests start (once per session): the
same schema and rows as on SQLite, queries and the report, and an outage mid-shift: the cell
keeps picking, rows wait in the local outbox and reach the server when it is back, none lost,
none twice."""

from __future__ import annotations

from datetime import timedelta

import pytest

from cell.core.commands import Command, VisionState
from cell.history.query import PickFilter, open_reader
from cell.history.report import build_report
from tests.history_helpers import JOB, T0, history_config, verify
from tests.pg_server import PostgresServer, why_no_postgresql
from tests.test_history import Hooks, fill
from tests.test_service import picked, production, small_config, wait_for

pytestmark = [
    pytest.mark.skipif(why_no_postgresql() is not None, reason=str(why_no_postgresql())),
    pytest.mark.slow,  # a PostgreSQL server in a subprocess
    pytest.mark.timeout(180),
]


@pytest.fixture(scope="session")
def pg():
    server = PostgresServer()
    server.start()
    yield server
    server.close()


@pytest.fixture
def pg_url(pg):
    """A clean database for each test (the schema dropped)."""
    import psycopg

    if pg.proc is None:
        pg.start()
    with psycopg.connect(pg.url, autocommit=True) as conn:
        conn.execute("DROP SCHEMA public CASCADE")
        conn.execute("CREATE SCHEMA public")
    return pg.url


def test_the_same_rows_and_queries_on_postgresql(tmp_path, pg_url):
    cfg = history_config(tmp_path, url=pg_url)
    store = fill(cfg)
    assert store.wait_sent(30)
    store.close()
    reader = open_reader(cfg)
    try:
        assert reader.db.dialect == "postgresql"
        assert [p["id"] for p in reader.list_picks()] == [f"{JOB}/{n}" for n in (1, 2, 3, 4, 6)]
        assert reader.get_pick(f"{JOB}/4")["outcome"] == "failed"
        assert reader.count_picks(PickFilter(cls="nut")) == 4
        assert reader.alarms()[0]["cleared_user"] == "anna"
        report = build_report(reader, "pg", T0 - timedelta(minutes=10), T0 + timedelta(minutes=10))
        assert (report.picked, report.misses, report.failed) == (3, 2, 1) and report.per_hour[0][1] == 3
        assert report.down_s == pytest.approx(120.0)
        versions = reader.db.execute("SELECT version FROM schema_version")
        assert versions == [(1,)]
    finally:
        reader.close()


def test_an_outage_queues_rows_locally_and_sends_them_once_when_the_server_is_back(tmp_path, pg, pg_url):
    cfg = history_config(tmp_path, url=pg_url, retry_initial_s=0.2, retry_max_s=1, connect_timeout_s=2)
    hooks = Hooks()
    store = fill(cfg, [verify(n, track=n) for n in range(1, 11)], hooks)
    assert store.wait_sent(30)
    pg.stop()  # the server goes away mid-shift
    for n in range(11, 31):
        store.handle(verify(n, track=n))
    assert store.wait_idle(30)  # the cell's side is done: rows are safe in the local outbox
    wait_for(lambda: store.stats().outbox == 20, 30, "20 rows in the outbox")
    wait_for(lambda: "history-server" in hooks.warnings, 30, "the outage's warning")
    assert "rows wait in the local queue" in hooks.warnings["history-server"]
    pg.start()
    assert store.wait_sent(60)
    wait_for(lambda: "history-server" in hooks.cleared, 30, "the warning cleared")
    for n in (5, 25):  # a resend (the forwarder killed between the server's commit and the outbox's delete)
        store.handle(verify(n, track=n))
    assert store.wait_sent(30)
    store.close()
    reader = open_reader(cfg)
    try:
        ids = [p["id"] for p in reader.list_picks(limit=None)]
    finally:
        reader.close()
    assert ids == [f"{JOB}/{n}" for n in range(1, 31)]  # none lost, none twice, in order


def test_a_shift_goes_on_through_a_server_outage(tmp_path, pg, pg_url):
    """A production shift (a rehearsal keeps its own local store, never the plant's database)."""
    cfg = small_config(tmp_path)
    cfg.history.url, cfg.history.retry_s, cfg.history.min_free_mb = pg_url, 0.2, 1
    cfg.history.retry_initial_s, cfg.history.retry_max_s = 0.2, 1
    cfg.history.connect_timeout_s = 2
    cfg.sim.feeder = cfg.sim.feeder.model_copy(update={"parts_per_minute": 0})
    with production(cfg) as service:
        service.command(Command.START_CONTINUOUS)
        wait_for(lambda: picked(service) >= 3, 120, "3 picks")
        pg.stop()
        wait_for(lambda: picked(service) >= 12, 120, "picks while the server is away")
        assert service.snapshot().vision_state == VisionState.CONTINUOUS_EXECUTION
        wait_for(lambda: any(w.source == "history" for w in service.snapshot().warnings), 30, "the warning")
        pg.start()
        wait_for(lambda: service.snapshot().waiting_for_parts, 120, "the table cleared")
        service.command(Command.STOP)
        wait_for(lambda: service.snapshot().vision_state == VisionState.READY, 60, "Ready")
        assert service.history.wait_sent(60)
        counters = service.snapshot().counters
    reader = open_reader(cfg)
    try:
        picks = reader.list_picks(limit=None)
    finally:
        reader.close()
    ids = [p["id"] for p in picks]
    assert len(ids) == len(set(ids))
    assert sum(p["outcome"] == "picked" for p in picks) == counters.picked_total == 17


def test_counters_after_an_outage_and_a_restart_count_the_rows_still_in_the_outbox(tmp_path, pg, pg_url):
    """The server goes away mid-shift and the service is restarted before the outbox is sent (here
    the server takes no INSERT at the restart, so the outbox stays unsent): the counters restored
    are the shift's, the server's rows and the outbox's together, not the server's alone."""
    import psycopg

    with psycopg.connect(pg_url, autocommit=True) as conn:  # a plain user (the superuser ignores REVOKE)
        conn.execute("DO $$ BEGIN CREATE ROLE cellw LOGIN; EXCEPTION WHEN duplicate_object THEN NULL; END $$")
        conn.execute("GRANT ALL ON SCHEMA public TO cellw")
    cfg = small_config(tmp_path)
    cfg.history.url, cfg.history.retry_s, cfg.history.min_free_mb = pg_url.replace("cell@", "cellw@"), 0.2, 1
    cfg.history.connect_timeout_s = 2
    cfg.sim.feeder = cfg.sim.feeder.model_copy(update={"parts_per_minute": 0})
    with production(cfg) as service:
        service.command(Command.START_CONTINUOUS)
        wait_for(lambda: picked(service) >= 3, 120, "3 picks")
        assert service.history.wait_sent(60)
        pg.stop()
        wait_for(lambda: service.snapshot().waiting_for_parts, 120, "the table cleared")
        service.command(Command.STOP)
        wait_for(lambda: service.snapshot().vision_state == VisionState.READY, 60, "Ready")
        assert service.history.wait_idle(60)
        before = service.snapshot()
        assert service.history.stats().outbox > 0
    pg.start()
    with psycopg.connect(pg_url, autocommit=True) as conn:
        conn.execute("REVOKE INSERT, UPDATE ON ALL TABLES IN SCHEMA public FROM cellw")
        on_server = conn.execute("SELECT count(*) FROM picks WHERE outcome = 'picked'").fetchone()[0]
    try:
        assert on_server < 17  # the server lacks the picks of the outage
        with production(cfg) as service:
            after = service.snapshot()
            assert service.history.stats().outbox > 0  # still unsent while the counters were restored
            assert after.counters == before.counters and picked(service) == 17
            assert [p.pick_id for p in after.last_picks] == [p.pick_id for p in before.last_picks]
    finally:
        with psycopg.connect(pg_url, autocommit=True) as conn:
            conn.execute("GRANT INSERT, UPDATE ON ALL TABLES IN SCHEMA public TO cellw")


def test_history_copy_moves_sqlite_rows_to_postgresql_once(tmp_path, pg_url, capsys):
    """`run-cell history copy --to URL`: every row of a cell's SQLite history reaches the server; run
    again (or after the cell wrote some there itself) nothing is added twice."""
    import sqlite3

    from cell.cli import main
    from tests.test_history import config_file

    cfg = history_config(tmp_path)
    fill(cfg).close()
    conf = config_file(tmp_path, cfg)
    local = sqlite3.connect(tmp_path / "data" / "history.sqlite")
    tables = ("calibrations", "jobs", "picks", "unreachable", "alarms", "commands", "states", "images", "marks")
    counts = {t: local.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in tables}
    local.close()
    assert counts["picks"] == 5 and counts["alarms"] >= 1
    assert main(["history", "copy", "--config", conf, "--to", pg_url]) == 0
    total = sum(counts.values())
    assert f"{total} rows read, {total} added, 0 already on the server" in capsys.readouterr().out

    on_server = history_config(tmp_path, url=pg_url)
    reader = open_reader(on_server)
    try:
        assert [p["id"] for p in reader.list_picks()] == [f"{JOB}/{n}" for n in (1, 2, 3, 4, 6)]
        assert reader.get_pick(f"{JOB}/4")["outcome"] == "failed"
        assert reader.alarms()[0]["cleared_user"] == "anna"
        server = {t: reader.db.execute(f"SELECT count(*) FROM {t}")[0][0] for t in tables}
    finally:
        reader.close()
    assert server == counts

    assert main(["history", "copy", "--config", conf, "--to", pg_url]) == 0  # idempotent
    assert f"{total} rows read, 0 added, {total} already on the server" in capsys.readouterr().out
    reader = open_reader(on_server)
    try:
        assert {t: reader.db.execute(f"SELECT count(*) FROM {t}")[0][0] for t in tables} == counts
    finally:
        reader.close()

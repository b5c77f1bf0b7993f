"""The PostgreSQL forwarder when the server misbehaves, against a real server (tests/pg_server.py):
INSERT revoked for the cell's role (it backs off on one connection, raises an alarm, and every
row arrives once after GRANT), a row the server refuses (the dead-letter: kept, counted, an
alarm, listed by `run-cell history --dead-letter`; the rows behind it arrive), and a path that
goes silent (a black-holing TCP proxy: a warning alarm, and closing the store returns with the
unsent rows in the outbox)."""

from __future__ import annotations

import contextlib
import json
import socket
import sqlite3
import threading

import psycopg
import pytest

from cell.cli import main
from cell.history.config import HistoryConfig
from cell.history.db import libpq_params, open_postgresql
from cell.history.query import open_reader
from cell.history.store import backoff_s
from tests import test_history_pg
from tests.blackhole_proxy import BlackHoleProxy
from tests.history_helpers import JOB, history_config, verify
from tests.pg_server import why_no_postgresql
from tests.test_history import Hooks, fill
from tests.test_service import wait_for

pytestmark = [
    pytest.mark.skipif(why_no_postgresql() is not None, reason=str(why_no_postgresql())),
    pytest.mark.slow,  # a PostgreSQL server in a subprocess
    pytest.mark.timeout(180),
]

pg = test_history_pg.pg  # the fixtures: the session's one server, a clean database for each test
pg_url = test_history_pg.pg_url
WRITER = "hist_writer"  # a role that is not a superuser (privileges bind it)


@pytest.fixture
def proxy(pg, pg_url):
    p = BlackHoleProxy(pg.port)
    yield p
    p.close()


class RecordingHooks(Hooks):
    """Hooks that keep every warning raised, in order."""

    def __init__(self):
        super().__init__()
        self.raised: list[tuple[str, str]] = []

    def raise_warning(self, key, reason, hint, source):
        self.raised.append((key, reason))
        super().raise_warning(key, reason, hint, source)


def superuser(pg_url: str) -> psycopg.Connection:
    return psycopg.connect(pg_url, autocommit=True)


def outbox_rows(cfg) -> int:
    with contextlib.closing(sqlite3.connect(cfg.history.data_dir / "history-outbox.sqlite")) as db:
        return db.execute("SELECT count(*) FROM outbox").fetchone()[0]


def pick_ids(cfg) -> list[str]:
    reader = open_reader(cfg)
    try:
        return [p["id"] for p in reader.list_picks(limit=None)]
    finally:
        reader.close()


def closed_in_a_thread(store, timeout_s: float) -> threading.Event:
    done = threading.Event()

    def run() -> None:
        store.close(timeout_s)
        done.set()

    threading.Thread(target=run, name="test-close", daemon=True).start()
    return done


def test_the_backoff_doubles_up_to_its_cap_with_jitter():
    for failures, full in ((1, 0.5), (2, 1.0), (3, 2.0), (4, 4.0), (5, 5.0), (40, 5.0), (5000, 5.0)):
        waits = [backoff_s(failures, 0.5, 5.0) for _ in range(200)]
        assert all(full / 2 <= w <= full for w in waits), (failures, min(waits), max(waits))
        assert len(set(waits)) > 1  # drawn, not fixed: cells that failed together spread out


def test_the_connection_carries_keepalives_a_user_timeout_and_a_statement_timeout(pg_url):
    h = HistoryConfig(
        keepalive_idle_s=7, keepalive_interval_s=3, keepalive_count=4, tcp_user_timeout_s=12.5, statement_timeout_s=9
    )
    db = open_postgresql(pg_url + "?options=-c%20work_mem%3D8MB", h, "pick-cell history test")
    try:
        s = socket.socket(fileno=db.conn.pgconn.socket)
        try:
            assert s.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 1
            assert s.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE) == 7
            assert s.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL) == 3
            assert s.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT) == 4
            assert s.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT) == 12_500
        finally:
            s.detach()  # the connection's socket: not ours to close
        assert db.execute("SHOW statement_timeout") == [("9s",)]
        assert db.execute("SHOW idle_in_transaction_session_timeout") == [("30s",)]  # the shipped default
        assert db.execute("SHOW work_mem") == [("8MB",)]  # the URL's own options are kept
        assert db.execute("SHOW application_name") == [("pick-cell history test",)]
    finally:
        db.close()


def test_no_timeouts_send_no_options_for_a_pooler(pg_url):
    h = HistoryConfig(statement_timeout_s=0, idle_in_transaction_timeout_s=0)
    assert "options" not in libpq_params(pg_url, h)
    h = HistoryConfig(statement_timeout_s=0, idle_in_transaction_timeout_s=2)
    assert libpq_params(pg_url, h)["options"] == "-c idle_in_transaction_session_timeout=2000"


def test_a_session_left_in_a_transaction_by_a_silent_path_is_ended_and_the_rows_sent_again_arrive(
    tmp_path, pg_url, proxy
):
    """A batch cut off mid-transaction by a path gone silent leaves the server holding that session
    and its locks (the server's TCP sees nothing wrong); the same rows sent again would wait on them
    until the server's keepalive gives up (hours by default). The server ends a session idle in a
    transaction (idle_in_transaction_session_timeout, on the cell's sessions), and where it does not
    (a session stuck part way through a message: seen with the whole service behind the proxy), the
    forwarder ends its own cell's stale sessions, after a failed try or at its next connect."""
    cfg = history_config(tmp_path, url=pg_url)
    fill(cfg, []).close()  # the schema
    for server_ends_it in (True, False):
        stale = open_postgresql(
            proxy.url(),
            HistoryConfig(idle_in_transaction_timeout_s=2 if server_ends_it else 0),
            "pick-cell history cell-a",
        )
        stale.conn.execute("BEGIN")
        stale.conn.execute("LOCK TABLE picks IN SHARE ROW EXCLUSIVE MODE")  # what an unfinished batch's inserts hold
        proxy.silence()  # the path goes silent with the transaction open
        cfg = history_config(
            tmp_path,
            url=pg_url,
            retry_initial_s=0.05,
            retry_max_s=0.4,
            statement_timeout_s=1,
            idle_in_transaction_timeout_s=2,
        )
        store = fill(cfg, [verify(n) for n in range(1, 4)] if server_ends_it else [verify(n) for n in range(4, 7)])
        try:
            assert store.wait_sent(60), f"the rows never got past the stale session's locks ({server_ends_it=})"
        finally:
            store.close()
            stale.close()
        proxy.silent.clear()
    assert pick_ids(cfg) == [f"{JOB}/{n}" for n in range(1, 7)]
    with superuser(pg_url) as su:
        left = su.execute("SELECT count(*) FROM pg_stat_activity WHERE application_name = 'pick-cell history cell-a'")
        assert left.fetchone()[0] == 0  # ended, by the server or by the cell


def test_insert_revoked_backs_off_on_one_connection_and_every_row_arrives_once_after_grant(tmp_path, pg_url):
    cfg = history_config(tmp_path, url=pg_url)
    fill(cfg, []).close()  # the schema, made by the superuser
    with superuser(pg_url) as su:
        with contextlib.suppress(psycopg.errors.DuplicateObject):
            su.execute(f"CREATE ROLE {WRITER} LOGIN")
        su.execute(f"GRANT USAGE, CREATE ON SCHEMA public TO {WRITER}")
        su.execute(f"GRANT SELECT, INSERT, UPDATE ON ALL TABLES IN SCHEMA public TO {WRITER}")
        su.execute(f"REVOKE INSERT ON picks FROM {WRITER}")
    writer_url = pg_url.replace("cell@", f"{WRITER}@")
    cfg = history_config(tmp_path, url=writer_url, retry_initial_s=0.05, retry_max_s=0.4)
    hooks = Hooks()
    store = fill(cfg, [verify(n) for n in range(1, 11)], hooks)
    try:
        wait_for(lambda: store.forwarder_stats().failures >= 8, 60, "8 failed tries")
        wait_for(lambda: "history-server" in hooks.warnings, 30, "the alarm")
        assert "permission denied for table picks" in hooks.warnings["history-server"]
        assert "rows wait in the local queue" in hooks.warnings["history-server"]
        with superuser(pg_url) as su:
            at_server = su.execute("SELECT count(*) FROM pg_stat_activity WHERE usename = %s", (WRITER,)).fetchone()
        stats = store.forwarder_stats()
        assert at_server[0] <= 2 and stats.connections <= 2  # the connection is kept, not one per try
        # every try after a failure waited as the backoff says: doubling from 0.05 s up to 0.4 s
        waits = stats.waits_s
        assert len(waits) >= 7
        for n, w in enumerate(waits[:7], start=1):
            full = min(0.4, 0.05 * 2 ** (n - 1))
            assert full / 2 <= w <= full, (n, w)
        assert store.stats().outbox == 10 and store.stats().dead_letter == 0  # kept, not refused
        with superuser(pg_url) as su:
            su.execute(f"GRANT INSERT ON picks TO {WRITER}")
        assert store.wait_sent(60)
        wait_for(lambda: "history-server" in hooks.cleared, 30, "the alarm cleared")
        assert store.forwarder_stats().connections <= 2
    finally:
        store.close()
    assert pick_ids(history_config(tmp_path, url=pg_url)) == [f"{JOB}/{n}" for n in range(1, 11)]


def test_a_row_the_server_refuses_goes_to_the_dead_letter_and_the_rows_behind_it_arrive(tmp_path, pg_url, capsys):
    cfg = history_config(tmp_path, url=pg_url, retry_initial_s=0.05, retry_max_s=0.4)
    hooks = Hooks()
    store = fill(cfg, [verify(n) for n in range(1, 4)], hooks)
    try:
        assert store.wait_sent(30)
        with superuser(pg_url) as su:
            su.execute("ALTER TABLE picks ADD CONSTRAINT track_on_the_table CHECK (track < 1000)")
        for n, track in ((4, 4), (5, 5000), (6, 6), (7, 7), (8, 8)):
            store.handle(verify(n, track=track, cls="nut\x00" if n == 7 else "nut"))  # 7: a NUL the server refuses
        assert store.wait_sent(60)
        wait_for(lambda: "history-dead-letter" in hooks.warnings, 30, "the dead-letter alarm")
        assert "kept aside" in hooks.warnings["history-dead-letter"]
        assert store.stats().dead_letter == 2 and store.forwarder_stats().dead_letter == 2
    finally:
        store.close()
    assert pick_ids(cfg) == [f"{JOB}/{n}" for n in (1, 2, 3, 4, 6, 8)]
    conf = tmp_path / "cell.toml"
    conf.write_text(f'[run]\nlog_dir = "{cfg.run.log_dir}"\n[history]\ndata_dir = "{cfg.history.data_dir}"\n')
    capsys.readouterr()
    assert main(["history", "--config", str(conf), "--dead-letter", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["statement"], r["params"][0]) for r in rows] == [("pick", f"{JOB}/5"), ("pick", f"{JOB}/7")]
    assert "track_on_the_table" in rows[0]["error"] and "NUL" in rows[1]["error"]
    assert main(["history", "--config", str(conf), "--dead-letter"]) == 0
    assert capsys.readouterr().out.strip().endswith(f"2 refused rows in {cfg.history.data_dir}/history-outbox.sqlite")
    assert main(["history", "--config", str(conf), "--dead-letter", "--since", "2026-12-01"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--dead-letter lists every refused row: --since does not apply" in err[0]


def test_closing_while_the_server_gives_no_answer_returns_and_keeps_the_rows(tmp_path, proxy):
    # the watchdog is set far off: the forwarder is still waiting for its answer when the store closes
    cfg = history_config(tmp_path, url=proxy.url(), answer_timeout_s=3600, statement_timeout_s=0, connect_timeout_s=2)
    store = fill(cfg, [verify(n) for n in range(1, 6)])
    assert store.wait_sent(30)
    proxy.silence()
    before = store.forwarder_stats().attempts
    for n in range(6, 11):
        store.handle(verify(n))
    assert store.wait_idle(30)
    wait_for(lambda: store.forwarder_stats().attempts > before, 30, "the forwarder sending into the silence")
    closed = closed_in_a_thread(store, 1.0)
    assert closed.wait(60), "the store's close did not return while the server gave no answer"
    assert outbox_rows(cfg) == 5  # for the next start
    wait_for(lambda: not store._forwarder.is_alive(), 30, "the forwarder's wait interrupted, the thread ended")


def test_a_silent_server_raises_a_warning_and_the_rows_wait_in_the_outbox(tmp_path, proxy):
    cfg = history_config(
        tmp_path,
        url=proxy.url(),
        statement_timeout_s=0.5,
        answer_timeout_s=1,
        connect_timeout_s=2,
        retry_initial_s=0.05,
        retry_max_s=0.4,
    )
    hooks = RecordingHooks()
    store = fill(cfg, [verify(n) for n in range(1, 6)], hooks)
    assert store.wait_sent(30)
    proxy.silence()
    for n in range(6, 11):
        store.handle(verify(n))
    assert store.wait_idle(30)
    silent = "gave no answer within 1 s (answer_timeout_s)"
    wait_for(lambda: any(k == "history-server" and silent in r for k, r in hooks.raised), 60, "the warning")
    assert store.stats().outbox == 5
    closed = closed_in_a_thread(store, 1.0)
    assert closed.wait(60), "the store's close did not return"
    assert outbox_rows(cfg) == 5

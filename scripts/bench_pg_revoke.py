"""The PostgreSQL forwarder while the server refuses every INSERT (issue 28): what it costs and
what arrives.

A real PostgreSQL server (Debian's binaries, started as the tests start it: tests/pg_server.py),
the history schema made by a superuser, then INSERT on `picks` revoked from the cell's role. The
history store runs with its shipped retry settings (`history.retry_initial_s`, `retry_max_s`) while
picks keep coming (`--picks-per-s`, as a running cell hands them over) for `--revoked-s` seconds;
meanwhile the process's CPU time (user + system: the forwarder, the writer and the feeding) and
the cell role's sessions at the server (pg_stat_activity, once a second) are sampled. Then GRANT,
and the bench waits until the outbox is empty and counts the rows at the server: every pick
once. Goals: at most 10 % of a core, at most 2 connections, an alarm raised; every row once.

    .venv/bin/python scripts/bench_pg_revoke.py [--revoked-s 60] [--picks-per-s 5]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.history_helpers import JOB, history_config, verify  # noqa: E402
from tests.pg_server import PostgresServer, why_no_postgresql  # noqa: E402

WRITER = "hist_writer"


class Alarms:
    """The store's hooks: what a service would show as alarms."""

    def __init__(self) -> None:
        self.raised: dict[str, str] = {}
        self.cleared: list[str] = []
        self.faults: list[str] = []

    def fault(self, reason: str, hint: str, source: str) -> None:
        self.faults.append(reason)

    def raise_warning(self, key: str, reason: str, hint: str, source: str) -> None:
        self.raised.setdefault(key, reason)

    def clear_warning(self, key: str) -> None:
        self.cleared.append(key)


def cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def sessions(su, role: str) -> int:
    row = su.execute("SELECT count(*) FROM pg_stat_activity WHERE usename = %s", (role,)).fetchone()
    return int(row[0]) if row else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--revoked-s", type=float, default=60.0, help="how long INSERT stays revoked (default 60)")
    ap.add_argument("--picks-per-s", type=float, default=5.0, help="picks handed to the store meanwhile (default 5)")
    args = ap.parse_args()
    if why := why_no_postgresql():
        print(f"cannot run: {why}", file=sys.stderr)
        return 2
    import psycopg

    from cell.history.store import HistoryStore

    server = PostgresServer()
    server.start()
    try:
        with tempfile.TemporaryDirectory(prefix="pg-revoke-") as tmp_name:
            tmp = Path(tmp_name)
            with psycopg.connect(server.url, autocommit=True) as su:
                HistoryStore(history_config(tmp / "schema", url=server.url).history, tmp / "schema", Alarms()).close()
                with contextlib.suppress(psycopg.errors.DuplicateObject):
                    su.execute(f"CREATE ROLE {WRITER} LOGIN")
                su.execute(f"GRANT USAGE, CREATE ON SCHEMA public TO {WRITER}")
                su.execute(f"GRANT SELECT, INSERT, UPDATE ON ALL TABLES IN SCHEMA public TO {WRITER}")
                su.execute(f"REVOKE INSERT ON picks FROM {WRITER}")
                cfg = history_config(tmp, url=server.url.replace("cell@", f"{WRITER}@"))
                h = cfg.history
                print(f"history.retry_initial_s {h.retry_initial_s}, retry_max_s {h.retry_max_s} (shipped defaults)")
                alarms = Alarms()
                store = HistoryStore(h, cfg.run.log_dir, alarms)
                try:
                    n, max_sessions = 0, 0
                    t0, c0 = time.monotonic(), cpu_s()
                    while (elapsed := time.monotonic() - t0) < args.revoked_s:
                        while n < elapsed * args.picks_per_s:
                            n += 1
                            store.handle(verify(n))
                        max_sessions = max(max_sessions, sessions(su, WRITER))
                        time.sleep(1.0)
                    wall, cpu = time.monotonic() - t0, cpu_s() - c0
                    stats = store.forwarder_stats()
                    print(
                        f"INSERT revoked for {wall:.0f} s, {n} picks handed over: process CPU {cpu:.2f} s "
                        f"({100 * cpu / wall:.2f} % of a core; goal <= 10 %), {stats.attempts} tries, "
                        f"{stats.connections} connection(s) opened, at most {max_sessions} session(s) at the server "
                        f"(goal <= 2), {store.stats().outbox} rows waiting in the outbox"
                    )
                    alarm = alarms.raised.get("history-server")
                    print(f"alarm: {alarm!r}" if alarm else "alarm: NONE raised")
                    su.execute(f"GRANT INSERT ON picks TO {WRITER}")
                    t1 = time.monotonic()
                    sent = store.wait_sent(120)
                    print(f"after GRANT: outbox empty in {time.monotonic() - t1:.1f} s" if sent else "outbox NOT empty")
                finally:
                    store.close()
                counted = su.execute("SELECT count(*), count(DISTINCT id) FROM picks").fetchone()
                rows, unique = counted if counted is not None else (0, 0)
                want = {f"{JOB}/{k}" for k in range(1, n + 1)}
                got = {r[0] for r in su.execute("SELECT id FROM picks").fetchall()}
                print(f"rows at the server {rows}, unique {unique}, of {n} picks; missing {len(want - got)}")
                ok = (
                    cpu / wall <= 0.10
                    and max_sessions <= 2
                    and stats.connections <= 2
                    and alarm is not None
                    and sent
                    and rows == unique == n
                    and got == want
                )
                print("PASS" if ok else "FAIL")
                return 0 if ok else 1
    finally:
        server.close()


if __name__ == "__main__":
    raise SystemExit(main())

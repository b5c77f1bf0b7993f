"""`run-cell history copy --to URL`: a cell's SQLite history into the plant's PostgreSQL.

For a cell that kept its history in SQLite and moves to PostgreSQL (history.url): every row of
every table is sent, in batches, each batch one transaction, with `ON CONFLICT DO NOTHING` on
the row's key, so a copy run twice, or cut short and run again, adds each row once and never
changes a row the server already holds (one the cell wrote there itself after the move). The
server's schema is created or migrated first, as the cell's own store does it; the SQLite file
is opened read-only (the service may go on writing to it; rows it writes after the copy's
snapshot of a table are taken by the next run).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cell.history.db import Database, HistoryError, parse_time
from cell.history.schema import VERSION, migrate, version

# Parents before children (a reader joins picks to jobs); every table of the schema but its version.
TABLES = ("calibrations", "jobs", "picks", "unreachable", "alarms", "commands", "states", "images", "marks")
KEYS = {"marks": "cell"}  # every other table's key is `id`


@dataclass
class TableCopy:
    table: str
    read: int = 0  # rows in the SQLite file
    added: int = 0  # rows the server did not hold yet


def copy_history(
    source: Database,
    target: Database,
    batch_rows: int = 1000,
    progress: Callable[[TableCopy], None] = lambda t: None,
) -> list[TableCopy]:
    """Every row of `source` (SQLite) that `target` (PostgreSQL) lacks; what was read and added per table."""
    if source.dialect != "sqlite" or target.dialect != "postgresql":
        raise HistoryError("history copy: from a SQLite file to a PostgreSQL server only")
    have = version(source)
    if have != VERSION:
        raise HistoryError(
            f"history copy: {source.where} has schema version {have}; this run-cell copies version {VERSION}",
            hint="run the cell once on it with this version (it migrates when opened), then copy"
            if have < VERSION
            else "copy it with the newer run-cell that wrote it",
        )
    migrate(target)
    done = []
    for table in TABLES:
        result = TableCopy(table)
        columns = [str(r[1]) for r in source.execute(f"PRAGMA table_info({table})")]
        times = [c.endswith("_utc") for c in columns]
        key = KEYS.get(table, "id")
        insert = target.sql(
            f"INSERT INTO {table} ({', '.join(columns)}) VALUES ({', '.join('?' for _ in columns)}) "
            f"ON CONFLICT ({key}) DO NOTHING RETURNING {key}"
        )
        last = 0
        while True:
            rows = source.execute(
                f"SELECT rowid, {', '.join(columns)} FROM {table} WHERE rowid > ? ORDER BY rowid LIMIT ?",
                (last, batch_rows),
            )
            if not rows:
                break
            last = int(rows[-1][0])
            params = [tuple(_value(v, t) for v, t in zip(r[1:], times, strict=True)) for r in rows]
            result.read += len(rows)
            result.added += _insert(target, insert, params)
        done.append(result)
        progress(result)
    return done


def _value(value: Any, is_time: bool) -> Any:
    return parse_time(value) if is_time else value


def _insert(target: Database, statement: str, params: list[tuple[Any, ...]]) -> int:
    """One batch in one transaction; the rows the server added (those it held already return nothing)."""
    added = 0
    with target.transaction(), target.conn.cursor() as cur:
        cur.executemany(statement, params, returning=True)
        while True:
            added += len(cur.fetchall())
            if not cur.nextset():
                break
    return added

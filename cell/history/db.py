"""One connection to the history database, SQLite or PostgreSQL, behind the same few calls.

Plain SQL (no ORM): statements are written once with `?` placeholders and `{TIME}`, `{REAL}`
type names; `Database` turns them into the dialect's (`%s`, TIMESTAMPTZ, DOUBLE PRECISION).
Times go in as aware datetimes: PostgreSQL stores them as TIMESTAMPTZ, SQLite as fixed-width
UTC text (`2026-12-01T06:00:00.000000Z`), so text order is time order there too.

The schema is versioned (`schema_version`) and migrated at open, in one transaction (on
PostgreSQL under an advisory lock, so cells starting together migrate once). A database
newer than this code is refused, naming its version.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import sqlite3
import threading
from collections.abc import Iterable, Iterator, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cell.errors import CellError, ConfigError

if TYPE_CHECKING:
    from cell.history.config import HistoryConfig

log = logging.getLogger(__name__)

_SQLITE_TIME = "%Y-%m-%dT%H:%M:%S.%fZ"
_PG_LOCK_KEY = 716_051_016  # the advisory lock the migrations take on PostgreSQL


class HistoryError(CellError):
    """The history store cannot be opened or written."""

    exit_code = 3


class HistoryCorrupt(ConfigError):
    """The database file is damaged (exit 2; the file is named)."""


def sqlite_time(t: datetime) -> str:
    return t.astimezone(UTC).strftime(_SQLITE_TIME)


def parse_time(value: Any) -> datetime | None:
    if value is None or isinstance(value, datetime):
        return value
    text = str(value)
    if text.endswith("Z"):
        text = text[:-1] + "+00:00"
    t = datetime.fromisoformat(text)
    return t if t.tzinfo else t.replace(tzinfo=UTC)


def required_time(value: Any, what: str) -> datetime:
    """The time a column that is never empty holds; HistoryError naming `what` if it holds none."""
    t = parse_time(value)
    if t is None:
        raise HistoryError(f"history: {what} has no time")
    return t


def sqlite_path(url: str) -> Path:
    return Path(url[len("sqlite:///") :])


def redact(url: str) -> str:
    """The URL without a password, for messages."""
    if "://" not in url or "@" not in url:
        return url
    scheme, rest = url.split("://", 1)
    creds, host = rest.rsplit("@", 1)
    user = creds.split(":", 1)[0]
    return f"{scheme}://{user}@{host}"


class Database:
    """A connection with the dialect's placeholders, types and transactions; thread-safe (one lock)."""

    def __init__(self, conn: Any, dialect: str, where: str):
        self.conn, self.dialect, self.where = conn, dialect, where
        self.lock = threading.RLock()

    # ---- statements ---------------------------------------------------------------------
    def sql(self, text: str) -> str:
        if self.dialect == "postgresql":
            text = text.replace("?", "%s")
            return text.format(TIME="TIMESTAMPTZ", REAL="DOUBLE PRECISION", BIGINT="BIGINT")
        return text.format(TIME="TEXT", REAL="REAL", BIGINT="INTEGER")

    def _params(self, params: Sequence[Any]) -> tuple:
        if self.dialect == "sqlite":
            return tuple(sqlite_time(p) if isinstance(p, datetime) else p for p in params)
        return tuple(params)

    def execute(self, text: str, params: Sequence[Any] = ()) -> list[tuple]:
        with self.lock:
            cur = self.conn.execute(self.sql(text), self._params(params))
            try:
                return cur.fetchall() if cur.description is not None else []
            finally:
                cur.close()

    def executemany(self, text: str, rows: Iterable[Sequence[Any]]) -> None:
        with self.lock:
            if self.dialect == "sqlite":
                self.conn.executemany(self.sql(text), [self._params(r) for r in rows])
            else:
                with self.conn.cursor() as cur:
                    cur.executemany(self.sql(text), [tuple(r) for r in rows])

    @contextlib.contextmanager
    def transaction(self) -> Iterator[None]:
        """All or nothing: a failure rolls the whole batch back (never a half-written row)."""
        with self.lock:
            if self.dialect == "sqlite":
                self.conn.execute("BEGIN IMMEDIATE")
                try:
                    yield
                except BaseException:
                    with contextlib.suppress(sqlite3.Error):
                        self.conn.execute("ROLLBACK")
                    raise
                self.conn.execute("COMMIT")
            else:
                with self.conn.transaction():
                    yield

    def close(self) -> None:
        with self.lock, contextlib.suppress(Exception):
            self.conn.close()

    def broken(self) -> bool:
        """The connection is gone (closed, or lost mid-statement): open a new one."""
        return bool(getattr(self.conn, "closed", False) or getattr(self.conn, "broken", False))

    def interrupt(self) -> None:
        """From another thread, without the lock (the owner may be blocked in it): end the
        connection's network I/O at once. The socket is shut down, so a call waiting for an
        answer that will never come fails now ("server closed the connection"); the owner then
        closes the connection. PostgreSQL only."""
        if self.dialect != "postgresql":
            return
        with contextlib.suppress(Exception):
            fd = self.conn.pgconn.socket
            s = socket.socket(fileno=os.dup(fd))  # a duplicate: shutdown acts on the socket, close on the copy
            try:
                s.shutdown(socket.SHUT_RDWR)
            finally:
                s.close()

    def integrity_check(self) -> str:
        """'ok' or what is wrong (SQLite's PRAGMA integrity_check; PostgreSQL keeps its own)."""
        if self.dialect != "sqlite":
            return "ok"
        rows = self.execute("PRAGMA integrity_check")
        return "; ".join(str(r[0]) for r in rows)


# ---- opening -------------------------------------------------------------------------------
def open_sqlite(path: Path, *, readonly: bool = False, on_corrupt: str = "refuse") -> Database:
    """The SQLite file (WAL, synchronous NORMAL: a killed process loses no committed row), checked
    readable; a damaged one is refused or moved aside as `on_corrupt` says."""
    path = Path(path)
    if not readonly:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise HistoryError(
                f"history cannot be written: cannot create {path.parent}: {e.strerror or e}",
                hint="set history.data_dir (or history.url) to a writable folder",
            ) from None
    elif not path.exists():
        raise ConfigError(f"history database {path} does not exist", hint="run the cell once, or set history.url")
    try:
        return _connect_sqlite(path, readonly)
    except sqlite3.DatabaseError as e:
        if readonly or on_corrupt != "move-aside" or not _is_corrupt(e):
            if _is_corrupt(e):
                raise HistoryCorrupt(
                    f"history database {path} is damaged ({e})",
                    hint='move it away, or set history.on_corrupt = "move-aside" to start a new one',
                ) from None
            raise HistoryError(f"history cannot be written: {path}: {e}", hint="check the disk and the file") from None
    aside = path.with_name(f"{path.name}.corrupt-{datetime.now(UTC):%Y%m%dT%H%M%SZ}")
    for suffix in ("", "-wal", "-shm"):
        src = Path(f"{path}{suffix}")
        if src.exists():
            src.rename(Path(f"{aside}{suffix}"))
    log.error("history database %s was damaged: moved to %s; a new one is started", path, aside)
    return _connect_sqlite(path, readonly)


def _is_corrupt(e: sqlite3.DatabaseError) -> bool:
    text = str(e).lower()
    return "not a database" in text or "malformed" in text or "corrupt" in text


def _connect_sqlite(path: Path, readonly: bool) -> Database:
    target = f"file:{path}?mode=ro" if readonly else str(path)
    conn = sqlite3.connect(target, uri=readonly, timeout=30.0, isolation_level=None, check_same_thread=False)
    try:
        if not readonly:
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")
        conn.execute("PRAGMA busy_timeout=30000")
        conn.execute("SELECT count(*) FROM sqlite_master").fetchall()  # reads the header and the schema
    except BaseException:
        conn.close()
        raise
    return Database(conn, "sqlite", str(path))


def libpq_params(url: str, history: HistoryConfig, application_name: str = "pick-cell") -> dict[str, Any]:
    """The connection's timeouts as libpq parameters (they override the URL's; `options` is added to).
    TCP keepalives end a connection whose peer vanished while the cell waits for an answer;
    tcp_user_timeout one whose data goes unacknowledged; statement_timeout has the server cancel a
    statement that runs too long; idle_in_transaction_session_timeout has it end a session that left
    a transaction open (a path gone silent mid-batch: its locks would hold the same rows sent again
    for as long as the server believes the old session alive, hours by default). (A peer that keeps
    the connection up but never answers is caught by the store's own `answer_timeout_s`.)"""
    from psycopg.conninfo import conninfo_to_dict

    given = conninfo_to_dict(url)
    params: dict[str, Any] = {
        "connect_timeout": max(1, round(history.connect_timeout_s)),
        "keepalives": 1,
        "keepalives_idle": history.keepalive_idle_s,
        "keepalives_interval": history.keepalive_interval_s,
        "keepalives_count": history.keepalive_count,
        "tcp_user_timeout": round(history.tcp_user_timeout_s * 1000),
    }
    settings = " ".join(  # none: no `options` at all (a pooler such as PgBouncer may refuse it)
        f"-c {name}={round(seconds * 1000)}"
        for name, seconds in (
            ("statement_timeout", history.statement_timeout_s),
            ("idle_in_transaction_session_timeout", history.idle_in_transaction_timeout_s),
        )
        if seconds > 0
    )
    if settings:
        params["options"] = f"{given['options']} {settings}" if given.get("options") else settings
    if not given.get("application_name"):
        params["application_name"] = application_name
    return params


def open_postgresql(url: str, history: HistoryConfig, application_name: str = "pick-cell") -> Database:
    """A connection to the plant's server with the configured timeouts (`libpq_params`)."""
    import psycopg  # only when the plant's server is used: 0.1 s of import

    try:
        conn = psycopg.connect(url, autocommit=True, **libpq_params(url, history, application_name))
    except psycopg.Error as e:
        raise HistoryUnreachable(f"history server {redact(url)} unreachable: {_first_line(e)}") from None
    return Database(conn, "postgresql", redact(url))


class HistoryUnreachable(HistoryError):
    """The PostgreSQL server cannot be reached (rows wait in the local outbox)."""


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def is_connection_error(e: BaseException) -> bool:
    """A PostgreSQL error that means the server or the connection went away (retry later)."""
    try:
        import psycopg
    except ImportError:
        return False
    return isinstance(e, (psycopg.OperationalError, psycopg.InterfaceError))


def is_row_refused(e: BaseException) -> bool:
    """The server (or the driver, before sending) refuses a row for what it holds: a value out of
    range, a NUL in a text, a CHECK or NOT NULL violated. Sending it again changes nothing. Any
    other error (no permission, disk full, the connection) may pass: the row is kept and retried."""
    try:
        import psycopg
    except ImportError:
        return False
    return isinstance(e, (psycopg.DataError, psycopg.IntegrityError))


def describe(e: BaseException) -> str:
    return _first_line(e)

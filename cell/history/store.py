"""The history store: a subscriber of the cell's event stream that writes jobs, picks, alarms,
commands, calibrations and state changes to a database, off the control thread.

Three threads, none of them the control thread:
- the bus's subscriber thread (`handle`) turns each event into row operations (cell.history.rows)
  and hands a frame worth keeping to the image saver; it only computes, so it keeps up and
  lets go of frames at once;
- the writer takes the pending rows in batches, each batch one transaction (all or nothing,
  never a half-written row), with this cell's mark (the time of its last event) in the same
  transaction; on SQLite straight into the database, on PostgreSQL into a local SQLite outbox;
- on PostgreSQL a forwarder sends the outbox to the server in order, deleting what the server
  committed. While the server cannot be reached rows wait in the outbox (a warning alarm
  says how many); they are sent when it is back. Inserts are keyed by the rows' ids, so a
  batch sent twice (the forwarder killed between the server's commit and the outbox's
  delete) is there once: none lost, none twice.

When rows cannot be written (a full disk, a damaged file) the store says "history cannot be
written: ..." through the cell's hooks: a fault (the job stops safely; `run-cell` exits 3,
the service goes to Error) when `history.required`, a warning alarm otherwise; it keeps the
rows and tries again every `history.retry_s`.

After a crash (`kill -9`) the rows of the last moments may not have been committed. At open,
the service's audit files after this cell's mark are read back and their keyed rows (jobs,
picks, failed and unreachable parts) written again: every pick verified before the crash is
in the store, once.
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
import socket
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from cell.events import (
    BY_KIND,
    Event,
    FaultRaised,
    FrameRef,
    PartFailed,
    PickVerified,
    RunEnded,
)
from cell.history.config import OUTBOX_FILE, HistoryConfig, data_dir, database_url
from cell.history.db import (
    Database,
    HistoryError,
    HistoryUnreachable,
    describe,
    open_postgresql,
    open_sqlite,
    parse_time,
    sqlite_path,
)
from cell.history.images import ImageSaver
from cell.history.rows import KEYED_KINDS, KINDS, STATEMENTS, ImageWanted, Op, RowMaker, image_id
from cell.history.schema import migrate

log = logging.getLogger(__name__)

MAX_PENDING = 500_000  # rows held while the database cannot be written; more are dropped (counted)
_RECONCILE_SLACK = timedelta(seconds=5)
_KIND_RE = re.compile(r'"kind":"([a-z_]+)"')
_OUTBOX_DDL = [
    "CREATE TABLE IF NOT EXISTS outbox (seq INTEGER PRIMARY KEY AUTOINCREMENT, op TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS marks (cell TEXT PRIMARY KEY, last_event_utc TEXT NOT NULL)",
]
EVENT_TYPES = tuple(BY_KIND[k] for k in sorted(KINDS) if k in BY_KIND)


class Hooks:
    """What the store may ask of the cell (cell.assembly.CellHooks); the default only logs."""

    def fault(self, reason: str, hint: str, source: str) -> None:
        log.error("%s: %s (%s)", source, reason, hint)

    def raise_warning(self, key: str, reason: str, hint: str, source: str) -> None:
        log.warning("%s: %s (%s)", source, reason, hint)

    def clear_warning(self, key: str) -> None:
        pass


@dataclass(frozen=True)
class HistoryStats:
    rows_written: int
    rows_pending: int
    rows_lost: int
    outbox: int  # rows waiting for the PostgreSQL server
    images_saved: int
    images_dropped: int
    images_skipped_low_disk: int
    write_error: str


def cell_name(config: HistoryConfig) -> str:
    return config.cell_name or socket.gethostname()


# ---- the outbox's encoding (PostgreSQL mode) ------------------------------------------------
def _encode(op: Op) -> str:
    params = [{"t": p.isoformat()} if isinstance(p, datetime) else p for p in op.params]
    return json.dumps([op.key, params], separators=(",", ":"))


def _decode(text: str) -> Op:
    key, params = json.loads(text)
    return Op(key, tuple(parse_time(p["t"]) if isinstance(p, dict) else p for p in params))


def image_kind(event: Event) -> str:
    """What went wrong that an image is kept for: miss, failed, fault, unknown (parts left); else ""."""
    if isinstance(event, PickVerified) and event.result == "missed":
        return "miss"
    if isinstance(event, PartFailed):
        return "failed"
    if isinstance(event, FaultRaised):
        return "fault"
    if isinstance(event, RunEnded) and event.unknown_left > 0 and event.outcome != "fault":
        return "unknown"
    return ""


class HistoryStore:
    """Open with `HistoryStore.open(config, log_dir, hooks)`; `handle` is the bus subscriber."""

    def __init__(self, config: HistoryConfig, log_dir: Path, hooks: Any = None):
        self.config, self.log_dir = config, Path(log_dir)
        self.hooks = hooks or Hooks()
        self.cell = cell_name(config)
        self.folder = data_dir(config, log_dir)
        self.url = database_url(config, log_dir)
        self.remote_url = self.url if self.url.startswith(("postgresql://", "postgres://")) else ""
        self.local = self._open_local()
        self.rows = RowMaker(self.cell)
        self._pending: deque[tuple[list[Op], datetime]] = deque()
        self._pending_rows = 0
        self._cond = threading.Condition()
        self._busy = False
        self._closing = False
        self.written = self.lost = 0
        self.write_error = ""
        self._faulted = False
        self.images = (
            ImageSaver(
                self.folder / "images",
                config,
                self.cell,
                self._enqueue_ops,
                lambda reason, hint: self.hooks.raise_warning("history-disk", reason, hint, "history"),
                lambda: self.hooks.clear_warning("history-disk"),
            )
            if config.images
            else None
        )
        self.reconcile_skipped = 0  # malformed audit lines skipped by the read-back (logged)
        self.reconciled = self._reconcile()
        self._writer = threading.Thread(target=self._write_loop, name="history-writer", daemon=True)
        self._writer.start()
        self.remote: Database | None = None
        self._forwarder: threading.Thread | None = None
        self._wake_forwarder = threading.Event()
        self.unreachable = ""
        if self.remote_url:
            self._connect_remote()
            self._forwarder = threading.Thread(target=self._forward_loop, name="history-forwarder", daemon=True)
            self._forwarder.start()

    # ---- opening -------------------------------------------------------------------------
    def _open_local(self) -> Database:
        if self.remote_url:
            db = open_sqlite(self.folder / OUTBOX_FILE, on_corrupt=self.config.on_corrupt)
            for statement in _OUTBOX_DDL:
                db.execute(statement)
            return db
        db = open_sqlite(sqlite_path(self.url), on_corrupt=self.config.on_corrupt)
        try:
            migrate(db)
        except Exception as e:
            db.close()
            if isinstance(e, HistoryError):
                raise
            raise HistoryError(f"history cannot be written: {db.where}: {describe(e)}") from None
        return db

    def _connect_remote(self) -> bool:
        try:
            db = open_postgresql(self.remote_url, self.config.connect_timeout_s)
            migrate(db)
        except HistoryUnreachable as e:
            self._unreachable(str(e))
            return False
        except Exception as e:
            self._unreachable(f"history server {self.remote_url.split('@')[-1]}: {describe(e)}")
            return False
        self.remote = db
        return True

    def _unreachable(self, why: str) -> None:
        if why != self.unreachable:
            log.warning("%s; rows wait in %s", why, self.folder / OUTBOX_FILE)
        self.unreachable = why
        self.hooks.raise_warning(
            "history-server",
            f"{why}: rows wait in the local queue ({self._outbox_count()})",
            "check the network and the history server; the cell keeps picking",
            "history",
        )

    @staticmethod
    def wants_frame(event: Event) -> bool:
        """For the bus: the history keeps the frames of what went wrong only (so its queue never holds
        the frames of good picks)."""
        return bool(image_kind(event))

    # ---- the subscriber (the bus's thread) ----------------------------------------------------
    def handle(self, event: Event) -> None:
        record = {"kind": event.kind, "time": event.time_utc, "job": event.job_id or "", **event.record()}
        wanted = self._image_for(event)
        ops = self.rows.ops(record, wanted)
        if ops:
            self._enqueue(ops, event.time_utc)

    def _image_for(self, event: Event) -> ImageWanted | None:
        if self.images is None:
            return None
        ref: FrameRef | None = getattr(event, "ref", None)
        if ref is None or not event.job_id:
            return None
        kind = image_kind(event)
        if not kind:
            return None
        wanted = ImageWanted(image_id(event.job_id, ref.frame_no), kind, event.job_id, getattr(event, "pick_id", ""))
        return wanted if self.images.offer(wanted, ref, event.time_utc) else None

    def _enqueue_ops(self, ops: list[Op]) -> None:
        self._enqueue(ops, None)

    def _enqueue(self, ops: list[Op], t: datetime | None) -> None:
        with self._cond:
            if self._pending_rows >= MAX_PENDING:
                self.lost += len(ops)
                return
            self._pending.append((ops, t or datetime.now(UTC)))
            self._pending_rows += len(ops)
            self._cond.notify()

    # ---- the writer --------------------------------------------------------------------------------
    def _take(self) -> list[tuple[list[Op], datetime]]:
        batch, rows = [], 0
        while self._pending and (rows == 0 or rows + len(self._pending[0][0]) <= self.config.batch_max_rows):
            item = self._pending.popleft()
            batch.append(item)
            rows += len(item[0])
        return batch

    def _write_loop(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._closing:
                    self._cond.wait()
                if not self._pending:
                    return
                batch = self._take()
                self._busy = True
            try:
                self._write(batch)
            except Exception as e:
                with self._cond:
                    self._pending.extendleft(reversed(batch))  # kept, in order, for the next try
                    self._busy = False
                    self._cond.notify_all()
                self._write_failed(e)
                with self._cond:
                    if self._closing:
                        return  # close() says how many rows were left
                    self._cond.wait(self.config.retry_s)
                continue
            n = sum(len(ops) for ops, _ in batch)
            with self._cond:
                self._pending_rows -= n
                self.written += n
                self._busy = False
                self._cond.notify_all()
            if self.write_error:
                self._write_recovered()

    def _write(self, batch: list[tuple[list[Op], datetime]]) -> None:
        ops = [op for item, _ in batch for op in item]
        last = max(t for _, t in batch)
        db = self.local
        with db.transaction():
            if self.remote_url:
                db.executemany("INSERT INTO outbox (op) VALUES (?)", [(_encode(op),) for op in ops])
            else:
                _apply(db, ops)
            db.execute(STATEMENTS["mark"], (self.cell, last))
        if self.remote_url:
            self._wake_forwarder.set()

    def _write_failed(self, e: Exception) -> None:
        reason = f"history cannot be written: {self.local.where}: {describe(e)}"
        hint = "free space on the data folder's disk (history.data_dir) or fix the database"
        first = not self.write_error
        self.write_error = reason
        if first:
            log.error("%s", reason)
        if self.config.required:
            if not self._faulted:
                self._faulted = True
                self.hooks.fault(reason, hint, "history")
        else:
            self.hooks.raise_warning(
                "history", reason, hint + "; the cell keeps picking without its history", "history"
            )

    def _write_recovered(self) -> None:
        log.info("history: written again after %s", self.write_error)
        self.write_error = ""
        self._faulted = False
        if not self.config.required:
            self.hooks.clear_warning("history")

    # ---- the forwarder (PostgreSQL) ---------------------------------------------------------------
    def _outbox_count(self) -> int:
        try:
            return int(self.local.execute("SELECT count(*) FROM outbox")[0][0])
        except Exception:
            return -1

    def _forward_loop(self) -> None:
        while True:
            if self.remote is None and not self._connect_remote():
                if self._wait_forwarder(self.config.retry_s):
                    return
                continue
            try:
                sent = self._forward_once()
            except Exception as e:
                with contextlib.suppress(Exception):
                    self.remote.close()  # type: ignore[union-attr]
                self.remote = None
                self._unreachable(f"history server {self.remote_url.split('@')[-1]}: {describe(e)}")
                continue
            if sent:
                continue
            if self.unreachable:
                self.unreachable = ""
                log.info("history server reachable again: the local queue is sent")
                self.hooks.clear_warning("history-server")
            if self._wait_forwarder(None):
                return

    def _wait_forwarder(self, timeout_s: float | None) -> bool:
        """Wait for rows (or the timeout); True when the store is closing and nothing is left to send."""
        self._wake_forwarder.wait(timeout_s if timeout_s is not None else 1.0)
        self._wake_forwarder.clear()
        return self._closing and (self.remote is None or self._outbox_count() == 0)

    def _forward_once(self) -> int:
        rows = self.local.execute("SELECT seq, op FROM outbox ORDER BY seq LIMIT ?", (self.config.batch_max_rows,))
        if not rows:
            return 0
        remote = self.remote
        assert remote is not None
        with remote.transaction():
            _apply(remote, [_decode(text) for _, text in rows])
        last = rows[-1][0]
        with self.local.transaction():
            self.local.execute("DELETE FROM outbox WHERE seq <= ?", (last,))
        return len(rows)

    # ---- after a crash: the audit read back ---------------------------------------------------------
    def mark(self) -> datetime | None:
        rows = self.local.execute("SELECT last_event_utc FROM marks WHERE cell = ?", (self.cell,))
        return parse_time(rows[0][0]) if rows else None

    def _reconcile(self) -> int:
        """Rows of keyed kinds from the service's audit files since this cell's mark (a crash may
        have lost the last batch); written at once, before anything reads the store. Returns how many."""
        mark = self.mark()
        if mark is None or not self.log_dir.is_dir():
            return 0
        since = mark - _RECONCILE_SLACK
        ops: list[Op] = []
        maker = RowMaker(self.cell)
        for path in sorted(self.log_dir.glob("cell-*.jsonl")):
            try:
                if path.stat().st_mtime < since.timestamp() - 60:
                    continue
                with open(path, encoding="utf-8") as f:
                    read, skipped = _reconcile_file(f, since, maker, path)
                ops.extend(read)
                self.reconcile_skipped += skipped
            except OSError as e:
                log.warning("history: cannot read %s back: %s", path, e)
        if self.reconcile_skipped:
            log.warning(
                "history: %d malformed audit lines skipped while reading back after %s (the rest is read back)",
                self.reconcile_skipped,
                mark.isoformat(),
            )
        if ops:
            with self.local.transaction():
                if self.remote_url:
                    self.local.executemany("INSERT INTO outbox (op) VALUES (?)", [(_encode(op),) for op in ops])
                else:
                    _apply(self.local, ops)
            log.info("history: %d rows read back from the audit files after %s", len(ops), mark.isoformat())
        return len(ops)

    # ---- after a restart: the counters -------------------------------------------------------------
    def unsent(self) -> list[Op]:
        """The rows still in the PostgreSQL outbox (none on SQLite: the database is written directly)."""
        if not self.remote_url:
            return []
        return [_decode(text) for (text,) in self.local.execute("SELECT op FROM outbox ORDER BY seq")]

    def shift_view(self, reader: Any, since: datetime, until: datetime) -> tuple[Any, list[Any]]:
        """The shift's counters and the last picks (cell.history.query.HistoryReader's) as the store
        holds them once its outbox is sent: after an outage and a restart the server lacks the rows
        still in the outbox, so its rows of the span are copied into a database in memory and the
        unsent rows applied over them, as the server will apply them (keyed, so none counts twice)."""
        ops = self.unsent()
        if not ops:
            return reader.counters(since, until), reader.last_picks()
        from cell.history.query import PICK_COLUMNS, HistoryReader, PickFilter

        mem = Database(sqlite3.connect(":memory:", isolation_level=None, check_same_thread=False), "sqlite", "memory")
        try:
            migrate(mem)
            src: Database = reader.db
            where, params = PickFilter(since, until).where(reader.cell)
            cols = ", ".join(PICK_COLUMNS)
            newest = (
                f"SELECT {cols} FROM picks{PickFilter().where(reader.cell)[0]} ORDER BY time_utc DESC, id DESC LIMIT 20"
            )
            jobs_where = "WHERE start_utc >= ? AND start_utc < ?" + (" AND cell = ?" if reader.cell else "")
            copies = [
                (f"INSERT OR IGNORE INTO picks ({cols})", src.execute(f"SELECT {cols} FROM picks{where}", params)),
                (f"INSERT OR IGNORE INTO picks ({cols})", src.execute(newest, PickFilter().where(reader.cell)[1])),
                ("INSERT OR IGNORE INTO unreachable", src.execute(f"SELECT * FROM unreachable{where}", params)),
                (
                    "INSERT OR IGNORE INTO jobs",
                    src.execute(
                        f"SELECT * FROM jobs {jobs_where}", [since, until] + ([reader.cell] if reader.cell else [])
                    ),
                ),
            ]
            with mem.transaction():
                for insert, rows in copies:
                    if rows:
                        mem.executemany(f"{insert} VALUES ({', '.join('?' * len(rows[0]))})", rows)
                _apply(mem, ops)
            view = HistoryReader(mem, reader.cell)
            return view.counters(since, until), view.last_picks()
        finally:
            mem.close()

    # ---- state and control --------------------------------------------------------------------------
    def stats(self) -> HistoryStats:
        images = self.images.stats if self.images is not None else None
        return HistoryStats(
            self.written,
            self._pending_rows,
            self.lost,
            self._outbox_count() if self.remote_url else 0,
            images.saved if images else 0,
            images.dropped if images else 0,
            images.skipped_low_disk if images else 0,
            self.write_error,
        )

    def wait_idle(self, timeout_s: float) -> bool:
        """True once every row handed over so far is written (to the database, or the outbox)."""
        deadline = time.monotonic() + timeout_s
        if self.images is not None and not self.images.wait_idle(timeout_s):
            return False
        with self._cond:
            while self._pending or self._busy:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def wait_sent(self, timeout_s: float) -> bool:
        """PostgreSQL: True once the outbox is empty (everything on the server)."""
        deadline = time.monotonic() + timeout_s
        if not self.wait_idle(timeout_s):
            return False
        while self.remote_url and self._outbox_count() != 0:
            if time.monotonic() > deadline:
                return False
            self._wake_forwarder.set()
            time.sleep(0.05)
        return True

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is pending within the time given (images first: their rows follow), then close.
        On PostgreSQL, what the server has not taken stays in the outbox for the next start."""
        if self.images is not None:
            self.images.close(timeout_s / 2)
        self.wait_idle(timeout_s)
        with self._cond:
            self._closing = True
            left = self._pending_rows
            self._cond.notify_all()
        self._writer.join(timeout_s)
        if left:
            log.error("history: %d rows not written at close (%s)", left, self.write_error or "timed out")
        if self._forwarder is not None:
            self._wake_forwarder.set()
            self._forwarder.join(timeout_s)
        if self.remote is not None:
            self.remote.close()
        self.local.close()


def _apply(db: Database, ops: Iterable[Op]) -> None:
    """Run the ops in order, consecutive ones of the same statement as one executemany."""
    run: list[tuple] = []
    key = ""
    for op in ops:
        if op.key != key and run:
            db.executemany(STATEMENTS[key], run)
            run = []
        key = op.key
        run.append(op.params)
    if run:
        db.executemany(STATEMENTS[key], run)


def _reconcile_file(
    lines: Iterable[str], since: datetime, maker: RowMaker, where: Path | str = "an audit file"
) -> tuple[list[Op], int]:
    """The keyed rows of one audit file's lines since `since`, and how many lines were skipped as
    malformed (a field missing or of the wrong type: logged, never a reason not to start)."""
    ops: list[Op] = []
    skipped = 0
    for n, line in enumerate(lines, 1):
        m = _KIND_RE.search(line)
        if m is None or m.group(1) not in KEYED_KINDS:
            continue
        try:
            e = json.loads(line)
        except json.JSONDecodeError:
            continue  # a torn last line
        try:
            if not isinstance(e, dict):
                raise TypeError(f"a {type(e).__name__}, not an object")
            t = parse_time(e.get("t_utc"))
            if t is None or t < since:
                continue
            e["time"] = t
            ops.extend(maker.ops(e))
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            skipped += 1
            if skipped <= 3:
                what = f"no {err}" if isinstance(err, KeyError) else str(err)
                log.warning("history: %s line %d (%s) skipped while reading back: %s", where, n, m.group(1), what)
    return ops, skipped

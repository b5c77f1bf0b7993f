"""The history store: a subscriber of the cell's event stream that writes jobs, picks, alarms,
commands, calibrations and state changes to a database, off the control thread.

Three threads, none of them the control thread:
- the bus's subscriber thread (`handle`) turns each event into row operations (cell.history.rows)
  and hands a frame worth keeping to the image saver; it only computes, so it keeps up and
  lets go of frames at once;
- the writer (a cell.core.worker.QueueWorker, as the image saver and the bus's subscribers)
  takes the pending rows in batches, each batch one transaction (all or nothing,
  never a half-written row), with this cell's mark (the time of its last event) in the same
  transaction; on SQLite straight into the database, on PostgreSQL into a local SQLite outbox;
- on PostgreSQL a forwarder sends the outbox to the server in order, deleting what the server
  committed. While the server cannot be reached, or refuses the rows (INSERT revoked, disk
  full), or does not answer, rows wait in the outbox (a warning alarm says why); the
  forwarder keeps its one connection while it is sound and tries again after a wait that
  doubles with each failure (`retry_initial_s` up to `retry_max_s`, with jitter). Inserts are
  keyed by the rows' ids, so a batch sent twice (the forwarder killed between the server's
  commit and the outbox's delete) is there once: none lost, none twice. A row the server
  refuses for what it holds (a data or integrity error) is moved to the outbox's dead-letter
  table (counted, a warning alarm, `run-cell history --dead-letter` lists it) and the rows
  behind it go on. A watchdog drops a connection that gives no answer within
  `answer_timeout_s`; closing the store interrupts the forwarder's network I/O and returns in
  bounded time, what is unsent staying in the outbox for the next start.

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
import random
import re
import socket
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from cell.audit import is_rehearsal
from cell.core.events import BY_KIND, Event, FaultRaised, FrameRef, PartFailed, PickVerified, RunEnded
from cell.core.worker import QueueWorker
from cell.history.config import OUTBOX_FILE, HistoryConfig, data_dir, database_url
from cell.history.db import (
    Database,
    HistoryError,
    HistoryUnreachable,
    describe,
    is_row_refused,
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
    # rows the server refused for what they hold: kept here, never sent again, never lost
    """CREATE TABLE IF NOT EXISTS dead_letter (seq INTEGER PRIMARY KEY AUTOINCREMENT, outbox_seq INTEGER NOT NULL,
        refused_utc TEXT NOT NULL, op TEXT NOT NULL, error TEXT NOT NULL)""",
]
EVENT_TYPES = tuple(BY_KIND[k] for k in sorted(KINDS) if k in BY_KIND)


_Pending = tuple[list[Op], datetime]  # a handful of row operations, and the time of the event they record


class _RowQueue:
    """The writer's queue (cell.core.worker.WorkQueue): row operations waiting, bounded by rows
    (MAX_PENDING, the batch being written counted until it is); `take` gives one transaction's
    worth, up to batch_max_rows (at least one item)."""

    def __init__(self, batch_max_rows: int):
        self.batch_max_rows = batch_max_rows
        self.items: deque[_Pending] = deque()
        self.pending_rows = 0  # queued or being written
        self.lost = 0  # rows dropped: MAX_PENDING were pending
        self._lock = threading.Lock()  # `done` comes from the writer's thread without the worker's lock

    def put(self, item: _Pending) -> bool:
        with self._lock:
            if self.pending_rows >= MAX_PENDING:
                self.lost += len(item[0])
                return False
            self.items.append(item)
            self.pending_rows += len(item[0])
            return True

    def take(self) -> list[_Pending]:
        batch, rows = [], 0
        while self.items and (rows == 0 or rows + len(self.items[0][0]) <= self.batch_max_rows):
            item = self.items.popleft()
            batch.append(item)
            rows += len(item[0])
        return batch

    def done(self, rows: int) -> None:
        with self._lock:
            self.pending_rows -= rows

    def __len__(self) -> int:
        return len(self.items)

    def clear(self) -> int:
        """At close: the items are let go, their rows still counted as pending (not written)."""
        n = len(self.items)
        self.items.clear()
        return n


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
    dead_letter: int = 0  # rows the PostgreSQL server refused, kept aside in the outbox file


@dataclass(frozen=True)
class ForwarderStats:
    """What the PostgreSQL forwarder did since the store opened (for tests and diagnosis)."""

    attempts: int  # batches sent to the server (each one transaction)
    connections: int  # connections opened or tried
    failures: int  # attempts that failed
    waits_s: tuple[float, ...]  # the waits chosen after the latest failures, oldest first (at most 64)
    dead_letter: int  # rows moved to the dead-letter table


# this cell's other forwarder sessions the server holds in an open transaction, unchanged for over N
# seconds (idle in it, or stuck part way through a message: 'active', waiting to read), ended
STALE_SESSIONS_SQL = (
    "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE application_name = ? AND pid <> pg_backend_pid() "
    "AND state <> 'idle' AND xact_start IS NOT NULL AND state_change < now() - make_interval(secs => ?)"
)


def cell_name(config: HistoryConfig) -> str:
    return config.cell_name or socket.gethostname()


# ---- the outbox's encoding (PostgreSQL mode) ------------------------------------------------
def _encode(op: Op) -> str:
    params = [{"t": p.isoformat()} if isinstance(p, datetime) else p for p in op.params]
    return json.dumps([op.key, params], separators=(",", ":"))


def _decode(text: str) -> Op:
    key, params = json.loads(text)
    return Op(key, tuple(parse_time(p["t"]) if isinstance(p, dict) else p for p in params))


def backoff_s(failures: int, initial_s: float, max_s: float) -> float:
    """The wait after `failures` failures in a row: initial_s doubled for each after the first, at
    most max_s, drawn between half and all of it (cells that lost the server together do not all
    come back at once)."""
    full = min(max_s, initial_s * 2 ** min(failures - 1, 60))
    return full * random.uniform(0.5, 1.0)


def read_dead_letter(outbox: Path) -> list[dict[str, Any]]:
    """The rows the PostgreSQL server refused, oldest first (`run-cell history --dead-letter`)."""
    if not outbox.exists():
        return []
    db = open_sqlite(outbox, readonly=True)
    try:
        if not db.execute("SELECT name FROM sqlite_master WHERE name = 'dead_letter'"):
            return []
        rows = db.execute("SELECT seq, refused_utc, op, error FROM dead_letter ORDER BY seq")
    finally:
        db.close()
    out = []
    for seq, refused, text, error in rows:
        try:
            key, params = json.loads(text)
        except (ValueError, TypeError):
            key, params = "", text
        out.append({"seq": seq, "refused_utc": refused, "statement": key, "params": params, "error": error})
    return out


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

    def __init__(self, config: HistoryConfig, log_dir: Path, hooks: Any = None, rehearsal: bool = False):
        self.config, self.log_dir = config, Path(log_dir)
        self.rehearsal = rehearsal  # a dry run's store: reads back only audit lines marked "rehearsal"
        self.hooks = hooks or Hooks()
        self.cell = cell_name(config)
        self.folder = data_dir(config, log_dir)
        self.url = database_url(config, log_dir)
        self.remote_url = self.url if self.url.startswith(("postgresql://", "postgres://")) else ""
        self.local = self._open_local()
        self.rows = RowMaker(self.cell)
        self._rows = _RowQueue(config.batch_max_rows)
        self._gave_up = False  # a write failed while closing: the rows left are not tried again
        self.written = 0
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
        self._writer: QueueWorker[_Pending, list[_Pending]] = QueueWorker(
            "history-writer", self._write_batch, self._rows, label="history: writer"
        )
        self.remote: Database | None = None  # the forwarder's connection (only it does I/O on it)
        self._forwarder: threading.Thread | None = None
        self._watchdog: threading.Thread | None = None
        self._wake_forwarder = threading.Event()
        self._first_try = threading.Event()  # the forwarder's first connection made (or failed)
        self._stop_forwarder = threading.Event()  # closing: no further tries, no waits
        # guards `remote`'s replacement, the I/O in progress and the stall flag; never held across I/O
        self._io = threading.Condition()
        self._io_since: float | None = None
        self._stalled = False
        self._watching = True
        self.unreachable = ""
        self.forward_attempts = self.forward_connections = self.forward_failures = self.dead_lettered = 0
        self._waits: deque[float] = deque(maxlen=64)
        if self.remote_url:  # connecting is the forwarder's: opening never waits on the network
            kept = self._dead_letter_count()
            if kept:
                log.warning(
                    "history: %d rows the server refused are kept in %s (run-cell history --dead-letter)",
                    kept,
                    self.folder / OUTBOX_FILE,
                )
            self._forwarder = threading.Thread(target=self._forward_loop, name="history-forwarder", daemon=True)
            self._watchdog = threading.Thread(target=self._watch_loop, name="history-watchdog", daemon=True)
            self._forwarder.start()
            self._watchdog.start()
            # the first connection's schema is there when open returns (readers may need it); a server
            # that cannot be reached delays the start by connect_timeout_s at most, as before
            self._first_try.wait(self.config.connect_timeout_s + 1.0)

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

    def _connect_remote(self) -> Database:
        """A new connection (bounded by connect_timeout_s), the schema migrated on it; raises."""
        self.forward_connections += 1
        db = open_postgresql(self.remote_url, self.config, self.session_name)
        with self._io:
            if self._stop_forwarder.is_set():
                db.close()
                raise HistoryUnreachable("history: closing")
            self.remote = db  # from here on close() and the watchdog can interrupt it
        try:
            with self._network_io():
                self._end_stale_sessions(db)
                migrate(db)
        except BaseException:
            self._drop_remote()  # the next try migrates on a new connection
            raise
        self._first_try.set()
        return db

    @property
    def session_name(self) -> str:
        """The forwarder's application_name at the server: this cell's, and only its forwarder's."""
        return f"pick-cell history {self.cell}"[:63]

    def _end_stale_sessions(self, remote: Database) -> None:
        """End this cell's own earlier forwarder sessions that the server still holds in an open
        transaction: a path that went silent in the middle of a batch leaves one behind, alive as far
        as the server's TCP can tell, and its locks make the same rows, sent again, wait for hours. The
        server ends such a session itself after idle_in_transaction_timeout_s, but not one stuck part
        way through a message (it shows as active, reading); so at each connect and after each failed
        try the forwarder ends the other sessions of its own name whose transaction has not moved for
        longer than that (there is one forwarder per cell). Never fails the try."""
        limit_s = self.config.idle_in_transaction_timeout_s
        if limit_s <= 0:
            return
        try:
            ended = remote.execute(STALE_SESSIONS_SQL, (self.session_name, limit_s))
        except Exception as e:  # e.g. a server that hides other sessions: the server's own timeout is left
            if remote.broken():
                raise
            log.info("history: could not look for this cell's stale sessions at the server: %s", describe(e))
            return
        if n := sum(1 for (done,) in ended if done):
            log.warning(
                "history: ended %d earlier session(s) of this cell that the server still held in an open "
                "transaction for over %g s (a path that went silent mid-batch)",
                n,
                limit_s,
            )

    def _drop_remote(self) -> None:
        with self._io:
            db, self.remote = self.remote, None
        if db is not None:
            db.close()

    @contextlib.contextmanager
    def _network_io(self) -> Iterator[None]:
        """Marks the forwarder's wait for the server, for the watchdog (answer_timeout_s)."""
        with self._io:
            self._io_since = time.monotonic()
            self._io.notify_all()
        try:
            yield
        finally:
            with self._io:
                self._io_since = None

    def _watch_loop(self) -> None:
        """A connection that gives no answer within answer_timeout_s (half-open, a silent proxy:
        TCP keeps it up) is interrupted; the forwarder then says so and tries again later."""
        with self._io:
            while self._watching:
                if self._io_since is None:
                    self._io.wait()
                    continue
                left = self._io_since + self.config.answer_timeout_s - time.monotonic()
                if left > 0:
                    self._io.wait(left)
                    continue
                self._io_since = None
                self._stalled = True
                if self.remote is not None:
                    self.remote.interrupt()  # a socket shutdown: does not block

    def _unreachable(self, why: str, hint: str = "") -> None:
        """The server failed; the rows wait. Logged and raised once for each distinct reason (each
        alarm is itself a row: one raised at every retry would grow the queue it reports)."""
        if why == self.unreachable:
            return
        log.warning("%s; rows wait in %s", why, self.folder / OUTBOX_FILE)
        self.unreachable = why
        self.hooks.raise_warning(
            "history-server",
            f"{why}: rows wait in the local queue ({self._outbox_count()})",
            hint or "check the network and the history server; the cell keeps picking",
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
        self._writer.offer((ops, t or datetime.now(UTC)))  # past MAX_PENDING rows: dropped, counted as lost

    @property
    def lost(self) -> int:
        return self._rows.lost

    # ---- the writer (its QueueWorker's thread) ------------------------------------------------------
    def _write_batch(self, batch: list[_Pending]) -> None:
        """One transaction's worth of rows; while it cannot be written it is kept and tried again
        every retry_s, in order (nothing behind it goes first), until the store closes."""
        while not self._gave_up:
            try:
                self._write(batch)
            except Exception as e:
                self._write_failed(e)
                if self._writer.closing_wait(self.config.retry_s):
                    self._gave_up = True  # close() says how many rows were left
                continue
            n = sum(len(ops) for ops, _ in batch)
            self._rows.done(n)
            self.written += n
            if self.write_error:
                self._write_recovered()
            return

    def _write(self, batch: list[_Pending]) -> None:
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

    def _dead_letter_count(self) -> int:
        try:
            return int(self.local.execute("SELECT count(*) FROM dead_letter")[0][0])
        except Exception:
            return -1

    def _forward_loop(self) -> None:
        failures = 0
        try:
            while True:
                try:
                    remote = self.remote or self._connect_remote()
                    if failures:  # a try blocked on a stale session's locks fails by statement_timeout_s
                        with self._network_io():
                            self._end_stale_sessions(remote)
                    sent = self._forward_once(remote)
                except Exception as e:
                    if self._stop_forwarder.is_set():
                        return  # closing: what is unsent stays in the outbox
                    failures += 1
                    self._server_failed(e)
                    self._first_try.set()
                    wait_s = backoff_s(failures, self.config.retry_initial_s, self.config.retry_max_s)
                    self._waits.append(wait_s)
                    if self._stop_forwarder.wait(wait_s):
                        return
                    continue
                if failures or self.unreachable:
                    failures = 0
                    self._server_back()
                if sent:
                    continue
                if self._stop_forwarder.is_set():
                    return  # everything sent
                self._wake_forwarder.wait()
                self._wake_forwarder.clear()
        except Exception as e:  # the outbox itself (closed under it): nothing more to do
            if not self._stop_forwarder.is_set():
                log.error("history: the forwarder stopped: %s", describe(e))
        finally:
            self._drop_remote()

    def _server_failed(self, e: Exception) -> None:
        """Count, drop a connection that is gone (keep a sound one: a refused INSERT or a full disk
        leave it usable), and say why the rows wait."""
        self.forward_failures += 1
        with self._io:
            stalled, self._stalled = self._stalled, False
        server = self.remote_url.split("@")[-1]
        if stalled or self.remote is None or self.remote.broken():
            self._drop_remote()
        if stalled:
            why = f"history server {server} gave no answer within {self.config.answer_timeout_s:g} s (answer_timeout_s)"
            hint = "check the network path to the history server; the connection is dropped and tried again"
        elif isinstance(e, HistoryUnreachable):
            why, hint = str(e), ""
        else:
            why = f"history server {server}: {describe(e)}"
            hint = (
                "grant the cell's database role INSERT, UPDATE and SELECT on the history tables; the cell keeps picking"
                if "permission denied" in why
                else ""
            )
        self._unreachable(why, hint)

    def _server_back(self) -> None:
        if self.unreachable:
            self.unreachable = ""
            log.info("history server reachable again: the local queue is sent")
            self.hooks.clear_warning("history-server")

    def _forward_once(self, remote: Database) -> int:
        """Send one batch of the outbox in one transaction; rows the server refuses for what they
        hold go to the dead-letter table (then the batch is sent row by row, each in a savepoint).
        Returns how many outbox rows were taken. Any other error leaves the outbox as it was."""
        rows = self.local.execute("SELECT seq, op FROM outbox ORDER BY seq LIMIT ?", (self.config.batch_max_rows,))
        if not rows:
            return 0
        refused: list[tuple[int, str, str]] = []
        ops: list[tuple[int, str, Op]] = []
        for seq, text in rows:
            try:
                op = _decode(text)
                if op.key not in STATEMENTS:
                    raise KeyError(f"unknown statement {op.key!r}")
            except (ValueError, KeyError, TypeError) as e:
                refused.append((seq, text, f"not a row this cell can send: {e}"))
                continue
            ops.append((seq, text, op))
        self.forward_attempts += 1
        with self._network_io():
            try:
                with remote.transaction():
                    _apply(remote, [op for _, _, op in ops])
            except Exception as e:
                if not is_row_refused(e) or remote.broken():
                    raise
                refused.extend(self._send_row_by_row(remote, ops))
        last = rows[-1][0]
        with self.local.transaction():
            if refused:
                now = datetime.now(UTC).isoformat()
                self.local.executemany(
                    "INSERT INTO dead_letter (outbox_seq, refused_utc, op, error) VALUES (?, ?, ?, ?)",
                    [(seq, now, text, error) for seq, text, error in refused],
                )
            self.local.execute("DELETE FROM outbox WHERE seq <= ?", (last,))
        if refused:
            self._dead_lettered(refused)
        return len(rows)

    def _send_row_by_row(self, remote: Database, ops: list[tuple[int, str, Op]]) -> list[tuple[int, str, str]]:
        """The batch again, in order, each row in a savepoint: the refused ones roll back alone."""
        refused: list[tuple[int, str, str]] = []
        with remote.transaction():
            for seq, text, op in ops:
                try:
                    with remote.transaction():
                        _apply(remote, [op])
                except Exception as e:
                    if not is_row_refused(e) or remote.broken():
                        raise
                    refused.append((seq, text, describe(e)))
        return refused

    def _dead_lettered(self, refused: list[tuple[int, str, str]]) -> None:
        self.dead_lettered += len(refused)
        where = self.folder / OUTBOX_FILE
        for seq, text, error in refused:
            log.error(
                "history: the server refused row %d (%s): %s; kept in %s (dead_letter)", seq, text[:200], error, where
            )
        # the reason names the error, not a count: a refused alarm row must not raise a new alarm each time
        self.hooks.raise_warning(
            "history-dead-letter",
            f"the history server refused a row: {refused[-1][2]}; it is kept aside in {where}, not sent again",
            "list the refused rows with `run-cell history --dead-letter`; fix the database's rules or the data",
            "history",
        )

    def forwarder_stats(self) -> ForwarderStats:
        return ForwarderStats(
            self.forward_attempts,
            self.forward_connections,
            self.forward_failures,
            tuple(self._waits),
            self.dead_lettered,
        )

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
                    read, skipped = _reconcile_file(f, since, maker, path, self.rehearsal)
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
            self._rows.pending_rows,
            self.lost,
            self._outbox_count() if self.remote_url else 0,
            images.saved if images else 0,
            images.dropped if images else 0,
            images.skipped_low_disk if images else 0,
            self.write_error,
            self._dead_letter_count() if self.remote_url else 0,
        )

    def wait_idle(self, timeout_s: float) -> bool:
        """True once every row handed over so far is written (to the database, or the outbox)."""
        deadline = time.monotonic() + timeout_s
        if self.images is not None and not self.images.wait_idle(timeout_s):
            return False
        return self._writer.wait_idle(max(deadline - time.monotonic(), 0.0))

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
        On PostgreSQL, what the server has not taken stays in the outbox for the next start: the
        forwarder sends what it can within timeout_s, then its network I/O is interrupted: the
        forwarder's part ends within timeout_s + 1 s whatever the network does (close never waits
        on a lock held across network I/O); the local parts (images, writer) each within timeout_s."""
        if self.images is not None:
            self.images.close(timeout_s)
        self.wait_idle(timeout_s)
        self._writer.close(timeout_s)  # a write failing now is not tried again
        left = self._rows.pending_rows
        if left:
            log.error("history: %d rows not written at close (%s)", left, self.write_error or "timed out")
        forwarder_done = True
        if self._forwarder is not None:
            forwarder_done = self._close_forwarder(time.monotonic() + timeout_s)
        if forwarder_done:
            self.local.close()
        # else: the forwarder is still connecting (connect_timeout_s); it finds the store closing and
        # ends; the outbox's file is closed with the process (everything in it is committed)

    def _close_forwarder(self, deadline: float) -> bool:
        """True once the forwarder has ended (it closes its own connection)."""
        assert self._forwarder is not None
        self._stop_forwarder.set()  # no further tries; a sound connection still sends what is left
        self._wake_forwarder.set()
        self._forwarder.join(max(0.0, deadline - time.monotonic()))
        if self._forwarder.is_alive():
            with self._io:
                if self.remote is not None:
                    self.remote.interrupt()
            self._forwarder.join(1.0)
        with self._io:
            self._watching = False
            self._io.notify_all()
        unsent = self._outbox_count()
        if unsent > 0:
            why = self.unreachable or "the server did not take them in time"
            log.warning("history: %d rows wait in %s for the next start (%s)", unsent, self.folder / OUTBOX_FILE, why)
        if self._forwarder.is_alive():
            log.warning("history: the forwarder is still connecting to %s; left behind", self.remote_url.split("@")[-1])
            return False
        return True


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
    lines: Iterable[str],
    since: datetime,
    maker: RowMaker,
    where: Path | str = "an audit file",
    rehearsal: bool = False,
) -> tuple[list[Op], int]:
    """The keyed rows of one audit file's lines since `since`, and how many lines were skipped as
    malformed (a field missing or of the wrong type: logged, never a reason not to start). Only the
    lines of the store's kind: a rehearsal's (marked "rehearsal": true) or production's (unmarked)."""
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
            if is_rehearsal(e) != rehearsal:
                continue  # the other store's
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

"""`[history]`: where the record of every shift is kept, and how much of what went wrong is kept
as images. Mounted on CellConfig as `history`."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from drivers.config import Strict

DB_FILE = "history.sqlite"
OUTBOX_FILE = "history-outbox.sqlite"
REHEARSAL_DIR = "rehearsal"  # a dry run's (and the demo's) own store: data/rehearsal/history.sqlite


class HistoryConfig(Strict):
    """The history store: a database the plant can query (SQLite here, or the plant's PostgreSQL)."""

    enabled: bool = Field(True, description="false: no history store (counters come from the audit files)")
    url: str = Field(
        "",
        description="sqlite:///PATH or postgresql://USER@HOST:PORT/DB; empty: sqlite:/// + data_dir/history.sqlite",
    )
    data_dir: Path | None = Field(
        None,
        description="the store's folder (database, images, PostgreSQL outbox); default: `data` beside run.log_dir",
    )
    required: bool = Field(
        True,
        description="true: a cell that cannot write its history stops safely (a fault); false: it keeps "
        "picking and raises a warning alarm",
    )
    on_corrupt: Literal["refuse", "move-aside"] = Field(
        "refuse",
        description="a damaged database file: refuse to start (exit 2, naming the file), or move it aside "
        "(history.sqlite.corrupt-TIME) and start a new one",
    )
    images: bool = Field(
        True, description="keep the frame and its annotation of each miss, failed part, fault, unknown"
    )
    images_max_mb: float = Field(2000.0, gt=0, description="the images folder is trimmed, oldest first, to this size")
    images_max_days: float = Field(90.0, gt=0, description="images older than this are deleted")
    min_free_mb: float = Field(
        500.0, ge=0, description="below this free space on the data folder's disk no image is saved (a warning alarm)"
    )
    images_queue: int = Field(
        8, ge=1, le=256, description="images waiting to be written; more are dropped (counted), never held"
    )
    batch_max_rows: int = Field(2000, ge=1, le=100_000, description="rows written in one transaction at most")
    retry_s: float = Field(
        5.0,
        gt=0,
        le=600,
        description="the local database (or PostgreSQL's local outbox) cannot be written: try again this often",
    )
    retry_initial_s: float = Field(
        1.0,
        gt=0,
        le=600,
        description="PostgreSQL failed (unreachable, INSERT refused, disk full, no answer): the first wait before "
        "trying again; doubled after each failure up to retry_max_s, each wait drawn between half and all of it",
    )
    retry_max_s: float = Field(
        60.0, gt=0, le=3600, description="PostgreSQL failing: the longest wait between two tries"
    )
    connect_timeout_s: float = Field(5.0, gt=0, le=120, description="PostgreSQL connect timeout")
    keepalive_idle_s: int = Field(
        10,
        ge=1,
        le=7200,
        description="PostgreSQL connection idle this long: TCP keepalive probes start (libpq keepalives_idle)",
    )
    keepalive_interval_s: int = Field(5, ge=1, le=600, description="between two TCP keepalive probes")
    keepalive_count: int = Field(
        3, ge=1, le=100, description="unanswered TCP keepalive probes before the connection is dead"
    )
    tcp_user_timeout_s: float = Field(
        30.0,
        ge=0,
        le=3600,
        description="data sent to PostgreSQL unacknowledged this long: the connection is dead (libpq tcp_user_timeout; "
        "0: the system's default)",
    )
    statement_timeout_s: float = Field(
        30.0, ge=0, le=3600, description="the server cancels a statement running longer (statement_timeout; 0: never)"
    )
    idle_in_transaction_timeout_s: float = Field(
        30.0,
        ge=0,
        le=3600,
        description="the server ends this cell's session when it leaves a transaction open this long "
        "(idle_in_transaction_session_timeout): a connection that went half-open in the middle of a batch "
        "holds its rows' locks until then, and the rows sent again wait on them; 0: never",
    )
    answer_timeout_s: float = Field(
        60.0,
        gt=0,
        le=3600,
        description="no answer from PostgreSQL to one batch within this (a half-open connection, a proxy that went "
        "silent): the cell drops the connection, raises a warning alarm and tries again later; keep it above "
        "statement_timeout_s",
    )
    cell_name: str = Field(
        "",
        max_length=64,
        description="this cell's name in a plant-wide database (rows carry it); default: the host name",
    )

    @model_validator(mode="after")
    def _retry_order(self) -> HistoryConfig:
        if self.retry_max_s < self.retry_initial_s:
            raise ValueError(f"retry_max_s {self.retry_max_s} is below retry_initial_s {self.retry_initial_s}")
        return self

    @field_validator("url")
    @classmethod
    def _known_scheme(cls, v: str) -> str:
        if v and not v.startswith(("sqlite:///", "postgresql://", "postgres://")):
            raise ValueError(f"{v!r}: give sqlite:///PATH or postgresql://USER@HOST:PORT/DB")
        return v


def data_dir(history: HistoryConfig, log_dir: Path) -> Path:
    """The store's folder: history.data_dir, else `data` beside the log folder (logs/ -> data/)."""
    if history.data_dir is not None:
        return Path(history.data_dir)
    log_dir = Path(log_dir)
    return log_dir.parent / "data"


def database_url(history: HistoryConfig, log_dir: Path) -> str:
    return history.url or f"sqlite:///{data_dir(history, log_dir) / DB_FILE}"


def rehearsal_history(history: HistoryConfig, log_dir: Path) -> HistoryConfig:
    """The store of a rehearsal (`--dry-run`, `make demo`): a SQLite database of its own in
    data_dir/rehearsal/ (with its own images), never the production store nor the plant's
    PostgreSQL, so production's counters, reports and OPC UA never count a simulated pick.
    `run-cell history --simulated` reads it."""
    return history.model_copy(update={"url": "", "data_dir": data_dir(history, log_dir) / REHEARSAL_DIR})

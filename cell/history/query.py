"""Reading the history: the small query API the CLI, the screen, the shift counters and OPC UA's
results (OPC 40100) use. Read-only; every filter is a bound parameter, never SQL text.

    reader = open_reader(config)                  # this cell's rows in the configured store
    reader.get_pick("20261201-060102-ab12/7")     # one pick as a dict, or None
    reader.list_picks(since=t0, until=t1, job_id=..., cls="bolt", outcome="missed", limit=100)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from cell.core.records import Counters, PickRecord
from cell.history.config import data_dir, database_url
from cell.history.db import (
    Database,
    HistoryError,
    open_postgresql,
    open_sqlite,
    parse_time,
    required_time,
    sqlite_path,
)
from cell.history.store import cell_name

PICK_COLUMNS = (
    "id",
    "job_id",
    "cell",
    "time_utc",
    "class",
    "track",
    "attempt",
    "pixel_x",
    "pixel_y",
    "table_x_mm",
    "table_y_mm",
    "robot_x_mm",
    "robot_y_mm",
    "robot_z_mm",
    "jaw_angle_deg",
    "calibration_id",
    "outcome",
    "cycle_ms",
    "image_id",
)
OUTCOMES = ("picked", "missed", "failed", "rehearsed", "placed")
ALARM_COLUMNS = (
    "id",
    "alarm_id",
    "severity",
    "raised_utc",
    "cleared_utc",
    "reason",
    "hint",
    "source",
    "job_id",
    "cleared_interface",
    "cleared_user",
    "cleared_address",
    "image_id",
)


@dataclass(frozen=True)
class PickFilter:
    since: datetime | None = None
    until: datetime | None = None
    job_id: str | None = None
    cls: str | None = None
    outcome: str | None = None

    def where(self, cell: str | None) -> tuple[str, list[Any]]:
        clauses, params = [], []
        for sql, value in (
            ("cell = ?", cell),
            ("time_utc >= ?", self.since),
            ("time_utc < ?", self.until),
            ("job_id = ?", self.job_id),
            ("class = ?", self.cls),
            ("outcome = ?", self.outcome),
        ):
            if value is not None:
                clauses.append(sql)
                params.append(value)
        return (" WHERE " + " AND ".join(clauses)) if clauses else "", params


def pick_json(row: tuple) -> dict:
    """A pick row as JSON: frames in names (pixel, table mm, robot mm)."""
    r = dict(zip(PICK_COLUMNS, row, strict=True))
    t = parse_time(r["time_utc"])
    return {
        "id": r["id"],
        "job_id": r["job_id"],
        "cell": r["cell"],
        "time_utc": t.isoformat(timespec="milliseconds") if t else None,
        "class": r["class"],
        "track": r["track"],
        "attempt": r["attempt"],
        "pixel": [r["pixel_x"], r["pixel_y"]],
        "table_mm": [r["table_x_mm"], r["table_y_mm"]],
        "robot_mm": [r["robot_x_mm"], r["robot_y_mm"], r["robot_z_mm"]],
        "jaw_angle_deg": r["jaw_angle_deg"],
        "calibration_id": r["calibration_id"],
        "outcome": r["outcome"],
        "cycle_ms": r["cycle_ms"],
        "image_id": r["image_id"],
    }


def alarm_json(row: tuple) -> dict:
    r = dict(zip(ALARM_COLUMNS, row, strict=True))
    for k in ("raised_utc", "cleared_utc"):
        t = parse_time(r[k])
        r[k] = t.isoformat(timespec="seconds") if t else None
    return r


class HistoryReader:
    """Queries over one database; `cell` limits them to one cell's rows (None: every cell's)."""

    def __init__(self, db: Database, cell: str | None, images_dir: Path | None = None):
        self.db, self.cell, self.images_dir = db, cell, images_dir

    def close(self) -> None:
        self.db.close()

    # ---- picks ----------------------------------------------------------------------------------
    def _this_cell(self) -> tuple[str, list[Any]]:
        """The clause and parameter keeping a lookup by id to this reader's cell (none: every cell's)."""
        return (" AND cell = ?", [self.cell]) if self.cell is not None else ("", [])

    def get_pick(self, pick_id: str) -> dict | None:
        """One pick of this reader's cell by id (a shared plant database holds other cells' picks too)."""
        where, params = self._this_cell()
        rows = self.db.execute(f"SELECT {', '.join(PICK_COLUMNS)} FROM picks WHERE id = ?{where}", [pick_id, *params])
        return pick_json(rows[0]) if rows else None

    def get_job(self, job_id: str) -> dict | None:
        """A job's row of this reader's cell: who started it, its recipe and its start arguments (MeasId, PartId ...)."""
        cols = ("id", "start_utc", "end_utc", "mode", "interface", "user_name", "recipe", "arguments", "outcome")
        where, params = self._this_cell()
        rows = self.db.execute(f"SELECT {', '.join(cols)} FROM jobs WHERE id = ?{where}", [job_id, *params])
        if not rows:
            return None
        d = dict(zip(cols, rows[0], strict=True))
        d["arguments"] = dump_arguments(d["arguments"])
        return d

    def list_picks(self, f: PickFilter = PickFilter(), limit: int | None = 1000, offset: int = 0) -> list[dict]:
        """Oldest first (limit None: all)."""
        where, params = f.where(self.cell)
        sql = f"SELECT {', '.join(PICK_COLUMNS)} FROM picks{where} ORDER BY time_utc, id"
        if limit is not None:
            sql += " LIMIT ? OFFSET ?"
            params += [limit, offset]
        return [pick_json(r) for r in self.db.execute(sql, params)]

    def count_picks(self, f: PickFilter = PickFilter()) -> int:
        where, params = f.where(self.cell)
        return int(self.db.execute(f"SELECT count(*) FROM picks{where}", params)[0][0])

    def last_picks(self, n: int = 20) -> list[PickRecord]:
        """The newest n picks as the screen and OPC UA show them, oldest first."""
        where, params = PickFilter().where(self.cell)
        rows = self.db.execute(
            f"SELECT {', '.join(PICK_COLUMNS)} FROM picks{where} ORDER BY time_utc DESC, id DESC LIMIT ?",
            params + [n],
        )
        return [pick_record(pick_json(r)) for r in reversed(rows)]

    def counters(self, since: datetime, until: datetime) -> Counters:
        """The shift counters over [since, until) (unknown_left: the last job's, in that span)."""
        where, params = PickFilter(since, until).where(self.cell)
        rows = self.db.execute(
            f"""SELECT
                sum(CASE WHEN outcome IN ('missed', 'failed') THEN 1 ELSE 0 END),
                sum(CASE WHEN attempt > 1 THEN 1 ELSE 0 END),
                sum(CASE WHEN outcome = 'failed' THEN 1 ELSE 0 END)
                FROM picks{where}""",
            params,
        )
        misses, retries, failed = (int(v or 0) for v in rows[0])
        picked_where = f"{where} AND outcome = 'picked'" if where else " WHERE outcome = 'picked'"
        by_class = self.db.execute(
            f"SELECT class, count(*) FROM picks{picked_where} GROUP BY class ORDER BY class", params
        )
        picked = tuple((str(cls), int(n)) for cls, n in by_class if n)
        uw, up = PickFilter(since, until).where(self.cell)
        unreachable = int(self.db.execute(f"SELECT count(*) FROM unreachable{uw}", up)[0][0])
        jw = "WHERE start_utc >= ? AND start_utc < ?" + (" AND cell = ?" if self.cell else "")
        jp = [since, until] + ([self.cell] if self.cell else [])
        last = self.db.execute(f"SELECT unknown_left FROM jobs {jw} ORDER BY start_utc DESC LIMIT 1", jp)
        unknown = int(last[0][0] or 0) if last else 0
        return Counters(picked, misses, retries, failed, unreachable, unknown)

    # ---- alarms, images ----------------------------------------------------------------------------
    def alarms(self, limit: int = 50, offset: int = 0) -> list[dict]:
        where = " WHERE cell = ?" if self.cell else ""
        params: list[Any] = [self.cell] if self.cell else []
        rows = self.db.execute(
            f"SELECT {', '.join(ALARM_COLUMNS)} FROM alarms{where} ORDER BY raised_utc DESC, id LIMIT ? OFFSET ?",
            params + [limit, offset],
        )
        return [alarm_json(r) for r in rows]

    def image_files(self, image_id: str) -> tuple[Path, Path] | None:
        """The frame and annotated files of an image row of this cell (None: no such image, or deleted)."""
        if self.images_dir is None:
            return None
        where = " AND cell = ?" if self.cell else ""
        rows = self.db.execute(
            f"SELECT frame_file, annotated_file FROM images WHERE id = ? AND deleted_utc IS NULL{where}",
            [image_id] + ([self.cell] if self.cell else []),
        )
        if not rows:
            return None
        root = self.images_dir.resolve()
        files = tuple((root / str(name)).resolve() for name in rows[0])
        if any(root not in f.parents for f in files):  # a row can never point outside the images folder
            return None
        return files  # type: ignore[return-value]

    def jobs(self, since: datetime, until: datetime) -> list[dict]:
        where = "WHERE start_utc >= ? AND start_utc < ?" + (" AND cell = ?" if self.cell else "")
        params = [since, until] + ([self.cell] if self.cell else [])
        cols = ("id", "start_utc", "end_utc", "mode", "interface", "user_name", "outcome", "reason", "image_id")
        rows = self.db.execute(f"SELECT {', '.join(cols)} FROM jobs {where} ORDER BY start_utc", params)
        out = []
        for r in rows:
            d = dict(zip(cols, r, strict=True))
            for k in ("start_utc", "end_utc"):
                t = parse_time(d[k])
                d[k] = t.isoformat(timespec="seconds") if t else None
            out.append(d)
        return out


def pick_record(p: dict[str, Any]) -> PickRecord:
    x, y, z = (float(v or 0.0) for v in p["robot_mm"])
    return PickRecord(
        required_time(p["time_utc"], "a pick"),
        int(p["track"]),
        p["class"],
        (float(p["table_mm"][0] or 0.0), float(p["table_mm"][1] or 0.0)),
        (x, y, z),
        p["jaw_angle_deg"],
        p["outcome"],
        p["id"],
        p["job_id"],
    )


def open_reader(config: Any, cell: str | None = "", readonly: bool = True) -> HistoryReader:
    """A reader of the configured store (CellConfig). `cell` "" is this cell; None every cell's.
    SQLite: a database that does not exist yet is an error saying so."""
    h = config.history
    if not h.enabled:
        raise HistoryError("the history store is off (history.enabled = false)", hint="set history.enabled = true")
    url = database_url(h, config.run.log_dir)
    who = cell_name(h) if cell == "" else cell
    images = data_dir(h, config.run.log_dir) / "images"
    if url.startswith("sqlite:///"):
        return HistoryReader(open_sqlite(sqlite_path(url), readonly=readonly), who, images)
    return HistoryReader(open_postgresql(url, h), who, images)


def dump_arguments(text: str | None) -> dict:
    try:
        return json.loads(text or "{}")
    except ValueError:
        return {}

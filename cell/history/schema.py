"""The history schema, versioned: MIGRATIONS[n] takes a database from version n to n + 1, the same
statements on SQLite and PostgreSQL (`{TIME}`, `{REAL}` become each dialect's type).

Rows are keyed by ids that come from the cell (pick ids, job ids, calibration content hashes)
or are made once when the row is (alarms, commands, states: random), so writing a row twice
(a resend after an outage, the audit read back after a crash) changes nothing.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime

from cell.history.db import Database, HistoryError

log = logging.getLogger(__name__)

_V1 = [
    """CREATE TABLE jobs (
        id TEXT PRIMARY KEY, cell TEXT NOT NULL, start_utc {TIME}, end_utc {TIME}, mode TEXT,
        interface TEXT, user_name TEXT, role TEXT, address TEXT, recipe TEXT, arguments TEXT,
        outcome TEXT, reason TEXT, picked INTEGER, misses INTEGER, failed INTEGER, unreachable INTEGER,
        unknown_left INTEGER, image_id TEXT)""",
    "CREATE INDEX jobs_start ON jobs (start_utc)",
    """CREATE TABLE picks (
        id TEXT PRIMARY KEY, job_id TEXT NOT NULL, cell TEXT NOT NULL, time_utc {TIME} NOT NULL,
        class TEXT NOT NULL, track INTEGER NOT NULL, attempt INTEGER NOT NULL,
        pixel_x {REAL}, pixel_y {REAL}, table_x_mm {REAL}, table_y_mm {REAL},
        robot_x_mm {REAL}, robot_y_mm {REAL}, robot_z_mm {REAL}, jaw_angle_deg {REAL},
        calibration_id TEXT NOT NULL, outcome TEXT NOT NULL, cycle_ms {REAL}, image_id TEXT)""",
    "CREATE INDEX picks_time ON picks (time_utc)",
    "CREATE INDEX picks_job ON picks (job_id)",
    """CREATE TABLE unreachable (
        id TEXT PRIMARY KEY, job_id TEXT NOT NULL, cell TEXT NOT NULL, time_utc {TIME} NOT NULL,
        class TEXT, track INTEGER, table_x_mm {REAL}, table_y_mm {REAL}, reason TEXT)""",
    "CREATE INDEX unreachable_time ON unreachable (time_utc)",
    """CREATE TABLE alarms (
        id TEXT PRIMARY KEY, cell TEXT NOT NULL, alarm_id TEXT NOT NULL, severity TEXT NOT NULL,
        raised_utc {TIME} NOT NULL, cleared_utc {TIME}, reason TEXT, hint TEXT, source TEXT, job_id TEXT,
        cleared_interface TEXT, cleared_user TEXT, cleared_address TEXT, image_id TEXT)""",
    "CREATE INDEX alarms_raised ON alarms (raised_utc)",
    """CREATE TABLE commands (
        id TEXT PRIMARY KEY, cell TEXT NOT NULL, time_utc {TIME} NOT NULL, command TEXT NOT NULL,
        interface TEXT, user_name TEXT, role TEXT, address TEXT, accepted INTEGER NOT NULL,
        refusal TEXT, message TEXT, vision_state TEXT, arguments TEXT)""",
    "CREATE INDEX commands_time ON commands (time_utc)",
    """CREATE TABLE calibrations (
        id TEXT PRIMARY KEY, cell TEXT NOT NULL, first_utc {TIME} NOT NULL, last_installed_utc {TIME} NOT NULL,
        model TEXT, cv_rms_mm {REAL}, cv_max_mm {REAL}, source_image TEXT, file TEXT,
        accepted_interface TEXT, accepted_user TEXT, accepted_utc {TIME})""",
    """CREATE TABLE states (
        id TEXT PRIMARY KEY, cell TEXT NOT NULL, time_utc {TIME} NOT NULL, source TEXT, target TEXT NOT NULL,
        reason TEXT)""",
    "CREATE INDEX states_time ON states (time_utc)",
    """CREATE TABLE images (
        id TEXT PRIMARY KEY, cell TEXT NOT NULL, time_utc {TIME} NOT NULL, kind TEXT NOT NULL, job_id TEXT,
        pick_id TEXT, frame_no INTEGER, frame_file TEXT, annotated_file TEXT, bytes INTEGER,
        deleted_utc {TIME})""",
    "CREATE INDEX images_time ON images (time_utc)",
    """CREATE TABLE marks (
        cell TEXT PRIMARY KEY, last_event_utc {TIME} NOT NULL)""",
]

MIGRATIONS: list[list[str]] = [_V1]
VERSION = len(MIGRATIONS)


def migrate(db: Database) -> int:
    """Bring the schema to VERSION (in one transaction); the version it was at before."""
    with db.transaction():
        if db.dialect == "postgresql":
            db.execute("SELECT pg_advisory_xact_lock(?)", (716_051_016,))
        db.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL, applied_utc {TIME} NOT NULL)")
        rows = db.execute("SELECT max(version) FROM schema_version")
        before = int(rows[0][0] or 0)
        if before > VERSION:
            raise HistoryError(
                f"history database {db.where} has schema version {before}; this cell knows up to {VERSION}",
                hint="update the cell's software, or point history.url at another database",
            )
        for n in range(before, VERSION):
            for statement in MIGRATIONS[n]:
                db.execute(statement)
            db.execute("INSERT INTO schema_version (version, applied_utc) VALUES (?, ?)", (n + 1, datetime.now(UTC)))
            log.info("history %s: schema migrated to version %d", db.where, n + 1)
    return before


def version(db: Database) -> int:
    try:
        rows = db.execute("SELECT max(version) FROM schema_version")
    except Exception:
        return 0
    return int(rows[0][0] or 0)

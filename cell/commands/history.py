"""`run-cell history`: the picks of a time span, a shift or a job, from the history store, as a
table, JSON or CSV."""

from __future__ import annotations

import argparse
import csv
import json
import sys
from datetime import UTC, date, datetime, time
from pathlib import Path
from zoneinfo import ZoneInfo

from cell.config import CellConfig, load_config
from cell.core.parts import NAME_PATTERN
from cell.errors import InputError
from cell.history.query import OUTCOMES, PICK_COLUMNS
from cell.shifts import zone_line

CSV_COLUMNS = tuple(c for c in PICK_COLUMNS if c != "cell")  # the store's, but the cell (one per CLI)


def add_store_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", dest="store_config", type=Path, help="cell config (TOML): [history], [shifts]")
    p.add_argument("--url", help="the store to read instead of history.url (sqlite:///PATH or postgresql://...)")
    p.add_argument(
        "--simulated",
        action="store_true",
        help="the rehearsals' store instead (the picks of dry runs and the demo, kept apart from production's: "
        "data/rehearsal/history.sqlite)",
    )


def part_class(text: str) -> str:
    """argparse type: a part class's name as the registry allows it (cell.core.parts)."""
    if not NAME_PATTERN.match(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a part class's name (bolt, nut, a taught type's name)")
    return text


def register(sub) -> None:
    p = sub.add_parser(
        "history",
        help="the picks kept in the history store: by time, shift, job, class or outcome",
        description="Print the picks kept in the history store (oldest first). Times are ISO 8601; without a "
        "zone they are the plant's ([shifts].time_zone). A shift is DATE/NAME (2026-12-01/early).",
    )
    p.add_argument(
        "action",
        nargs="?",
        choices=["copy"],
        help="copy: send every row of the SQLite history to the PostgreSQL server --to names (rows it holds "
        "already are left as they are: run it again at will)",
    )
    p.add_argument("--to", metavar="URL", help="copy: the server, postgresql://USER@HOST:PORT/DB")
    add_store_arguments(p)
    p.add_argument("--since", help="from this time (ISO 8601, or a date)")
    p.add_argument("--until", help="before this time (ISO 8601, or a date)")
    p.add_argument("--shift", help="one shift, e.g. 2026-12-01/early")
    p.add_argument("--job", help="one job's picks (its id)")
    p.add_argument("--class", dest="cls", type=part_class, help="one part class (bolt, nut, a taught type's name)")
    p.add_argument("--outcome", choices=OUTCOMES, help="one outcome")
    p.add_argument("--limit", type=int, default=None, help="at most this many (default: all)")
    p.add_argument(
        "--dead-letter",
        action="store_true",
        help="instead of picks: the rows the PostgreSQL server refused, kept aside in the local outbox",
    )
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--json", action="store_true", help="a JSON array of picks")
    fmt.add_argument("--csv", action="store_true", help="CSV with a header line")
    p.set_defaults(func=cmd_history)


def store_config(args: argparse.Namespace) -> CellConfig:
    config = load_config(args.store_config)
    if args.simulated:
        from cell.history.config import rehearsal_history

        if args.url:
            raise InputError(
                "--simulated reads the rehearsals' own store: --url does not apply",
                hint="leave out --url (the rehearsals' store is data/rehearsal/history.sqlite beside the history's)",
            )
        config.history = rehearsal_history(config.history, config.run.log_dir)
        return config
    if args.url:
        try:
            config.history = config.history.model_validate({**config.history.model_dump(), "url": args.url})
        except ValueError as e:
            raise InputError(f"--url {args.url}: {str(e).splitlines()[-1].strip()}") from None
    return config


def parse_when(text: str, zone: ZoneInfo, option: str) -> datetime:
    """An ISO time (or a date: its midnight), in the plant's zone unless it names its own."""
    try:
        t = datetime.fromisoformat(text)
    except ValueError:
        try:
            t = datetime.combine(date.fromisoformat(text), time())
        except ValueError:
            raise InputError(f"{option} {text!r}: expected an ISO 8601 time like 2026-12-01T14:32 or a date") from None
    return (t if t.tzinfo else t.replace(tzinfo=zone)).astimezone(UTC)


def cmd_history(args: argparse.Namespace) -> int:
    from cell.history.query import PickFilter, open_reader
    from cell.shifts import ShiftCalendar

    config = store_config(args)
    if args.action == "copy" or args.to:
        return _copy(args, config)
    if args.limit is not None and args.limit < 1:
        raise InputError(f"--limit {args.limit}: give 1 or more")
    if args.dead_letter:
        return _dead_letter(args, config)
    calendar = ShiftCalendar(config.shifts)
    since = parse_when(args.since, calendar.zone, "--since") if args.since else None
    until = parse_when(args.until, calendar.zone, "--until") if args.until else None
    if args.shift:
        try:
            shift = calendar.by_id(args.shift)
        except ValueError as e:
            raise InputError(f"--shift: {e}") from None
        since = max(since or shift.start_utc, shift.start_utc)
        until = min(until or shift.end_utc, shift.end_utc)
    reader = open_reader(config)
    try:
        picks = reader.list_picks(PickFilter(since, until, args.job, args.cls, args.outcome), limit=args.limit)
    finally:
        reader.close()
    if args.json:
        json.dump(picks, sys.stdout, indent=1)
        print()
    elif args.csv:
        writer = csv.writer(sys.stdout, lineterminator="\n")
        writer.writerow(CSV_COLUMNS)
        for p in picks:
            writer.writerow(
                [p["id"], p["job_id"], p["time_utc"], p["class"], p["track"], p["attempt"], *p["pixel"]]
                + [*p["table_mm"], *p["robot_mm"], p["jaw_angle_deg"], p["calibration_id"], p["outcome"]]
                + [p["cycle_ms"], p["image_id"] or ""]
            )
    else:
        for line in _table(picks, calendar.zone):
            print(line)
    return 0


def _copy(args: argparse.Namespace, config: CellConfig) -> int:
    from cell.history.config import database_url
    from cell.history.copy import copy_history
    from cell.history.db import open_postgresql, open_sqlite, redact, sqlite_path

    if args.action != "copy" or not args.to:
        raise InputError("history copy --to URL: both are needed", hint="run-cell history copy --to postgresql://...")
    given = [o for o, v in (("--since", args.since), ("--until", args.until), ("--shift", args.shift)) if v]
    given += [o for o, v in (("--job", args.job), ("--class", args.cls), ("--outcome", args.outcome)) if v]
    given += [o for o, v in (("--limit", args.limit), ("--dead-letter", args.dead_letter)) if v]
    given += [o for o, v in (("--json", args.json), ("--csv", args.csv), ("--simulated", args.simulated)) if v]
    if given:  # rehearsals' picks never go to the plant's server
        raise InputError(f"history copy sends every row: {', '.join(given)} does not apply", hint="leave it out")
    if not args.to.startswith(("postgresql://", "postgres://")):
        raise InputError(f"--to {redact(args.to)}: give the server as postgresql://USER@HOST:PORT/DB")
    source_url = database_url(config.history, config.run.log_dir)
    if not source_url.startswith("sqlite:///"):
        raise InputError(
            f"history copy: the store is {redact(source_url)}, not a SQLite file",
            hint="give the SQLite history with --url sqlite:///PATH, or the config that kept it",
        )
    source = open_sqlite(sqlite_path(source_url), readonly=True)
    try:
        target = open_postgresql(args.to, config.history, "pick-cell history copy")
        try:
            print(f"copying {sqlite_path(source_url)} to {redact(args.to)}")
            tables = copy_history(
                source, target, progress=lambda t: print(f"  {t.table:13} {t.read:8} rows, {t.added:8} added")
            )
        finally:
            target.close()
    finally:
        source.close()
    read, added = sum(t.read for t in tables), sum(t.added for t in tables)
    print(f"{read} rows read, {added} added, {read - added} already on the server")
    return 0


def _dead_letter(args: argparse.Namespace, config: CellConfig) -> int:
    from cell.history.config import OUTBOX_FILE, data_dir
    from cell.history.store import read_dead_letter

    given = [o for o, v in (("--since", args.since), ("--until", args.until), ("--shift", args.shift)) if v]
    given += [o for o, v in (("--job", args.job), ("--class", args.cls), ("--outcome", args.outcome)) if v]
    given += ["--simulated"] if args.simulated else []
    if given or args.csv:
        raise InputError(
            f"--dead-letter lists every refused row: {', '.join(given or ['--csv'])} does not apply",
            hint="leave it out (--limit and --json do apply)",
        )
    outbox = data_dir(config.history, config.run.log_dir) / OUTBOX_FILE
    rows = read_dead_letter(outbox)[: args.limit]
    if args.json:
        json.dump(rows, sys.stdout, indent=1)
        print()
        return 0
    for r in rows:
        print(f"{r['refused_utc']}  #{r['seq']}  {r['statement']}: {r['error']}")
        print(f"    {json.dumps(r['params'])}")
    print(f"{len(rows)} refused rows in {outbox}" if rows else f"no refused rows ({outbox})")
    return 0


def _table(picks: list[dict], zone: ZoneInfo) -> list[str]:
    """The picks on the plant's clock, the zone (and its offset) said first."""
    if not picks:
        return ["no picks"]
    first, last = (datetime.fromisoformat(picks[i]["time_utc"]) for i in (0, -1))
    out = [
        zone_line(zone, first, last),
        f"{'time (' + str(zone) + ')':26} {'pick':28} {'class':5} {'table x, y mm':>15} {'robot x, y, z mm':>22}  outcome",
    ]
    for p in picks:
        t = datetime.fromisoformat(p["time_utc"]).astimezone(zone)
        tx, ty = (v or 0.0 for v in p["table_mm"])
        rx, ry, rz = (v or 0.0 for v in p["robot_mm"])
        image = "  (image)" if p["image_id"] else ""
        out.append(
            f"{t:%Y-%m-%d %H:%M:%S}.{t.microsecond // 1000:03d}    {p['id']:28} {p['class']:5} "
            f"{tx:7.1f},{ty:7.1f} {rx:7.1f},{ry:7.1f},{rz:6.1f}  {p['outcome']}{image}"
        )
    out.append(f"{len(picks)} picks")
    return out

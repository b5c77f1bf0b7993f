#!/usr/bin/env python3
"""Disk use of a running cell: what the history store and the logs grow by, per pick and per
hour of continuous running, and what that makes over a year.

Runs `run-cell serve --dry-run` in a temporary folder with the built-in simulated cell and its
feeder (parts arriving at [sim.feeder] parts_per_minute, default 6 a minute, on simulated time
`--speed` times faster than the wall clock), starts a continuous job through the screen's API,
lets it clear the table it starts with (`--warmup` wall seconds: that table's misses and images
are a start's, not a shift's), then measures what the audit files (JSON lines), the operator
logs, the images folder and the picks grow by over `--seconds` of wall time; the history
store's bytes per pick are its pages in use (after its WAL is checkpointed, the empty schema's
taken off) over all its picks. The figures are per pick and per simulated hour (each idle
capture writes audit lines too: an idle hour costs audit bytes and no history rows), then
multiplied out to a year of two 8-hour shifts on 250 days and of 24/7. Keep --speed low enough
that the cell keeps up with the simulated clock (a capture every capture_interval_s while idle):
at 20 it does not, and idle captures are undercounted.

    python scripts/disk_use.py [--warmup 40] [--seconds 90] [--speed 5]

A dry run's audit lines carry `"rehearsal": true` (17 bytes a line) that production's do not:
the figures are that much above production's.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.ports import free_port  # noqa: E402


def post(url: str, csrf: str) -> None:
    req = urllib.request.Request(url, b"{}", {"Content-Type": "application/json", "X-CSRF-Token": csrf}, method="POST")
    with urllib.request.urlopen(req, timeout=30) as reply:
        reply.read()


def folder_bytes(folder: Path, pattern: str = "*") -> int:
    return sum(p.stat().st_size for p in folder.rglob(pattern) if p.is_file()) if folder.is_dir() else 0


def used_bytes(db: Path) -> tuple[int, int]:
    """(bytes in use by the database's pages, picks) after a checkpoint: what the rows take."""
    conn = sqlite3.connect(db)
    try:
        conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        pages, free, size = (
            conn.execute(f"PRAGMA {p}").fetchone()[0] for p in ("page_count", "freelist_count", "page_size")
        )
        picks = conn.execute("SELECT count(*) FROM picks").fetchone()[0]
        return (pages - free) * size, int(picks)
    finally:
        conn.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--warmup", type=float, default=40.0, help="wall seconds before measuring: the first table")
    parser.add_argument("--seconds", type=float, default=90.0, help="wall seconds measured")
    parser.add_argument("--speed", type=float, default=5.0, help="[sim] speed_factor: simulated s per wall s")
    parser.add_argument("--keep", action="store_true", help="keep the run's folder (its logs and store) to look at")
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="cell-disk-use-"))
    (work / "cell.toml").write_text(f"[sim]\nspeed_factor = {args.speed}\n")
    http = free_port()
    cmd = [sys.executable, "-m", "cell.cli", "serve", "--dry-run", "--config", "cell.toml"]
    cmd += ["--opcua-port", str(free_port()), "--http-port", str(http)]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(cmd, cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith("ready:"):
            break
    else:
        print(f"run-cell serve ended before its ready line (exit {proc.wait()})", file=sys.stderr)
        return 1
    threading.Thread(target=proc.stdout.read, daemon=True).start()  # keep its pipe drained
    base = f"http://127.0.0.1:{http}"
    with urllib.request.urlopen(base + "/api/session", timeout=30) as reply:
        csrf = json.loads(reply.read())["csrf"]
    post(base + "/api/command/StartContinuous", csrf)
    data = work / "data" / "rehearsal"
    time.sleep(args.warmup)  # the measurement's spans, not a synchronisation
    before, t0 = sizes(work, data), time.monotonic()
    time.sleep(args.seconds)
    after, wall_s = sizes(work, data), time.monotonic() - t0
    post(base + "/api/command/Stop", csrf)
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=120)

    history_b, all_picks = used_bytes(data / "history.sqlite")
    history_b -= _empty_store_bytes(work)  # the schema itself, there before the first row
    per_pick_history = history_b / max(all_picks, 1)
    grown = {k: after[k] - before[k] for k in after}
    picks = grown["picks"]
    hours = wall_s * args.speed / 3600
    print(f"continuous dry run, measured {wall_s:.0f} s wall x speed {args.speed:g} = {hours * 60:.1f} simulated min:")
    print(f"  picks: {picks} ({picks / hours:.0f}/h); the feeder brings {_feeder_rate()}/h")
    print(f"  history store: {per_pick_history:.0f} B/pick ({all_picks} picks, {history_b / 1e3:.1f} kB of rows)")
    print(
        f"  audit files: +{grown['audit'] / 1e3:.1f} kB, {grown['lines']} lines, {grown['audit'] / max(picks, 1):.0f} B/pick"
    )
    print(f"  operator logs: +{grown['oplog'] / 1e3:.1f} kB; images: +{grown['images'] / 1e3:.1f} kB")
    per_hour = {
        "history": per_pick_history * picks / hours,
        "audit": (grown["audit"] - 17 * grown["lines"]) / hours,
        "operator log": grown["oplog"] / hours,
        "images": grown["images"] / hours,
    }
    print(f"per simulated hour at {picks / hours:.0f} picks/h (audit without the dry run's rehearsal marks):")
    for name, b in per_hour.items():
        print(f"  {name:13} {b / 1e6:8.2f} MB/h")
    for label, h in (("two 8 h shifts x 250 days", 16 * 250), ("24/7 (8760 h)", 8760)):
        total = {n: b * h / 1e9 for n, b in per_hour.items()}
        parts = ", ".join(f"{n} {v:.1f} GB" for n, v in total.items())
        print(f"a year, {label}: {parts}")
    if args.keep:
        print(f"(folder kept: {work})")
    else:
        shutil.rmtree(work, ignore_errors=True)
    return 0


def sizes(work: Path, data: Path) -> dict[str, int]:
    conn = sqlite3.connect(f"file:{data / 'history.sqlite'}?mode=ro", uri=True)
    try:
        picks = int(conn.execute("SELECT count(*) FROM picks").fetchone()[0])
    finally:
        conn.close()
    return {
        "picks": picks,
        "audit": folder_bytes(work / "logs", "*.jsonl"),
        "lines": sum(1 for p in (work / "logs").glob("*.jsonl") for _ in p.open()),
        "oplog": folder_bytes(work / "logs", "*.log"),
        "images": folder_bytes(data / "images"),
    }


def _feeder_rate() -> int:
    sys.path.insert(0, str(REPO))
    from cell.run_config import FeederConfig

    return round(FeederConfig().parts_per_minute * 60)


def _empty_store_bytes(work: Path) -> int:
    """A new store's size: the schema's pages (from this run's own code)."""
    sys.path.insert(0, str(REPO))
    from cell.history.db import open_sqlite
    from cell.history.schema import migrate

    db_path = work / "empty.sqlite"
    db = open_sqlite(db_path)
    migrate(db)
    db.close()
    size = used_bytes(db_path)[0]
    for suffix in ("", "-wal", "-shm"):
        Path(f"{db_path}{suffix}").unlink(missing_ok=True)
    return size


if __name__ == "__main__":
    sys.exit(main())

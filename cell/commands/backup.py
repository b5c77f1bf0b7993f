"""`run-cell backup --out FILE` and `run-cell restore FILE --into DIR` (cell.backup)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "backup",
        help="one archive of everything the cell keeps: config, calibration, users, keys, recipes, history",
        description="Write one tar.gz holding the config, the calibration and its backups, the robot frame, the "
        "users file, the certificates and keys with the OPC UA trust lists, the recipes and the history database "
        "(copied live with SQLite's online backup: the service may run), with a manifest of versions and sha256 "
        "sums. The archive is written whole or not at all, mode 0600. docs/operations.md.",
    )
    p.add_argument("--config", dest="backup_config", type=Path, help="the cell's config (TOML)")
    p.add_argument("--out", required=True, type=Path, help="the archive to write (NAME.tar.gz)")
    p.add_argument(
        "--cell-dir",
        type=Path,
        default=None,
        help="the folder the config's relative paths start at (the service's WorkingDirectory); "
        "default: the current folder",
    )
    p.set_defaults(func=cmd_backup)

    r = sub.add_parser(
        "restore",
        help="restore a backup archive into a new, empty folder (never over a live cell)",
        description="Check a backup archive (names, manifest, every file's sha256) and restore it into a new or "
        "empty folder, file modes kept. Refused, with nothing written, when the folder holds anything, a running "
        "service holds its files, or the archive does not match its manifest.",
    )
    r.add_argument("archive", type=Path, help="the archive run-cell backup wrote")
    r.add_argument("--into", required=True, type=Path, help="a new or empty folder")
    r.set_defaults(func=cmd_restore)


def cmd_backup(args: argparse.Namespace) -> int:
    from cell.backup import backup

    result = backup(args.backup_config, args.out, args.cell_dir)
    m = result.manifest
    total = sum(f["bytes"] for f in m["files"])
    print(f"backup {result.path}: {len(m['files'])} files, {total / 1e6:.2f} MB before compression")
    for f in m["files"]:
        print(f"  {f['role']:24} {f['name']}  ({f['bytes']} bytes, mode {f['mode']})")
    if m["calibration_id"]:
        print(f"calibration {m['calibration_id']}")
    if m["history"]:
        rows = m["history"]["rows"]
        print("history: " + ", ".join(f"{n} {t}" for t, n in rows.items() if t not in ("schema_version", "marks")))
    for a in m["absent"]:
        print(f"  not there (not backed up): {a['role']} {a['path']}")
    for note in result.notes:
        print(f"note: {note}")
    return 0


def cmd_restore(args: argparse.Namespace) -> int:
    from cell.backup import restore

    result = restore(args.archive, args.into)
    m = result.manifest
    print(f"restored {len(m['files'])} files of {args.archive} (made {m['created_utc']}) into {result.target}")
    if m.get("calibration_id"):
        print(f"calibration {m['calibration_id']} (its content hash checked)")
    print(f"users: {', '.join(result.users) or 'none'}")
    print(f"recipes: {', '.join(result.recipes) or 'none'}")
    if result.history_rows:
        rows = result.history_rows
        print("history: " + ", ".join(f"{n} {t}" for t, n in rows.items() if t not in ("schema_version", "marks")))
    for note in result.notes:
        print(f"note: {note}")
    if result.config is not None:
        print(f"start it from that folder: cd {result.target} && run-cell serve --config {result.config}")
    print("the files belong to the user who restored them: chown -R the service's user before starting it")
    return 0

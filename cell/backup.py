"""`run-cell backup` and `run-cell restore`: everything a cell keeps, in one archive, and back.

What a cell keeps is read off its config (relative paths start at the cell's folder, the
service's working directory): the config file itself, the active calibration and its backups,
the taught robot frame, the users file, the servers' certificates and keys with the OPC UA
trust lists (trusted/ and rejected/ client certificates), the screen's and MQTT's TLS files,
the recipes, and the history database. The database is copied with SQLite's online backup
API, from a read-only connection: a consistent snapshot even while the service writes to it,
never a half-copied file. (History in PostgreSQL is the plant's to back up, pg_dump; the
cell's local outbox of rows not yet sent is copied the same way.)

The archive (tar.gz, mode 0600: it holds keys and password hashes) is written whole or not at
all (a temporary file beside it, synced, then renamed). Its first member, manifest.json, says
the package's and each file format's version and lists every file with its size, mode and
sha256; the files follow under files/, each at its path relative to the cell's folder (a path
outside that folder under files/outside/, its absolute path below that).

Restore checks everything before it writes anything: every member's name (no absolute path,
no `..`, nothing but regular files; a name in an archive is never trusted as a path), that the
members are exactly the manifest's and each matches its size and sha256, that the target folder
is empty or new and that no running service holds its data folder (cell.locks). It extracts
into a hidden folder beside the target with the files' modes (keys stay 0600), checks the
calibration's content hash and the history's rows against the manifest, then renames that folder
into place: a target is either untouched or whole.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import secrets
import shutil
import sqlite3
import stat
import tarfile
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO

from cell.atomicfile import write_atomic
from cell.config import CellConfig, load_config
from cell.errors import CellError, InputError, OutputError

FORMAT = "pick-cell/backup"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
FILES = "files"
OUTSIDE = "outside"
MAX_MANIFEST_BYTES = 16 * 2**20
CHUNK = 1 << 20


class BackupRefused(CellError):
    """A backup or restore that cannot be done safely; nothing was written."""


# ---- what a cell keeps ---------------------------------------------------------------------
@dataclass
class Item:
    """One file of the cell: its role, where it is now, its name in the archive."""

    role: str
    source: Path
    name: str  # relative to files/, POSIX


@dataclass
class Plan:
    items: list[Item] = field(default_factory=list)
    absent: list[dict[str, str]] = field(default_factory=list)  # configured but not there (no taught frame yet)
    history_db: Item | None = None  # copied with the online backup API
    notes: list[str] = field(default_factory=list)


def archive_name(path: Path, cell_dir: Path) -> str:
    """A file's name in the archive (and in a restored folder): relative to the cell's folder,
    or outside/ABSOLUTE-PATH for one that lies elsewhere."""
    absolute = Path(os.path.abspath(Path(cell_dir) / path))
    try:
        rel = absolute.relative_to(Path(os.path.abspath(cell_dir)))
    except ValueError:
        rel = Path(OUTSIDE) / absolute.relative_to(absolute.anchor)
    return rel.as_posix()


def plan(config: CellConfig, config_file: Path | None, cell_dir: Path) -> Plan:
    """Every file of the cell its config names, and those it names that are not there."""
    from cell.access.security import certificate_dir
    from cell.history.config import OUTBOX_FILE, data_dir, database_url
    from cell.history.db import sqlite_path

    out = Plan()
    seen: set[str] = set()
    cell_dir = Path(os.path.abspath(cell_dir))

    def at(path: Path) -> Path:
        return cell_dir / path  # an absolute path stays itself

    def add_file(role: str, path: Path | None, required: bool = False) -> None:
        if path is None:
            return
        where = at(path)
        if where.is_file():
            name = archive_name(where, cell_dir)
            if name not in seen:
                seen.add(name)
                out.items.append(Item(role, where, name))
        elif required:
            raise BackupRefused(f"{where}: the {role} is not there", hint="give the cell's folder with --cell-dir")
        else:
            out.absent.append({"role": role, "path": str(path)})

    def add_folder(role: str, folder: Path | None) -> None:
        if folder is None:
            return
        where = at(folder)
        if not where.is_dir():
            out.absent.append({"role": role, "path": str(folder)})
            return
        for dirpath, dirnames, filenames in os.walk(where):
            dirnames.sort()
            for f in sorted(filenames):
                p = Path(dirpath) / f
                if f.startswith(".") and f.endswith(".tmp") or not p.is_file() or p.is_symlink():
                    continue  # a file being written (atomicfile's temporary) or not a plain file
                add_file(role, p)

    if config_file is not None:
        add_file("config", Path(os.path.abspath(config_file)), required=True)
    add_file("calibration", config.calibration.active_path)
    add_folder("calibration backups", config.calibration.backup_dir)
    add_file("robot frame", config.planning.taught_path)
    add_file("users file", config.service.users_file)
    cert_dir = certificate_dir(config)
    add_folder("certificates and keys", cert_dir)
    add_folder("trusted OPC UA clients", config.service.trusted_clients_dir)
    add_folder("rejected OPC UA clients", config.service.rejected_clients_dir)
    add_file("screen TLS certificate", config.service.web.tls_certificate)
    add_file("screen TLS key", config.service.web.tls_key)
    add_file("MQTT CA", config.telemetry.mqtt.ca_file)
    add_file("MQTT client certificate", config.telemetry.mqtt.client_cert_file)
    add_file("MQTT client key", config.telemetry.mqtt.client_key_file)
    add_folder("recipes", config.service.machine_vision.recipes_dir)
    if config.history.enabled:
        url = database_url(config.history, config.run.log_dir)
        if url.startswith("sqlite:///"):
            db, role = sqlite_path(url), "history database"
        else:
            db, role = data_dir(config.history, config.run.log_dir) / OUTBOX_FILE, "history outbox"
            out.notes.append(
                "the history is in PostgreSQL: back that database up with the plant's tools (pg_dump); "
                "this archive holds the cell's outbox of rows not yet sent"
            )
        if at(db).is_file():
            out.history_db = Item(role, at(db), archive_name(at(db), cell_dir))
        else:
            out.absent.append({"role": role, "path": str(db)})
    return out


# ---- the history database, copied live ----------------------------------------------------
def snapshot_sqlite(source: Path, target: Path) -> dict[str, int]:
    """A consistent copy of a live SQLite database (the online backup API, from a read-only
    connection: the service goes on writing), checked whole; the rows of each table."""
    try:
        src = sqlite3.connect(f"file:{source}?mode=ro", uri=True, timeout=30.0)
    except sqlite3.Error as e:
        raise BackupRefused(f"{source}: cannot open the history database: {e}") from None
    try:
        src.execute("PRAGMA busy_timeout=30000")
        dst = sqlite3.connect(target)
        try:
            src.backup(dst)
            dst.execute("PRAGMA journal_mode=DELETE")  # one file, whatever the source's journal
            check = dst.execute("PRAGMA integrity_check").fetchone()[0]
            if check != "ok":
                raise BackupRefused(f"{source}: the history database's copy is damaged: {check}")
            return table_rows(dst)
        finally:
            dst.close()
    except sqlite3.DatabaseError as e:
        raise BackupRefused(f"{source}: cannot copy the history database: {e}") from None
    finally:
        src.close()


def table_rows(conn: sqlite3.Connection) -> dict[str, int]:
    names = [r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
    return {n: int(conn.execute(f'SELECT count(*) FROM "{n}"').fetchone()[0]) for n in names}


# ---- backup --------------------------------------------------------------------------------
def _sha256_file(path: Path) -> tuple[str, int]:
    h, size = hashlib.sha256(), 0
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            h.update(chunk)
            size += len(chunk)
    return h.hexdigest(), size


def versions() -> dict[str, Any]:
    from importlib.metadata import PackageNotFoundError, version

    from cell.calibration.store import SCHEMA, SCHEMA_VERSION
    from cell.history.schema import VERSION as HISTORY_VERSION

    try:
        package = version("pick-cell")
    except PackageNotFoundError:
        package = "unknown"
    return {
        "package": package,
        "calibration_schema": SCHEMA,
        "calibration_version": SCHEMA_VERSION,
        "history_schema_version": HISTORY_VERSION,
    }


@dataclass
class BackupResult:
    path: Path
    manifest: dict[str, Any]
    notes: list[str]


def backup(config_file: Path | None, out: Path, cell_dir: Path | None = None) -> BackupResult:
    """Write the cell's archive to `out` (whole or not at all)."""
    cell_dir = Path(cell_dir or Path.cwd())
    config = load_config(config_file)
    the_plan = plan(config, config_file, cell_dir)
    out = Path(out)
    if out.suffixes[-2:] != [".tar", ".gz"] and out.suffix != ".tgz":
        raise BackupRefused(f"--out {out}: the archive is a tar.gz", hint="name it CELL.tar.gz")
    staging = Path(os.path.abspath(out)).parent / f".{out.name}.{secrets.token_hex(4)}.d"
    try:
        staging.mkdir(parents=True, mode=0o700)
    except OSError as e:
        raise OutputError(f"{out}: cannot write beside it: {e.strerror or e}") from None
    try:
        files: list[dict[str, Any]] = []
        # the copy taken now is what goes in: a file replaced meanwhile cannot make a hash lie
        kept: dict[str, Path] = {}
        history: dict[str, Any] | None = None
        calibration_id = None
        for item in the_plan.items:
            copy = staging / str(len(kept))
            try:
                shutil.copyfile(item.source, copy)
                os.chmod(copy, stat.S_IMODE(item.source.stat().st_mode))
            except OSError as e:
                raise BackupRefused(
                    f"{item.source}: cannot read the {item.role}: {e.strerror or e}",
                    hint="run the backup as the service's user (or root): keys and the users file are theirs alone",
                ) from None
            if item.role == "calibration":
                calibration_id = _calibration_id(copy)
            kept[item.name] = copy
        db = the_plan.history_db
        if db is not None:
            copy = staging / "history.sqlite"
            history = {"file": db.name, "rows": snapshot_sqlite(db.source, copy)}
            os.chmod(copy, stat.S_IMODE(db.source.stat().st_mode))
            kept[db.name] = copy
        for item in [*the_plan.items, *([db] if db is not None else [])]:
            digest, size = _sha256_file(kept[item.name])
            mode = stat.S_IMODE(kept[item.name].stat().st_mode)
            files.append(
                {"name": item.name, "role": item.role, "source": str(item.source), "bytes": size}
                | {"mode": f"{mode:04o}", "sha256": digest}
            )
        config_name = next((f["name"] for f in files if f["role"] == "config"), None)
        manifest: dict[str, Any] = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "created_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "versions": versions(),
            "cell_dir": str(Path(os.path.abspath(cell_dir))),
            "config": config_name,
            "calibration_id": calibration_id,
            "history": history,
            "files": files,
            "absent": the_plan.absent,
            "notes": the_plan.notes,
        }
        manifest_bytes = json.dumps(manifest, indent=1).encode("utf-8")

        def write(f: BinaryIO) -> None:
            os.fchmod(f.fileno(), 0o600)  # keys and password hashes
            with tarfile.open(fileobj=f, mode="w:gz", format=tarfile.PAX_FORMAT) as tar:
                _add(tar, MANIFEST, io.BytesIO(manifest_bytes), len(manifest_bytes), 0o600)
                for entry in files:
                    with open(kept[entry["name"]], "rb") as src:
                        _add(tar, f"{FILES}/{entry['name']}", src, entry["bytes"], int(entry["mode"], 8))

        write_atomic(out, write)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return BackupResult(out, manifest, the_plan.notes)


def _add(tar: tarfile.TarFile, name: str, data: BinaryIO, size: int, mode: int) -> None:
    info = tarfile.TarInfo(name)
    info.size, info.mode, info.mtime = size, mode, int(datetime.now(UTC).timestamp())
    tar.addfile(info, data)


def _calibration_id(path: Path) -> str | None:
    from cell.calibration.store import Calibration

    try:
        return Calibration.load(path).content_id
    except CellError:
        return None  # kept as it is; restore compares only what it could read here


# ---- restore -------------------------------------------------------------------------------
def safe_member_name(name: object) -> PurePosixPath:
    """A member's name as a relative path inside the target, or BackupRefused: never absolute,
    never `..`, no backslash or NUL, nothing empty."""
    if not isinstance(name, str) or not name or "\\" in name or "\x00" in name:
        raise BackupRefused(f"archive member {name!r}: not a plain relative name; nothing was restored")
    path = PurePosixPath(name)
    if path.is_absolute() or any(part in ("..", "") for part in name.split("/")):
        raise BackupRefused(
            f"archive member {name!r}: an absolute path or '..' would write outside the target; nothing was restored",
            hint="the archive was not made by run-cell backup, or was altered",
        )
    return path


@dataclass
class RestoreResult:
    target: Path
    manifest: dict[str, Any]
    config: Path | None
    users: list[str]
    recipes: list[str]
    history_rows: dict[str, int]
    notes: list[str]


def _refuse_live_target(target: Path) -> None:
    if target.is_symlink() or (target.exists() and not target.is_dir()):
        raise BackupRefused(f"--into {target}: not a folder", hint="give a new folder to restore into")
    if target.is_dir() and any(target.iterdir()):
        raise BackupRefused(
            f"--into {target}: the folder is not empty; restore never overwrites a cell",
            hint="restore into a new folder, then stop the service and swap the folders",
        )


def _refuse_held(target: Path, config: CellConfig, cell_dir: Path) -> None:
    """A service (or a recalibration, a user command, a teach) running on the target's files."""
    from cell.history.config import data_dir
    from cell.locks import cell_resource, holder_of

    def at(p: Path) -> Path:
        return Path(os.path.abspath(target)) / archive_name(p, cell_dir)

    checks = [
        (cell_resource(at(data_dir(config.history, config.run.log_dir))), "its data folder"),
        (str(at(config.calibration.active_path)), "its calibration"),
        (str(at(config.planning.taught_path)), "its robot frame"),
    ]
    if config.service.users_file is not None:
        checks.append((str(at(config.service.users_file)), "its users file"))
    for resource, what in checks:
        holder = holder_of(resource)
        if holder:
            raise BackupRefused(
                f"--into {target}: a live cell: {holder} holds {what} ({resource})",
                hint="stop the service (systemctl stop pick-cell) or restore into another folder",
            )


def _read_manifest(tar: tarfile.TarFile, archive: Path) -> dict[str, Any]:
    first = tar.next()
    if first is None or first.name != MANIFEST or not first.isfile() or first.size > MAX_MANIFEST_BYTES:
        raise BackupRefused(f"{archive}: no manifest.json first: not an archive made by run-cell backup")
    f = tar.extractfile(first)
    assert f is not None
    try:
        manifest = json.loads(f.read())
    except (ValueError, UnicodeDecodeError) as e:
        raise BackupRefused(f"{archive}: manifest.json is not valid JSON: {e}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise BackupRefused(f"{archive}: manifest.json is not a {FORMAT} manifest")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise BackupRefused(
            f"{archive}: backup format version {manifest.get('format_version')!r}; this run-cell reads {FORMAT_VERSION}",
            hint="restore it with the run-cell version that made it (run-cell --version)",
        )
    files = manifest.get("files")
    if not isinstance(files, list) or not all(isinstance(f, dict) for f in files):
        raise BackupRefused(f"{archive}: manifest.json lists no files")
    for entry in files:
        safe_member_name(entry.get("name"))
        if not isinstance(entry.get("sha256"), str) or not isinstance(entry.get("bytes"), int):
            raise BackupRefused(f"{archive}: manifest entry {entry.get('name')!r} has no sha256 or size")
        try:
            mode = int(str(entry.get("mode")), 8)
        except ValueError:
            raise BackupRefused(f"{archive}: manifest entry {entry['name']!r}: mode {entry.get('mode')!r}") from None
        if mode & ~0o777:
            raise BackupRefused(f"{archive}: manifest entry {entry['name']!r}: mode {entry['mode']} is not a file's")
    return manifest


def _open_archive(archive: Path) -> tarfile.TarFile:
    try:
        return tarfile.open(archive, mode="r:gz")
    except FileNotFoundError:
        raise InputError(f"{archive}: no such archive", hint="give the file run-cell backup --out wrote") from None
    except (tarfile.TarError, OSError, EOFError) as e:
        raise BackupRefused(f"{archive}: not a readable tar.gz archive: {e}") from None


def _extract(tar: tarfile.TarFile, archive: Path, manifest: dict[str, Any], staging: Path) -> None:
    """Every member after the manifest, checked against it, into `staging`."""
    expected = {e["name"]: e for e in manifest["files"]}
    done: set[str] = set()
    while True:
        try:
            member = tar.next()
        except (tarfile.TarError, OSError, EOFError) as e:
            raise BackupRefused(f"{archive}: the archive is damaged: {e}; nothing was restored") from None
        if member is None:
            break
        path = safe_member_name(member.name)
        if path.parts[0] != FILES or len(path.parts) < 2:
            raise BackupRefused(f"{archive}: member {member.name!r} is not under {FILES}/; nothing was restored")
        name = PurePosixPath(*path.parts[1:]).as_posix()
        if not member.isfile():
            raise BackupRefused(f"{archive}: member {member.name!r} is not a plain file (a link, a device); refused")
        if name not in expected or name in done:
            raise BackupRefused(
                f"{archive}: member {member.name!r} is not in the manifest (or twice): the archive was altered; "
                "nothing was restored"
            )
        entry = expected[name]
        dest = staging / name
        dest.parent.mkdir(parents=True, exist_ok=True)
        src = tar.extractfile(member)
        assert src is not None
        h, size = hashlib.sha256(), 0
        fd = os.open(dest, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "wb") as out:
            while chunk := src.read(CHUNK):
                h.update(chunk)
                size += len(chunk)
                out.write(chunk)
            out.flush()
            os.fsync(out.fileno())
        if size != entry["bytes"] or h.hexdigest() != entry["sha256"]:
            raise BackupRefused(
                f"{archive}: {name} does not match the manifest ({size} bytes, sha256 {h.hexdigest()[:16]}…; "
                f"listed {entry['bytes']} bytes, {entry['sha256'][:16]}…): the archive is damaged or was altered; "
                "nothing was restored"
            )
        os.chmod(dest, int(entry["mode"], 8))
        done.add(name)
    missing = sorted(set(expected) - done)
    if missing:
        raise BackupRefused(
            f"{archive}: {len(missing)} file(s) the manifest lists are missing: {', '.join(missing[:5])}; "
            "nothing was restored"
        )


def restore(archive: Path, target: Path) -> RestoreResult:
    """Restore `archive` into the new or empty folder `target` (see the module's docstring)."""
    archive, target = Path(archive), Path(target)
    _refuse_live_target(target)
    staging = Path(os.path.abspath(target)).parent / f".{target.name}.restore-{secrets.token_hex(4)}"
    with _open_archive(archive) as tar:
        try:
            manifest = _read_manifest(tar, archive)
        except (tarfile.TarError, OSError, EOFError) as e:
            raise BackupRefused(f"{archive}: the archive is damaged: {e}") from None
        try:
            staging.parent.mkdir(parents=True, exist_ok=True)
            staging.mkdir(mode=0o700)
        except OSError as e:
            raise OutputError(f"--into {target}: cannot create {staging}: {e.strerror or e}") from None
        try:
            _extract(tar, archive, manifest, staging)
            result = _check_restored(staging, target, manifest)
            _refuse_live_target(target)  # again: nothing came meanwhile
            _refuse_held(target, _restored_config(staging, manifest), _cell_dir(manifest))
            os.chmod(staging, 0o755)
            os.replace(staging, target)  # a new name, or over an empty folder: all at once
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    return result


def _cell_dir(manifest: dict[str, Any]) -> Path:
    cell_dir = manifest.get("cell_dir")
    if not isinstance(cell_dir, str) or not cell_dir.startswith("/"):
        raise BackupRefused(f"manifest.json: cell_dir {cell_dir!r} is not an absolute path")
    return Path(cell_dir)


def _restored_config(root: Path, manifest: dict[str, Any]) -> CellConfig:
    name = manifest.get("config")
    if not name:
        return CellConfig()
    return load_config(root / safe_member_name(name))


def _check_restored(root: Path, target: Path, manifest: dict[str, Any]) -> RestoreResult:
    """The restored files read as the cell will read them: the config, the calibration's hash,
    the users, the recipes and the history's rows against the manifest's."""
    from cell.access.users import read_users
    from cell.calibration.store import Calibration

    config = _restored_config(root, manifest)
    cell_dir = _cell_dir(manifest)

    def at(p: Path) -> Path:
        return root / archive_name(p, cell_dir)

    notes: list[str] = []
    outside = [e["name"] for e in manifest["files"] if e["name"].startswith(OUTSIDE + "/")]
    if outside:
        notes.append(
            f"{len(outside)} file(s) lay outside the cell's folder ({manifest.get('cell_dir')}): restored under "
            f"{target / OUTSIDE}; the config names them by their absolute paths: move them there or edit the config"
        )
    want = manifest.get("calibration_id")
    cal = at(config.calibration.active_path)
    if want and cal.is_file():
        got = Calibration.load(cal).content_id
        if got != want:
            raise BackupRefused(f"restored calibration {got} is not the one backed up ({want}); nothing was restored")
    users: list[str] = []
    if config.service.users_file is not None and at(config.service.users_file).is_file():
        users = sorted(read_users(at(config.service.users_file)))
    recipes_dir = at(config.service.machine_vision.recipes_dir)
    recipes = sorted(p.stem for p in recipes_dir.glob("*.toml")) if recipes_dir.is_dir() else []
    rows: dict[str, int] = {}
    history = manifest.get("history")
    if isinstance(history, dict) and history.get("file"):
        conn = sqlite3.connect(f"file:{root / safe_member_name(history['file'])}?mode=ro", uri=True)
        try:
            rows = table_rows(conn)
        finally:
            conn.close()
        if rows != history.get("rows"):
            raise BackupRefused(f"restored history rows {rows} are not the backed-up {history.get('rows')}")
    config_name = manifest.get("config")
    config_path = target / safe_member_name(config_name) if config_name else None
    return RestoreResult(target, manifest, config_path, users, recipes, rows, notes + list(manifest.get("notes", [])))

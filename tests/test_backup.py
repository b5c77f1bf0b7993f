"""`run-cell backup` and `run-cell restore` on a real cell folder: a calibration with a backup,
users, a recipe, OPC UA keys and a trust list, history rows in a real SQLite store. The round
trip gives back the same calibration hash, users, recipes and rows; every refusal (a live cell,
an altered archive, a member that would escape the target, a missing member) says why, exits
non-zero and leaves nothing half-written."""

from __future__ import annotations

import io
import json
import sqlite3
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from cell.access.users import UserEntry, hash_password, read_users, write_users
from cell.backup import snapshot_sqlite
from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.camera_model import CameraModel
from cell.cli import main
from cell.config import load_config
from cell.core.events import Role
from cell.history.store import HistoryStore
from cell.recipes import RecipeBook
from tests.history_helpers import shift_events

pytestmark = pytest.mark.timeout(60)

CONFIG = """\
[service]
users_file = "users.json"
[history]
cell_name = "cell-a"
min_free_mb = 1
"""

RECIPE = """\
description = "bolts into the left bin; nuts stay"
[pick.bolt]
pick_above_table_mm = 3.5
jaw_across_axis = true
bin_robot_mm = [-200.0, 60.0, 60.0]
"""


@pytest.fixture
def cell(tmp_path, monkeypatch) -> Path:
    """A cell's folder, as the service's WorkingDirectory holds it; the test runs in it."""
    root = tmp_path / "cell"
    (root / "configs").mkdir(parents=True)
    (root / "configs" / "line.toml").write_text(CONFIG)
    monkeypatch.chdir(root)
    cam = CameraModel.looking_down(64, 48, 0.30, (132, 88))
    (root / "calibration" / "backups").mkdir(parents=True)
    Calibration("camera", CameraMap(cam), (64, 48), cam).save(root / "calibration" / "active.json")
    (root / "calibration" / "backups" / "active-20261201T060000Z.json").write_text("{}")
    keys = root / "calibration" / "opcua"
    (keys / "trusted").mkdir(parents=True)
    (keys / "server-key.pem").write_bytes(b"-----BEGIN PRIVATE KEY-----\nnot a real key\n")
    (keys / "server-key.pem").chmod(0o600)
    (keys / "server-cert.der").write_bytes(b"\x30\x82cert")
    (keys / "trusted" / "plc.der").write_bytes(b"\x30\x82plc")
    write_users(root / "users.json", [UserEntry("anna", Role.OPERATOR, hash_password("secret-pass", 1000))])
    (root / "recipes").mkdir()
    (root / "recipes" / "bolts-only.toml").write_text(RECIPE)
    config = load_config(root / "configs" / "line.toml")
    store = HistoryStore(config.history, config.run.log_dir)
    for e in shift_events():
        store.handle(e)
    assert store.wait_idle(30)
    store.close()
    return root


def rows(db: Path) -> dict[str, list]:
    conn = sqlite3.connect(db)
    try:
        return {t: conn.execute(f"SELECT * FROM {t} ORDER BY id").fetchall() for t in ("picks", "jobs", "alarms")}
    finally:
        conn.close()


def test_a_backup_restored_into_a_new_folder_is_the_same_cell(cell, tmp_path, capsys):
    archive = tmp_path / "cell.tar.gz"
    assert main(["backup", "--config", "configs/line.toml", "--out", str(archive)]) == 0
    out = capsys.readouterr().out
    assert "history: " in out and "5 picks" in out
    assert archive.stat().st_mode & 0o777 == 0o600  # keys and password hashes
    with tarfile.open(archive) as tar:
        names = tar.getnames()
        manifest = json.loads(tar.extractfile("manifest.json").read())  # type: ignore[union-attr]
    assert names[0] == "manifest.json"
    expected = {
        "configs/line.toml",
        "calibration/active.json",
        "calibration/backups/active-20261201T060000Z.json",
        "calibration/opcua/server-key.pem",
        "calibration/opcua/server-cert.der",
        "calibration/opcua/trusted/plc.der",
        "users.json",
        "recipes/bolts-only.toml",
        "data/history.sqlite",
    }
    assert {f["name"] for f in manifest["files"]} == expected
    assert set(names) == {"manifest.json"} | {f"files/{n}" for n in expected}
    assert manifest["versions"]["history_schema_version"] >= 1 and manifest["config"] == "configs/line.toml"
    assert {a["role"] for a in manifest["absent"]} == {"robot frame"}  # never taught: said, not an error

    target = tmp_path / "restored"
    target.mkdir()  # an empty folder is a new one
    assert main(["restore", str(archive), "--into", str(target)]) == 0
    out = capsys.readouterr().out
    assert "users: anna" in out and "recipes: bolts-only" in out
    calibration = Calibration.load(cell / "calibration" / "active.json").content_id
    assert Calibration.load(target / "calibration" / "active.json").content_id == calibration
    assert manifest["calibration_id"] == calibration
    assert read_users(target / "users.json") == read_users(cell / "users.json")
    assert [(r.recipe_id, r.error) for r in RecipeBook(target / "recipes").list()] == [("bolts-only", "")]
    assert rows(target / "data" / "history.sqlite") == rows(cell / "data" / "history.sqlite")
    assert len(rows(target / "data" / "history.sqlite")["picks"]) == 5
    for secret in ("calibration/opcua/server-key.pem", "users.json"):
        assert (target / secret).stat().st_mode & 0o777 == 0o600, secret
    assert (target / "configs" / "line.toml").read_text() == CONFIG
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging folder left


def test_the_history_is_copied_while_a_writer_holds_a_transaction(cell, tmp_path):
    """The online backup takes the last committed state, without waiting for the writer to finish."""
    db = cell / "data" / "history.sqlite"
    writer = sqlite3.connect(db, isolation_level=None)
    try:
        writer.execute("BEGIN IMMEDIATE")
        writer.execute("DELETE FROM picks")  # not committed: the copy must still hold every pick
        counts = snapshot_sqlite(db, tmp_path / "copy.sqlite")
    finally:
        writer.execute("ROLLBACK")
        writer.close()
    assert counts["picks"] == 5
    assert rows(tmp_path / "copy.sqlite") == rows(db)


def _rewrite(archive: Path, out: Path, change) -> None:
    """A copy of `archive` whose members pass through change(name, data) -> [(name, data), ...]."""
    with tarfile.open(archive) as tar:
        members = [(m.name, tar.extractfile(m).read(), m.mode) for m in tar.getmembers()]  # type: ignore[union-attr]
    with tarfile.open(out, "w:gz") as tar:
        for name, data, mode in members:
            for new_name, new_data in change(name, data):
                info = tarfile.TarInfo(new_name)
                info.size, info.mode = len(new_data), mode
                tar.addfile(info, io.BytesIO(new_data))


def _manifest_edit(edit):
    def change(name, data):
        if name == "manifest.json":
            m = json.loads(data)
            edit(m)
            return [(name, json.dumps(m).encode())]
        return [(name, data)]

    return change


@pytest.fixture
def archive(cell, tmp_path) -> Path:
    path = tmp_path / "cell.tar.gz"
    assert main(["backup", "--config", "configs/line.toml", "--out", str(path)]) == 0
    return path


def _refused(capsys, argv, *words) -> str:
    assert main(argv) != 0
    err = capsys.readouterr().err
    assert all(w in err for w in words), err
    assert "Traceback" not in err
    return err


def _only(tmp_path, *names) -> None:
    """Nothing half-written: tmp_path holds only these (no target, no staging folder)."""
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names)


def test_restore_refuses_a_live_cell_its_folder_not_empty_or_its_data_held(archive, cell, tmp_path, capsys):
    _refused(capsys, ["restore", str(archive), "--into", str(cell)], "not empty", "never overwrites")
    assert Calibration.load(cell / "calibration" / "active.json")  # untouched
    target = tmp_path / "new"
    # a service started in that folder holds its data folder's lock (run-cell serve: cell.locks.cell_lock)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys; from cell.locks import cell_lock\n"
         f"with cell_lock({str(target / 'data')!r}):\n print('held', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=Path(__file__).parent.parent,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        _refused(capsys, ["restore", str(archive), "--into", str(target)], "a live cell", f"pid {holder.pid}")
    finally:
        holder.communicate("")
    _only(tmp_path, "cell", "cell.tar.gz")
    assert main(["restore", str(archive), "--into", str(target)]) == 0  # once it is gone


def test_restore_refuses_an_altered_file(archive, tmp_path, capsys):
    tampered = tmp_path / "tampered.tar.gz"
    _rewrite(archive, tampered, lambda n, d: [(n, d.replace(b"anna", b"mall"))])
    _refused(capsys, ["restore", str(tampered), "--into", str(tmp_path / "t")], "does not match the manifest")
    _only(tmp_path, "cell", "cell.tar.gz", "tampered.tar.gz")


@pytest.mark.parametrize(
    "change, words",
    [
        (lambda n, d: [(n, d), ("files/../../escaped", b"x")] if n == "manifest.json" else [(n, d)], "'..'"),
        (lambda n, d: [(n, d), ("/tmp/escaped", b"x")] if n == "manifest.json" else [(n, d)], "absolute path"),
        (_manifest_edit(lambda m: m["files"].append(m["files"][0] | {"name": "../../escaped"})), "'..'"),
        (lambda n, d: [(n, d), ("files/extra.txt", b"x")] if n == "manifest.json" else [(n, d)], "not in the manifest"),
        (lambda n, d: [] if n == "files/users.json" else [(n, d)], "missing: users.json"),
        (lambda n, d: [] if n == "manifest.json" else [(n, d)], "no manifest.json"),
    ],
    ids=["dot-dot-member", "absolute-member", "dot-dot-in-manifest", "extra-member", "missing-member", "no-manifest"],
)
def test_restore_refuses_a_member_that_escapes_or_does_not_match(archive, tmp_path, capsys, change, words):
    bad = tmp_path / "bad.tar.gz"
    _rewrite(archive, bad, change)
    _refused(capsys, ["restore", str(bad), "--into", str(tmp_path / "t")], words)
    _only(tmp_path, "cell", "cell.tar.gz", "bad.tar.gz")
    assert not Path("/tmp/escaped").exists()


def test_restore_of_a_missing_or_broken_archive_says_so(tmp_path, capsys):
    _refused(capsys, ["restore", str(tmp_path / "none.tar.gz"), "--into", str(tmp_path / "t")], "no such archive")
    (tmp_path / "junk.tar.gz").write_bytes(b"not gzip at all")
    _refused(capsys, ["restore", str(tmp_path / "junk.tar.gz"), "--into", str(tmp_path / "t")], "not a readable")
    _only(tmp_path, "junk.tar.gz")


def test_backup_refuses_a_damaged_history_or_a_missing_config_and_writes_nothing(cell, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    _refused(capsys, ["backup", "--config", "configs/none.toml", "--out", str(out / "c.tar.gz")], "none.toml")
    (cell / "data" / "history.sqlite").write_bytes(b"SQLite format 3\x00" + b"\xff" * 4000)
    for side in ("-wal", "-shm"):
        (cell / "data" / f"history.sqlite{side}").unlink(missing_ok=True)
    _refused(capsys, ["backup", "--config", "configs/line.toml", "--out", str(out / "c.tar.gz")], "history database")
    assert list(out.iterdir()) == []  # no archive, no temporary file, no staging folder


def test_a_running_line_service_holds_its_data_folder(tmp_path):
    """What restore's live-cell check reads: `run-cell serve` (open_service) holds the lock of its
    data folder for as long as it runs, naming itself."""
    import contextlib
    import os

    from cell.commands.serve import open_service
    from cell.config import CellConfig
    from cell.locks import cell_resource, holder_of

    cfg = CellConfig()
    cfg.camera.width_px, cfg.camera.height_px = 960, 540
    cfg.sim.reference_marks_mm = []
    cfg.run.log_dir = tmp_path / "logs"
    with contextlib.ExitStack() as stack:
        open_service(cfg, False, stack)
        assert holder_of(cell_resource(tmp_path / "data")) == f"{Path(sys.argv[0]).name} pid {os.getpid()}"
    assert holder_of(cell_resource(tmp_path / "data")) is None


def test_a_file_outside_the_cells_folder_comes_back_under_outside_and_is_said(cell, tmp_path, capsys):
    etc = tmp_path / "etc"
    etc.mkdir()
    (etc / "line.toml").write_text(CONFIG)
    archive = tmp_path / "cell.tar.gz"
    assert main(["backup", "--config", str(etc / "line.toml"), "--out", str(archive), "--cell-dir", str(cell)]) == 0
    target = tmp_path / "restored"
    assert main(["restore", str(archive), "--into", str(target)]) == 0
    out = capsys.readouterr().out
    inside = target / "outside" / (etc / "line.toml").relative_to("/")
    assert inside.read_text() == CONFIG
    assert "outside the cell's folder" in out and "users: anna" in out

"""The history store in the running cell: counters and last picks back after a restart, a full
disk (the cell stops safely, or keeps picking with a warning), `kill -9` mid-shift and a clean
restart with every verified pick there once."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import time

import httpx
import pytest

from cell.cli import main
from cell.core.commands import Command, VisionState
from cell.service.shiftlog import read_shift
from tests.serve_process import ServeProcess
from tests.test_service import picked, production, small_config, wait_for

V = VisionState
pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]


def no_feeder(tmp_path, **history):
    cfg = small_config(tmp_path)
    cfg.sim.feeder = cfg.sim.feeder.model_copy(update={"parts_per_minute": 0})
    cfg.history.min_free_mb = 1
    for k, v in history.items():
        setattr(cfg.history, k, v)
    return cfg


def test_counters_and_last_picks_come_back_from_the_store_after_a_restart(tmp_path):
    cfg = no_feeder(tmp_path)
    with production(cfg) as service:
        service.command(Command.START_SINGLE)
        wait_for(lambda: service.snapshot().vision_state == V.READY, 120, "the job's end")
        before = service.snapshot()
        assert picked(service) == 17
    with production(cfg) as service:
        after = service.snapshot()
        assert after.counters == before.counters and after.shift == before.shift
        assert [p.pick_id for p in after.last_picks] == [p.pick_id for p in before.last_picks]
        assert len({p.pick_id for p in after.last_picks}) == len(after.last_picks) == 17
    db = sqlite3.connect(tmp_path / "data" / "history.sqlite")
    audit_picked = sum(e["kind"] == "verify" and e["result"] == "picked" for e in read_shift(tmp_path / "logs"))
    assert db.execute("SELECT count(*) FROM picks WHERE outcome = 'picked'").fetchone() == (audit_picked,)


@pytest.fixture
def tiny_disk(tmp_path):
    """A 1 MiB tmpfs for the data folder (needs root and mount(8)); skipped, saying why, elsewhere."""
    where = tmp_path / "disk"
    where.mkdir()
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("a full disk needs a tmpfs: root and mount(8); the injected write failure covers the logic")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(where)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield where
    finally:
        if subprocess.run(["umount", str(where)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(where)], check=False)  # a file still open: detach it anyway


def fill_disk(where) -> None:
    fd = os.open(where / "filler", os.O_WRONLY | os.O_CREAT)
    try:
        while os.write(fd, b"\0" * 4096):
            pass
    except OSError:
        pass  # full
    finally:
        os.close(fd)


def test_a_full_disk_stops_the_cell_safely_when_the_history_is_required(tmp_path, tiny_disk):
    cfg = no_feeder(tmp_path, data_dir=tiny_disk, images=False)
    with production(cfg) as service:
        fill_disk(tiny_disk)
        service.command(Command.START_SINGLE)
        wait_for(lambda: service.snapshot().vision_state == V.ERROR, 120, "Error")
        alarm = service.snapshot().alarm
        assert alarm.reason.startswith("history cannot be written: ") and "full" in alarm.reason
        assert alarm.source == "history" and picked(service) < 17
    events = read_shift(tmp_path / "logs")
    assert [e["step"] for e in events if e["kind"] == "safe_step"][-2:] == ["home", "release torque"]
    (tiny_disk / "filler").unlink()
    db = sqlite3.connect(tiny_disk / "history.sqlite")
    assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)


def test_after_a_full_disk_fault_with_history_required_start_is_refused_while_the_disk_is_full(tmp_path, tiny_disk):
    """A Reset clears the fault's alarm, not the disk: every start is refused with the store's reason
    until the store has written again, also after the Reset; then the cell runs, with its history."""
    from cell.core.commands import InvalidState

    cfg = no_feeder(tmp_path, data_dir=tiny_disk, images=False, retry_s=0.2)
    with production(cfg) as service:
        fill_disk(tiny_disk)
        service.command(Command.START_SINGLE)
        wait_for(lambda: service.snapshot().vision_state == V.ERROR, 120, "Error")
        service.command(Command.RESET)
        snap = service.snapshot()
        assert snap.vision_state == V.READY and "history cannot be written" in snap.hold
        assert Command.START_SINGLE not in snap.allowed and Command.START_CONTINUOUS not in snap.allowed
        for command in (Command.START_SINGLE, Command.START_CONTINUOUS):
            with pytest.raises(InvalidState, match="not allowed now: history cannot be written: .*full"):
                service.command(command)
        (tiny_disk / "filler").unlink()  # space again: the store's writer writes its rows on its next try
        wait_for(lambda: Command.START_SINGLE in service.snapshot().allowed, 60, "Start allowed again")
        service.command(Command.START_SINGLE)
        wait_for(lambda: service.snapshot().vision_state == V.READY, 120, "the job's end")
        assert service.history.wait_idle(30)
        job = service.history.local.execute("SELECT count(*) FROM picks WHERE outcome = 'picked'")
        assert job[0][0] == picked(service) > 0


def test_a_full_disk_with_the_history_not_required_keeps_picking_with_a_warning(tmp_path, tiny_disk):
    cfg = no_feeder(tmp_path, data_dir=tiny_disk, images=False, required=False)
    with production(cfg) as service:
        fill_disk(tiny_disk)
        service.command(Command.START_SINGLE)
        wait_for(lambda: service.snapshot().vision_state == V.READY, 120, "the job's end")
        snap = service.snapshot()
        assert picked(service) == 17 and snap.alarm is None
        (warning,) = [w for w in snap.warnings if w.source == "history"]
        assert warning.reason.startswith("history cannot be written: ")
        (tiny_disk / "filler").unlink()  # room again: the kept rows go in, the warning goes
        wait_for(lambda: not service.snapshot().warnings, 60, "the warning cleared")
    db = sqlite3.connect(tiny_disk / "history.sqlite")
    assert db.execute("SELECT count(*) FROM picks WHERE outcome = 'picked'").fetchone() == (17,)


def test_run_cell_on_a_full_history_disk_exits_3_saying_so(tmp_path, tiny_disk, capsys):
    config = tmp_path / "cell.toml"
    config.write_text(f'[history]\ndata_dir = "{tiny_disk}"\nimages = false\n')
    fill_disk(tiny_disk)
    assert main(["--config", str(config), "--dry-run", "--log-dir", str(tmp_path / "logs")]) == 3
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "history cannot be written: " in last and "full" in last


def _speedy_config(workdir):
    path = workdir / "cell.toml"
    path.write_text(
        "[camera]\nwidth_px = 960\nheight_px = 540\n[sim]\nreference_marks_mm = []\nspeed_factor = 60\n"
        "[sim.feeder]\nparts_per_minute = 6\nmax_on_table = 25\n[service]\ncapture_interval_s = 0.5\n"
    )
    return path


def _verified(log_dir) -> list[str]:
    out = []
    for path in sorted(log_dir.glob("cell-*.jsonl")):
        for line in path.read_text().splitlines():
            try:
                e = json.loads(line)
            except json.JSONDecodeError:
                continue  # the line being written when the process was killed
            if e["kind"] == "verify":
                out.append(e["pick_id"])
    return out


def test_kill_9_mid_shift_then_a_restart_keeps_every_verified_pick_once(tmp_path):
    workdir = tmp_path / "cell"
    workdir.mkdir()
    config = _speedy_config(workdir)
    serve = ServeProcess(workdir, "--config", str(config))
    try:
        token = httpx.get(serve.url + "api/session").json()["csrf"]
        httpx.post(serve.url + "api/command/StartContinuous", headers={"x-csrf-token": token})
        deadline = time.monotonic() + 120
        while len(_verified(workdir / "logs")) < 40:
            assert time.monotonic() < deadline and serve.proc.poll() is None, "40 picks"
            time.sleep(0.1)
        serve.proc.send_signal(signal.SIGKILL)  # mid-shift: the arm moving, rows in flight
        serve.proc.wait(10)
    finally:
        serve.stop()
    before_kill = _verified(workdir / "logs")
    again = ServeProcess(workdir, "--config", str(config))
    try:
        state = httpx.get(again.url + "api/state").json()
    finally:
        assert again.stop() == 0
    db = sqlite3.connect(workdir / "data" / "rehearsal" / "history.sqlite")  # serve --dry-run: a rehearsal's store
    assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
    ids = [r[0] for r in db.execute("SELECT id FROM picks")]
    assert len(ids) == len(set(ids))
    missing = set(before_kill) - set(ids)
    assert not missing, f"{len(missing)} verified picks not in the store: {sorted(missing)[:5]}"
    c = state["counters"]
    in_audit = sum(1 for _ in before_kill)
    assert c["picked_bolts"] + c["picked_nuts"] + c["misses"] <= in_audit  # counted from the store, not twice
    shown = db.execute("SELECT count(*) FROM picks WHERE outcome = 'picked'").fetchone()[0]
    assert c["picked_bolts"] + c["picked_nuts"] == shown

"""Rehearsals apart from production (issue 33, item 5): a dry run (`run-cell --dry-run`, `run-cell
serve --dry-run`, `make demo`) writes its picks to a store of its own and marks its audit lines, so
production's counters, report, OPC UA counters and read-backs after a restart never count them;
`run-cell history --simulated` lists them."""

from __future__ import annotations

import asyncio
import json
import sqlite3

import pytest
from asyncua import Client

from cell.cli import main
from cell.core.commands import Command, VisionState
from cell.service.opcua import OpcUaServer
from tests.ports import free_port
from tests.test_history_service import no_feeder, production
from tests.test_opcua import COUNTERS, Cell
from tests.test_service import picked, running, wait_for

V = VisionState
pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]


def one_job(service) -> int:
    service.command(Command.START_SINGLE)
    wait_for(lambda: service.snapshot().vision_state == V.READY, 120, "the job's end")
    return picked(service)


def opcua_counters(service) -> dict:
    """The counters a PLC reads from the service's OPC UA server (started on it for the reading)."""

    async def go():
        server = OpcUaServer(service, service.config)
        await server.start()
        try:
            url = f"opc.tcp://127.0.0.1:{service.config.service.opcua_port}/{service.config.service.opcua_path}"
            async with Client(url, timeout=10) as client:
                cell = await Cell(client).open()
                return {name: await cell.read(name) for name in COUNTERS}
        finally:
            await server.stop()

    return asyncio.run(asyncio.wait_for(go(), 120))


def production_rows(tmp_path) -> list:
    db = sqlite3.connect(tmp_path / "data" / "history.sqlite")
    try:
        return db.execute("SELECT id, job_id, time_utc, class, outcome FROM picks ORDER BY id").fetchall()
    finally:
        db.close()


def counted(report: dict) -> dict:
    """A report's figures but the time since the last production event (the cell is Off since,
    downtime grows with the wall clock while nothing runs)."""
    state_s = {k: v for k, v in report["state_s"].items() if k != "Off"}
    return {**{k: v for k, v in report.items() if k not in ("state_s", "down_s")}, "state_s": state_s}


def cli_json(capsys, *argv: str):
    capsys.readouterr()
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


def test_a_dry_run_after_a_production_shift_leaves_production_counters_report_and_opcua_unchanged(tmp_path, capsys):
    cfg = no_feeder(tmp_path)
    cfg.service.opcua_port = free_port()
    conf = tmp_path / "cell.toml"  # what `run-cell report` and `run-cell history` read: this folder's store
    conf.write_text(f'[run]\nlog_dir = "{tmp_path / "logs"}"\n')

    with production(cfg) as service:
        assert one_job(service) > 0
        counters = service.snapshot().counters
        opcua = opcua_counters(service)
    assert opcua["PickedBolts"] + opcua["PickedNuts"] > 0
    rows = production_rows(tmp_path)
    report = cli_json(capsys, "report", "--config", str(conf), "--json")
    assert report["picked"] == counters.picked_total

    with running(cfg) as rehearsal:  # `run-cell serve --dry-run` in the same folder
        assert picked(rehearsal) == 0  # it starts from its own store, not production's shift
        rehearsed = one_job(rehearsal)
    assert rehearsed > 0
    # `run-cell --dry-run` (what `make demo` runs) in the same folder too
    assert main(["--dry-run", "--log-dir", str(tmp_path / "logs")]) == 0

    assert production_rows(tmp_path) == rows
    assert counted(cli_json(capsys, "report", "--config", str(conf), "--json")) == counted(report)
    with production(cfg) as service:  # restarted: counters from the store, after reading the audit back
        assert service.snapshot().counters == counters
        assert opcua_counters(service) == opcua
        service.prime_ledger_from_audit()  # the counters from the audit files (the store unreadable)
        assert service.snapshot().counters == counters
    assert production_rows(tmp_path) == rows  # the restart's read-back of the audit files added none

    simulated = cli_json(capsys, "history", "--config", str(conf), "--simulated", "--outcome", "picked", "--json")
    job_ids = {p["job_id"] for p in simulated}
    assert len(job_ids) == 2  # the serve dry run's job and run-cell --dry-run's
    assert not job_ids & {r[1] for r in rows}
    assert len(simulated) >= rehearsed


def test_history_simulated_refuses_a_url(tmp_path, capsys):
    conf = tmp_path / "cell.toml"
    conf.write_text(f'[run]\nlog_dir = "{tmp_path / "logs"}"\n')
    assert main(["history", "--config", str(conf), "--simulated", "--url", "sqlite:///x.sqlite"]) == 2
    err = capsys.readouterr().err
    assert "--url does not apply" in err and "hint: leave out --url" in err

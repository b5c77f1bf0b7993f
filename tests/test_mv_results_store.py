"""OPC 40100-1 results from the history store (issue 28, defect 4): a lookup never runs on the
OPC UA loop, so a store whose read hangs (PostgreSQL slow or half-open) delays only that
lookup while every other client is answered; the lookups waiting at once are bounded; and a
store shared by several cells (a plant database) serves a cell only its own picks and jobs."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua

from cell.core.events import JobStarted
from cell.history.query import open_reader
from cell.history.store import HistoryStore
from cell.service.results import HistoryBackedResults, LookupsBusy, MemoryResultStore
from tests.history_helpers import OPERATOR, T0, history_config, verify
from tests.mv_harness import MachineVisionHarness, shared_cache_dir
from tests.pg_server import why_no_postgresql
from tests.test_history import Hooks
from tests.test_history_pg import pg, pg_url  # noqa: F401 - fixtures: a live PostgreSQL server

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]
MV_URI = "http://opcfoundation.org/UA/MachineVision"
_T = ua.VariantType


def write_cell(cfg: Any, cell: str, job_id: str) -> None:
    cfg.history.cell_name = cell
    store = HistoryStore(cfg.history, cfg.run.log_dir, Hooks())
    store.handle(JobStarted(time_utc=T0, job_id=job_id, mode="single", origin=OPERATOR, recipe=f"recipe-{cell}"))
    store.handle(verify(1, job=job_id, job_id=job_id))
    assert store.wait_idle(30)
    if cfg.history.url:
        assert store.wait_sent(30)
    store.close()


def check_only_own_rows(cfg_a: Any) -> None:
    cfg_a.history.cell_name = "cell-a"
    reader = open_reader(cfg_a)
    results = HistoryBackedResults(MemoryResultStore(10), reader, True)
    try:
        assert reader.get_pick("job-b/1") is None  # cell-b's pick, in the same store
        assert reader.get_job("job-b") is None
        assert reader.get_pick("job-a/1")["cell"] == "cell-a"
        assert reader.get_job("job-a")["recipe"] == "recipe-cell-a"
        own, other = results.lookup("job-a/1"), results.lookup("job-b/1")
        assert own is not None and other is not None
        assert own.result(timeout=30).recipe_id == "recipe-cell-a"
        assert other.result(timeout=30) is None
    finally:
        results.close()
        reader.close()


def test_another_cells_rows_in_the_same_sqlite_store_are_not_served(tmp_path: Path) -> None:
    for cell, job in (("cell-a", "job-a"), ("cell-b", "job-b")):  # one data folder: one database file
        write_cell(history_config(tmp_path), cell, job)
    check_only_own_rows(history_config(tmp_path))


@pytest.mark.skipif(why_no_postgresql() is not None, reason=str(why_no_postgresql()))
def test_another_cells_rows_in_a_shared_plant_database_are_not_served(tmp_path: Path, pg_url: str) -> None:  # noqa: F811
    for cell, job in (("cell-a", "job-a"), ("cell-b", "job-b")):  # two cells, one PostgreSQL database
        write_cell(history_config(tmp_path / cell, url=pg_url), cell, job)
    check_only_own_rows(history_config(tmp_path / "cell-a", url=pg_url))


class StuckReader:
    """A history reader whose read hangs until released, as on a half-open PostgreSQL connection."""

    def __init__(self) -> None:
        self.entered, self.release = threading.Event(), threading.Event()

    def get_pick(self, pick_id: str) -> dict | None:
        self.entered.set()
        self.release.wait(120)
        return None

    def get_job(self, job_id: str) -> dict | None:
        return None


def test_a_stuck_history_lookup_leaves_every_other_client_answered(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    reader = StuckReader()
    results = HistoryBackedResults(MemoryResultStore(100), reader, True, max_waiting=1)
    h = MachineVisionHarness(tmp_path, shared_cache_dir(tmp_path_factory), results=results)
    mv = h.config.service.machine_vision.model_copy(update={"result_lookup_timeout_s": 60.0})
    h.config = h.config.model_copy(update={"service": h.config.service.model_copy(update={"machine_vision": mv})})
    h.start()

    async def get_result(client: Client, result_id: str) -> str:
        mv_ns = await client.get_namespace_index(MV_URI)
        app = await client.get_namespace_index("urn:pick-cell")
        rm = await client.nodes.objects.get_child([f"{app}:VisionSystem", f"{mv_ns}:ResultManagement"])
        try:
            await rm.call_method(
                f"{mv_ns}:GetResultById",
                ua.Variant(ua.ResultIdDataType(Id=result_id), _T.ExtensionObject),
                ua.Variant(0, _T.Int32),
            )
        except ua.UaStatusCodeError as e:
            return ua.StatusCode(e.code).name
        return "Good"

    async def scenario() -> tuple[str, str, str]:
        endpoint = h.endpoint
        async with (
            Client(endpoint, timeout=60, watchdog_intervall=30) as stuck,
            Client(endpoint, timeout=60, watchdog_intervall=30) as other,
        ):
            await stuck.load_data_type_definitions()
            await other.load_data_type_definitions()
            waiting = asyncio.create_task(get_result(stuck, "old-job/7"))  # not in memory: asks the store
            assert await asyncio.to_thread(reader.entered.wait, 60), "the lookup never reached the store"
            # while the store hangs: another client reads, and its own lookup is refused at once (bounded)
            app = await other.get_namespace_index("urn:pick-cell")
            mv_ns = await other.get_namespace_index(MV_URI)
            state = await asyncio.wait_for(
                other.nodes.objects.get_child([f"{app}:VisionSystem", f"{mv_ns}:VisionStateMachine", "0:CurrentState"]),
                60,
            )
            read = (await asyncio.wait_for(state.read_value(), 60)).Text
            second = await asyncio.wait_for(get_result(other, "old-job/8"), 60)
            assert not waiting.done()  # the first lookup still waits on the store meanwhile
            reader.release.set()
            return read, second, await asyncio.wait_for(waiting, 60)

    try:
        assert asyncio.run(scenario()) == ("Operational", "BadResourceUnavailable", "BadNotFound")
    finally:
        reader.release.set()
        h.stop()


def test_history_lookups_are_bounded_and_a_closed_store_asks_nothing() -> None:
    reader = StuckReader()
    results = HistoryBackedResults(MemoryResultStore(10), reader, True, max_waiting=2)
    try:
        first, second = results.lookup("a/1"), results.lookup("a/2")
        assert reader.entered.wait(30)
        with pytest.raises(LookupsBusy, match="result_lookups_max = 2"):
            results.lookup("a/3")
        assert results.lookup("a/end") is None  # a job's end lives in memory only
        reader.release.set()
        assert first is not None and second is not None
        assert (first.result(timeout=30), second.result(timeout=30)) == (None, None)
    finally:
        reader.release.set()
        results.close()
    assert results.lookup("a/4") is None

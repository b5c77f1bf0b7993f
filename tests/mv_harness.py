"""An OPC UA server with the Machine Vision interface over a FakeLineService, on its own
thread and loop, for tests that drive it from a client (asyncua or another stack). The server
is the production one (cell.service.opcua_security.GuardedServer, as `run-cell serve` builds it
on loopback without users): the caller's role is `service.machine_vision.client_role`."""

from __future__ import annotations

import asyncio
import logging
import threading
from pathlib import Path

from asyncua import Server, ua

from cell.config import CellConfig
from cell.recipes import RecipeBook
from cell.service.machinevision import MachineVisionServer
from cell.service.mv_addressspace import ModelLoad, cache_key, init_server_with_models
from cell.service.opcua_security import GuardedServer, GuardSettings
from cell.service.results import ResultFilter, ResultStore
from tests.mv_fake_service import FakeLineService
from tests.ports import free_port

RECIPE_BOLTS = """description = "bolts only, nuts stay"
products = ["kit-7"]
pick_order = "rows"

[pick.bolt]
pick_above_table_mm = 3.5
jaw_across_axis = true
bin_robot_mm = [-200.0, 60.0, 60.0]
"""

RECIPE_NUTS = """description = "nuts only"
[pick.nut]
pick_above_table_mm = 2.0
bin_robot_mm = [200.0, 60.0, 60.0]
"""


def config_for(tmp: Path, serial: str = "PC-0042") -> CellConfig:
    cfg = CellConfig()
    mv = cfg.service.machine_vision.model_copy(
        update={"serial_number": serial, "recipes_dir": tmp / "recipes", "model_cache_dir": tmp / "cache"}
    )
    return cfg.model_copy(update={"service": cfg.service.model_copy(update={"machine_vision": mv})})


class MachineVisionHarness:
    """`start()` returns once clients can connect at `endpoint`; `stop()` ends it all."""

    def __init__(
        self,
        tmp: Path,
        cache_dir: Path | None = None,
        pick_interval_s: float = 0.05,
        results: ResultStore | None = None,
    ):
        self.config = config_for(tmp)
        self.results = results
        self.book = RecipeBook(self.config.service.machine_vision.recipes_dir)
        self.book.add("bolts-only", RECIPE_BOLTS)
        self.book.add("nuts-only", RECIPE_NUTS)
        self.service = FakeLineService(self.book, pick_interval_s=pick_interval_s)
        self.cache_dir = cache_dir
        self.endpoint = f"opc.tcp://127.0.0.1:{free_port()}/cell"
        self.load: ModelLoad | None = None
        self.mv: MachineVisionServer | None = None
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._server: GuardedServer | None = None

    def start(self) -> MachineVisionHarness:
        logging.getLogger("asyncua").setLevel(logging.WARNING)
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self._start(), self._loop).result(timeout=60)
        return self

    async def _start(self) -> None:
        server = GuardedServer(GuardSettings.from_config(self.config, "urn:pick-cell:server", secure=False))
        self.load = await init_server_with_models(server, self.cache_dir)
        server.set_endpoint(self.endpoint)
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        self.mv = MachineVisionServer(
            server, self.service, self.config, recipes=self.book, results=self.results, dry_run=True
        )
        await self.mv.start()
        await server.start()
        self._server = server

    def results_job_ids(self) -> list[str]:
        """The jobs the results store holds results of, oldest first."""
        assert self.mv is not None
        page, _ = self.mv.results.query(ResultFilter(), 0, 100000)
        return list(dict.fromkeys(r.job_id for r in page))

    def stop(self) -> None:
        async def _stop() -> None:
            if self.mv is not None:
                await self.mv.stop()
            if self._server is not None:
                await self._server.stop()

        try:
            asyncio.run_coroutine_threadsafe(_stop(), self._loop).result(timeout=90)
        finally:
            self.service.close()
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=10)


def shared_cache_dir(tmp_path_factory) -> Path:
    """One address space cache for the whole test run (all xdist workers): built cold once,
    under a lock, so the other tests start warm."""
    import fcntl

    # the folder outlives the run (every xdist worker finds it): one per cache key, so a run of other
    # code (another checkout) never finds a cache that is not its own, nor deletes this one's
    key = cache_key()
    root = tmp_path_factory.getbasetemp().parent / f"mv-aspace-cache-{key[:16]}"
    root.mkdir(exist_ok=True)
    with open(root / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / f"aspace-{key}.pickle").exists():

            async def build() -> None:
                await init_server_with_models(Server(), root)

            asyncio.run(build())
    return root

"""The real line service (`run-cell serve --dry-run` in a subprocess) as an OPC 40100-1 Machine
Vision system, driven by a client that knows only the specification: it prepares a recipe
that picks bolts only, runs a single job with the specification's arguments, receives a
ResultReadyEvent per pick, reads a result back by id, is refused a recipe switch while a job
runs, and stops a continuous job."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from asyncua import Client, ua

from tests.mv_harness import RECIPE_BOLTS, shared_cache_dir
from tests.serve_process import ServeProcess
from tests.test_mv_opcua import Events, SpecClient, cause, content, ext, job_args

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]
_T = ua.VariantType


@pytest.fixture
def serve(tmp_path: Path, tmp_path_factory: pytest.TempPathFactory):
    cache = shared_cache_dir(tmp_path_factory)
    (tmp_path / "recipes").mkdir()
    (tmp_path / "recipes" / "bolts-only.toml").write_text(RECIPE_BOLTS)
    (tmp_path / "cell.toml").write_text(
        "[camera]\nwidth_px = 960\nheight_px = 540\n"
        "[sim]\nreference_marks_mm = []\n"
        "[sim.feeder]\nparts_per_minute = 0\n"
        "[service]\ncapture_interval_s = 0.2\n"
        f'[service.machine_vision]\nrecipes_dir = "{tmp_path / "recipes"}"\nmodel_cache_dir = "{cache}"\n'
        'serial_number = "PC-0007"\n'
    )
    proc = ServeProcess(tmp_path, "--config", str(tmp_path / "cell.toml"), "--log-dir", str(tmp_path / "logs"))
    yield proc
    assert proc.stop() == 0


def test_the_service_is_a_machine_vision_system_for_a_specification_only_client(serve: ServeProcess) -> None:
    endpoint = next(line.split("OPC UA ", 1)[1].split(";")[0] for line in serve.lines if line.startswith("ready:"))

    async def scenario() -> None:
        async with Client(endpoint, timeout=30, watchdog_intervall=15) as client:
            s = await SpecClient(client).setup()
            assert (await s.state(s.sm), await s.state(s.auto)) == ("Operational", "Ready")
            handler = Events()
            sub = await client.create_subscription(50, handler)
            ready_type = await client.nodes.base_event_type.get_child([f"{s.mv}:ResultReadyEventType"])
            await sub.subscribe_events(s.vs, ready_type)

            prepare = (ext(ua.RecipeIdExternalDataType(Id="bolts-only")), ext(ua.RecipeIdInternalDataType(Id="")))
            internal, completed, error = await s.call(s.recipes, "PrepareRecipe", *prepare)
            assert (internal.Id, completed, error) == ("bolts-only", True, 0)
            job = (await s.call(s.auto, "StartSingleJob", *job_args("m-1", "p-1", "bolts-only", "kit-7", {})))[0].Id
            assert job
            await s.wait_state(s.auto, "Ready", timeout_s=150)
            (end,) = await handler.wait(lambda e: e.ResultId.Id == f"{job}/end", 1, timeout_s=30)
            assert end.ResultState == 1 and end.InternalRecipeId.Id == "bolts-only"
            picks = [e for e in handler.items if e.JobId.Id == job and not e.ResultId.Id.endswith("/end")]
            assert len(picks) == 9  # the built-in table's nine bolts; its nuts stay: the recipe picks bolts only
            first = sorted(picks, key=lambda e: int(e.ResultId.Id.rsplit("/", 1)[1]))[0]
            handle, result, error = await s.call(
                s.results, "GetResultById", ext(ua.ResultIdDataType(Id=first.ResultId.Id)), ua.Variant(1000, _T.Int32)
            )
            assert error == 0 and result.JobId.Id == job and result.IsSimulated is True
            c = content(result)
            assert c["Class"] == "bolt" and c["Outcome"] == "picked" and len(c["RobotMm"]) == 3
            assert (result.MeasId.Id, result.PartId.Id, result.ProductId.Id) == ("m-1", "p-1", "kit-7")
            await s.call(s.results, "ReleaseResultHandle", ua.Variant(handle, _T.UInt32))

            await s.call(s.recipes, "UnprepareRecipe", *prepare)
            job2 = (await s.call(s.auto, "StartContinuous", *job_args("m-2", "", "", "", {})))[0].Id
            await s.wait_state(s.auto, "ContinuousExecution")
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await s.call(s.recipes, "PrepareRecipe", *prepare)
            assert refused.value.code == ua.StatusCodes.BadInvalidState
            await handler.wait(lambda e: e.JobId.Id == job2, 1, timeout_s=60)  # the nuts left behind
            assert await s.call(s.auto, "Stop", *cause("end of lot")) == [0]
            await s.wait_state(s.auto, "Ready", timeout_s=60)
            await sub.delete()

    asyncio.run(scenario())

"""A client that knows only OPC 40100-1 drives the cell's Machine Vision model: it finds the
vision system by its type definition (namespace URI, BrowseName), never by our names, runs
a job with the specification's arguments, receives ResultReadyEvents, reads a missed result
back, is refused what the state does not allow with the specification's status codes,
switches the recipe, adds one through its Handle, stops, halts and resets."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, Node, ua

from cell.core.events import Role
from tests.mv_harness import RECIPE_BOLTS, MachineVisionHarness, shared_cache_dir

MV_URI = "http://opcfoundation.org/UA/MachineVision"
DI_URI = "http://opcfoundation.org/UA/DI/"
_T = ua.VariantType
pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]
# asyncua's client probes the server every watchdog_intervall and drops the connection when one
# probe takes longer: a loaded 2-core machine can take more than the default 1 s.


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return shared_cache_dir(tmp_path_factory)


@pytest.fixture
def harness(cache_dir: Path, tmp_path: Path):
    h = MachineVisionHarness(tmp_path, cache_dir).start()
    yield h
    h.stop()


class SpecClient:
    """Everything looked up by the specification's names in its namespace."""

    def __init__(self, client: Client):
        self.c = client

    async def setup(self) -> SpecClient:
        await self.c.load_data_type_definitions()
        self.mv = await self.c.get_namespace_index(MV_URI)
        self.di = await self.c.get_namespace_index(DI_URI)
        vs_type = await self.c.nodes.base_object_type.get_child([f"{self.mv}:VisionSystemType"])
        self.vs = await self._find(self.c.nodes.objects, vs_type.nodeid, depth=2)
        assert self.vs is not None, "an object of VisionSystemType reachable from Objects"
        self.sm = await self.child(self.vs, "VisionStateMachine")
        self.auto = await self.child(self.sm, "AutomaticModeStateMachine")
        self.results = await self.child(self.vs, "ResultManagement")
        self.recipes = await self.child(self.vs, "RecipeManagement")
        return self

    async def _find(self, node: Node, type_id: ua.NodeId, depth: int) -> Node | None:
        for ref in await node.get_references(
            refs=ua.ObjectIds.HierarchicalReferences, nodeclassmask=ua.NodeClass.Object
        ):
            if ref.TypeDefinition == type_id:
                return self.c.get_node(ref.NodeId)
        if depth > 0:
            for child in await node.get_children(nodeclassmask=ua.NodeClass.Object):
                found = await self._find(child, type_id, depth - 1)
                if found is not None:
                    return found
        return None

    async def child(self, node: Node, *names: str) -> Node:
        return await node.get_child([f"{self.mv}:{n}" for n in names])

    async def call(self, parent: Node, method: str, *args: ua.Variant) -> list[Any]:
        out = await parent.call_method(await self.child(parent, method), *args)
        return out if isinstance(out, list) else [out]

    async def state(self, machine: Node) -> str:
        return (await (await machine.get_child(["0:CurrentState"])).read_value()).Text

    async def last_transition(self, machine: Node) -> str:
        return (await (await machine.get_child(["0:LastTransition"])).read_value()).Text

    async def wait_transition(self, machine: Node, want: str, timeout_s: float = 20.0) -> None:
        """Until LastTransition reads `want` (a state read right after a Start may still be the old one)."""
        deadline = asyncio.get_running_loop().time() + timeout_s
        while (last := await self.last_transition(machine)) != want:
            assert asyncio.get_running_loop().time() < deadline, f"last transition still {last}, waiting for {want}"
            await asyncio.sleep(0.05)

    async def wait_state(self, machine: Node, want: str, timeout_s: float = 20.0) -> None:
        deadline = asyncio.get_running_loop().time() + timeout_s
        while (state := await self.state(machine)) != want:
            assert asyncio.get_running_loop().time() < deadline, f"still {state}, waiting for {want}"
            await asyncio.sleep(0.05)


def ext(value: Any) -> ua.Variant:
    return ua.Variant(value, _T.ExtensionObject)


def cause(text: str = "") -> tuple[ua.Variant, ua.Variant]:
    return ua.Variant(0, _T.Int32), ua.Variant(text, _T.String)


def job_args(meas: str, part: str, recipe: str, product: str, params: dict[str, str]) -> list[ua.Variant]:
    return [
        ext(ua.MeasIdDataType(Id=meas)),
        ext(ua.PartIdDataType(Id=part)),
        ext(ua.RecipeIdExternalDataType(Id=recipe)),
        ext(ua.ProductIdDataType(Id=product)),
        ua.Variant(
            [ua.KeyValuePair(Key=ua.QualifiedName(k, 0), Value=ua.Variant(v)) for k, v in params.items()],
            _T.ExtensionObject,
            is_array=True,
        ),
    ]


class Events:
    def __init__(self) -> None:
        self.items: list[Any] = []

    def event_notification(self, event: Any) -> None:
        self.items.append(event)

    async def wait(self, predicate, count: int, timeout_s: float = 20.0) -> list[Any]:
        deadline = asyncio.get_running_loop().time() + timeout_s
        while len(found := [e for e in self.items if predicate(e)]) < count:
            assert asyncio.get_running_loop().time() < deadline, f"{len(found)} of {count} events"
            await asyncio.sleep(0.05)
        return found


def content(result: Any) -> dict[str, Any]:
    return {v.Value.Key.Name: v.Value.Value.Value for v in result.ResultContent}


async def _status(coro) -> int:
    with pytest.raises(ua.UaStatusCodeError) as err:
        await coro
    return err.value.code


def test_a_specification_only_client_runs_the_cell(harness: MachineVisionHarness) -> None:
    async def scenario() -> None:
        async with Client(harness.endpoint, timeout=30, watchdog_intervall=15) as client:
            s = await SpecClient(client).setup()
            assert (await s.state(s.sm), await s.state(s.auto)) == ("Operational", "Ready")
            for variable in (await s.child(s.vs, "SystemState"), await s.child(s.vs, "DiagnosticLevel")):
                assert await _status(variable.write_value(await variable.read_data_value())) in (
                    ua.StatusCodes.BadNotWritable,
                    ua.StatusCodes.BadUserAccessDenied,
                )
            ident = await s.vs.get_child([f"{s.di}:Identification"])
            assert await (await ident.get_child([f"{s.di}:SerialNumber"])).read_value() == "PC-0042"

            job_id = (
                await s.call(s.auto, "StartContinuous", *job_args("meas-1", "part-9", "", "kit-7", {"lot": "A1"}))
            )[0].Id
            assert job_id
            assert harness.service.commands[-1][2].as_json() == {
                "product_id": "kit-7",
                "part_id": "part-9",
                "meas_id": "meas-1",
                "parameters": {"lot": "A1"},
            }
            await s.wait_state(s.auto, "ContinuousExecution")
            assert await s.last_transition(s.auto) == "ReadyToContinuousExecution"
            await asyncio.sleep(0.3)  # picks 1.. happen before this client subscribes: it misses them

            handler = Events()
            sub = await client.create_subscription(50, handler)
            await sub.subscribe_events(
                s.vs, await client.nodes.base_event_type.get_child([f"{s.mv}:ResultReadyEventType"])
            )
            seen = await handler.wait(lambda e: e.JobId.Id == job_id, 3)
            assert all(e.ResultState == 1 and e.InternalConfigurationId.Id == "cal-1" for e in seen)
            first_seen = min(int(e.ResultId.Id.rsplit("/", 1)[1]) for e in seen)
            assert first_seen > 1, "the first picks were made before the subscription"

            handle, missed, error = await s.call(
                s.results, "GetResultById", ext(ua.ResultIdDataType(Id=f"{job_id}/1")), ua.Variant(1000, _T.Int32)
            )
            assert error == 0 and missed.ResultId.Id == f"{job_id}/1" and missed.JobId.Id == job_id
            assert (missed.MeasId.Id, missed.PartId.Id, missed.ProductId.Id) == ("meas-1", "part-9", "kit-7")
            assert missed.IsSimulated is True and missed.ResultState == 1
            c = content(missed)
            assert (c["Class"], c["Outcome"], c["TableMm"], c["RobotMm"], c["JawAngleDeg"]) == (
                "bolt",
                "picked",
                [10.0, 20.0],
                [-122.0, 60.0, 3.5],
                30.0,
            )
            assert (await s.call(s.results, "ReleaseResultHandle", ua.Variant(handle, _T.UInt32))) == [0]
            released_again = s.call(s.results, "ReleaseResultHandle", ua.Variant(handle, _T.UInt32))
            assert await _status(released_again) == ua.StatusCodes.BadInvalidArgument
            parts = await s.call(
                s.results,
                "GetResultComponentsById",
                ext(ua.ResultIdDataType(Id=f"{job_id}/2")),
                ua.Variant(0, _T.Int32),
            )
            assert (parts[3], parts[4], parts[12].Id, parts[-1]) == (
                True,
                1,
                job_id,
                0,
            )  # IsSimulated, state, JobId, Error
            missing = s.call(
                s.results, "GetResultById", ext(ua.ResultIdDataType(Id="no-such/1")), ua.Variant(0, _T.Int32)
            )
            assert await _status(missing) == ua.StatusCodes.BadNotFound

            # the state does not allow it: the specification's status code, nothing changed
            prepare = (ext(ua.RecipeIdExternalDataType(Id="bolts-only")), ext(ua.RecipeIdInternalDataType(Id="")))
            assert await _status(s.call(s.recipes, "PrepareRecipe", *prepare)) == ua.StatusCodes.BadInvalidState
            assert await _status(s.call(s.sm, "Reset", *cause())) == ua.StatusCodes.BadInvalidState

            assert await s.call(s.auto, "Stop", *cause("end of lot")) == [0]
            await s.wait_state(s.auto, "Ready")
            assert await s.last_transition(s.auto) == "ContinuousExecutionToReadyStop"
            (end,) = await handler.wait(lambda e: e.ResultId.Id == f"{job_id}/end", 1)
            assert end.ResultState == 3  # Aborted: stopped before the table was clear

            listed = await s.call(s.results, "GetResultListFiltered", *_filter(job_id=job_id, max_results=2))
            complete, count, _handle, page, error = listed
            assert (complete, error, len(page)) == (False, 0, 2) and count >= 4
            assert [r.ResultId.Id for r in page] == [f"{job_id}/1", f"{job_id}/2"]

            # switch the recipe in Ready; the next job runs with it
            internal, completed, error = await s.call(s.recipes, "PrepareRecipe", *prepare)
            assert (internal.Id, completed, error) == ("bolts-only", True, 0)
            assert harness.service.recipe == "bolts-only"
            _, count, _, recipes, _ = await s.call(
                s.recipes,
                "GetRecipeListFiltered",
                ext(ua.RecipeIdExternalDataType(Id="")),
                ext(ua.ProductIdDataType(Id="")),
                ua.Variant(ua.TriStateBooleanDataType.TRUE_1, _T.Int32),
                ua.Variant(0, _T.UInt32),
                ua.Variant(0, _T.UInt32),
                ua.Variant(0, _T.Int32),
            )
            assert [r.Id for r in recipes] == ["bolts-only"] and len(recipes[0].Hash) == 32
            folder = await s.child(s.recipes, "Recipes")
            prepared = {}
            for recipe in await folder.get_children():
                prepared[(await recipe.read_browse_name()).Name] = await (
                    await s.child(recipe, "IsPrepared")
                ).read_value()
            assert prepared == {"bolts-only": True, "nuts-only": False}

            job2 = (await s.call(s.auto, "StartSingleJob", *job_args("meas-2", "", "", "", {})))[0].Id
            (end2,) = await handler.wait(lambda e: e.ResultId.Id == f"{job2}/end", 1)
            # the job ran and ended on its own: Ready again by its own transition (waited for, not read
            # at once: right after the Start the state may still read the Ready before it)
            await s.wait_transition(s.auto, "SingleExecutionToReadyAuto")
            await s.wait_state(s.auto, "Ready")
            assert end2.ResultState == 1 and end2.InternalRecipeId.Id == "bolts-only"
            assert end2.CreationTime is not None and end2.JobId.Id == job2
            await sub.delete()

    asyncio.run(scenario())


def _filter(job_id: str = "", max_results: int = 0) -> list[ua.Variant]:
    empty = ext(ua.MeasIdDataType(Id=""))
    return [
        ua.Variant(0, _T.Int32),  # ResultState: any
        empty,
        ext(ua.PartIdDataType(Id="")),
        ext(ua.RecipeIdExternalDataType(Id="")),
        ext(ua.RecipeIdInternalDataType(Id="")),
        ext(ua.ConfigurationIdDataType(Id="")),
        ext(ua.ConfigurationIdDataType(Id="")),
        ext(ua.ProductIdDataType(Id="")),
        ext(ua.JobIdDataType(Id=job_id)),
        ua.Variant(max_results, _T.UInt32),
        ua.Variant(0, _T.UInt32),
        ua.Variant(0, _T.Int32),
    ]


def test_halt_reset_and_safety_follow_the_specification(harness: MachineVisionHarness) -> None:
    async def scenario() -> None:
        async with Client(harness.endpoint, timeout=30, watchdog_intervall=15) as client:
            s = await SpecClient(client).setup()
            handler = Events()
            sub = await client.create_subscription(50, handler)
            transition_type = ua.NodeId(ua.ObjectIds.TransitionEventType)
            for machine in (s.sm, s.auto):
                await sub.subscribe_events(machine, transition_type)
            system_state = await s.child(s.vs, "SystemState")
            assert (await system_state.read_value()).State == ua.SystemStateDataType.SBY_2

            assert await s.call(s.sm, "Halt", *cause("maintenance")) == [0]
            await s.wait_state(s.sm, "Halted")
            assert await s.last_transition(s.sm) == "OperationalToHalted"
            assert await s.state(s.auto) == ""
            await _wait_value(system_state, lambda v: v.State == ua.SystemStateDataType.SDT_4)
            start = s.call(s.auto, "StartSingleJob", *job_args("", "", "", "", {}))
            assert await _status(start) == ua.StatusCodes.BadInvalidState

            assert await s.call(s.sm, "Reset", *cause()) == [0]
            await s.wait_state(s.auto, "Ready")
            assert await s.state(s.sm) == "Operational"
            chain = await handler.wait(lambda e: True, 4)
            names = [e.Transition.Text for e in chain]
            assert names == [
                "OperationalToHalted",
                "HaltedToPreoperational",
                "PreoperationalToOperationalAuto",
                "InitializedToReadyAuto",
            ]
            assert (await (await s.sm.get_child(["0:LastTransition", "0:Id"])).read_value()).NamespaceIndex == s.mv

            # the dry run is chosen at start: asking for it succeeds, switching it off is not supported
            simulation = (ua.Variant(0, _T.Int32), ua.Variant("", _T.String))
            assert await s.call(s.auto, "SimulationMode", ua.Variant(True, _T.Boolean), *simulation) == [0]
            off = s.call(s.auto, "SimulationMode", ua.Variant(False, _T.Boolean), *simulation)
            assert await _status(off) == ua.StatusCodes.BadNotSupported

            # the environment reports its safety state: a trigger halts the cell
            triggered = await s.child(s.vs, "SafetyStateManagement", "VisionSafetyTriggered")
            safety = await s.child(s.vs, "SafetyStateManagement")
            assert await s.call(
                safety, "ReportSafetyState", ua.Variant(True, _T.Boolean), ua.Variant("door 3 open", _T.String)
            ) == [0]
            assert await triggered.read_value() is True
            await s.wait_state(s.sm, "Halted")
            assert harness.service.commands[-1][0].value == "Halt"
            assert harness.service.commands[-1][1].interface.value == "opcua"
            await sub.delete()

    asyncio.run(scenario())


async def _wait_value(node: Node, predicate, timeout_s: float = 20.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout_s
    while not predicate(value := await node.read_value()):
        assert asyncio.get_running_loop().time() < deadline, f"still {value}"
        await asyncio.sleep(0.05)


def test_add_a_recipe_through_its_handle_and_a_bad_one_refused(harness: MachineVisionHarness) -> None:
    async def add(s: SpecClient, recipe_id: str, text: str) -> Any:
        internal, node_id, _product, transfer, error = await s.call(
            s.recipes, "AddRecipe", ext(ua.RecipeIdExternalDataType(Id=recipe_id)), ext(ua.ProductIdDataType(Id=""))
        )
        assert (internal.Id, transfer, error) == (recipe_id, True, 0)
        handle = await s.c.get_node(node_id).get_child([f"{s.mv}:Handle"])
        fh = await handle.call_method("0:Open", ua.Variant(6, _T.Byte))  # Write | EraseExisting
        await handle.call_method("0:Write", ua.Variant(fh, _T.UInt32), ua.Variant(text.encode(), _T.ByteString))
        return await handle.call_method("0:Close", ua.Variant(fh, _T.UInt32))

    async def scenario() -> None:
        async with Client(harness.endpoint, timeout=30, watchdog_intervall=15) as client:
            s = await SpecClient(client).setup()
            await add(s, "bolts-copy", RECIPE_BOLTS)
            assert harness.book.load("bolts-copy").classes == {"bolt"}
            bad = RECIPE_BOLTS.replace("pick_above_table_mm = 3.5", "pick_above_table_mm = -3")
            assert await _status(add(s, "bolts-bad", bad)) == ua.StatusCodes.BadInvalidArgument
            assert not (harness.book.folder / "bolts-bad.toml").exists()
            folder = await s.child(s.recipes, "Recipes")

            async def names() -> list[str]:
                return sorted(d.BrowseName.Name for d in await folder.get_children_descriptions())

            deadline = asyncio.get_running_loop().time() + 10
            while (listed := await names()) != ["bolts-copy", "bolts-only", "nuts-only"]:  # the refused one goes
                assert asyncio.get_running_loop().time() < deadline, listed
                await asyncio.sleep(0.05)
            assert await s.call(s.recipes, "RemoveRecipe", ext(ua.RecipeIdExternalDataType(Id="bolts-copy"))) == [0]
            assert not (harness.book.folder / "bolts-copy.toml").exists()

    asyncio.run(scenario())


def test_a_client_without_the_role_is_refused(cache_dir: Path, tmp_path: Path) -> None:
    h = MachineVisionHarness(tmp_path, cache_dir)
    mv = h.config.service.machine_vision.model_copy(update={"client_role": Role.OPERATOR})
    h.config = h.config.model_copy(update={"service": h.config.service.model_copy(update={"machine_vision": mv})})
    h.start()

    async def scenario() -> None:
        async with Client(h.endpoint, timeout=30, watchdog_intervall=15) as client:
            s = await SpecClient(client).setup()
            prepare = (ext(ua.RecipeIdExternalDataType(Id="nuts-only")), ext(ua.RecipeIdInternalDataType(Id="")))
            assert await _status(s.call(s.recipes, "PrepareRecipe", *prepare)) == ua.StatusCodes.BadUserAccessDenied
            assert h.service.recipe == ""

    try:
        asyncio.run(scenario())
    finally:
        h.stop()


def test_a_failed_publication_is_logged_once_and_retried(
    harness: MachineVisionHarness, caplog: pytest.LogCaptureFixture
) -> None:
    """The server cannot fire two results in a row: each is tried again on the next round,
    the failure logged once, and no result is lost."""
    generator = harness.mv._generators["result"]
    original, failures = generator.trigger, []

    async def flaky(*args: Any, **kwargs: Any) -> Any:
        if len(failures) < 2:
            failures.append(args)
            raise OSError("injected: the event could not be queued")
        return await original(*args, **kwargs)

    generator.trigger = flaky

    async def scenario() -> list[str]:
        async with Client(harness.endpoint, timeout=30, watchdog_intervall=15) as client:
            s = await SpecClient(client).setup()
            handler = Events()
            sub = await client.create_subscription(50, handler)
            await sub.subscribe_events(
                s.vs, await client.nodes.base_event_type.get_child([f"{s.mv}:ResultReadyEventType"])
            )
            job = (await s.call(s.auto, "StartSingleJob", *job_args("", "", "", "", {})))[0].Id
            seen = await handler.wait(lambda e: e.JobId.Id == job, 4, timeout_s=30)  # 3 picks and the job's end
            await sub.delete()
            return sorted(e.ResultId.Id for e in seen)

    with caplog.at_level(logging.WARNING, logger="cell.service.machinevision"):
        ids = asyncio.run(scenario())
    job = ids[0].rsplit("/", 1)[0]
    assert ids == [f"{job}/1", f"{job}/2", f"{job}/3", f"{job}/end"] and len(failures) == 2
    warned = [r for r in caplog.records if "not published" in r.getMessage()]
    assert len(warned) == 1, [r.getMessage() for r in warned]

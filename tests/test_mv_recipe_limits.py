"""OPC 40100-1 recipe transfer within bounds (issue 28, defect 3): AddRecipe and the recipe
Handle need AddRecipe's role (the command table's engineer) before anything is added; the
recipes and the transfers open at once are bounded (BadTooManyOperations past them); an idle
transfer expires with its node; and no call makes the server's loop walk the whole address
space (an index of the recipe nodes instead)."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, Node, ua

from cell.core.events import Role
from tests.mv_harness import RECIPE_BOLTS, MachineVisionHarness, shared_cache_dir

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]
MV_URI = "http://opcfoundation.org/UA/MachineVision"
_T = ua.VariantType


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return shared_cache_dir(tmp_path_factory)


def started(tmp_path: Path, cache_dir: Path, **mv: Any) -> MachineVisionHarness:
    h = MachineVisionHarness(tmp_path, cache_dir)
    section = h.config.service.machine_vision.model_copy(update=mv)
    h.config = h.config.model_copy(update={"service": h.config.service.model_copy(update={"machine_vision": section})})
    return h.start()


class Recipes:
    def __init__(self, client: Client) -> None:
        self.c = client

    async def setup(self) -> Recipes:
        await self.c.load_data_type_definitions()
        self.mv = await self.c.get_namespace_index(MV_URI)
        app = await self.c.get_namespace_index("urn:pick-cell")
        vs = await self.c.nodes.objects.get_child([f"{app}:VisionSystem"])
        self.rm = await vs.get_child([f"{self.mv}:RecipeManagement"])
        self.folder = await self.rm.get_child([f"{self.mv}:Recipes"])
        return self

    async def add(self, recipe_id: str) -> list[Any]:
        return await self.rm.call_method(
            f"{self.mv}:AddRecipe",
            ua.Variant(ua.RecipeIdExternalDataType(Id=recipe_id), _T.ExtensionObject),
            ua.Variant(ua.ProductIdDataType(Id=""), _T.ExtensionObject),
        )

    async def names(self) -> list[str]:
        return sorted(d.BrowseName.Name for d in await self.folder.get_children_descriptions())

    async def handle(self, recipe_node: ua.NodeId) -> Node:
        return await self.c.get_node(recipe_node).get_child([f"{self.mv}:Handle"])


async def code(call: Any) -> str:
    try:
        await call
    except ua.UaStatusCodeError as e:
        return ua.StatusCode(e.code).name
    return "Good"


def test_add_recipe_needs_the_role_before_anything_is_added(tmp_path: Path, cache_dir: Path) -> None:
    h = started(tmp_path, cache_dir, client_role=Role.OPERATOR)

    async def scenario() -> tuple[str, list[str], str]:
        async with Client(h.endpoint, timeout=30, watchdog_intervall=15) as client:
            r = await Recipes(client).setup()
            before = await r.names()
            refused = await code(r.add("kit-1"))
            handle = await r.handle((await r.folder.get_child([f"{h.mv._ns['app']}:bolts-only"])).nodeid)
            opened = await code(handle.call_method("0:Open", ua.Variant(6, _T.Byte)))
            assert await r.names() == before  # no recipe node added
            return refused, before, opened

    try:
        refused, before, opened = asyncio.run(scenario())
        assert refused == "BadUserAccessDenied" and opened == "BadUserAccessDenied"
        assert before == ["bolts-only", "nuts-only"]
        assert h.mv is not None and not h.mv._transfers  # no transfer buffer either
    finally:
        h.stop()


def test_recipes_and_open_transfers_are_bounded(tmp_path: Path, cache_dir: Path) -> None:
    h = started(tmp_path, cache_dir, recipes_max=5, recipe_transfers_max=3)

    async def scenario() -> list[str]:
        async with Client(h.endpoint, timeout=30, watchdog_intervall=15) as client:
            r = await Recipes(client).setup()
            out = [await code(r.add(f"kit-{i}")) for i in range(4)]  # 3 transfers open at once at most
            assert h.mv is not None
            handle = await r.handle(h.mv._recipe_nodes["kit-0"].nodeid)  # kit-0 written: a transfer slot frees
            fh = await handle.call_method("0:Open", ua.Variant(6, _T.Byte))
            data = ua.Variant(RECIPE_BOLTS.encode(), _T.ByteString)
            await handle.call_method("0:Write", ua.Variant(fh, _T.UInt32), data)
            await handle.call_method("0:Close", ua.Variant(fh, _T.UInt32))
            out.append(await code(r.add("kit-4")))  # a slot is free, but 3 files + 2 pending: 5 recipes
            out.append(",".join(await r.names()))
            return out

    try:
        assert asyncio.run(scenario()) == [
            "Good",
            "Good",
            "Good",
            "BadTooManyOperations",
            "BadTooManyOperations",
            "bolts-only,kit-0,kit-1,kit-2,nuts-only",
        ]
    finally:
        h.stop()


def test_an_idle_transfer_expires_with_its_node(tmp_path: Path, cache_dir: Path) -> None:
    h = started(tmp_path, cache_dir, recipe_transfer_timeout_s=0.5)

    async def scenario() -> str:
        async with Client(h.endpoint, timeout=30, watchdog_intervall=15) as client:
            r = await Recipes(client).setup()
            node_id = (await r.add("kit-idle"))[1]
            handle = await r.handle(node_id)
            assert "kit-idle" in await r.names()
            deadline = asyncio.get_running_loop().time() + 30
            while "kit-idle" in await r.names():  # the publisher's round drops it
                assert asyncio.get_running_loop().time() < deadline, "the idle transfer was never dropped"
                await asyncio.sleep(0.1)
            return await code(handle.call_method("0:Open", ua.Variant(6, _T.Byte)))

    try:
        assert asyncio.run(scenario()) in (
            "BadNodeIdInvalid",
            "BadNodeIdUnknown",
            "BadMethodInvalid",
        )  # the Handle is gone
        assert h.mv is not None and not h.mv._transfers
    finally:
        h.stop()


def test_recipe_calls_never_walk_the_whole_address_space(tmp_path: Path, cache_dir: Path) -> None:
    """AddRecipe, the Handle's Open/Write/Close, a refused transfer and RemoveRecipe: the
    address space is never iterated (asyncua's delete_nodes and a namespace-wide read-only pass
    did, on the loop, for every call)."""
    h = started(tmp_path, cache_dir)
    assert h.mv is not None
    aspace = h.mv.server.iserver.aspace
    walks: list[str] = []
    keys = aspace.keys

    def counted_keys() -> Any:
        walks.append("keys")
        return keys()

    async def scenario() -> list[str]:
        async with Client(h.endpoint, timeout=30, watchdog_intervall=15) as client:
            r = await Recipes(client).setup()
            aspace.keys = counted_keys  # from here on: every walk counted
            out = []
            for recipe_id, text in (("kit-good", RECIPE_BOLTS), ("kit-bad", "not = [a recipe")):
                node_id = (await r.add(recipe_id))[1]
                handle = await r.handle(node_id)
                fh = await handle.call_method("0:Open", ua.Variant(6, _T.Byte))
                await handle.call_method("0:Write", ua.Variant(fh, _T.UInt32), ua.Variant(text.encode(), _T.ByteString))
                out.append(await code(handle.call_method("0:Close", ua.Variant(fh, _T.UInt32))))
            remove = ua.Variant(ua.RecipeIdExternalDataType(Id="kit-good"), _T.ExtensionObject)
            out.append(await code(r.rm.call_method(f"{r.mv}:RemoveRecipe", remove)))
            deadline = asyncio.get_running_loop().time() + 30
            while (names := await r.names()) != ["bolts-only", "nuts-only"]:  # both gone again
                assert asyncio.get_running_loop().time() < deadline, names
                await asyncio.sleep(0.05)
            return out

    try:
        assert asyncio.run(scenario()) == ["Good", "BadInvalidArgument", "Good"]
        assert walks == []
    finally:
        aspace.keys = keys
        h.stop()


def test_adding_the_same_recipe_again_starts_its_transfer_over_in_the_same_slot(
    tmp_path: Path, cache_dir: Path
) -> None:
    h = started(tmp_path, cache_dir, recipe_transfers_max=1)

    async def scenario() -> list[Any]:
        async with Client(h.endpoint, timeout=30, watchdog_intervall=15) as client:
            r = await Recipes(client).setup()
            first = (await r.add("kit-again"))[1]
            handle = await r.handle(first)
            fh = await handle.call_method("0:Open", ua.Variant(6, _T.Byte))
            await handle.call_method("0:Write", ua.Variant(fh, _T.UInt32), ua.Variant(b"half a rec", _T.ByteString))
            second = (await r.add("kit-again"))[1]  # the client lost its connection and starts over
            stale = await code(handle.call_method("0:Close", ua.Variant(fh, _T.UInt32)))  # the old handle is gone
            fh = await handle.call_method("0:Open", ua.Variant(6, _T.Byte))
            data = ua.Variant(RECIPE_BOLTS.encode(), _T.ByteString)
            await handle.call_method("0:Write", ua.Variant(fh, _T.UInt32), data)
            closed = await code(handle.call_method("0:Close", ua.Variant(fh, _T.UInt32)))
            return [first == second, stale, closed]

    try:
        assert asyncio.run(scenario()) == [True, "BadInvalidState", "Good"]
        assert h.book.load("kit-again").classes == {"bolt"}
    finally:
        h.stop()

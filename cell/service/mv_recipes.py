"""OPC 40100-1 RecipeManagement: GetRecipeListFiltered, PrepareRecipe, UnprepareRecipe,
AddRecipe, RemoveRecipe, the Recipes folder's RecipeType objects with their Prepare and
Unprepare, and AddRecipe's transfer through a recipe's Handle (FileType: Open, Write, Close ...),
with the transfers' limits and expiry."""

from __future__ import annotations

import asyncio
import contextlib
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from asyncua import Node, ua

from cell.core.commands import Command, CommandRefused, RecipeRequest, needed_role
from cell.core.events import Role
from cell.recipes import RecipeError, RecipeInfo, read_recipe_if_any
from cell.service.mv_parts import (
    CHILD_REFS,
    MachineVisionParts,
    MethodError,
    bad_recipe_id,
    log,
    spec_id,
    valid_recipe_id,
)
from cell.service.mv_results import external_id, internal_id
from cell.service.ua_values import node_id, status

_T = ua.VariantType
_FILE_MAX_BYTES = 64 * 1024  # a recipe written through a Handle
# A recipe's own methods (each recipe object in Recipes), with their roles; its Handle (FileType)
# writes a new recipe, so every one of the Handle's methods needs AddRecipe's.
RECIPE_METHODS: dict[str, Role] = {
    "Prepare": needed_role(Command.PREPARE_RECIPE),
    "Unprepare": needed_role(Command.UNPREPARE_RECIPE),
}
HANDLE_ROLE = needed_role(Command.ADD_RECIPE)


@dataclass
class RecipeTransfer:
    """A recipe being written through its Handle (FileType) after AddRecipe."""

    recipe_id: str
    node: Node
    data: bytearray
    open_handle: int = 0
    used_s: float = 0.0  # time.monotonic() of its last call: an idle transfer expires


class RecipeManagementPart(MachineVisionParts):
    """RecipeManagement of MachineVisionServer: its methods, the recipe objects and transfers."""

    # ---- recipes ----------------------------------------------------------------------
    async def _get_recipe_list(
        self,
        external_id: Any = None,
        product_id: Any = None,
        is_prepared: Any = 2,
        max_results: int = 0,
        start_index: int = 0,
        timeout: int = 0,
    ) -> list[ua.Variant]:
        want_id, want_product = spec_id(external_id), spec_id(product_id)
        prepared = self.service.snapshot().recipe
        tri = int(getattr(is_prepared, "value", is_prepared) or 0)
        listed = []
        for info in await asyncio.to_thread(self.recipes.list):
            if info.error or (want_id and info.recipe_id != want_id):
                continue
            if want_product and want_product not in info.products:
                continue
            if tri in (0, 1) and (info.recipe_id == prepared) != bool(tri):
                continue
            listed.append(internal_id(info.recipe_id, info.sha256))
        start = max(0, int(start_index or 0))
        count = int(max_results or 0) or len(listed)
        page = listed[start : start + count]
        handle = self._new_handle([p.Id for p in page])
        return [
            ua.Variant(start + len(page) >= len(listed), _T.Boolean),
            ua.Variant(len(listed), _T.UInt32),
            ua.Variant(handle, _T.UInt32),
            ua.Variant(page, _T.ExtensionObject, is_array=True),
            ua.Variant(0, _T.Int32),
        ]

    def _recipe_from(self, external_id: Any, internal_id: Any) -> str:
        recipe_id = spec_id(internal_id) or spec_id(external_id)
        if not recipe_id:
            raise MethodError(ua.StatusCodes.BadInvalidArgument, "no recipe named (ExternalId or InternalIdIn)")
        if not valid_recipe_id(recipe_id):
            bad_recipe_id(f"recipe id {recipe_id!r}")
        return recipe_id

    async def _prepare_recipe(self, external_id: Any = None, internal_id: Any = None) -> list[ua.Variant]:
        recipe_id = self._recipe_from(external_id, internal_id)
        self._command(Command.PREPARE_RECIPE, RecipeRequest(recipe_id))
        await self._refresh_recipe_folder()
        await self._say_unbinned(recipe_id)
        return [
            ua.Variant(self._internal(recipe_id), _T.ExtensionObject),
            ua.Variant(True, _T.Boolean),
            ua.Variant(0, _T.Int32),
        ]

    async def _say_unbinned(self, recipe_id: str) -> None:
        """A recipe prepared with taught types without a bin (found and counted, left on the table): PrepareRecipe's
        answer has no words (its Error is 0, OK: the recipe is prepared, a type without a bin is no error), so
        the words go out as a VisionInformationEvent from the VisionSystem (OPC 40100-1 11.4.3: low severity,
        no interaction needed), its Message the one the service's log has. Best effort: the call's answer stands."""
        try:
            info = await asyncio.to_thread(self.recipes.info, recipe_id)
            recipe = await asyncio.to_thread(read_recipe_if_any, info.path)
            words = recipe.unbinned_words(recipe_id) if recipe is not None else None
            if not words:
                return
            gen = self._generators["info"]
            gen.event.Message = ua.LocalizedText(words)
            gen.event.Severity = 200
            await gen.trigger()
        except Exception:
            log.exception("Machine Vision: the information event for recipe %s was not sent", recipe_id)

    async def _unprepare_recipe(self, external_id: Any = None, internal_id: Any = None) -> list[ua.Variant]:
        recipe_id = spec_id(internal_id) or spec_id(external_id) or self.service.snapshot().recipe
        self._command(Command.UNPREPARE_RECIPE, RecipeRequest(recipe_id))
        await self._refresh_recipe_folder()
        return [ua.Variant(self._internal(recipe_id), _T.ExtensionObject), ua.Variant(0, _T.Int32)]

    def _internal(self, recipe_id: str) -> Any:
        try:
            sha = self.recipes.info(recipe_id).sha256 if recipe_id else ""
        except RecipeError:
            sha = ""
        return internal_id(recipe_id, sha)

    async def _remove_recipe(self, external_id: Any = None) -> list[ua.Variant]:
        recipe_id = self._recipe_from(external_id, None)
        self._command(Command.REMOVE_RECIPE, RecipeRequest(recipe_id))
        await self._refresh_recipe_folder()
        return self._ok()

    async def _add_recipe(self, external_id: Any = None, product_id: Any = None) -> list[ua.Variant]:
        """A new recipe: its object in Recipes, to be written through its Handle; an identical
        existing one (same id and hash) needs no transfer. The caller's role was checked before
        (AddRecipe's, from the command table); the count of recipes and of transfers open at once
        is bounded (service.machine_vision.recipes_max, recipe_transfers_max): past it,
        BadTooManyOperations and nothing added."""
        recipe_id = self._recipe_from(external_id, None)
        existing = await asyncio.to_thread(self._existing, recipe_id)
        if existing is not None:
            given = bytes(getattr(external_id, "Hash", b"") or b"")
            if given and given.hex() == existing.sha256:
                node = await self._recipe_node(recipe_id)
                return self._add_outputs(recipe_id, existing.sha256, node.nodeid, False)
            raise MethodError(
                ua.StatusCodes.BadInvalidArgument, f"recipe {recipe_id!r} exists with other content: remove it first"
            )
        again = next((t for t in self._transfers.values() if t.recipe_id == recipe_id), None)
        if again is not None:  # a client starting over (its connection dropped mid-transfer): the same slot, emptied
            again.open_handle, again.data, again.used_s = 0, bytearray(), time.monotonic()
            return self._add_outputs(recipe_id, "", again.node.nodeid, True)
        mv = self.mv
        if len(self._transfers) >= mv.recipe_transfers_max:
            raise MethodError(
                ua.StatusCodes.BadTooManyOperations,
                f"{len(self._transfers)} recipe transfers open (service.machine_vision.recipe_transfers_max = "
                f"{mv.recipe_transfers_max}): close one, or wait {mv.recipe_transfer_timeout_s:g} s for an idle one "
                "to expire",
            )
        if len(self._recipe_nodes) >= mv.recipes_max:
            raise MethodError(
                ua.StatusCodes.BadTooManyOperations,
                f"{len(self._recipe_nodes)} recipes (service.machine_vision.recipes_max = {mv.recipes_max}): "
                "remove one first",
            )
        node = await self._recipe_node(recipe_id)
        self._transfers[node.nodeid] = RecipeTransfer(recipe_id, node, bytearray(), used_s=time.monotonic())
        return self._add_outputs(recipe_id, "", node.nodeid, True)

    def _existing(self, recipe_id: str) -> RecipeInfo | None:
        """The recipe file's info (on a worker thread: it reads and hashes the file), None if there is none."""
        try:
            return self.recipes.info(recipe_id)
        except RecipeError:
            return None

    def _add_outputs(self, recipe_id: str, sha: str, node_id: ua.NodeId, transfer: bool) -> list[ua.Variant]:
        return [
            ua.Variant(internal_id(recipe_id, sha), _T.ExtensionObject),
            ua.Variant(node_id, _T.NodeId),
            ua.Variant(ua.NodeId(), _T.NodeId),
            ua.Variant(transfer, _T.Boolean),
            ua.Variant(0, _T.Int32),
        ]

    async def _recipe_node(self, recipe_id: str) -> Node:
        """The RecipeType object for `recipe_id` in Recipes, made if missing, with its Handle bound.
        Found in the index, never by browsing; made and trimmed touching only its own nodes."""
        node = self._recipe_nodes.get(recipe_id)
        if node is not None:
            return node
        folder, app = self._n["recipe_folder"], self._ns["app"]
        nid = node_id(f"VisionSystem.Recipes.{recipe_id}", app)
        node = await folder.add_object(
            nid, ua.QualifiedName(recipe_id, app), node_id(1002, self._ns["mv"]), instantiate_optional=True
        )
        for name in ("LinkProduct", "UnlinkProduct", "LinkedProducts"):
            with contextlib.suppress(ua.UaStatusCodeError):
                self._delete_subtree((await node.get_child([f"{self._ns['mv']}:{name}"])).nodeid)
        await self._bind_recipe_node(node, recipe_id)
        await self._read_only(self._subtree(node.nodeid))
        self._recipe_nodes[recipe_id] = node
        return node

    def _subtree(self, root: ua.NodeId) -> set[ua.NodeId]:
        """`root` and its children (components and properties), read from the address space directly."""
        aspace = self.server.iserver.aspace
        found: set[ua.NodeId] = set()
        todo = [root]
        while todo:
            nid = todo.pop()
            if nid in found or nid not in aspace:
                continue
            found.add(nid)
            todo += [r.NodeId for r in aspace[nid].references if r.IsForward and r.ReferenceTypeId in CHILD_REFS]
        return found

    def _delete_subtree(self, root: ua.NodeId) -> None:
        """Delete `root` and its children, and the references to them from the nodes they refer to
        (references are kept both ways): asyncua's delete_nodes looks through every node of the
        address space for each node it deletes, which a client could make the loop do at will."""
        aspace = self.server.iserver.aspace
        doomed = self._subtree(root)
        neighbours = {r.NodeId for nid in doomed for r in aspace[nid].references} - doomed
        for nid in doomed:
            data = aspace[nid]
            value = data.attributes.get(ua.AttributeIds.Value)
            for handle, callback in list(value.datachange_callbacks.items()) if value is not None else []:
                with contextlib.suppress(Exception):  # a client's monitored item: told the node is gone
                    callback(handle, None, status(ua.StatusCodes.BadNodeIdUnknown))
                    aspace.delete_datachange_callback(handle)
            del aspace[nid]
        for nid in neighbours:
            if nid in aspace:
                data = aspace[nid]
                data.references = [r for r in data.references if r.NodeId not in doomed]

    async def _bind_recipe_node(self, node: Node, recipe_id: str) -> None:
        mv = self._ns["mv"]

        async def prepare() -> list[ua.Variant]:
            self._command(Command.PREPARE_RECIPE, RecipeRequest(recipe_id))
            await self._refresh_recipe_folder()
            await self._say_unbinned(recipe_id)
            return [ua.Variant(True, _T.Boolean), ua.Variant(0, _T.Int32)]

        async def unprepare() -> list[ua.Variant]:
            self._command(Command.UNPREPARE_RECIPE, RecipeRequest(recipe_id))
            await self._refresh_recipe_folder()
            return [ua.Variant(0, _T.Int32)]

        handlers = {"Prepare": prepare, "Unprepare": unprepare}
        for name, role in RECIPE_METHODS.items():
            self.server.link_method(await node.get_child([f"{mv}:{name}"]), self._wrap(name, handlers[name], role))
        handle = await node.get_child([f"{mv}:Handle"])
        file_methods: dict[str, Callable[..., Awaitable[list[ua.Variant]]]] = {
            "Open": self._file_open,
            "Write": self._file_write,
            "Read": self._file_read,
            "Close": self._file_close,
            "GetPosition": self._file_position,
            "SetPosition": self._file_set_position,
        }
        for name, fn in file_methods.items():
            self.server.link_method(await handle.get_child([f"0:{name}"]), self._wrap_file(name, node.nodeid, fn))

    def _wrap_file(self, name: str, recipe_node: ua.NodeId, fn: Callable[..., Awaitable[list[ua.Variant]]]) -> Any:
        async def handler(*args: Any) -> list[ua.Variant]:
            return await fn(recipe_node, *args)

        return self._wrap(f"Handle.{name}", handler, HANDLE_ROLE)

    def _transfer(self, recipe_node: ua.NodeId, handle: int | None = None) -> RecipeTransfer:
        t = self._transfers.get(recipe_node)
        if t is None or (handle is not None and t.open_handle != handle):
            raise MethodError(ua.StatusCodes.BadInvalidState, "no recipe transfer open on this Handle")
        t.used_s = time.monotonic()
        return t

    async def _file_open(self, recipe_node: ua.NodeId, mode: int = 0) -> list[ua.Variant]:
        t = self._transfer(recipe_node)
        if not int(mode) & 0x2:  # Write: only a new recipe's content is written, never read back here
            raise MethodError(ua.StatusCodes.BadNotWritable, "open a new recipe's Handle for writing (mode 2 or 6)")
        t.open_handle, t.data = secrets.randbelow(2**31 - 1) + 1, bytearray()
        return [ua.Variant(t.open_handle, _T.UInt32)]

    async def _file_write(self, recipe_node: ua.NodeId, handle: int, data: bytes) -> list[ua.Variant]:
        t = self._transfer(recipe_node, int(handle))
        if len(t.data) + len(data or b"") > _FILE_MAX_BYTES:
            raise MethodError(ua.StatusCodes.BadOutOfRange, f"a recipe is at most {_FILE_MAX_BYTES // 1024} KiB")
        t.data.extend(data or b"")
        return []

    async def _file_read(self, recipe_node: ua.NodeId, handle: int, length: int) -> list[ua.Variant]:
        raise MethodError(ua.StatusCodes.BadInvalidState, "a recipe Handle is open for writing only")

    async def _file_position(self, recipe_node: ua.NodeId, handle: int) -> list[ua.Variant]:
        t = self._transfer(recipe_node, int(handle))
        return [ua.Variant(len(t.data), _T.UInt64)]

    async def _file_set_position(self, recipe_node: ua.NodeId, handle: int, position: int) -> list[ua.Variant]:
        t = self._transfer(recipe_node, int(handle))
        if int(position) != len(t.data):
            raise MethodError(ua.StatusCodes.BadInvalidArgument, "a recipe is written from start to end")
        return []

    async def _file_close(self, recipe_node: ua.NodeId, handle: int) -> list[ua.Variant]:
        """The whole recipe has arrived: the service validates and stores it (AddRecipe)."""
        t = self._transfer(recipe_node, int(handle))
        t.open_handle = 0
        try:
            text = bytes(t.data).decode("utf-8")
        except UnicodeDecodeError:
            self._drop_transfer(t)
            raise MethodError(ua.StatusCodes.BadInvalidArgument, f"recipe {t.recipe_id!r}: not UTF-8 text") from None
        try:
            self._command(Command.ADD_RECIPE, RecipeRequest(t.recipe_id, text))
        except CommandRefused:
            self._drop_transfer(t)
            raise
        self._transfers.pop(t.node.nodeid, None)
        await self._refresh_recipe_folder()
        return []

    def _drop_transfer(self, t: RecipeTransfer) -> None:
        """Forget a transfer (refused, or idle too long); its node goes once the call that refused it
        has been answered (deleting the method's own node while it runs confuses asyncua's reply)."""
        self._transfers.pop(t.node.nodeid, None)

        async def delete() -> None:
            await asyncio.sleep(0.2)
            await self._refresh_recipe_folder()

        task = asyncio.create_task(delete())
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    def _expire_transfers(self) -> None:
        """Drop every transfer idle for longer than service.machine_vision.recipe_transfer_timeout_s."""
        timeout_s = self.mv.recipe_transfer_timeout_s
        now = time.monotonic()
        for t in [t for t in self._transfers.values() if now - t.used_s > timeout_s]:
            log.info(
                "OPC UA AddRecipe %r: no call on its Handle for %g s (recipe_transfer_timeout_s): dropped",
                t.recipe_id,
                timeout_s,
            )
            self._drop_transfer(t)

    async def _refresh_recipe_folder(self) -> None:
        """One RecipeType object per valid recipe file, with IsPrepared, InternalId, LastModified;
        an object with neither a file nor a transfer goes. The files are read on a worker thread."""
        mv = self._ns["mv"]
        prepared = self.service.snapshot().recipe
        present = set()
        for info in await asyncio.to_thread(self.recipes.list):
            if info.error:
                continue
            present.add(info.recipe_id)
            node = await self._recipe_node(info.recipe_id)
            values = {
                "IsPrepared": ua.Variant(info.recipe_id == prepared, _T.Boolean),
                "InternalId": ua.Variant(internal_id(info.recipe_id, info.sha256), _T.ExtensionObject),
                "ExternalId": ua.Variant(external_id(info.recipe_id, info.sha256), _T.ExtensionObject),
                "LastModified": ua.Variant(info.modified_utc, _T.DateTime),
            }
            for name, value in values.items():
                with contextlib.suppress(ua.UaStatusCodeError):
                    await (await node.get_child([f"{mv}:{name}"])).write_value(value)
        pending = set(t.recipe_id for t in self._transfers.values())
        for recipe_id, node in list(self._recipe_nodes.items()):
            if recipe_id not in present and recipe_id not in pending:
                self._delete_subtree(node.nodeid)
                del self._recipe_nodes[recipe_id]

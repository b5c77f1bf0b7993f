"""OPC 40100-1 ResultManagement: GetResultById (waiting for a result still being made, or
asking the history store), GetResultComponentsById, GetResultListFiltered, the result and
recipe list handles with their Release*Handle, and the ResultReadyEventType event fired for
every result. The results themselves are made in cell/service/mv_results.py."""

from __future__ import annotations

import asyncio
import secrets
from typing import Any

from asyncua import ua

from cell.service.mv_parts import MachineVisionParts, MethodError, spec_id
from cell.service.mv_results import result_data, result_message
from cell.service.results import LookupsBusy, ResultFilter, VisionResult

_T = ua.VariantType
_HANDLES_KEPT = 1000  # result and recipe handles a client has not released; the oldest go first
_RESULT_WAIT_MAX_S = 10.0  # the longest GetResultById waits for a result still being made
_RESULT_POLL_S = 0.05  # how often a waiting GetResultById looks in memory (never in the store) again


class ResultManagementPart(MachineVisionParts):
    """ResultManagement of MachineVisionServer: its methods, handles and result events."""

    # ---- results ----------------------------------------------------------------------
    def _new_handle(self, ids: list[str]) -> int:
        handle = secrets.randbelow(2**31 - 1) + 1
        self._handles[handle] = ids
        while len(self._handles) > _HANDLES_KEPT:
            self._handles.pop(next(iter(self._handles)))
        return handle

    async def _release_handle(self, handle: int = 0) -> list[ua.Variant]:
        if self._handles.pop(int(handle or 0), None) is None:
            raise MethodError(ua.StatusCodes.BadInvalidArgument, f"handle {handle} unknown or already released")
        return self._ok()

    async def _wait_result(self, result_id: Any, timeout_ms: int) -> VisionResult:
        """The result: from memory, where a result still being made appears (looked at again until
        the client's Timeout, at most _RESULT_WAIT_MAX_S); an older one from the history store,
        asked once on its own worker thread and waited for at most result_lookup_timeout_s. Nothing
        here blocks the loop: every other client is answered meanwhile, whatever the database does."""
        wanted = spec_id(result_id)
        if not wanted:
            raise MethodError(ua.StatusCodes.BadInvalidArgument, "ResultId is empty")
        loop = asyncio.get_running_loop()
        start = loop.time()
        client_deadline = start + min(max(int(timeout_ms or 0), 0) / 1000.0, _RESULT_WAIT_MAX_S)
        deadline = client_deadline
        found = self.results.get(wanted)
        if found is not None:
            return found
        store: asyncio.Future[VisionResult | None] | None = None
        busy: LookupsBusy | None = None
        try:
            future = self.results.lookup(wanted)
        except LookupsBusy as e:
            future, busy = None, e
        if future is not None:
            store = asyncio.wrap_future(future)
            deadline = max(deadline, start + self.mv.result_lookup_timeout_s)
        try:
            while True:
                if store is not None and store.done():
                    from_store = store.result()
                    if from_store is not None:
                        return from_store
                    store, deadline = None, client_deadline  # not there: memory until the client's Timeout
                found = self.results.get(wanted)
                if found is not None:
                    return found
                now = loop.time()
                if now >= deadline:
                    break
                wait = min(_RESULT_POLL_S, deadline - now)
                if store is not None:
                    await asyncio.wait({store}, timeout=wait)
                else:
                    await asyncio.sleep(wait)
        finally:
            if store is not None and not store.done():
                store.cancel()  # a lookup not yet begun is not made; one under way ends on its own
        if store is not None:
            raise MethodError(
                ua.StatusCodes.BadResourceUnavailable,
                f"result {wanted!r} not in memory, and the history store did not answer within "
                f"{self.mv.result_lookup_timeout_s:g} s (service.machine_vision.result_lookup_timeout_s)",
            )
        if busy is not None:
            raise MethodError(
                ua.StatusCodes.BadResourceUnavailable,
                f"result {wanted!r} not in memory, and the history store was not asked: {busy}",
            )
        raise MethodError(ua.StatusCodes.BadNotFound, f"result {wanted!r} not found (or no longer kept)")

    async def _get_result(self, result_id: Any = None, timeout: int = 0) -> list[ua.Variant]:
        r = await self._wait_result(result_id, timeout)
        return [
            ua.Variant(self._new_handle([r.result_id]), _T.UInt32),
            ua.Variant(result_data(r), _T.ExtensionObject),
            ua.Variant(0, _T.Int32),
        ]

    async def _get_result_components(self, result_id: Any = None, timeout: int = 0) -> list[ua.Variant]:
        r = await self._wait_result(result_id, timeout)
        d = result_data(r)
        return [
            ua.Variant(False, _T.Boolean),
            ua.Variant(self._new_handle([r.result_id]), _T.UInt32),
            ua.Variant(False, _T.Boolean),
            ua.Variant(r.is_simulated, _T.Boolean),
            ua.Variant(r.result_state, _T.Int32),
            ua.Variant(d.MeasId, _T.ExtensionObject),
            ua.Variant(d.PartId, _T.ExtensionObject),
            ua.Variant(d.ExternalRecipeId, _T.ExtensionObject),
            ua.Variant(d.InternalRecipeId, _T.ExtensionObject),
            ua.Variant(d.ProductId, _T.ExtensionObject),
            ua.Variant(d.ExternalConfigurationId, _T.ExtensionObject),
            ua.Variant(d.InternalConfigurationId, _T.ExtensionObject),
            ua.Variant(d.JobId, _T.ExtensionObject),
            ua.Variant(r.creation_time, _T.DateTime),
            ua.Variant(d.ProcessingTimes, _T.ExtensionObject),
            ua.Variant(d.ResultContent, _T.Variant, is_array=True),
            ua.Variant(0, _T.Int32),
        ]

    async def _get_result_list(self, *args: Any) -> list[ua.Variant]:
        state, meas, part, ext_recipe, int_recipe, ext_conf, int_conf, product, job, max_results, start, _timeout = (
            list(args) + [None] * 12
        )[:12]
        where = ResultFilter(
            result_state=int(state or 0),
            job_id=spec_id(job),
            meas_id=spec_id(meas),
            part_id=spec_id(part),
            product_id=spec_id(product),
            recipe_id=spec_id(int_recipe) or spec_id(ext_recipe),
            configuration_id=spec_id(int_conf) or spec_id(ext_conf),
        )
        start_index = max(0, int(start or 0))
        count = min(int(max_results or 0) or 1000, 1000)
        page, total = self.results.query(where, start_index, count)
        return [
            ua.Variant(start_index + len(page) >= total, _T.Boolean),
            ua.Variant(total, _T.UInt32),
            ua.Variant(self._new_handle([r.result_id for r in page]), _T.UInt32),
            ua.Variant([result_data(r) for r in page], _T.ExtensionObject, is_array=True),
            ua.Variant(0, _T.Int32),
        ]

    async def _fire_result(self, r: VisionResult) -> None:
        assert self.node is not None
        gen = self._generators["result"]
        d = result_data(r)
        ev = gen.event
        ev.Message = ua.LocalizedText(result_message(r))
        ev.Severity = 100 if r.result_state == 1 else 500
        for name in (
            "ResultId",
            "JobId",
            "MeasId",
            "PartId",
            "ProductId",
            "ExternalRecipeId",
            "InternalRecipeId",
            "ExternalConfigurationId",
            "InternalConfigurationId",
            "ProcessingTimes",
        ):
            value = getattr(d, name)
            ev.add_property(name, value, _T.Null if value is None else _T.ExtensionObject)
        ev.add_property("IsPartial", False, _T.Boolean)
        ev.add_property("IsSimulated", r.is_simulated, _T.Boolean)
        ev.add_property("ResultState", r.result_state, _T.Int32)
        ev.add_property("CreationTime", r.creation_time, _T.DateTime)
        ev.add_property("ResultContent", d.ResultContent, _T.Variant)
        await gen.trigger(r.creation_time)

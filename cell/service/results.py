"""Vision results as OPC 40100-1 sees them: every pick attempt's verdict is one, and every
job's end one more. They are kept in a `ResultStore` so a client that was away can fetch what
it missed (GetResultById, GetResultListFiltered). `MemoryResultStore` keeps the newest N in
memory; a store backed by the history database provides the same Protocol.

Frames in names: `table_mm` the plate frame, `robot_mm` the arm's base frame.
"""

from __future__ import annotations

import logging
import pickle
import queue
import sys
import threading
from collections import OrderedDict
from concurrent.futures import Future
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any, Protocol

# OPC 40100-1 ResultStateDataType (an Int32; negative values are the application's own).
RESULT_COMPLETED = 1
RESULT_PROCESSING = 2
log = logging.getLogger(__name__)

RESULT_ABORTED = 3
RESULT_FAILED = 4

PICK_STATES = {"picked": RESULT_COMPLETED, "rehearsed": RESULT_COMPLETED, "missed": RESULT_FAILED}
JOB_STATES = {"done": RESULT_COMPLETED, "stopped": RESULT_ABORTED, "halted": RESULT_ABORTED, "fault": RESULT_FAILED}


@dataclass(frozen=True, slots=True)  # slots: 10,000 are kept; a __dict__ each would be a third of them
class VisionResult:
    """One result: a pick attempt (kind "pick") or a job's end (kind "job")."""

    result_id: str  # a pick's pick_id (`<job>/<attempt>`), or `<job>/end`
    job_id: str
    kind: str  # pick | job
    result_state: int  # RESULT_*
    creation_time: datetime  # UTC, when it was decided
    start_time: datetime  # UTC, when its processing began (the target chosen, the job started)
    processing_ms: float
    is_simulated: bool
    recipe_id: str = ""  # the recipe in force (ExternalRecipeId / InternalRecipeId)
    recipe_sha256: str = ""
    configuration_id: str = ""  # the calibration in force (InternalConfigurationId)
    meas_id: str = ""
    part_id: str = ""
    product_id: str = ""
    content: dict[str, Any] = field(
        default_factory=dict
    )  # what ResultContent carries (see docs/opcua-machinevision.md)


@dataclass(frozen=True)
class ResultFilter:
    """GetResultListFiltered's criteria; an empty string or 0 matches anything."""

    result_state: int = 0
    job_id: str = ""
    meas_id: str = ""
    part_id: str = ""
    product_id: str = ""
    recipe_id: str = ""
    configuration_id: str = ""

    def matches(self, r: VisionResult) -> bool:
        return self.matches_key(_filter_key(r))

    def matches_key(self, key: tuple[int, str, str, str, str, str, str]) -> bool:
        """As `matches`, on a kept result's filter fields (result state, job, meas, part, product,
        recipe and configuration ids)."""
        state, *texts = key
        if self.result_state and state != self.result_state:
            return False
        wants = (self.job_id, self.meas_id, self.part_id, self.product_id, self.recipe_id, self.configuration_id)
        return all(not want or want == have for want, have in zip(wants, texts, strict=True))


class LookupsBusy(Exception):
    """Every slot for lookups in the history store is taken (the store is slow or away): not looked up."""


class ResultStore(Protocol):
    """Where results are kept. Thread-safe: added from the service's event thread, read from OPC UA's loop.
    `get` and `query` answer from memory and never wait on anything; `lookup` asks a slower store
    (the history database) on a worker thread, for a result no longer in memory."""

    def add(self, result: VisionResult) -> None: ...

    def get(self, result_id: str) -> VisionResult | None: ...

    def lookup(self, result_id: str) -> Future[VisionResult | None] | None:
        """The result from the slower store, answered on a worker thread; None when there is no such
        store (or it cannot hold this result). LookupsBusy when too many lookups wait already."""
        ...

    def query(self, where: ResultFilter, start_index: int, max_results: int) -> tuple[list[VisionResult], int]:
        """The matches from `start_index` on (oldest first), at most `max_results`, and how many match in all."""
        ...


class MemoryResultStore:
    """The newest `capacity` results in memory; older ones are forgotten (GetResultById: not found).

    Each result is kept as one pickled blob (about 600 bytes, from the C allocator) beside the few
    fields a filter reads, not as its two dozen small Python objects: kept for hours among the
    short-lived objects of every pick, those pinned pages of Python's small-object allocator and
    cost some 3.5 KB of RSS a result (35 MB at 10,000) where the blob costs what it holds (about
    1.3 KB of RSS a result in the soaks). `get` and a page of `query` unpickle only what they return
    (about 20 us a result)."""

    def __init__(self, capacity: int = 1000):
        if capacity < 1:
            raise ValueError(f"capacity {capacity}: at least 1")
        self.capacity = capacity
        self._results: OrderedDict[str, tuple[tuple[int, str, str, str, str, str, str], bytes]] = OrderedDict()
        self._lock = threading.Lock()

    def add(self, result: VisionResult) -> None:
        blob = pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)
        with self._lock:
            self._results[result.result_id] = (_filter_key(result), blob)
            self._results.move_to_end(result.result_id)
            while len(self._results) > self.capacity:
                self._results.popitem(last=False)

    def get(self, result_id: str) -> VisionResult | None:
        with self._lock:
            kept = self._results.get(result_id)
        return None if kept is None else _load(kept[1])

    def lookup(self, result_id: str) -> Future[VisionResult | None] | None:
        return None  # memory is all there is

    def query(self, where: ResultFilter, start_index: int, max_results: int) -> tuple[list[VisionResult], int]:
        with self._lock:
            matches = [blob for key, blob in self._results.values() if where.matches_key(key)]
        return [_load(b) for b in matches[start_index : start_index + max_results]], len(matches)

    def __len__(self) -> int:
        with self._lock:
            return len(self._results)


def _filter_key(r: VisionResult) -> tuple[int, str, str, str, str, str, str]:
    """What ResultFilter reads, the repeated strings shared among results (interned)."""
    i = sys.intern
    return (
        r.result_state,
        i(r.job_id),
        i(r.meas_id),
        i(r.part_id),
        i(r.product_id),
        i(r.recipe_id),
        i(r.configuration_id),
    )


def _load(blob: bytes) -> VisionResult:
    result: VisionResult = pickle.loads(blob)  # our own blob, made by add(): never a client's bytes
    return result


class HistoryBackedResults:
    """The newest results in memory, and every older pick answered from the history store, so a
    client that was away for longer than the memory holds can still fetch what it missed by id.

    `reader` is a cell.history.query.HistoryReader (opened read-only for this cell: it serves this
    cell's rows only); its job rows give the recipe and the specification's ids (MeasId, PartId,
    ProductId) the job was started with. The store is read on one worker thread of its own, one
    query at a time, never on the OPC UA loop: a slow or half-open database delays only the
    lookups, at most `max_waiting` of them (queued or running); past that `lookup` refuses."""

    def __init__(self, memory: MemoryResultStore, reader: Any, simulated: bool, max_waiting: int = 4):
        if max_waiting < 1:
            raise ValueError(f"max_waiting {max_waiting}: at least 1")
        self.memory, self.reader, self.simulated, self.max_waiting = memory, reader, simulated, max_waiting
        self._jobs: queue.SimpleQueue[tuple[str, Future[VisionResult | None]] | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._waiting = 0  # lookups queued or running
        self._thread: threading.Thread | None = None
        self._closed = False

    def add(self, result: VisionResult) -> None:
        self.memory.add(result)

    def get(self, result_id: str) -> VisionResult | None:
        return self.memory.get(result_id)

    @property
    def waiting(self) -> int:
        with self._lock:
            return self._waiting

    def lookup(self, result_id: str) -> Future[VisionResult | None] | None:
        if result_id.endswith("/end"):  # a job's end is a result of memory only
            return None
        with self._lock:
            if self._closed:
                return None
            if self._waiting >= self.max_waiting:
                raise LookupsBusy(
                    f"{self._waiting} lookups already wait for the history store "
                    f"(service.machine_vision.result_lookups_max = {self.max_waiting})"
                )
            self._waiting += 1
            if self._thread is None:  # a daemon: a read stuck on a dead connection never holds the exit
                self._thread = threading.Thread(target=self._work, name="opcua-result-lookup", daemon=True)
                self._thread.start()
        future: Future[VisionResult | None] = Future()
        self._jobs.put((result_id, future))
        return future

    def close(self) -> None:
        """No more lookups; the worker ends after the one it is in (it is not waited for)."""
        with self._lock:
            self._closed = True
        self._jobs.put(None)

    def _work(self) -> None:
        while (job := self._jobs.get()) is not None:
            result_id, future = job
            try:
                if future.set_running_or_notify_cancel():  # a caller that gave up is not looked up
                    future.set_result(self._read(result_id))
            except BaseException as e:  # noqa: BLE001 - handed to the caller, never the thread's end
                future.set_exception(e)
            finally:
                with self._lock:
                    self._waiting -= 1

    def _read(self, result_id: str) -> VisionResult | None:
        try:
            pick = self.reader.get_pick(result_id)
            job = self.reader.get_job(pick["job_id"]) if pick else None
            return None if pick is None else self._from_history(pick, job or {})
        except Exception:  # the store is a fallback: its trouble is logged, the answer is "not found"
            log.warning("results: the history store could not be read for %s", result_id, exc_info=True)
            return None

    def query(self, where: ResultFilter, start_index: int, max_results: int) -> tuple[list[VisionResult], int]:
        return self.memory.query(where, start_index, max_results)

    def _from_history(self, pick: dict[str, Any], job: dict[str, Any]) -> VisionResult:
        t = datetime.fromisoformat(pick["time_utc"])
        args = job.get("arguments") or {}
        return VisionResult(
            pick["id"],
            pick["job_id"],
            "pick",
            PICK_STATES.get(pick["outcome"], RESULT_FAILED),
            t,
            t - timedelta(milliseconds=float(pick["cycle_ms"] or 0.0)),
            float(pick["cycle_ms"] or 0.0),
            self.simulated,
            recipe_id=job.get("recipe") or "",
            configuration_id=pick["calibration_id"] or "",
            meas_id=str(args.get("meas_id", "")),
            part_id=str(args.get("part_id", "")),
            product_id=str(args.get("product_id", "")),
            content={
                "Class": pick["class"],
                "Outcome": pick["outcome"],
                "TableMm": [float(v or 0.0) for v in pick["table_mm"]],
                "RobotMm": [float(v or 0.0) for v in pick["robot_mm"]],
                "JawAngleDeg": float(pick["jaw_angle_deg"] or 0.0),
                "PixelPx": [float(v or 0.0) for v in pick["pixel"]],
                "Track": int(pick["track"]),
                "Attempt": int(pick["attempt"]),
                "CycleMs": float(pick["cycle_ms"] or 0.0),
            },
        )

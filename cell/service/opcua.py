"""The cell's OPC UA server (asyncua): an object `Cell` in namespace urn:pick-cell with the
OPC 40100-1 style methods and the cell's state, counters, last pick, alarm and calibration.

It holds only a LineServiceAPI. A method call becomes `service.command()`; a command the
state does not allow returns BadInvalidState, a call with arguments BadTooManyArguments:
the cell stays as it was. Service events (from the cell's worker thread) only mark the
values dirty; one task on the server's loop writes what changed, and the heartbeat, so
a slow client never holds the cell up. Node tree and types: docs/opcua.md.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from datetime import UTC, datetime
from types import MappingProxyType
from typing import Any

from asyncua import ua
from asyncua.server.event_generator import EventGenerator

from cell.access.network import reachable_urls
from cell.access.security import credentials_configured
from cell.access.throttle import LoginThrottle
from cell.access.users import Authenticator
from cell.asyncwait import wait_event
from cell.config import CellConfig
from cell.core.api import LineServiceAPI
from cell.core.commands import STATE_COMMANDS, Command, CommandRefused, Refusal
from cell.core.eventbus import Subscription
from cell.core.events import (
    Event,
    JobStarted,
    Origin,
    PartClassesChanged,
    PartFailed,
    PickVerified,
    SnapshotChanged,
)
from cell.core.parts import BUILT_IN_PARTS, PartRegistry
from cell.core.records import PickRecord, PickRecords, Snapshot
from cell.core.values import Kind, kinds, snapshot_values
from cell.errors import ConfigError
from cell.service.machinevision import MachineVisionServer
from cell.service.mv_addressspace import cache_dir_for, init_server_with_models
from cell.service.opcua_security import GuardedServer, GuardSettings, caller_origin
from cell.service.results import HistoryBackedResults, MemoryResultStore, ResultStore
from cell.service.ua_values import data_value, node_id, status

log = logging.getLogger(__name__)

NAMESPACE = "urn:pick-cell"
APP_URI = "urn:pick-cell:server"
_T = ua.VariantType
_EPOCH = datetime(1601, 1, 1, tzinfo=UTC)  # OPC UA's "no time"

# The Cell object's variables: BrowseName -> the value's key in cell.core.values (one mapping from
# the Snapshot for OPC UA, Sparkplug and /metrics). Between "WaitingForParts" and "Misses" come the
# counters of the part classes, named by the registry (cell.core.parts: PickedBolts, PickedNuts ...).
_BEFORE_CLASSES = {
    "VisionState": "vision_state",
    "CellState": "cell_state",
    "Paused": "paused",
    "Pausing": "pausing",
    "WaitingForParts": "waiting_for_parts",
}
_AFTER_CLASSES = {
    "Misses": "misses",
    "Retries": "retries",
    "Failed": "failed",
    "Unreachable": "unreachable",
    "UnknownLeft": "unknown_left",
    "PartsPerMinute": "parts_per_minute",
    "LastPickClass": "last_pick_class",
    "LastPickTableMm": "last_pick_table_mm",
    "LastPickRobotMm": "last_pick_robot_mm",
    "LastPickAngleDeg": "last_pick_angle_deg",
    "LastPickOutcome": "last_pick_outcome",
    "LastPickTime": "last_pick_time",
    "ActiveAlarm": "fault",
    "ActiveWarnings": "warnings",
    "Heartbeat": "heartbeat",
    "CalibrationModel": "calibration_model",
    "CalibrationCvRmsMm": "calibration_cv_rms_mm",
    "CalibrationCvMaxMm": "calibration_cv_max_mm",
    "CalibrationTime": "calibration_time",
    "JobId": "job_id",
    "DroppedEvents": "dropped_events",
    "Shift": "shift",
}
_UA_TYPE: dict[Kind, tuple[ua.VariantType, bool]] = {
    Kind.TEXT: (_T.String, False),
    Kind.FLAG: (_T.Boolean, False),
    Kind.COUNT: (_T.UInt32, False),
    Kind.NUMBER: (_T.Double, False),
    Kind.TIME: (_T.DateTime, False),
    Kind.NUMBERS: (_T.Double, True),
    Kind.TEXTS: (_T.String, True),
}
# OPC UA has no null: what a value that is not known reads as
_NONE: dict[Kind, Any] = {Kind.TEXT: "", Kind.NUMBER: 0.0, Kind.TIME: _EPOCH, Kind.TEXTS: []}
_NONE_BY_KEY = {"last_pick_table_mm": [0.0, 0.0], "last_pick_robot_mm": [0.0, 0.0, 0.0]}


@functools.lru_cache(maxsize=16)  # made once per registry, not at every publish
def browse_names(parts: PartRegistry) -> Mapping[str, str]:
    """BrowseName -> value key, in the Cell object's order."""
    return MappingProxyType({**_BEFORE_CLASSES, **{p.opcua_name: p.counter_key for p in parts}, **_AFTER_CLASSES})


def variables(parts: PartRegistry) -> dict[str, tuple[ua.VariantType, bool]]:
    """BrowseName -> (type, array?) of every Cell variable."""
    kind = kinds(parts)
    return {name: _UA_TYPE[kind[key]] for name, key in browse_names(parts).items()}


VARIABLES = variables(BUILT_IN_PARTS)  # the variables with the built-in part classes (documented in docs/opcua.md)


def _values(s: Snapshot, parts: PartRegistry) -> dict[str, Any]:
    values, kind = snapshot_values(s, parts), kinds(parts)
    out: dict[str, Any] = {}
    for name, key in browse_names(parts).items():
        value = values[key]
        if value is None or (key in _NONE_BY_KEY and not value):
            value = _NONE_BY_KEY.get(key, _NONE.get(kind[key]))
        elif kind[key] is Kind.NUMBER:
            value = _finite(value)
        out[name] = value
    return out


# The PickEventType's own fields (besides BaseEventType's Message, Severity, Time ...).
PICK_EVENT_FIELDS = [
    ("TrackId", _T.UInt32),
    ("PartClass", _T.String),
    ("TableMm", _T.Double),
    ("RobotMm", _T.Double),
    ("AngleDeg", _T.Double),
    ("Outcome", _T.String),
]
_NODE_ADDED = 1  # ModelChangeStructureDataType.Verb bit NodeAdded (ReferenceAdded is 4)
_PICKS_QUEUED = 100  # picks waiting for the loop; a stalled loop drops the oldest, never holds the cell
_STATUS = {  # a refused command's status code
    Refusal.INVALID_STATE: ua.StatusCodes.BadInvalidState,
    Refusal.ACCESS_DENIED: ua.StatusCodes.BadUserAccessDenied,
    Refusal.SHUTTING_DOWN: ua.StatusCodes.BadShutdown,
    Refusal.BAD_ARGUMENT: ua.StatusCodes.BadInvalidArgument,
    Refusal.NOT_RECORDED: ua.StatusCodes.BadResourceUnavailable,
}
_RETRY_LOG_S = 60.0
_READER_CLOSE_WAIT_S = 5.0  # closing the history reader waits for a lookup under way at most this long


async def _close_off_loop(reader: Any, wait_s: float) -> None:
    """Close the history reader on a daemon thread: its close waits for a query under way, which a
    half-open database connection can hold for ever; the loop (and the shutdown) waits at most `wait_s`."""
    done: concurrent.futures.Future[None] = concurrent.futures.Future()

    def close() -> None:
        try:
            reader.close()
        finally:
            done.set_result(None)

    threading.Thread(target=close, name="opcua-history-close", daemon=True).start()
    try:
        await asyncio.wait_for(asyncio.wrap_future(done), wait_s)
    except TimeoutError:
        log.warning("OPC UA: the history reader did not close within %g s (a query stuck); left to end", wait_s)


def _finite(v: float) -> float:
    return float(v) if math.isfinite(v) else 0.0


class OpcUaServer:
    def __init__(self, service: LineServiceAPI, config: CellConfig, throttle: LoginThrottle | None = None):
        self.service, self.cfg, self.config = service, config.service, config
        self.machine_vision: MachineVisionServer | None = None
        self._reader: Any = None  # the history store, read for results older than memory holds
        self._history_results: HistoryBackedResults | None = None
        self.secure = credentials_configured(self.cfg)
        self.endpoint = f"opc.tcp://{self.cfg.host}:{self.cfg.opcua_port}/{self.cfg.opcua_path}"
        # issue 21: policies, trust list, users with roles, throttle, limits (cell/service/opcua_security.py)
        users = Authenticator(self.cfg)
        self.server = GuardedServer(
            GuardSettings.from_config(config, APP_URI, self.secure),
            users.authenticate if self.secure else None,
            throttle or LoginThrottle(self.cfg.login),
            users.credential if self.secure else None,  # a removed or changed user's sessions end (issue 28)
        )
        self.parts = service.parts  # the part classes, whose counters are variables of their own
        self.variables = variables(self.parts)
        self._grown: PartRegistry | None = None  # a registry grown while serving, its variables not added yet
        self._cell: Any = None  # the Cell object's node, and its namespace: new counters are added to it
        self._ns = 0
        self.nodes: dict[str, ua.NodeId] = {}
        self._written: dict[str, object] = {}
        self._dirty = asyncio.Event()
        self._picks: deque[PickRecord] = deque(maxlen=_PICKS_QUEUED)
        self._pick_events: EventGenerator | None = None
        self._model_changes: EventGenerator | None = None  # Cell's GeneralModelChangeEvent: variables added
        self._task: asyncio.Task[None] | None = None
        self._subscription: Subscription | None = None
        self._records = PickRecords()
        self._last_failure_log = -_RETRY_LOG_S
        self._publishing = asyncio.Lock()

    @property
    def ready_text(self) -> str:
        # a wildcard bind (0.0.0.0, ::) as the machine's addresses, which a PLC's engineer can type
        return f"OPC UA {reachable_urls('opc.tcp', self.cfg.host, self.cfg.opcua_port, f'/{self.cfg.opcua_path}')}"

    @property
    def starting_text(self) -> str:
        return f"the OPC UA server on {self.endpoint}"

    async def start(self) -> None:
        for name in ("asyncua", "asyncua.server", "asyncua.uaprotocol"):
            logging.getLogger(name).setLevel(logging.WARNING)
        s = self.server
        await init_server_with_models(s, cache_dir_for(self.config.service.machine_vision))  # OPC 40100-1, DI
        s.set_endpoint(self.endpoint)
        s.set_server_name("pick-cell")
        await s.set_application_uri(APP_URI)
        if self.secure:
            await self._secure()
        else:
            s.set_security_policy([ua.SecurityPolicyType.NoSecurity])
            s.set_identity_tokens([ua.AnonymousIdentityToken])
        ns = await s.register_namespace(NAMESPACE)
        cell = await s.nodes.objects.add_object(node_id("Cell", ns), ua.QualifiedName("Cell", ns))
        self._cell, self._ns = cell, ns
        await self._add_variables(self.variables, self.parts)
        for command in STATE_COMMANDS:
            await cell.add_method(
                node_id(command.value, ns), ua.QualifiedName(command.value, ns), self._method(command), [], []
            )
        etype = await s.create_custom_event_type(ns, "PickEventType", ua.ObjectIds.BaseEventType, PICK_EVENT_FIELDS)
        self._pick_events = await s.get_event_generator(etype, cell.nodeid)
        self._model_changes = await s.get_event_generator(ua.ObjectIds.GeneralModelChangeEventType, cell.nodeid)
        loop = asyncio.get_running_loop()
        self._subscription = self.service.subscribe(
            "opcua",
            lambda e: self._on_event(loop, e),
            kinds=(SnapshotChanged, PickVerified, PartFailed, JobStarted, PartClassesChanged),
        )
        self._note_parts(self.service.parts)  # grown before the subscription began
        simulated = self.service.snapshot().simulated
        self.machine_vision = MachineVisionServer(
            s, self.service, self.config, results=self._results(simulated), dry_run=simulated
        )
        await self.machine_vision.start()
        quiet = logging.getLogger("asyncua.server.server")
        quiet.setLevel(logging.CRITICAL)  # its traceback for a taken port; we say it in one line
        try:
            await s.start()
        except OSError as e:
            raise ConfigError(
                f"OPC UA: cannot listen on {self.cfg.host}:{self.cfg.opcua_port}: {e.strerror or e}",
                hint="another program holds the port: choose another with --opcua-port",
            ) from None
        finally:
            quiet.setLevel(logging.WARNING)
        self._task = asyncio.create_task(self._publish())
        log.info(
            "OPC UA server on %s (%s)",
            self.endpoint,
            "Basic256Sha256 SignAndEncrypt, user" if self.secure else "loopback, no security",
        )

    def _results(self, simulated: bool) -> ResultStore:
        """Results for OPC 40100-1's ResultManagement: the newest in memory, older picks from the
        history store (a client that was away fetches what it missed), when there is one."""
        memory = MemoryResultStore(self.config.service.machine_vision.results_kept)
        if not self.config.history.enabled:
            return memory
        try:
            from cell.history.query import open_reader

            self._reader = open_reader(self.config)
        except Exception as e:  # no store yet, or its server is away: the newest results still answer
            log.warning("OPC UA results: the history store cannot be read (%s); only the newest results are kept", e)
            return memory
        self._history_results = HistoryBackedResults(
            memory, self._reader, simulated, self.config.service.machine_vision.result_lookups_max
        )
        return self._history_results

    async def _secure(self) -> None:
        await self.server.secure()  # certificate, configured policies only, user name tokens, trust list

    def _method(self, command: Command) -> Callable[..., Awaitable[ua.StatusCode | list[ua.Variant]]]:
        async def call(parent: ua.NodeId, *args: ua.Variant) -> ua.StatusCode | list[ua.Variant]:
            if args:
                log.warning("OPC UA %s called with %d arguments: refused", command.value, len(args))
                return status(ua.StatusCodes.BadTooManyArguments)
            origin = self._origin(parent)
            if origin is None:  # deny by default: a caller without a role may do nothing
                log.info("OPC UA %s refused: the caller has no role", command.value)
                return status(ua.StatusCodes.BadUserAccessDenied)
            try:
                self.service.command(command, origin)
            except CommandRefused as e:
                log.info("OPC UA %s refused: %s", command.value, e)
                return status(_STATUS[e.reason])
            await self._publish_now()  # the caller reads the state its command made
            return []

        return call

    @staticmethod
    def _origin(parent: ua.NodeId) -> Origin | None:
        """Who called: the session's user and role, capped at service.machine_vision.client_role
        (loopback with no users: anonymous, with that role); None: a caller without a role.
        cell.service.opcua_security.caller_origin, from the request being handled."""
        return caller_origin()

    async def _add_variables(self, wanted: Mapping[str, tuple[ua.VariantType, bool]], parts: PartRegistry) -> None:
        """The Cell variables of `wanted` it does not have yet, with their current values (at start: all)."""
        values = _values(self.service.snapshot(), parts)
        for name, (vtype, array) in wanted.items():
            if name in self.nodes:
                continue
            var = await self._cell.add_variable(
                node_id(name, self._ns),
                ua.QualifiedName(name, self._ns),
                ua.Variant(values[name], vtype, is_array=array or None),
            )
            self.nodes[name] = var.nodeid
            self._written[name] = values[name]

    def _note_parts(self, parts: PartRegistry) -> None:
        """On the loop: a registry larger than the one served is added at the publisher's next round."""
        if len(parts) > len(self._grown or self.parts):
            self._grown = parts

    async def _add_part_classes(self) -> None:
        """The registry grew while serving (PartClassesChanged): a Picked<Plural> variable for each new class,
        added to Cell (after its other variables) before any value is written by the new registry."""
        parts, self._grown = self._grown, None
        if parts is None or len(parts) <= len(self.parts):
            return
        wanted = variables(parts)
        new = [name for name in wanted if name not in self.nodes]
        await self._add_variables(wanted, parts)
        self.parts, self.variables = parts, wanted
        log.info("OPC UA: Cell has %s now (part classes new to the service)", ", ".join(new))
        if self._model_changes is not None and new:
            await self._model_changed(self._model_changes, new)

    async def _model_changed(self, events: EventGenerator, added: list[str]) -> None:
        """A GeneralModelChangeEvent from Cell naming the variables added (NodeAdded): a client that browsed Cell
        hears it should browse again. Best effort: the variables are there whether or not it goes out."""
        ev = events.event
        ev.Message = ua.LocalizedText(f"Cell: {', '.join(added)} added (part classes new to the service)")
        ev.Severity = 100
        ev.Changes = [
            ua.ModelChangeStructureDataType(
                Affected=self.nodes[name],
                AffectedType=ua.NodeId(ua.Int32(ua.ObjectIds.BaseDataVariableType)),
                Verb=_NODE_ADDED,
            )
            for name in added
        ]
        ev.data_types["Changes"] = _T.ExtensionObject  # asyncua keeps the DataType's NodeId there, not a VariantType
        try:
            await events.trigger()
        except Exception:
            log.exception("OPC UA: the GeneralModelChangeEvent for %s was not sent", ", ".join(added))

    def _on_event(self, loop: asyncio.AbstractEventLoop, event: Event) -> None:
        """On the subscriber's thread: queue picks for the events, note a grown registry, wake the publisher."""
        record = self._records.of(event)
        if record is not None:
            self._picks.append(record)  # deque.append is atomic; the loop drains it
        if not loop.is_closed():
            try:
                if isinstance(event, PartClassesChanged):
                    loop.call_soon_threadsafe(self._note_parts, event.parts)
                loop.call_soon_threadsafe(self._dirty.set)
            except RuntimeError:
                pass  # the server's loop is shutting down

    async def _publish(self) -> None:
        """Write every value that changed (the heartbeat at least once a second). A failed write is
        logged (once a minute at most) and retried on the next round; the task never dies of it."""
        while True:
            await wait_event(self._dirty, 0.5)
            self._dirty.clear()
            try:
                await self._publish_once()
            except asyncio.CancelledError:
                raise
            except Exception:
                now = time.monotonic()
                if now - self._last_failure_log >= _RETRY_LOG_S:
                    self._last_failure_log = now
                    log.exception("OPC UA: publishing failed; retrying")
                await asyncio.sleep(0.5)

    async def _publish_now(self) -> None:
        try:
            await self._publish_once()
        except Exception:  # the publishing task retries; the method's answer stands
            log.debug("OPC UA: immediate publish failed", exc_info=True)

    async def _publish_once(self) -> None:
        async with self._publishing:  # the task and a method's immediate publish, one at a time
            await self._write_changes()

    async def _write_changes(self) -> None:
        self._note_parts(self.service.parts)  # the event's registry, should a full queue have dropped the event
        if self._grown is not None:
            await self._add_part_classes()
        while self._picks:
            await self._fire(self._picks[0])
            self._picks.popleft()
        now = datetime.now(UTC)
        for name, value in _values(self.service.snapshot(), self.parts).items():
            if self._written.get(name) != value:
                vtype, array = self.variables[name]
                variant = ua.Variant(value, vtype, is_array=array or None)
                await self.server.write_attribute_value(self.nodes[name], data_value(variant, now))
                self._written[name] = value

    async def _fire(self, p: PickRecord) -> None:
        """One pick as a PickEventType event from Cell."""
        events = self._pick_events
        if events is None:
            raise RuntimeError("OPC UA: a pick event before the server started")
        ev = events.event
        ev.Message = ua.LocalizedText(
            f"part {p.track_id} {p.cls} {p.outcome} at table ({p.table_mm[0]:.1f}, {p.table_mm[1]:.1f}) mm"
        )
        ev.Severity = 100 if p.outcome in ("picked", "rehearsed") else 500
        ev.TrackId, ev.PartClass, ev.Outcome = ua.Variant(p.track_id, _T.UInt32), p.cls, p.outcome
        ev.TableMm, ev.RobotMm = [float(v) for v in p.table_mm], [float(v) for v in p.robot_mm]
        ev.AngleDeg = float(p.angle_deg) if p.angle_deg is not None else 0.0
        await events.trigger(p.time_utc)

    async def stop(self) -> None:
        if self._subscription is not None:
            await asyncio.to_thread(self.service.unsubscribe, self._subscription)
            self._subscription = None
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
        if self.machine_vision is not None:
            await self.machine_vision.stop()
        if self._history_results is not None:
            self._history_results.close()  # its worker takes no more lookups
        if self._reader is not None:
            await _close_off_loop(self._reader, _READER_CLOSE_WAIT_S)
            self._reader = None
        await self.server.stop()

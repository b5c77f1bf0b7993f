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
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from typing import Any

from asyncua import ua
from asyncua.server.event_generator import EventGenerator

from cell.asyncwait import wait_event
from cell.config import CellConfig
from cell.errors import ConfigError
from cell.eventbus import Subscription
from cell.events import Event, JobStarted, Origin, PartFailed, PickVerified, SnapshotChanged
from cell.service.api import STATE_COMMANDS, Command, CommandRefused, LineServiceAPI, PickRecord, Refusal, Snapshot
from cell.service.ledger import PickRecords
from cell.service.machinevision import MachineVisionServer
from cell.service.mv_addressspace import cache_dir_for, init_server_with_models
from cell.service.opcua_security import GuardedServer, GuardSettings, caller_origin
from cell.service.results import HistoryBackedResults, MemoryResultStore, ResultStore
from cell.service.security import credentials_configured
from cell.service.throttle import LoginThrottle
from cell.service.ua_values import data_value, node_id, status
from cell.service.users import Authenticator

log = logging.getLogger(__name__)

NAMESPACE = "urn:pick-cell"
APP_URI = "urn:pick-cell:server"
_T = ua.VariantType
_EPOCH = datetime(1601, 1, 1, tzinfo=UTC)  # OPC UA's "no time"

# BrowseName -> (type, array?) ; the values come from a Snapshot in _values().
VARIABLES: dict[str, tuple[ua.VariantType, bool]] = {
    "VisionState": (_T.String, False),
    "CellState": (_T.String, False),
    "Paused": (_T.Boolean, False),
    "Pausing": (_T.Boolean, False),
    "WaitingForParts": (_T.Boolean, False),
    "PickedBolts": (_T.UInt32, False),
    "PickedNuts": (_T.UInt32, False),
    "Misses": (_T.UInt32, False),
    "Retries": (_T.UInt32, False),
    "Failed": (_T.UInt32, False),
    "Unreachable": (_T.UInt32, False),
    "UnknownLeft": (_T.UInt32, False),
    "PartsPerMinute": (_T.Double, False),
    "LastPickClass": (_T.String, False),
    "LastPickTableMm": (_T.Double, True),
    "LastPickRobotMm": (_T.Double, True),
    "LastPickAngleDeg": (_T.Double, False),
    "LastPickOutcome": (_T.String, False),
    "LastPickTime": (_T.DateTime, False),
    "ActiveAlarm": (_T.String, False),
    "ActiveWarnings": (_T.String, True),
    "Heartbeat": (_T.UInt32, False),
    "CalibrationModel": (_T.String, False),
    "CalibrationCvRmsMm": (_T.Double, False),
    "CalibrationCvMaxMm": (_T.Double, False),
    "CalibrationTime": (_T.DateTime, False),
    "JobId": (_T.String, False),
    "DroppedEvents": (_T.UInt32, False),
    "Shift": (_T.String, False),
}


def _values(s: Snapshot) -> dict[str, Any]:
    c, last, cal = s.counters, (s.last_picks[-1] if s.last_picks else None), s.calibration
    alarm = "" if s.alarm is None else f"{s.alarm.reason} (hint: {s.alarm.hint})"
    return {
        "VisionState": s.vision_state.value,
        "CellState": s.cell_state,
        "Paused": s.paused,
        "Pausing": s.pausing,
        "WaitingForParts": s.waiting_for_parts,
        "PickedBolts": c.picked_bolts,
        "PickedNuts": c.picked_nuts,
        "Misses": c.misses,
        "Retries": c.retries,
        "Failed": c.failed,
        "Unreachable": c.unreachable,
        "UnknownLeft": c.unknown_left,
        "PartsPerMinute": round(s.parts_per_min, 3),
        "LastPickClass": last.cls if last else "",
        "LastPickTableMm": [float(v) for v in last.table_mm] if last else [0.0, 0.0],
        "LastPickRobotMm": [float(v) for v in last.robot_mm] if last else [0.0, 0.0, 0.0],
        "LastPickAngleDeg": float(last.angle_deg) if last and last.angle_deg is not None else 0.0,
        "LastPickOutcome": last.outcome if last else "",
        "LastPickTime": last.time_utc if last else _EPOCH,
        "ActiveAlarm": alarm,
        "ActiveWarnings": [f"{w.reason} (hint: {w.hint})" for w in s.warnings],
        "Heartbeat": s.heartbeat,
        "CalibrationModel": cal.model if cal else "",
        "CalibrationCvRmsMm": _finite(cal.cv_rms_mm) if cal else 0.0,
        "CalibrationCvMaxMm": _finite(cal.cv_max_mm) if cal else 0.0,
        "CalibrationTime": (cal.time_utc or _EPOCH) if cal else _EPOCH,
        "JobId": s.job_id,
        "DroppedEvents": sum(x.dropped + x.failed for x in s.subscribers),
        "Shift": s.shift,
    }


# The PickEventType's own fields (besides BaseEventType's Message, Severity, Time ...).
PICK_EVENT_FIELDS = [
    ("TrackId", _T.UInt32),
    ("PartClass", _T.String),
    ("TableMm", _T.Double),
    ("RobotMm", _T.Double),
    ("AngleDeg", _T.Double),
    ("Outcome", _T.String),
]
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
        self.nodes: dict[str, ua.NodeId] = {}
        self._written: dict[str, object] = {}
        self._dirty = asyncio.Event()
        self._picks: deque[PickRecord] = deque(maxlen=_PICKS_QUEUED)
        self._pick_events: EventGenerator | None = None
        self._task: asyncio.Task[None] | None = None
        self._subscription: Subscription | None = None
        self._records = PickRecords()
        self._last_failure_log = -_RETRY_LOG_S
        self._publishing = asyncio.Lock()

    @property
    def ready_text(self) -> str:
        return f"OPC UA {self.endpoint}"

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
        values = _values(self.service.snapshot())
        for name, (vtype, array) in VARIABLES.items():
            var = await cell.add_variable(
                node_id(name, ns), ua.QualifiedName(name, ns), ua.Variant(values[name], vtype, is_array=array or None)
            )
            self.nodes[name] = var.nodeid
            self._written[name] = values[name]
        for command in STATE_COMMANDS:
            await cell.add_method(
                node_id(command.value, ns), ua.QualifiedName(command.value, ns), self._method(command), [], []
            )
        etype = await s.create_custom_event_type(ns, "PickEventType", ua.ObjectIds.BaseEventType, PICK_EVENT_FIELDS)
        self._pick_events = await s.get_event_generator(etype, cell.nodeid)
        loop = asyncio.get_running_loop()
        self._subscription = self.service.subscribe(
            "opcua",
            lambda e: self._on_event(loop, e),
            kinds=(SnapshotChanged, PickVerified, PartFailed, JobStarted),
        )
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

    def _on_event(self, loop: asyncio.AbstractEventLoop, event: Event) -> None:
        """On the subscriber's thread: queue picks for the events, wake the publisher."""
        record = self._records.of(event)
        if record is not None:
            self._picks.append(record)  # deque.append is atomic; the loop drains it
        if not loop.is_closed():
            try:
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
        while self._picks:
            await self._fire(self._picks[0])
            self._picks.popleft()
        now = datetime.now(UTC)
        for name, value in _values(self.service.snapshot()).items():
            if self._written.get(name) != value:
                vtype, array = VARIABLES[name]
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

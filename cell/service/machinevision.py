"""The cell as an OPC 40100-1 Machine Vision system: one object of `VisionSystemType`, built
from the OPC Foundation's NodeSet (cell/service/nodesets, loaded by mv_addressspace), that a
PLC, SCADA or MES implementing the companion specification can drive without knowing our names.

- VisionStateMachine follows the service's VisionState (Preoperational, Operational with the
  AutomaticModeStateMachine's Initialized, Ready, SingleExecution, ContinuousExecution,
  Halted, Error): CurrentState and LastTransition with their Id, Number and TransitionTime,
  and a TransitionEventType event for every transition of the specification's machine (a jump
  the service makes at once, Halted to Ready on Reset, is the chain of the specification's
  transitions: HaltedToPreoperational, PreoperationalToOperationalAuto, InitializedToReadyAuto).
- Its methods (Halt, Reset, StartSingleJob, StartContinuous, Stop, Abort, the recipe and
  safety methods) are `service.command()` calls with the caller as Origin: a refusal comes
  back as the status code the specification names (BadInvalidState, BadUserAccessDenied ...).
- ResultManagement: every pick attempt's verdict and every job's end is a result, fired as a
  ResultReadyEventType event and kept in a ResultStore for GetResultById /
  GetResultListFiltered / GetResultComponentsById.
- RecipeManagement: recipes are cell.recipes TOML files; AddRecipe opens a transfer: the
  client writes the TOML through the new recipe's Handle (a FileType: Open, Write, Close)
  and Close hands it to the service (validated; refused with BadInvalidArgument if bad).
- SystemState (SEMI E10), SafetyStateManagement, DiagnosticLevel and DI Identification.

Service events arrive on this interface's own subscriber thread; they are queued for the
server's asyncio loop, where one task writes the nodes and fires the events. A failed write
is logged once and tried again; it never reaches the cell. docs/opcua-machinevision.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib import metadata
from typing import Any

from asyncua import Node, Server, ua
from asyncua.common.instantiate_util import instantiate
from asyncua.server.event_generator import EventGenerator

from cell.asyncwait import wait_event
from cell.config import CellConfig
from cell.core.api import LineServiceAPI
from cell.core.commands import (
    AccessDenied,
    BadArgument,
    Command,
    CommandRefused,
    InvalidState,
    JobRequest,
    NotRecorded,
    RecipeRequest,
    ShuttingDown,
    VisionState,
    needed_role,
)
from cell.core.eventbus import Subscription
from cell.core.events import (
    AlarmCleared,
    AlarmRaised,
    CalibrationInstalled,
    CommandHandled,
    ConfigLoaded,
    Event,
    Interface,
    JobEnded,
    JobStarted,
    Origin,
    PickVerified,
    Role,
    TargetChosen,
    VisionStateChanged,
)
from cell.core.records import Snapshot
from cell.recipes import RecipeBook, RecipeError, RecipeInfo, check_recipe_id
from cell.service.mv_addressspace import DI_URI, MV_URI
from cell.service.mv_results import ResultMaker, external_id, internal_id, result_data, result_message
from cell.service.opcua_security import caller_origin
from cell.service.results import (
    LookupsBusy,
    MemoryResultStore,
    ResultFilter,
    ResultStore,
    VisionResult,
)
from cell.service.ua_values import mv_struct, node_id, status

log = logging.getLogger(__name__)

APP_NAMESPACE = "urn:pick-cell"
_T = ua.VariantType
_EPOCH = datetime(1601, 1, 1, tzinfo=UTC)

# Where each outward state sits in the specification's two machines: (top state, sub state).
STATE_PLACE: dict[VisionState, tuple[str, str]] = {
    VisionState.PREOPERATIONAL: ("Preoperational", ""),
    VisionState.HALTED: ("Halted", ""),
    VisionState.ERROR: ("Error", ""),
    VisionState.INITIALIZED: ("Operational", "Initialized"),
    VisionState.READY: ("Operational", "Ready"),
    VisionState.SINGLE_EXECUTION: ("Operational", "SingleExecution"),
    VisionState.CONTINUOUS_EXECUTION: ("Operational", "ContinuousExecution"),
}

# SEMI E10 state (OPC 40100-1 SystemStateDataType value) for each outward state.
SYSTEM_STATE: dict[VisionState, int] = {
    VisionState.SINGLE_EXECUTION: 1,  # PRD: production
    VisionState.CONTINUOUS_EXECUTION: 1,
    VisionState.READY: 2,  # SBY: standby, ready for a start
    VisionState.INITIALIZED: 2,
    VisionState.PREOPERATIONAL: 4,  # SDT: starting, devices opening, calibration loading
    VisionState.HALTED: 4,  # SDT: stopped on purpose (Halt, a signal) until Reset
    VisionState.ERROR: 5,  # UDT: a fault
}
ENGINEERING = 3  # ENG: a user is working on the system (a recalibration holding starts)

# A refusal's status code, as OPC 40100-1 and OPC 10000-4 name them.
REFUSAL_STATUS: dict[type[CommandRefused], int] = {
    InvalidState: ua.StatusCodes.BadInvalidState,
    AccessDenied: ua.StatusCodes.BadUserAccessDenied,
    ShuttingDown: ua.StatusCodes.BadShutdown,
    BadArgument: ua.StatusCodes.BadInvalidArgument,
    NotRecorded: ua.StatusCodes.BadResourceUnavailable,
}

# Optional parts of the type this server does not implement: removed from the instance so a
# client never calls a method that would do nothing (relative BrowseName paths, MV namespace).
NOT_IMPLEMENTED = (
    ("ConfigurationManagement",),
    ("VisionStateMachine", "ErrorStepModel"),
    ("VisionStateMachine", "HaltedStepModel"),
    ("VisionStateMachine", "PreoperationalStepModel"),
    ("VisionStateMachine", "AutomaticModeStateMachine", "InitializedStepModel"),
    ("VisionStateMachine", "AutomaticModeStateMachine", "ReadyStepModel"),
    ("VisionStateMachine", "AutomaticModeStateMachine", "SingleExecutionStepModel"),
    ("VisionStateMachine", "AutomaticModeStateMachine", "ContinuousExecutionStepModel"),
    ("RecipeManagement", "PrepareProduct"),
    ("RecipeManagement", "UnprepareProduct"),
    ("RecipeManagement", "UnlinkProduct"),
    ("RecipeManagement", "Products"),
    ("RecipeManagement", "RecipeTransfer"),
    ("ResultManagement", "Results"),
    ("ResultManagement", "ResultTransfer"),
)
# The service's events this interface listens to (results, state, recipes, the SystemState's words).
EVENT_KINDS = (
    ConfigLoaded,
    CalibrationInstalled,
    CommandHandled,
    VisionStateChanged,
    JobStarted,
    TargetChosen,
    PickVerified,
    JobEnded,
    AlarmRaised,
    AlarmCleared,
)
_RECIPE_COMMANDS = {Command.ADD_RECIPE, Command.REMOVE_RECIPE, Command.PREPARE_RECIPE, Command.UNPREPARE_RECIPE}
_CHILD_REFS = {
    node_id(i) for i in (ua.ObjectIds.HasComponent, ua.ObjectIds.HasProperty, ua.ObjectIds.HasOrderedComponent)
}
_STATE_TYPES = {node_id(ua.ObjectIds.StateType), node_id(ua.ObjectIds.InitialStateType)}
_TRANSITION_TYPE = node_id(ua.ObjectIds.TransitionType)
_HANDLES_KEPT = 1000  # result and recipe handles a client has not released; the oldest go first
_RESULT_WAIT_MAX_S = 10.0  # the longest GetResultById waits for a result still being made
_RESULT_POLL_S = 0.05  # how often a waiting GetResultById looks in memory (never in the store) again
_FILE_MAX_BYTES = 64 * 1024  # a recipe written through a Handle
_TRIES = 5  # an event that cannot be published is tried this many rounds (about a second apart), then dropped

# The methods served, by their path below the VisionSystem (BrowseNames in the Machine
# Vision namespace), the handler's name and the least role that may call it, checked before
# the handler does anything: a command's is the command table's (cell/service/api.py); the
# others change nothing but what the caller asked for (handles, lists) or, for the safety
# state and the confirmations, what an operator reports.
METHODS: dict[tuple[str, ...], tuple[str, Role]] = {
    ("VisionStateMachine", "Halt"): ("_halt", needed_role(Command.HALT)),
    ("VisionStateMachine", "Reset"): ("_reset", needed_role(Command.RESET)),
    ("VisionStateMachine", "ConfirmAll"): ("_confirm_all", Role.OPERATOR),
    ("VisionStateMachine", "SelectModeAutomatic"): ("_select_automatic", Role.OPERATOR),
    ("VisionStateMachine", "AutomaticModeStateMachine", "StartSingleJob"): (
        "_start_single",
        needed_role(Command.START_SINGLE),
    ),
    ("VisionStateMachine", "AutomaticModeStateMachine", "StartContinuous"): (
        "_start_continuous",
        needed_role(Command.START_CONTINUOUS),
    ),
    ("VisionStateMachine", "AutomaticModeStateMachine", "Stop"): ("_stop", needed_role(Command.STOP)),
    ("VisionStateMachine", "AutomaticModeStateMachine", "Abort"): ("_abort", needed_role(Command.ABORT)),
    ("VisionStateMachine", "AutomaticModeStateMachine", "SimulationMode"): ("_simulation_mode", Role.OPERATOR),
    ("RecipeManagement", "GetRecipeListFiltered"): ("_get_recipe_list", Role.VIEWER),
    ("RecipeManagement", "PrepareRecipe"): ("_prepare_recipe", needed_role(Command.PREPARE_RECIPE)),
    ("RecipeManagement", "UnprepareRecipe"): ("_unprepare_recipe", needed_role(Command.UNPREPARE_RECIPE)),
    ("RecipeManagement", "AddRecipe"): ("_add_recipe", needed_role(Command.ADD_RECIPE)),
    ("RecipeManagement", "RemoveRecipe"): ("_remove_recipe", needed_role(Command.REMOVE_RECIPE)),
    ("RecipeManagement", "ReleaseRecipeHandle"): ("_release_handle", Role.VIEWER),
    ("ResultManagement", "GetResultById"): ("_get_result", Role.VIEWER),
    ("ResultManagement", "GetResultComponentsById"): ("_get_result_components", Role.VIEWER),
    ("ResultManagement", "GetResultListFiltered"): ("_get_result_list", Role.VIEWER),
    ("ResultManagement", "ReleaseResultHandle"): ("_release_handle", Role.VIEWER),
    ("SafetyStateManagement", "ReportSafetyState"): ("_report_safety", Role.OPERATOR),
}
# A recipe's own methods (each recipe object in Recipes), with their roles; its Handle (FileType)
# writes a new recipe, so every one of the Handle's methods needs AddRecipe's.
RECIPE_METHODS: dict[str, Role] = {
    "Prepare": needed_role(Command.PREPARE_RECIPE),
    "Unprepare": needed_role(Command.UNPREPARE_RECIPE),
}
HANDLE_ROLE = needed_role(Command.ADD_RECIPE)


def _version() -> str:
    try:
        return metadata.version("pick-cell")
    except metadata.PackageNotFoundError:
        return "unknown"


class MethodError(Exception):
    """A method call ends with this status code (the reason is logged)."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


@dataclass
class _Transfer:
    """A recipe being written through its Handle (FileType) after AddRecipe."""

    recipe_id: str
    node: Node
    data: bytearray
    open_handle: int = 0
    used_s: float = 0.0  # time.monotonic() of its last call: an idle transfer expires


class MachineVisionServer:
    """Builds and runs the VisionSystemType object. `server` must have been initialised with
    `mv_addressspace.init_server_with_models`; call `start()` on the server's loop before
    `server.start()`, and `stop()` before `server.stop()`."""

    def __init__(
        self,
        server: Server,
        service: LineServiceAPI,
        config: CellConfig,
        *,
        results: ResultStore | None = None,
        recipes: RecipeBook | None = None,
        dry_run: bool = False,
    ):
        mv = config.service.machine_vision
        self.server, self.service, self.config, self.mv = server, service, config, mv
        self.results = results if results is not None else MemoryResultStore(mv.results_kept)
        self.recipes = recipes if recipes is not None else RecipeBook(mv.recipes_dir)
        self._maker = ResultMaker(self.results, self.recipes, dry_run)
        self.node: Node | None = None  # the VisionSystem object
        self._n: dict[str, Node] = {}
        self._states: dict[str, tuple[ua.NodeId, int]] = {}  # state BrowseName -> (type's node, number)
        self._transitions: dict[str, tuple[ua.NodeId, int]] = {}
        self._place = ("", "")
        self._queue: deque[Event | VisionResult] = deque(maxlen=10000)
        self._wake: asyncio.Event | None = None
        self._task: asyncio.Task[None] | None = None
        self._subscription: Subscription | None = None
        self._last_command: Command | None = None
        self._failing: set[str] = set()
        self._tries = 0
        self._written: dict[str, Any] = {}
        self._handles: dict[int, list[str]] = {}
        self._transfers: dict[ua.NodeId, _Transfer] = {}
        self._recipe_nodes: dict[str, Node] = {}  # recipe id -> its object in Recipes (files and transfers)
        self._lookups_waiting = 0  # GetResultById calls waiting for the history store
        self._safety = (False, "")
        self._ns: dict[str, int] = {}
        self._generators: dict[str, EventGenerator] = {}
        self._background: set[asyncio.Task[None]] = set()

    # ---- start and stop ---------------------------------------------------------------
    async def start(self) -> None:
        s = self.server
        self._ns = {
            "mv": await s.get_namespace_index(MV_URI),
            "di": await s.get_namespace_index(DI_URI),
            "app": await s.register_namespace(APP_NAMESPACE),
        }
        await self._build()
        await self._bind_methods()
        self._wake = asyncio.Event()
        loop = asyncio.get_running_loop()
        snapshot = self.service.snapshot()
        await self._enter(snapshot.vision_state, initial=True)
        await self._write_values(snapshot)
        self._subscription = self.service.subscribe(
            "opcua-machinevision", lambda e: self._on_event(loop, e), kinds=EVENT_KINDS, maxsize=4096
        )
        self._task = asyncio.create_task(self._publish(), name="machinevision-publish")

    async def stop(self) -> None:
        if self._subscription is not None:  # off the loop: it waits for the subscriber thread to end
            await asyncio.to_thread(self.service.unsubscribe, self._subscription)
            self._subscription = None
        for task in list(self._background):
            task.cancel()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    # ---- the address space ------------------------------------------------------------
    def _mv(self, name: str) -> ua.QualifiedName:
        return ua.QualifiedName(name, self._ns["mv"])

    async def _build(self) -> None:
        quiet = logging.getLogger("asyncua.common.copy_node_util")
        level = quiet.level
        quiet.setLevel(logging.ERROR)  # it warns of every attribute a VariableType lacks (AccessLevel ...)
        try:
            await self._build_nodes()
        finally:
            quiet.setLevel(level)

    async def _build_nodes(self) -> None:
        mv, app = self._ns["mv"], self._ns["app"]
        vs_type = self.server.get_node(node_id(1003, mv))  # VisionSystemType
        if (await vs_type.read_browse_name()).Name != "VisionSystemType":
            raise RuntimeError("the Machine Vision NodeSet is not loaded (mv_addressspace.init_server_with_models)")
        self.node = await self.server.nodes.objects.add_object(
            node_id("VisionSystem", app),
            ua.QualifiedName("VisionSystem", app),
            vs_type.nodeid,
            instantiate_optional=True,
        )
        await self._prune([await self._child(*path) for path in NOT_IMPLEMENTED])
        names = {
            "vsm": ("VisionStateMachine",),
            "auto": ("VisionStateMachine", "AutomaticModeStateMachine"),
            "recipes": ("RecipeManagement",),
            "recipe_folder": ("RecipeManagement", "Recipes"),
            "results": ("ResultManagement",),
            "safety": ("SafetyStateManagement",),
            "safety_triggered": ("SafetyStateManagement", "VisionSafetyTriggered"),
            "safety_info": ("SafetyStateManagement", "VisionSafetyInformation"),
            "system_state": ("SystemState",),
            "diagnostic_level": ("DiagnosticLevel",),
        }
        for key, path in names.items():
            self._n[key] = await self._child(*path)
        for key in ("vsm", "auto"):
            await self._state_variables(key)
        await self._read_type_states()
        await self._identification()
        transition = node_id(ua.ObjectIds.TransitionEventType)
        assert self.node is not None  # built by _build_nodes
        self._generators = {
            "vsm": await self.server.get_event_generator(transition, self._n["vsm"].nodeid),
            "auto": await self.server.get_event_generator(transition, self._n["auto"].nodeid),
            "result": await self.server.get_event_generator(
                node_id(1024, mv), self.node.nodeid
            ),  # ResultReadyEventType
        }
        await self._n["diagnostic_level"].write_value(ua.Variant(0, _T.UInt16))
        await self._read_only()
        await self._write_safety()
        await self._refresh_recipe_folder()

    async def _read_only(self, nodes: set[ua.NodeId] | None = None) -> None:
        """No client writes any variable (the NodeSet declares some writable): state is the cell's,
        changed only through the methods and their command table. `nodes`: only these (a new
        recipe's); None: every node of the application's namespace (once, at start)."""
        aspace, app = self.server.iserver.aspace, self._ns["app"]
        mask = ua.AccessLevel.CurrentRead.mask
        read = ua.DataValue(ua.Variant(mask, _T.Byte))
        chosen = nodes if nodes is not None else [n for n in aspace.keys() if n.NamespaceIndex == app]
        for nid in chosen:
            attrs = aspace[nid].attributes
            for attr in (ua.AttributeIds.AccessLevel, ua.AttributeIds.UserAccessLevel):
                if attr not in attrs:
                    continue
                now = attrs[attr].value
                if now is None or now.Value is None or now.Value.Value != mask:  # no value yet: read-only too
                    await self.server.write_attribute_value(nid, read, attr)

    async def _prune(self, roots: list[Node]) -> None:
        """Remove these subtrees before the server listens: one pass over the address space for
        all of them (asyncua's delete_nodes makes one per node, seconds for a hundred nodes)."""
        doomed: set[ua.NodeId] = set()
        todo = [n.nodeid for n in roots]
        aspace = self.server.iserver.aspace
        while todo:
            nid = todo.pop()
            if nid in doomed:
                continue
            doomed.add(nid)
            todo += [r.NodeId for r in aspace[nid].references if r.IsForward and r.ReferenceTypeId in _CHILD_REFS]
        for nid in doomed:
            del aspace._nodes[nid]
        for ndata in aspace._nodes.values():
            if any(r.NodeId in doomed for r in ndata.references):
                ndata.references = [r for r in ndata.references if r.NodeId not in doomed]

    async def _state_variables(self, key: str) -> None:
        """CurrentState with its Id and Number, LastTransition with Id, Number and TransitionTime
        (the NodeSet's declarations carry only CurrentState and its Id)."""
        machine, app = self._n[key], self._ns["app"]
        base = str(machine.nodeid.Identifier)
        current = await machine.get_child(["0:CurrentState"])
        if not await _has_child(current, "0:Number"):
            await current.add_property(
                node_id(f"{base}.CurrentState.Number", app), ua.QualifiedName("Number", 0), ua.Variant(0, _T.UInt32)
            )
        if not await _has_child(machine, "0:LastTransition"):
            transition_type = self.server.get_node(node_id(ua.ObjectIds.FiniteTransitionVariableType))
            await instantiate(
                machine,
                transition_type,
                nodeid=node_id(f"{base}.LastTransition", app),
                bname=ua.QualifiedName("LastTransition", 0),
                instantiate_optional=True,
            )
        self._n[f"{key}.current"] = current
        self._n[f"{key}.last"] = await machine.get_child(["0:LastTransition"])
        for var in (current, self._n[f"{key}.last"]):  # typed from the start: writes are checked against it
            await self.server.write_attribute_value(
                (await var.get_child(["0:Id"])).nodeid, ua.DataValue(ua.Variant(ua.NodeId(), _T.NodeId))
            )

    async def _child(self, *path: str) -> Node:
        assert self.node is not None
        return await self.node.get_child([f"{self._ns['mv']}:{p}" for p in path])

    async def _read_type_states(self) -> None:
        """The specification's states and transitions (nodes of the types) by BrowseName, with their numbers."""
        mv = self._ns["mv"]
        for type_id in (1017, 1021):  # VisionStateMachineType, VisionAutomaticModeStateMachineType
            for child in await self.server.get_node(node_id(type_id, mv)).get_children(refs=ua.ObjectIds.HasComponent):
                tdef = await child.read_type_definition()
                if tdef not in _STATE_TYPES and tdef != _TRANSITION_TYPE:
                    continue
                name = (await child.read_browse_name()).Name
                prop = "0:StateNumber" if tdef in _STATE_TYPES else "0:TransitionNumber"
                number = int(await (await child.get_child([prop])).read_value())
                (self._states if tdef in _STATE_TYPES else self._transitions)[name] = (child.nodeid, number)

    async def _identification(self) -> None:
        """DI Identification: the IVendorNameplateType and ITagNameplateType properties."""
        di = self._ns["di"]
        assert self.node is not None
        ident = await self.node.add_object(
            node_id("VisionSystem.Identification", self._ns["app"]),
            ua.QualifiedName("Identification", di),
            node_id(1005, di),  # FunctionalGroupType
            instantiate_optional=False,
        )
        for interface in (15035, 15048):  # IVendorNameplateType, ITagNameplateType
            await ident.add_reference(node_id(interface, di), ua.ObjectIds.HasInterface)
        mv = self.mv
        serial = mv.serial_number
        props: list[tuple[str, Any, ua.VariantType]] = [
            ("Manufacturer", ua.LocalizedText(mv.manufacturer), _T.LocalizedText),
            ("Model", ua.LocalizedText("pick-cell vision-guided pick-and-place cell"), _T.LocalizedText),
            ("ProductCode", "pick-cell", _T.String),
            ("SoftwareRevision", _version(), _T.String),
            ("SerialNumber", serial, _T.String),
            ("ProductInstanceUri", f"urn:pick-cell:{serial or 'unset'}", _T.String),
            ("AssetId", mv.asset_id, _T.String),
            ("ComponentName", ua.LocalizedText(mv.asset_id or "pick-cell"), _T.LocalizedText),
        ]
        for name, value, vtype in props:
            await ident.add_property(
                node_id(f"VisionSystem.Identification.{name}", self._ns["app"]),
                ua.QualifiedName(name, di),
                ua.Variant(value, vtype),
            )

    # ---- methods ----------------------------------------------------------------------
    async def _bind_methods(self) -> None:
        for path, (handler, role) in METHODS.items():
            self.server.link_method(await self._child(*path), self._wrap(path[-1], getattr(self, handler), role))

    def _wrap(self, name: str, handler: Callable[..., Awaitable[list[ua.Variant]]], role: Role) -> Callable[..., Any]:
        """The method as asyncua calls it: the caller's role checked first (deny by default: a
        caller without one may do nothing), then the handler; a refusal is a status code."""

        async def call(parent: ua.NodeId, *args: ua.Variant) -> Any:
            values = [a.Value if isinstance(a, ua.Variant) else a for a in args]
            try:
                origin = self._origin()
                if not origin.may(role):
                    raise MethodError(
                        ua.StatusCodes.BadUserAccessDenied,
                        f"{origin.describe()} may not call {name}: it needs the {role.value} role",
                    )
                return await handler(*values)
            except MethodError as e:
                log.info("OPC UA %s refused: %s", name, e)
                return status(e.status)
            except CommandRefused as e:
                code = next(
                    (s for cls, s in REFUSAL_STATUS.items() if isinstance(e, cls)), ua.StatusCodes.BadInvalidState
                )
                log.info("OPC UA %s refused (%s): %s", name, e.reason.value, e)
                return status(code)
            except (TypeError, ValueError, AttributeError) as e:  # arguments of the wrong number or type
                log.warning("OPC UA %s: arguments not understood: %s: %s", name, type(e).__name__, e)
                return status(ua.StatusCodes.BadInvalidArgument)

        return call

    @staticmethod
    def _origin() -> Origin:
        """The caller: its user and role as the GuardedServer saw its session (capped at
        service.machine_vision.client_role). No role, or no client's request: refused."""
        origin = caller_origin()
        if origin is None:
            raise MethodError(ua.StatusCodes.BadUserAccessDenied, "the caller has no role: it may do nothing")
        return origin

    def _command(self, command: Command, request: JobRequest | RecipeRequest | None = None) -> str | None:
        return self.service.command(command, self._origin(), request).job_id

    @staticmethod
    def _ok() -> list[ua.Variant]:
        return [ua.Variant(0, _T.Int32)]

    async def _halt(self, cause: int = 0, description: str = "") -> list[ua.Variant]:
        self._command(Command.HALT)
        return self._ok()

    async def _reset(self, cause: int = 0, description: str = "") -> list[ua.Variant]:
        self._command(Command.RESET)
        return self._ok()

    async def _confirm_all(self, comment: Any = None) -> list[ua.Variant]:
        """Acknowledge every condition: the cell's alarms need no acknowledgement beyond Reset,
        so this only records who confirmed (it changes no state)."""
        log.info("OPC UA ConfirmAll by %s: %s", self._origin().describe(), getattr(comment, "Text", comment))
        return []

    async def _select_automatic(self) -> list[ua.Variant]:
        return self._ok()  # the cell has only the automatic mode: always selected

    async def _start(self, command: Command, args: list[Any]) -> list[ua.Variant]:
        meas, part, recipe, product, parameters = (args + [None] * 5)[:5]
        request = JobRequest(
            recipe_id=_id(recipe),
            product_id=_id(product),
            part_id=_id(part),
            meas_id=_id(meas),
            parameters=tuple((_key(kv), _text(getattr(kv, "Value", None))) for kv in parameters or []),
        )
        if request.recipe_id and not _valid_id(request.recipe_id):
            _bad(f"RecipeId {request.recipe_id!r}")
        job_id = self._command(command, request) or ""
        return [ua.Variant(mv_struct("JobIdDataType")(Id=job_id), _T.ExtensionObject), ua.Variant(0, _T.Int32)]

    async def _start_single(self, *args: Any) -> list[ua.Variant]:
        return await self._start(Command.START_SINGLE, list(args))

    async def _start_continuous(self, *args: Any) -> list[ua.Variant]:
        return await self._start(Command.START_CONTINUOUS, list(args))

    async def _stop(self, cause: int = 0, description: str = "") -> list[ua.Variant]:
        self._command(Command.STOP)
        return self._ok()

    async def _abort(self, cause: int = 0, description: str = "") -> list[ua.Variant]:
        self._command(Command.ABORT)
        return self._ok()

    async def _simulation_mode(self, activate: bool = False, cause: int = 0, description: str = "") -> list[ua.Variant]:
        """The dry run is chosen when the service starts (`run-cell serve --dry-run`): asking for
        the mode the cell is in succeeds, asking to switch is not supported while it runs."""
        if bool(activate) != self._maker.simulated:
            raise MethodError(
                ua.StatusCodes.BadNotSupported,
                f"SimulationMode({bool(activate)}): the dry run is chosen at start (run-cell serve --dry-run)",
            )
        return self._ok()

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
        want_id, want_product = _id(external_id), _id(product_id)
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
        recipe_id = _id(internal_id) or _id(external_id)
        if not recipe_id:
            raise MethodError(ua.StatusCodes.BadInvalidArgument, "no recipe named (ExternalId or InternalIdIn)")
        if not _valid_id(recipe_id):
            _bad(f"recipe id {recipe_id!r}")
        return recipe_id

    async def _prepare_recipe(self, external_id: Any = None, internal_id: Any = None) -> list[ua.Variant]:
        recipe_id = self._recipe_from(external_id, internal_id)
        self._command(Command.PREPARE_RECIPE, RecipeRequest(recipe_id))
        await self._refresh_recipe_folder()
        return [
            ua.Variant(self._internal(recipe_id), _T.ExtensionObject),
            ua.Variant(True, _T.Boolean),
            ua.Variant(0, _T.Int32),
        ]

    async def _unprepare_recipe(self, external_id: Any = None, internal_id: Any = None) -> list[ua.Variant]:
        recipe_id = _id(internal_id) or _id(external_id) or self.service.snapshot().recipe
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
        self._transfers[node.nodeid] = _Transfer(recipe_id, node, bytearray(), used_s=time.monotonic())
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
            todo += [r.NodeId for r in aspace[nid].references if r.IsForward and r.ReferenceTypeId in _CHILD_REFS]
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

    def _transfer(self, recipe_node: ua.NodeId, handle: int | None = None) -> _Transfer:
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

    def _drop_transfer(self, t: _Transfer) -> None:
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
        wanted = _id(result_id)
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
            job_id=_id(job),
            meas_id=_id(meas),
            part_id=_id(part),
            product_id=_id(product),
            recipe_id=_id(int_recipe) or _id(ext_recipe),
            configuration_id=_id(int_conf) or _id(ext_conf),
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

    # ---- safety -----------------------------------------------------------------------
    async def _report_safety(self, triggered: bool = False, information: str = "") -> list[ua.Variant]:
        """The environment reports its safety state; a trigger halts the cell (the safe stop)."""
        self._safety = (bool(triggered), str(information or ""))
        await self._write_safety()
        if triggered and self.service.snapshot().vision_state in (
            VisionState.INITIALIZED,
            VisionState.READY,
            VisionState.SINGLE_EXECUTION,
            VisionState.CONTINUOUS_EXECUTION,
        ):
            self._command(Command.HALT)
        return self._ok()

    async def _write_safety(self) -> None:
        await self._n["safety_triggered"].write_value(ua.Variant(self._safety[0], _T.Boolean))
        await self._n["safety_info"].write_value(ua.Variant(self._safety[1], _T.String))

    # ---- from the service's events to the nodes --------------------------------------
    def _on_event(self, loop: asyncio.AbstractEventLoop, e: Event) -> None:
        """On the subscriber thread: results are made and stored here (GetResultById finds a
        result as soon as it exists); the loop publishes."""
        try:
            result = self._maker.on_event(e)
        except Exception:  # noqa: BLE001 - a malformed event must not stop the others
            log.exception("OPC UA Machine Vision: cannot make a result of %s", e.kind)
            result = None
        self._queue.append(result if result is not None else e)
        if self._wake is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._wake.set)

    async def _publish(self) -> None:
        assert self._wake is not None
        while True:
            await wait_event(self._wake, 1.0)
            self._wake.clear()
            self._expire_transfers()
            while self._queue:
                item = self._queue[0]
                if not await self._guard(type(item).__name__, self._handle(item)):
                    self._tries += 1
                    if self._tries < _TRIES:
                        break  # tried again on the next round
                    log.warning("OPC UA Machine Vision: %s dropped after %d tries", type(item).__name__, _TRIES)
                self._tries = 0
                self._queue.popleft()
            await self._guard("values", self._write_values(self.service.snapshot()))

    async def _guard(self, what: str, work: Awaitable[None]) -> bool:
        """Run one write; a failure is logged once (until it works again) and reported False."""
        try:
            await work
        except Exception as e:  # noqa: BLE001 - the publisher must outlive any failed write
            if what not in self._failing:
                self._failing.add(what)
                log.warning("OPC UA Machine Vision: %s not published (%s: %s); retrying", what, type(e).__name__, e)
            return False
        if what in self._failing:
            self._failing.discard(what)
            log.info("OPC UA Machine Vision: %s published again", what)
        return True

    async def _handle(self, item: Event | VisionResult) -> None:
        if isinstance(item, VisionResult):
            await self._fire_result(item)
        elif isinstance(item, CommandHandled) and item.accepted:
            try:
                command = Command(item.command)
            except ValueError:
                return
            if item.origin.interface not in (Interface.SIGNAL, Interface.SERVICE):
                self._last_command = command  # a person's or a client's: the transition takes the method's name
            if command in _RECIPE_COMMANDS:  # from any interface: the Recipes folder follows
                await self._refresh_recipe_folder()
        elif isinstance(item, VisionStateChanged):
            with contextlib.suppress(ValueError):
                await self._enter(VisionState(item.target))

    async def _write_values(self, s: Snapshot) -> None:
        if STATE_PLACE[s.vision_state] != self._place:  # a state change whose event was dropped
            await self._enter(s.vision_state)
        state = SYSTEM_STATE[s.vision_state]
        if s.hold and s.vision_state in (VisionState.READY, VisionState.INITIALIZED):
            state = ENGINEERING
        description = s.vision_state.value
        if s.alarm is not None:
            description = f"{description}: {s.alarm.reason}"
        elif s.hold:
            description = f"{description}: {s.hold}"
        value = mv_struct("SystemStateDescriptionDataType")(
            State=mv_struct("SystemStateDataType")(state), StateDescription=description
        )
        if self._written.get("system_state") != (state, description):
            await self._n["system_state"].write_value(ua.Variant(value, _T.ExtensionObject))
            self._written["system_state"] = (state, description)
        if self._written.get("recipe") != s.recipe:
            await self._refresh_recipe_folder()
            self._written["recipe"] = s.recipe

    # ---- the state machines -----------------------------------------------------------
    async def _enter(self, state: VisionState, initial: bool = False) -> None:
        target = STATE_PLACE[state]
        if initial:
            await self._set_current(target)
            self._place = target
            return
        for machine, name, src, dst in self._path(self._place, target):
            await self._transition(machine, name, src, dst)
        await self._set_current(target)
        self._place = target
        self._last_command = None

    def _path(self, source: tuple[str, str], target: tuple[str, str]) -> list[tuple[str, str, str, str]]:
        """The specification's transitions from `source` to `target`: (machine, name, from, to)."""
        (top0, sub0), (top1, sub1) = source, target
        steps: list[tuple[str, str, str, str]] = []
        method = self._last_command
        if top0 != top1:
            if top0 in ("Halted", "Error") and top1 == "Operational":
                steps.append(
                    ("vsm", self._name(f"{top0}ToPreoperational", method is Command.RESET), top0, "Preoperational")
                )
                top0 = "Preoperational"
            if top0 != top1:
                manual = method is Command.HALT and top1 == "Halted"
                steps.append(("vsm", self._name(f"{top0}To{top1}", manual), top0, top1))
            if top1 == "Operational":
                sub0 = "Initialized"
        if top1 == "Operational" and sub1 and sub0 != sub1:
            if sub0 in ("SingleExecution", "ContinuousExecution") and sub1 == "Ready":
                kinds: dict[Command | None, str] = {Command.STOP: "Stop", Command.ABORT: "Abort"}
                kind = kinds.get(method, "Auto")
                name = f"{sub0}ToReady{kind}"
            else:
                starts = {"SingleExecution": Command.START_SINGLE, "ContinuousExecution": Command.START_CONTINUOUS}
                name = self._name(f"{sub0}To{sub1}", starts.get(sub1) is method and method is not None)
            steps.append(("auto", name, sub0, sub1))
        return [s for s in steps if s[1] in self._transitions]

    def _name(self, base: str, by_method: bool) -> str:
        if by_method and base in self._transitions:
            return base
        return f"{base}Auto" if f"{base}Auto" in self._transitions else base

    async def _set_current(self, place: tuple[str, str]) -> None:
        top, sub = place
        await self._write_state("vsm", top)
        await self._write_state("auto", sub)

    async def _write_state(self, machine: str, state: str) -> None:
        node = self._n[f"{machine}.current"]
        nid, number = self._states.get(state, (ua.NodeId(), 0))
        await node.write_value(ua.Variant(ua.LocalizedText(state), _T.LocalizedText))
        await (await node.get_child(["0:Id"])).write_value(ua.Variant(nid, _T.NodeId))
        for prop, value in (
            ("0:Number", ua.Variant(number, _T.UInt32)),
            ("0:Name", ua.Variant(ua.QualifiedName(state, self._ns["mv"]), _T.QualifiedName)),
        ):
            with contextlib.suppress(ua.UaStatusCodeError):
                await (await node.get_child([prop])).write_value(value)

    async def _transition(self, machine: str, name: str, source: str, target: str) -> None:
        now = datetime.now(UTC)
        nid, number = self._transitions[name]
        last = self._n[f"{machine}.last"]
        await last.write_value(ua.Variant(ua.LocalizedText(name), _T.LocalizedText))
        await (await last.get_child(["0:Id"])).write_value(ua.Variant(nid, _T.NodeId))
        for prop, value in (
            ("0:Number", ua.Variant(number, _T.UInt32)),
            ("0:Name", ua.Variant(ua.QualifiedName(name, self._ns["mv"]), _T.QualifiedName)),
            ("0:TransitionTime", ua.Variant(now, _T.DateTime)),
        ):
            with contextlib.suppress(ua.UaStatusCodeError):
                await (await last.get_child([prop])).write_value(value)
        gen = self._generators[machine]
        ev = gen.event
        ev.Message = ua.LocalizedText(f"{source} -> {target} ({name})")
        ev.Severity = 100
        state_id = self._states.get
        for field, field_value, vtype in (
            ("Transition", ua.LocalizedText(name), _T.LocalizedText),
            ("Transition/Id", nid, _T.NodeId),
            ("FromState", ua.LocalizedText(source), _T.LocalizedText),
            ("FromState/Id", state_id(source, (ua.NodeId(), 0))[0], _T.NodeId),
            ("ToState", ua.LocalizedText(target), _T.LocalizedText),
            ("ToState/Id", state_id(target, (ua.NodeId(), 0))[0], _T.NodeId),
        ):
            ev.add_property(field, field_value, vtype)  # the value and its type: asyncua wraps it in a Variant
        await gen.trigger(now)

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


async def _has_child(node: Node, name: str) -> bool:
    try:
        await node.get_child([name])
    except ua.UaStatusCodeError:
        return False
    return True


# ---- conversions ------------------------------------------------------------------------
def _id(value: Any) -> str:
    """The Id of one of the specification's *IdDataType structures (or a plain string)."""
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    return str(getattr(value, "Id", "") or "")


def _text(value: Any) -> str:
    """A parameter's value as text (KeyValuePair.Value is a Variant of any type)."""
    value = value.Value if isinstance(value, ua.Variant) else value
    if value is None:
        return ""
    return value.Text or "" if isinstance(value, ua.LocalizedText) else str(value)


def _key(kv: Any) -> str:
    key = getattr(kv, "Key", "")
    return str(getattr(key, "Name", key))


def _valid_id(recipe_id: str) -> bool:
    try:
        check_recipe_id(recipe_id)
    except RecipeError:
        return False
    return True


def _bad(what: str) -> None:
    raise MethodError(ua.StatusCodes.BadInvalidArgument, f"{what}: not an allowed recipe id")

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

MachineVisionServer (this module) holds the server itself: construction, start and stop, building
and binding the nodes, the method wrapper with its role check, and the event stream's
publication. The specification's parts are mixins it inherits: the state machines
(mv_statemachine.py), RecipeManagement (mv_recipes.py), ResultManagement
(mv_result_methods.py), SafetyStateManagement and SystemState (mv_safety.py); what they share
is in mv_parts.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from importlib import metadata
from typing import Any

from asyncua import Node, Server, ua
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
from cell.recipes import RecipeBook
from cell.service.mv_addressspace import DI_URI, MV_URI
from cell.service.mv_parts import CHILD_REFS, MethodError, log
from cell.service.mv_recipes import HANDLE_ROLE, RECIPE_METHODS, RecipeManagementPart, RecipeTransfer
from cell.service.mv_result_methods import ResultManagementPart
from cell.service.mv_results import ResultMaker
from cell.service.mv_safety import ENGINEERING, SYSTEM_STATE, SafetyStatePart
from cell.service.mv_statemachine import STATE_PLACE, VisionStateMachinePart
from cell.service.opcua_security import caller_origin
from cell.service.results import MemoryResultStore, ResultStore, VisionResult
from cell.service.ua_values import node_id, status

# Re-exported: the tables and names other modules and the tests import from here.
__all__ = [
    "APP_NAMESPACE",
    "ENGINEERING",
    "EVENT_KINDS",
    "HANDLE_ROLE",
    "METHODS",
    "NOT_IMPLEMENTED",
    "RECIPE_METHODS",
    "REFUSAL_STATUS",
    "STATE_PLACE",
    "SYSTEM_STATE",
    "MachineVisionServer",
    "MethodError",
]

APP_NAMESPACE = "urn:pick-cell"
_T = ua.VariantType
_EPOCH = datetime(1601, 1, 1, tzinfo=UTC)

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


def _version() -> str:
    try:
        return metadata.version("pick-cell")
    except metadata.PackageNotFoundError:
        return "unknown"


class MachineVisionServer(VisionStateMachinePart, RecipeManagementPart, ResultManagementPart, SafetyStatePart):
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
        self._transfers: dict[ua.NodeId, RecipeTransfer] = {}
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
            "info": await self.server.get_event_generator(node_id(1038, mv), self.node.nodeid),  # VisionInformation
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
            todo += [r.NodeId for r in aspace[nid].references if r.IsForward and r.ReferenceTypeId in CHILD_REFS]
        for nid in doomed:
            del aspace._nodes[nid]
        for ndata in aspace._nodes.values():
            if any(r.NodeId in doomed for r in ndata.references):
                ndata.references = [r for r in ndata.references if r.NodeId not in doomed]

    async def _child(self, *path: str) -> Node:
        assert self.node is not None
        return await self.node.get_child([f"{self._ns['mv']}:{p}" for p in path])

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

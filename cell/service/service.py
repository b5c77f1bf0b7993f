"""The line service: one worker thread runs the cell's jobs through the Runner and its state
machine; every interface (OPC UA, the screen, MQTT, signals) only calls `command()`.

A command is checked against the one command table (cell.core.api: states, guards,
roles) under the service's lock, recorded (accepted or refused, with who sent it), then
becomes a job for the worker or a request on the running job's Controls: nothing reaches
the arm or the camera another way.

What happens goes out as typed events on one bus (cell.core.eventbus): the audit log is its
synchronous record; the ledger (counters, last picks), OPC UA, the screen and whatever
comes next subscribe, each on its own thread. The service itself never waits on them.

Outward states (OPC 40100-1): Preoperational while starting; Ready between jobs (the last
job homed the arm); SingleExecution / ContinuousExecution while a job runs; Halted after a
Halt (the runner's safe stop: arm safe, torque released); Error after a fault. Both of
the last two need an explicit Reset. Paused means at rest: a pause asked for while the arm
moves shows as pausing until the runner reaches its safe point.

Shutdown, in order: `refuse_commands()` (every interface's command now gets ShuttingDown),
`close()` halts the job safely and waits for the worker (False if the arm's safe state
could not be confirmed in time), then the interfaces and subscribers are stopped.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, NoReturn

import numpy as np

from cell.assembly import Cell
from cell.audit import AuditWriteFailed, is_rehearsal
from cell.calibration.store import Calibration
from cell.config import CellConfig
from cell.core.commands import (
    AccessDenied,
    BadArgument,
    Command,
    CommandRefused,
    CommandResult,
    InvalidState,
    JobRequest,
    NotRecorded,
    PartTypeRequest,
    RecipeRequest,
    Refusal,
    Request,
    Rest,
    ShuttingDown,
    VisionState,
    allowed,
    needed_role,
    state_refusal,
)
from cell.core.eventbus import EventBus, Subscription
from cell.core.events import (
    SERVICE_ORIGIN,
    AlarmCleared,
    AlarmRaised,
    CalibrationInstalled,
    CommandHandled,
    Event,
    JobEnded,
    JobStarted,
    Origin,
    PartClassesChanged,
    ServiceStarted,
    ServiceStopped,
    SnapshotChanged,
    VisionStateChanged,
    new_job_id,
)
from cell.core.parts import PartRegistry
from cell.core.records import Alarm, CalibrationInfo, LiveFrame, PartImage, Snapshot
from cell.errors import REPORTED_ERRORS, CellError
from cell.memory import release_free_memory
from cell.planning import Planner, table_to_robot
from cell.recipes import (
    Recipe,
    RecipeBook,
    RecipeError,
    add_taught_type,
    bin_of,
    check_bin,
    check_recipe_id,
    parse_recipe,
    read_recipe_if_any,
    taught_class,
)
from cell.runner import Runner, make_parked_arm_safe
from cell.service.ledger import Ledger
from cell.service.shiftlog import ShiftLog, iter_since
from cell.shifts import ShiftCalendar
from cell.signals import Controls
from cell.statemachine import State
from cell.summary import Counts
from cell.vision.locate import locate
from cell.vision.shapes import ShapeModel, ShapeModelError
from cell.vision.teaching import check_type_name
from cell.vision.types import LocateResult
from drivers.cameras.base import Camera

log = logging.getLogger(__name__)

V = VisionState
_IDLE_CELL_STATE = {V.ERROR: "FAULT", V.HALTED: "STOPPED"}  # between jobs; otherwise IDLE
_LEDGER_CATCH_UP_S = 2.0  # at a job's end, how long the state waits for the counters to include it
_TO_REST = frozenset({Command.HALT, Command.STOP, Command.PAUSE, Command.ABORT, Command.RESET})


def calibration_info(cal: Calibration, source_image: str = "") -> CalibrationInfo:
    cv = cal.statistics.get("cross_validated", {})
    try:
        made = datetime.fromisoformat(cal.created_utc) if cal.created_utc else None
    except ValueError:
        made = None
    return CalibrationInfo(
        cal.model_name,
        float(cv.get("rms_mm", float("nan"))),
        float(cv.get("max_mm", float("nan"))),
        made,
        source_image or (cal.image_sha256[:12] and f"sha256 {cal.image_sha256[:12]}"),
        cal.content_id,
    )


def split_hint(reason: str) -> tuple[str, str]:
    """CellError's text is 'what (hint: what to do)'; the alarm shows them apart."""
    if reason.endswith(")") and " (hint: " in reason:
        what, hint = reason[:-1].rsplit(" (hint: ", 1)
        return what, hint
    return reason, "remove the cause, then Reset"


@dataclass(frozen=True)
class Vision:
    """The calibration in use, with its drift watch: swapped as one, so locate and the watch agree."""

    calibration: Calibration
    info: CalibrationInfo
    drift_watch: Callable[[np.ndarray], object] | None


@dataclass
class _Job:
    job_id: str
    mode: str  # single | continuous
    controls: Controls
    origin: Origin
    request: JobRequest
    runner: Runner | None = None
    halt: bool = False  # Halt or a signal: end in Halted
    abort: bool = False  # Abort: the safe stop, then Ready
    fault: tuple[str, str, str] | None = None  # (reason, hint, source) of a fault raised from outside the job
    ended: bool = False  # its runner has returned (the counters catch up): only Halt can still act
    halt_only: bool = False  # no job: a Halt between jobs, the safe stop of the parked arm
    made_safe: bool = False  # the arm's torque was released (by the runner's safe stop or after it)


HEIGHT_WARNING = "camera-height"  # the warning alarm's key while the calibration's camera height is in doubt


class LineService:
    """Implements cell.core.api.LineServiceAPI."""

    def __init__(self, cell: Cell, bus: EventBus, record: ShiftLog):
        self.cell, self.config, self.bus, self.record = cell, cell.config, bus, record
        self._lock = threading.RLock()  # guards the outward state below
        self._device_lock = threading.Lock()  # the camera between the runner and a plate capture
        self._vstate = V.PREOPERATIONAL
        self._alarm: Alarm | None = None
        self._warnings: dict[str, Alarm] = {}
        self._alarm_ids = itertools.count(1)
        self._job: _Job | None = None
        self._holds: dict[int, str] = {}
        self._hold_ids = itertools.count(1)
        self._still_ops = 0  # plate captures in progress: the cell must stay at rest
        self._teach_ops = 0  # frames of example parts being taken for teaching: no job may start meanwhile
        self._vision = Vision(cell.calibration, calibration_info(cell.calibration), cell.drift_watch(cell.calibration))
        self._accepting = True
        self._closing_reason = ""
        self._closed = False
        self._t0 = time.monotonic()
        self._jobs: queue.Queue[_Job | None] = queue.Queue()
        self._worker = threading.Thread(target=self._work, name="cell-worker", daemon=True)
        interval = self.config.service.capture_interval_s
        self.capture_interval_s = interval / self.config.sim.speed_factor if cell.sim is not None else interval
        self.camera = _Locked(cell.camera, self._device_lock)
        cell.camera.on_warning = lambda key, reason, hint: self.raise_warning(key, reason, hint, "camera")
        cell.camera.on_clear = self.clear_warning
        self.recipes = RecipeBook(self.config.service.machine_vision.recipes_dir)
        # the part classes counted: the built-in ones and every taught type of the recipes in the folder at
        # start-up; a recipe added, prepared or taught later grows it (never shrinks it): PartClassesChanged
        self.parts: PartRegistry = self.recipes.taught_parts()
        self._recipe_id: str = ""  # the prepared recipe (none: the cell's own config)
        self._recipe: Recipe | None = None
        self._shapes: tuple[ShapeModel, ...] = ()  # the prepared recipe's taught types' shape models
        bus.add_record(record.record, owner=record)
        self.history: Any = None  # the history store (cell.history.store), set by open_service when configured
        self.ledger = Ledger((), self._changed, ShiftCalendar(self.config.shifts))
        if not self.config.history.enabled:  # else restored from the store (cell.commands.serve.open_service)
            self.prime_ledger_from_audit()
        self._ledger_sub = bus.subscribe("ledger", self.ledger.handle, maxsize=100_000)

    def prime_ledger_from_audit(self) -> None:
        """The running shift's counters from the service's audit files (no history store, or it cannot be read):
        a rehearsal's lines for a rehearsal (a dry run), production's for production, never the other's."""
        rehearsal = bool(getattr(self.record, "rehearsal", False))
        events = iter_since(self.config.run.log_dir, self.ledger.current_shift.start_utc)
        self.ledger.prime(e for e in events if is_rehearsal(e) == rehearsal)

    # ---- life -----------------------------------------------------------------------
    def start(self) -> None:
        self.bus.emit(
            ServiceStarted(
                counters=self.ledger.as_dict(),
                calibration=self._vision.info.model,
                capture_interval_s=self.capture_interval_s,
            )
        )
        self.bus.emit(self._calibration_event(self._vision, None))
        self._warn_of_height(self._vision.calibration)
        self._worker.start()
        self._set_state(V.READY, "service started")

    def refuse_commands(self, reason: str = "the service is stopping") -> None:
        """From now on every command is refused (ShuttingDown): the first step of an orderly stop."""
        with self._lock:
            self._accepting = False
            self._closing_reason = reason

    def close(self, timeout_s: float | None = None) -> bool:
        """Halt any job (the safe stop), end the worker, write the last line; idempotent. False when the
        worker did not end in time: the arm's safe state is not confirmed."""
        self.refuse_commands()
        with self._lock:
            if self._closed:
                return not self._worker.is_alive()
            self._closed = True
            job = self._job
            if job is not None:
                job.halt = True
                job.controls.request(job.controls.stop, reason="the service is stopping")
        ended = True
        if self._worker.is_alive():
            self._jobs.put(None)
            self._worker.join(timeout_s or self.config.run.motion_timeout_s + 10)
            ended = not self._worker.is_alive()
        if not ended:
            log.error("the worker did not end within its timeout: the arm's safe state is not confirmed")
        self._emit_best_effort(ServiceStopped(counters=self.ledger.as_dict()))
        self.bus.wait_idle(5.0)
        return ended

    # ---- LineServiceAPI: commands --------------------------------------------------------
    def command(
        self, command: Command, origin: Origin = SERVICE_ORIGIN, request: Request | None = None
    ) -> CommandResult:
        with self._lock:
            try:
                self._check(command, origin)
                payload = self._arguments(command, request)
                result = self._accept(command, origin, request, payload)
            except CommandRefused as e:
                self._record_command(command, origin, request, refused=e)
                log.info("command %s from %s refused: %s", command.value, origin.describe(), e)
                raise
        self._changed("state")
        return result

    def _check(self, command: Command, origin: Origin) -> None:
        """The command table: shutting down, the role, then the state and its guards."""
        if not self._accepting:
            raise ShuttingDown(command, f"{command.value} refused: {self._closing_reason}", self._vstate)
        role = needed_role(command)
        if not origin.may(role):
            raise AccessDenied(
                command,
                f"{command.value} needs the {role.value} role; {origin.user or 'this user'} is {origin.role_name}",
                self._vstate,
            )
        why = state_refusal(command, self._rest(), self._hold_reason())
        if why is not None:
            raise InvalidState(command, why, self._vstate)

    def _arguments(self, command: Command, request: Any) -> Any:
        """A command's arguments checked before anything is recorded or done (BadArgument if wrong):
        the recipe a recipe command names, loaded and validated; the recipe a start asks for."""
        try:
            if command in (Command.PREPARE_RECIPE, Command.ADD_RECIPE, Command.REMOVE_RECIPE):
                if not isinstance(request, RecipeRequest):
                    raise BadArgument(command, f"{command.value} needs a recipe id", self._vstate)
                if command is Command.PREPARE_RECIPE:
                    return (request.recipe_id, *self.recipes.load_with_shapes(request.recipe_id))
                if command is Command.ADD_RECIPE:
                    parse_recipe(request.content, f"recipe {check_recipe_id(request.recipe_id)!r}")
                    return (request.recipe_id, request.content)
                if request.recipe_id == self._recipe_id:
                    raise BadArgument(
                        command, f"recipe {request.recipe_id!r} is prepared: unprepare it first", self._vstate
                    )
                self.recipes.info(request.recipe_id)
                return request.recipe_id
            if command is Command.ADD_PART_TYPE:
                return self._part_type(request)
            if command in (Command.START_SINGLE, Command.START_CONTINUOUS) and isinstance(request, JobRequest):
                wanted = request.recipe_id
                if wanted and wanted != self._recipe_id:
                    prepared = f"{self._recipe_id!r} is" if self._recipe_id else "none is"
                    raise BadArgument(
                        command,
                        f"recipe {wanted!r} is not the prepared one ({prepared}): PrepareRecipe first",
                        self._vstate,
                    )
        except RecipeError as e:
            raise BadArgument(command, str(e), self._vstate) from None
        return None

    def _part_type(self, request: Any) -> tuple[str, ShapeModel, tuple[float, float, float] | None, str]:
        """AddPartType's arguments: a recipe id (never a path), a valid type name, its model's JSON; the recipe,
        when it exists, valid (a broken recipe is not made worse): BadArgument saying which, before the record."""
        command = Command.ADD_PART_TYPE
        if not isinstance(request, PartTypeRequest):
            raise BadArgument(command, f"{command.value} needs a recipe id and a shape model", self._vstate)
        try:
            check_type_name(request.name)
            model = ShapeModel.from_json(request.model_json, f"the shape model of {request.name!r}")
        except CellError as e:
            raise BadArgument(command, str(e), self._vstate) from None
        if model.name != request.name:
            raise BadArgument(
                command, f"a shape model of {model.name!r}, but the type is named {request.name!r}", self._vstate
            )
        path = self.recipes.path(request.recipe_id)  # RecipeError: not a recipe id
        recipe = read_recipe_if_any(path)  # a broken recipe is not made worse
        where, note = None, ""
        try:
            if request.bin_robot_mm is not None and request.bin_of:
                raise BadArgument(command, "give the bin's coordinates or another class's bin, not both", self._vstate)
            if request.bin_robot_mm is not None:
                where = check_bin("bin_robot_mm", request.bin_robot_mm, self.config.planning)
            elif request.bin_of:
                found = bin_of(recipe, self.config.planning, request.bin_of)
                where, note = (
                    check_bin(f"the bin of {request.bin_of}", found, self.config.planning),
                    f"the bin of {request.bin_of}",
                )
        except CellError as e:
            raise BadArgument(command, str(e) + (f" ({e.hint})" if e.hint else ""), self._vstate) from None
        return request.recipe_id, model, where, note

    def _accept(self, command: Command, origin: Origin, request: Any, payload: Any = None) -> CommandResult:
        try:
            self._record_command(command, origin, request)
        except AuditWriteFailed as e:
            if command not in _TO_REST:  # bringing the cell to rest is never held up by the record
                raise NotRecorded(command, f"{command.value} not carried out: {e}", self._vstate) from None
        log.info("command %s from %s", command.value, origin.describe())
        handler = getattr(self, "_cmd_" + command.name.lower(), None)
        if handler is None:
            raise BadArgument(command, f"{command.value} is not handled by this service", self._vstate)
        try:
            out = handler(origin, request if payload is None else payload)
        except RecipeError as e:  # the recipe file could not be written or removed after all
            raise BadArgument(command, str(e), self._vstate) from None
        if isinstance(out, tuple):  # what the command says back (AddPartType: the bin, the class_no)
            return CommandResult(command, None, out)
        return CommandResult(command, out)

    def _record_command(
        self, command: Command, origin: Origin, request: Any, refused: CommandRefused | None = None
    ) -> None:
        event = CommandHandled(
            command=command.value,
            origin=origin,
            accepted=refused is None,
            vision_state=self._vstate.value,
            refusal="" if refused is None else refused.reason.value,
            message="" if refused is None else str(refused),
            arguments=request.as_json() if request is not None else {},
        )
        if refused is None:
            self.bus.emit(event)
        elif refused.reason is Refusal.NOT_RECORDED:  # its record broke: a new file is tried for the refusal
            try:
                self.bus.emit(event)
            except AuditWriteFailed as e:
                log.error("not recorded (%s): %s", event.kind, e)
        else:
            self._emit_best_effort(event)

    # ---- the commands (under the lock, already allowed and recorded) ---------------------------
    def _cmd_start_single(self, origin: Origin, request: Any) -> str:
        return self._start_job("single", origin, request)

    def _cmd_start_continuous(self, origin: Origin, request: Any) -> str:
        return self._start_job("continuous", origin, request)

    def _start_job(self, mode: str, origin: Origin, request: Any) -> str:
        req = request if isinstance(request, JobRequest) else JobRequest()
        job = _Job(new_job_id(), mode, Controls(), origin, req)
        started = JobStarted(
            job_id=job.job_id, mode=mode, origin=origin, recipe=self._recipe_id, arguments=req.as_json()
        )
        try:  # nothing starts without its record, and nobody hears of a start that was not recorded
            self.bus.emit(started, unrecorded_too=False)
        except AuditWriteFailed as e:
            command = Command.START_SINGLE if mode == "single" else Command.START_CONTINUOUS
            raise NotRecorded(command, f"{command.value} not carried out: {e}", self._vstate) from None
        self._job = job
        self._jobs.put(job)
        self._set_state(V.SINGLE_EXECUTION if mode == "single" else V.CONTINUOUS_EXECUTION, "job started")
        return job.job_id

    def _cmd_stop(self, origin: Origin, request: Any) -> None:
        job = self._running_job()
        job.controls.request(job.controls.finish)

    def _cmd_abort(self, origin: Origin, request: Any) -> None:
        job = self._running_job()
        job.abort = True
        job.controls.request(job.controls.stop, reason=f"Abort from {origin.interface.value}")

    def _cmd_pause(self, origin: Origin, request: Any) -> None:
        job = self._running_job()
        job.controls.request(job.controls.pause)

    def _cmd_resume(self, origin: Origin, request: Any) -> None:
        job = self._running_job()
        job.controls.request(job.controls.pause, on=False)

    def _cmd_halt(self, origin: Origin, request: Any) -> None:
        """The safe stop, whatever the moment: a running job's runner makes the arm safe; between jobs
        (or once the job has parked the arm) the worker does, and the state is Halted after it."""
        job = self._job
        if job is None:  # the last job parked the arm with its torque on: the worker releases it
            job = _Job("", "halt", Controls(), origin, JobRequest(), halt=True, ended=True, halt_only=True)
            self._job = job
            self._jobs.put(job)
            return
        job.halt = True
        job.controls.request(job.controls.stop, reason=f"Halt from {origin.interface.value}")

    def _cmd_reset(self, origin: Origin, request: Any) -> None:
        if self._alarm is not None:
            self._emit_best_effort(AlarmCleared(alarm_id=self._alarm.alarm_id, origin=origin))
            self._alarm = None
        self._set_state(V.READY, f"reset by {origin.describe()}")

    def _cmd_prepare_recipe(self, origin: Origin, prepared: tuple[str, Recipe, tuple[ShapeModel, ...]]) -> None:
        """In Ready only (the table): the next job picks the recipe's classes, with its bins and limits,
        and finds its taught types by their shape models."""
        self._recipe_id, self._recipe, shapes = prepared
        self._shapes = tuple(shapes)
        self._grow_parts(self._recipe_id, self._recipe.types)
        if words := self._recipe.unbinned_words(self._recipe_id):  # said once, when the recipe is prepared
            log.warning("%s", words)
        log.info("recipe %s prepared by %s", self._recipe_id, origin.describe())

    def _cmd_unprepare_recipe(self, origin: Origin, request: Any) -> None:
        self._recipe_id, self._recipe, self._shapes = "", None, ()

    def _cmd_add_recipe(self, origin: Origin, added: tuple[str, str]) -> None:
        recipe_id, content = added
        self.recipes.add(recipe_id, content)  # validated before it was recorded; the write is atomic
        self._grow_parts(recipe_id, parse_recipe(content, f"recipe {recipe_id!r}").types)

    def _grow_parts(self, recipe_id: str, names: Iterable[str]) -> None:
        """Under the lock: the taught types of `recipe_id` the registry does not count yet added to it (none is
        ever taken away while the service runs: a counter an interface shows stays), announced on the bus
        (PartClassesChanged) so OPC UA, Sparkplug, /metrics and the screen count them from now on."""
        grown, added = self.parts, []
        for name in names:
            if name in grown:
                continue
            try:
                grown = grown.with_classes((taught_class(name),))
            except ValueError as e:  # its counter's name is another class's (l-bracket, l_bracket)
                log.warning("recipe %s: the taught type %s gets no counter of its own: %s", recipe_id, name, e)
                continue
            added.append(name)
        if not added:
            return
        self.parts = grown
        self._emit_best_effort(PartClassesChanged(recipe=recipe_id, added=tuple(added), parts=grown))
        log.info(
            "recipe %s: part classes %s counted from now on (OPC UA, Sparkplug, /metrics, the screen)",
            recipe_id,
            ", ".join(added),
        )

    def _cmd_remove_recipe(self, origin: Origin, recipe_id: str) -> None:
        self.recipes.remove(recipe_id)

    def _cmd_add_part_type(
        self, origin: Origin, added: tuple[str, ShapeModel, tuple[float, float, float] | None, str]
    ) -> tuple[str, ...]:
        """The model file beside the recipe and `[types.NAME]` in it, both written whole or not at all (as
        `run-cell part teach`); no job runs (the table), so a prepared recipe is loaded again at once."""
        recipe_id, model, where, note = added
        try:
            self.recipes.folder.mkdir(parents=True, exist_ok=True)
            done = add_taught_type(self.recipes.path(recipe_id), model, where, note)
        except (OSError, ShapeModelError) as e:
            raise RecipeError(f"recipe {recipe_id!r}: the part type {model.name!r} was not written: {e}") from None
        log.info(
            "part type %s (model %s, sha256 %s) added to recipe %s: %s",
            model.name,
            done.model_path.name,
            done.sha256[:12],
            recipe_id,
            "; ".join(said := done.lines(model.name, recipe_id)),
        )
        self._grow_parts(recipe_id, (model.name,))
        if recipe_id == self._recipe_id:
            self._cmd_prepare_recipe(origin, (recipe_id, *self.recipes.load_with_shapes(recipe_id)))
        return tuple(said)

    def job_config(self) -> CellConfig:
        """The config a job starts with: the cell's, with the prepared recipe's handling and limits."""
        return self.config if self._recipe is None else self._recipe.apply(self.config)

    def _running_job(self) -> _Job:
        assert self._job is not None, "the command table allows this command only while a job runs"
        return self._job

    # ---- holds, plate capture, calibration swap -------------------------------------------------
    def hold(self, reason: str, origin: Origin = SERVICE_ORIGIN) -> Callable[[], None]:
        with self._lock:
            n = next(self._hold_ids)
            self._holds[n] = reason

        def release() -> None:
            with self._lock:
                gone = self._holds.pop(n, None)
            if gone is not None:
                self._changed("hold")

        self._changed("hold")
        return release

    def authorize(
        self,
        command: Command,
        origin: Origin,
        action: str = "",
        *,
        state: bool = True,
        arguments: dict[str, Any] | None = None,
    ) -> None:
        """The command table's rules for `command` (its role; with `state` its states and guards too) checked
        for `origin` before an interface's own step has any effect: an uploaded plate's fit, a recalibration
        report's answer, the camera check (issue 28). Refused: recorded and raised (CommandRefused), nothing
        done. Allowed: nothing is done here; with `action` (the step's name in the record) it is recorded as
        accepted, without it the command records itself when carried out (install_calibration)."""
        name = action or command.value
        with self._lock:
            try:
                if state or not self._accepting:
                    self._check(command, origin)
                elif not origin.may(role := needed_role(command)):
                    raise AccessDenied(
                        command,
                        f"{command.value} needs the {role.value} role; {origin.user or 'this user'} is {origin.role_name}",
                        self._vstate,
                    )
            except CommandRefused as e:
                message = str(e) if not action else f"{action} refused: {e}"
                refused = type(e)(command, message, e.state)
                self._emit_best_effort(self._step_record(name, origin, arguments, refused))
                log.info("%s from %s refused: %s", name, origin.describe(), e)
                raise refused from None
            if action:
                try:
                    self.bus.emit(self._step_record(name, origin, arguments, None))
                except AuditWriteFailed as e:
                    raise NotRecorded(command, f"{action} not carried out: {e}", self._vstate) from None
                log.info("%s from %s", name, origin.describe())

    def refuse(
        self, command: Command, origin: Origin, action: str, message: str, arguments: dict[str, Any] | None = None
    ) -> NoReturn:
        """LineServiceAPI.refuse: an interface's own rule refused `action` (a step of `command`); recorded, raised."""
        with self._lock:
            refused = AccessDenied(command, f"{action} refused: {message}", self._vstate)
            self._emit_best_effort(self._step_record(action, origin, arguments, refused))
        log.info("%s from %s refused: %s", action, origin.describe(), message)
        raise refused

    def _step_record(
        self, name: str, origin: Origin, arguments: dict[str, Any] | None, refused: CommandRefused | None
    ) -> CommandHandled:
        return CommandHandled(
            command=name,
            origin=origin,
            accepted=refused is None,
            vision_state=self._vstate.value,
            refusal="" if refused is None else refused.reason.value,
            message="" if refused is None else str(refused),
            arguments=arguments or {},
        )

    def capture_plate_image(self, origin: Origin = SERVICE_ORIGIN) -> np.ndarray:
        with self._lock:
            try:
                self._check(Command.CAPTURE_PLATE, origin)
            except CommandRefused as e:
                self._record_command(Command.CAPTURE_PLATE, origin, None, refused=e)
                raise
            self._record_command(Command.CAPTURE_PLATE, origin, None)
            self._still_ops += 1  # Start and Resume wait until the frame is taken
        try:
            plate = self.cell.plate_image
            if plate is None:
                raise CellError("this cell has no camera to capture a plate from")
            if self.cell.sim is not None:
                return plate()
            with self._device_lock:
                return plate()
        finally:
            with self._lock:
                self._still_ops -= 1

    def capture_part_image(self, origin: Origin = SERVICE_ORIGIN) -> PartImage:
        """CapturePartImage (the role, no job), recorded; then a frame under the device lock, Start held meanwhile."""
        with self._lock:
            try:
                self._check(Command.CAPTURE_PART_IMAGE, origin)
                if self._job is not None:  # a Halt's safe stop still running between jobs
                    raise InvalidState(
                        Command.CAPTURE_PART_IMAGE,
                        f"{Command.CAPTURE_PART_IMAGE.value} is not allowed now: the cell is coming to rest (wait)",
                        self._vstate,
                    )
            except CommandRefused as e:
                self._record_command(Command.CAPTURE_PART_IMAGE, origin, None, refused=e)
                raise
            self._record_command(Command.CAPTURE_PART_IMAGE, origin, None)
            self._teach_ops += 1  # Start waits until the frame is taken
            calibration = self._vision.calibration
        try:
            with self._device_lock:
                camera = self.cell.camera
                if camera.is_connected:
                    image = camera.capture()
                else:
                    with camera:
                        image = camera.capture()
        finally:
            with self._lock:
                self._teach_ops -= 1
            self._changed("hold")
        return PartImage(image, calibration, datetime.now(UTC))

    def preview_frame(self, origin: Origin = SERVICE_ORIGIN) -> LiveFrame | None:
        """A camera frame for a live view while the cell is at rest (Ready, Halted, Error or paused), else
        None. Under the device lock, checked there: a job started meanwhile waits for the frame to be taken."""
        with self._device_lock:
            with self._lock:
                if not self._at_rest():
                    return None
            camera = self.cell.camera
            if camera.is_connected:  # a paused job holds it open
                image = camera.capture()
            else:
                with camera:
                    image = camera.capture()
            taken = time.monotonic()
        log.debug("live frame for %s", origin.describe())
        return LiveFrame(image, taken, datetime.now(UTC))

    def install_calibration(
        self, calibration: Calibration, info: CalibrationInfo, origin: Origin = SERVICE_ORIGIN
    ) -> None:
        with self._lock:
            try:
                self._check(Command.INSTALL_CALIBRATION, origin)
                self._record_command(Command.INSTALL_CALIBRATION, origin, None)
            except CommandRefused as e:
                self._record_command(Command.INSTALL_CALIBRATION, origin, None, refused=e)
                raise
            if not info.calibration_id:
                info = CalibrationInfo(**{**info.__dict__, "calibration_id": calibration.content_id})
            vision = Vision(calibration, info, self.cell.drift_watch(calibration))
            self._vision = vision  # locate and the drift watch change together, at rest
            self._emit_best_effort(self._calibration_event(vision, origin))
        self._changed("calibration")
        self._warn_of_height(calibration)

    def _warn_of_height(self, calibration: Calibration) -> None:
        """A warning alarm while the active calibration does not know the camera's height well
        enough for the part-height correction (Calibration.height_doubt)."""
        doubt = calibration.height_doubt(
            self.config.parts.tallest_centre_height_mm, self.config.calibration.max_height_cost_mm
        )
        if doubt is None:
            self.clear_warning(HEIGHT_WARNING)
        else:
            self.raise_warning(HEIGHT_WARNING, *doubt, "calibration")

    def _calibration_event(self, vision: Vision, origin: Origin | None) -> CalibrationInstalled:
        i = vision.info
        return CalibrationInstalled(
            calibration_id=i.calibration_id,
            model=i.model,
            cv_rms_mm=i.cv_rms_mm,
            cv_max_mm=i.cv_max_mm,
            source_image=i.source_image,
            file=str(self.config.calibration.active_path),
            origin=origin,
        )

    # ---- LineServiceAPI: state and events --------------------------------------------------------
    def snapshot(self) -> Snapshot:
        with self._lock:
            rest, job = self._rest(), self._job
            cell_state = self._cell_state()
            return Snapshot(
                vision_state=self._vstate,
                cell_state=cell_state,
                paused=rest.paused,
                waiting_for_parts=cell_state == State.WAIT.name,
                counters=self.ledger.counters(),
                parts_per_min=self.ledger.parts_per_min() if job is not None and not rest.pausing else 0.0,
                last_picks=self.ledger.last_picks(),
                alarm=self._alarm,
                calibration=self._vision.info,
                heartbeat=self.heartbeat,
                allowed=allowed(
                    self._vstate, rest.pausing, rest.paused, self._hold_reason(), rest.ending, rest.capturing
                ),
                pausing=rest.pausing and not rest.paused,
                job_id=job.job_id if job is not None else "",  # "" for a Halt between jobs
                recipe=self._recipe_id,
                simulated=self.cell.sim is not None or not self.cell.expect_motion,
                job_mode=job.mode if job is not None and not job.halt_only else "",
                hold=self._hold_reason(),
                warnings=tuple(self._warnings.values()),
                subscribers=self.bus.stats(),
                shift=self.ledger.shift,
            )

    @property
    def heartbeat(self) -> int:
        return int(time.monotonic() - self._t0)

    def subscribe(
        self,
        name: str,
        handler: Callable[[Event], object],
        *,
        kinds: Iterable[type[Event]] | None = None,
        maxsize: int = 1024,
        frames: bool | Callable[[Event], bool] = False,
        batch_s: float = 0.0,
    ) -> Subscription:
        return self.bus.subscribe(name, handler, kinds=kinds, maxsize=maxsize, frames=frames, batch_s=batch_s)

    def unsubscribe(self, subscription: Subscription) -> None:
        self.bus.unsubscribe(subscription)

    # ---- faults and warnings raised by other parts (history, telemetry, logins) ----------------
    def fault(self, reason: str, hint: str, source: str) -> None:
        """Another part of the cell cannot go on (e.g. the required history cannot be written): a
        running job stops safely and the cell goes to Error with this alarm; needs a Reset."""
        with self._lock:
            job = self._job
            if job is not None:
                if job.fault is None:
                    job.fault = (reason, hint, source)
                    job.controls.request_fault(reason)
                return
            if self._alarm is None:
                self._raise_fault_alarm(reason, hint, source)
            self._set_state(V.ERROR, reason)
        self._changed("alarm")

    def _raise_fault_alarm(self, what: str, hint: str, source: str) -> None:
        self._alarm = Alarm(what, hint, datetime.now(UTC), f"A{next(self._alarm_ids)}", "fault", source)
        self._emit_best_effort(
            AlarmRaised(alarm_id=self._alarm.alarm_id, severity="fault", reason=what, hint=hint, source=source)
        )

    # ---- warnings raised by other parts (history, telemetry, logins) ------------------------
    def raise_warning(self, key: str, reason: str, hint: str, source: str) -> None:
        """A warning alarm shown until cleared by its source (`clear_warning`); no Reset needed."""
        with self._lock:
            if key in self._warnings and self._warnings[key].reason == reason:
                return
            alarm = Alarm(reason, hint, datetime.now(UTC), f"A{next(self._alarm_ids)}", "warning", source)
            self._warnings[key] = alarm
            self._emit_best_effort(
                AlarmRaised(alarm_id=alarm.alarm_id, severity="warning", reason=reason, hint=hint, source=source)
            )
        self._changed("alarm")

    def clear_warning(self, key: str) -> None:
        with self._lock:
            alarm = self._warnings.pop(key, None)
            if alarm is not None:
                self._emit_best_effort(AlarmCleared(alarm_id=alarm.alarm_id, origin=SERVICE_ORIGIN))
        if alarm is not None:
            self._changed("alarm")

    # ---- the worker -------------------------------------------------------------------------------
    def _work(self) -> None:
        while (job := self._jobs.get()) is not None:
            try:
                self._run_job(job)
            except BaseException:  # nothing may end the worker: the cell would take commands and run none
                log.exception("job %s: the worker caught an error outside the runner", job.job_id)
                with self._lock:
                    self._end_job(job, "fault", "internal error outside the runner (details in the log)")
                self._changed("alarm")
            job = None  # its runner, last frame and what was found on it: not kept until the next job
            release_free_memory()  # at rest: what the job's frames used goes back to the system

    def _run_job(self, job: _Job) -> None:
        if job.halt_only:
            self._make_parked_arm_safe(job)
            with self._lock:
                self._job = None
                if job.fault is not None:  # raised by another part while the arm was made safe
                    reason, hint, source = job.fault
                    self._raise_fault_alarm(reason, hint, source)
                    self._set_state(V.ERROR, reason)
                else:
                    self._set_state(V.HALTED, f"halted between jobs by {job.origin.describe()}")
            self._changed("state")
            return
        outcome, reason, counts = "fault", "", {}
        try:
            self.record.best_effort = False
            self.record.ensure_writable()  # no job runs without its record
            config = self.job_config()
            recipe = self._recipe
            perception = _Perception(
                self, config, None if recipe is None else recipe.classes, self._shapes if recipe is not None else ()
            )
            job.runner = Runner(
                self.camera,
                self.cell.arm,
                perception.locate,
                Planner(
                    config.planning,
                    table_to_robot(config.planning),
                    None if recipe is None else recipe.taught_plans(),
                    None if recipe is None else recipe.class_numbers(),
                ),
                config.run,
                _JobEvents(self.bus),
                job.controls,
                self.cell.expect_motion,
                progress=lambda line: log.info("%s", line),
                sim_motion_s=self.cell.motion_time_s if self.cell.sim is not None else None,
                drift_watch=perception.drift,
                continuous_interval_s=self.capture_interval_s if job.mode == "continuous" else None,
                job_id=job.job_id,
                calibration_id=perception.calibration_id,
            )
            summary = job.runner.run()
            job.made_safe = job.runner.made_safe
            outcome, reason, counts = summary.outcome, summary.reason, summary.counts()
        except (*REPORTED_ERRORS, OSError) as e:  # the record could not be opened: nothing moved
            reason = f"{type(e).__name__}: {e}"
        except Exception as e:  # a bug in the loop itself: the runner made the arm safe where it could
            log.exception("job %s ended by an internal error", job.job_id)
            reason = f"internal error: {type(e).__name__}: {e}"
        with self._lock:
            job.ended = True  # from now on only Halt acts (on the parked arm, below)
        self._changed("state")
        self._ledger_sub.wait_idle(_LEDGER_CATCH_UP_S)  # the arm is at rest: the counters catch up before Ready
        while True:
            with self._lock:
                if not ((job.halt or job.abort) and not job.made_safe):
                    self._end_job(job, outcome, reason, counts)
                    break
            self._make_parked_arm_safe(job)  # a Halt came as the job ended: the arm only parked
        self._changed("alarm" if outcome == "fault" else "state")

    def _make_parked_arm_safe(self, job: _Job) -> None:
        """The worker's safe stop of an arm no runner holds (cell.runner.make_parked_arm_safe)."""
        job.made_safe = True  # tried once: a failed step is in the record, the state says Halted anyway
        make_parked_arm_safe(
            self.cell.arm,
            self.config.run.motion_timeout_s,
            _JobEvents(self.bus),
            f"{'Halt' if job.halt else 'Abort'} from {job.origin.describe()}",
            job.job_id or None,
        )

    def _end_job(self, job: _Job, outcome: str, reason: str, counts: Counts | None = None) -> None:
        """Under the lock: the job's end recorded, the outward state set, a fault's alarm raised."""
        self._job = None
        source = "job"
        if job.fault is not None:  # stopped for another part of the cell: a fault with its reason
            outcome, (reason, hint, source) = "fault", job.fault
            reason = f"{reason} (hint: {hint})"
        ended = "halted" if job.halt and outcome != "fault" else outcome
        if not job.halt_only:  # a Halt between jobs started no job: it ends none
            self._emit_best_effort(
                JobEnded(job_id=job.job_id, mode=job.mode, outcome=ended, reason=reason, counts=counts or {})
            )
        if outcome == "fault":
            what, hint = split_hint(reason)
            self._raise_fault_alarm(what, hint, source)
            self._set_state(V.ERROR, reason)
        elif job.halt:
            self._set_state(V.HALTED, reason)
        else:
            self._set_state(V.READY, reason)

    # ---- helpers ----------------------------------------------------------------------------------
    def _rest(self) -> Rest:
        job, capturing = self._job, self._still_ops > 0
        if job is None:
            return Rest(self._vstate, capturing=capturing)
        pausing = job.controls.pause.is_set()
        runner = job.runner
        paused = pausing and runner is not None and runner.sm.state is State.PAUSED
        ending = job.ended or (runner is not None and runner.ending)
        return Rest(self._vstate, pausing and not ending, paused and not ending, ending, capturing)

    def _at_rest(self) -> bool:
        """Nothing moves and no job captures: Ready, Halted or Error between jobs, or a job paused."""
        if self._job is None:
            return self._vstate in (V.READY, V.HALTED, V.ERROR)
        return self._rest().paused

    def _cell_state(self) -> str:
        job = self._job
        if job is None or job.runner is None:
            return _IDLE_CELL_STATE.get(self._vstate, State.IDLE.name)
        return job.runner.sm.state.name

    def _hold_reason(self) -> str:
        if self._still_ops:
            return "a plate image is being captured for recalibration"
        if self._teach_ops:
            return "a frame of example parts is being captured for teaching (wait for it)"
        if broken := self._history_broken():
            return broken
        return next(iter(self._holds.values()), "")

    def _history_broken(self) -> str:
        """Why no job may start while the required history cannot be written ("" when it can): the
        fault's alarm is raised once, but a Reset does not mend the store, so this holds every start
        (and resume) until the store's writer has written again."""
        if self.history is None or not self.config.history.required:
            return ""
        error = str(getattr(self.history, "write_error", "") or "")
        if not error:
            return ""
        return f"{error} (hint: free space on the data folder's disk (history.data_dir) or fix the database)"

    def _set_state(self, state: VisionState, reason: str) -> None:
        """Under the lock; the caller tells the interfaces once it has let go of it."""
        with self._lock:
            if state == self._vstate:
                return
            self._emit_best_effort(VisionStateChanged(source=self._vstate.value, target=state.value, reason=reason))
            log.info("vision state %s -> %s: %s", self._vstate.value, state.value, reason)
            self._vstate = state

    def _emit_best_effort(self, event: Event) -> None:
        """A record that must not stop what it records (a refusal, a fault's alarm, the service's end)."""
        try:  # best effort down to the shift log: a broken file is not replaced for this event
            self.bus.emit(event, best_effort=True)
        except AuditWriteFailed as e:
            log.error("not recorded (%s): %s", event.kind, e)

    def _changed(self, what: str) -> None:
        """Tell the interfaces to read the snapshot again (never under the lock: nothing waits on them)."""
        self.bus.emit(SnapshotChanged(what=what))


class _JobEvents:
    """The bus as one job sees it: its own best-effort switch (set while making safe), so a failed
    record during the safe stop is dropped, never raised, and the next job starts strict again."""

    def __init__(self, bus: EventBus):
        self.bus, self.best_effort = bus, False

    def emit(self, event: Event) -> None:
        try:  # the switch goes down to the shift log: making safe on a full disk creates no file per event
            self.bus.emit(event, best_effort=self.best_effort)
        except AuditWriteFailed:
            if not self.best_effort:
                raise


class _Perception:
    """Locate and the drift watch for one job, bound per frame to the calibration in use then; parts
    of a class the job's recipe does not pick are left on the table."""

    def __init__(
        self,
        service: LineService,
        config: CellConfig,
        classes: frozenset[str] | None,
        shapes: tuple[ShapeModel, ...] = (),
    ):
        self.service, self.config, self.classes, self.shapes = service, config, classes, shapes
        self.recipe = service._recipe_id
        self.bound: Vision = service._vision

    def locate(self, frame: np.ndarray) -> LocateResult:
        """The finder of `run-cell locate --recipe`: the recipe's taught types, then bolt and nut."""
        self.bound = self.service._vision  # one reference read: the pair swapped together
        result = locate(frame, self.bound.calibration, self.config, self.shapes)
        if self.classes is not None:
            for part in result.objects:
                if part.pick and part.cls not in self.classes:
                    part.pick, part.reason = False, f"{part.reason}; not picked by recipe {self.recipe}"
        return result

    def drift(self, frame: np.ndarray) -> object:
        watch = self.bound.drift_watch
        return None if watch is None else watch(frame)

    def calibration_id(self) -> str:
        return self.bound.info.calibration_id


class _Locked(Camera):
    """The cell's camera with each capture under the service's device lock."""

    def __init__(self, camera: Camera, lock: threading.Lock):
        self.inner, self.lock = camera, lock
        self.source, self.width_px, self.height_px = camera.source, camera.width_px, camera.height_px

    def connect(self) -> None:
        with self.lock:
            self.inner.connect()

    def disconnect(self) -> None:
        with self.lock:
            self.inner.disconnect()

    @property
    def is_connected(self) -> bool:
        return self.inner.is_connected

    def _grab(self) -> np.ndarray:
        with self.lock:
            return self.inner.capture()

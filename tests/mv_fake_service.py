"""A LineServiceAPI for the Machine Vision interface's tests: the real command table
(cell.core.api), the real event bus and recipe book, and a job that makes a pick every
`pick_interval_s` on its own thread (no camera, no arm). Only what the interface needs."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from datetime import UTC, datetime

from cell.core.commands import (
    RUNNING,
    AccessDenied,
    BadArgument,
    Command,
    CommandRefused,
    CommandResult,
    InvalidState,
    JobRequest,
    RecipeRequest,
    Rest,
    VisionState,
    allowed,
    needed_role,
    state_refusal,
)
from cell.core.eventbus import EventBus, Subscription
from cell.core.events import (
    SERVICE_ORIGIN,
    CommandHandled,
    Event,
    JobEnded,
    JobStarted,
    Origin,
    PickVerified,
    TargetChosen,
    VisionStateChanged,
    new_job_id,
    pick_id,
)
from cell.core.parts import BUILT_IN_PARTS
from cell.core.records import Counters, Snapshot
from cell.recipes import RecipeBook, RecipeError


class FakeLineService:
    def __init__(self, recipes: RecipeBook, pick_interval_s: float = 0.05, single_picks: int = 3):
        self.bus = EventBus()
        self.recipes = recipes
        self.parts = BUILT_IN_PARTS
        self.pick_interval_s, self.single_picks = pick_interval_s, single_picks
        self.state = VisionState.READY
        self.recipe = ""
        self.commands: list[tuple[Command, Origin, object]] = []
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._job: threading.Thread | None = None
        self._job_id = ""

    # ---- LineServiceAPI ----
    def command(
        self, command: Command, origin: Origin = SERVICE_ORIGIN, request: JobRequest | RecipeRequest | None = None
    ) -> CommandResult:
        with self._lock:
            try:
                result = self._command(command, origin, request)
            except CommandRefused as e:
                self._emit(
                    CommandHandled(
                        command=command.value,
                        origin=origin,
                        accepted=False,
                        vision_state=self.state.value,
                        refusal=e.reason.value,
                        message=str(e),
                    )
                )
                raise
            self.commands.append((command, origin, request))
            return result

    def _command(self, command: Command, origin: Origin, request: object) -> CommandResult:
        if not origin.role.may(needed_role(command)):
            raise AccessDenied(command, f"{command.value}: {origin.role.value} may not", self.state)
        why = state_refusal(command, Rest(self.state))
        if why:
            raise InvalidState(command, why, self.state)
        if command in (Command.PREPARE_RECIPE, Command.ADD_RECIPE, Command.REMOVE_RECIPE):
            self._recipe_command(command, request)  # refuses before anything is recorded
        self._emit(CommandHandled(command=command.value, origin=origin, accepted=True, vision_state=self.state.value))
        if command in (Command.START_SINGLE, Command.START_CONTINUOUS):
            return CommandResult(command, self._start(command, origin, request or JobRequest()))
        if command in (Command.STOP, Command.ABORT, Command.HALT):
            self._end_job("halted" if command is Command.HALT else "stopped")
            self._enter(VisionState.HALTED if command is Command.HALT else VisionState.READY, command.value)
        elif command is Command.RESET:
            self._enter(VisionState.READY, "reset")
        elif command is Command.UNPREPARE_RECIPE:
            self.recipe = ""
        return CommandResult(command)

    def _recipe_command(self, command: Command, request: object) -> None:
        if not isinstance(request, RecipeRequest):
            raise BadArgument(command, f"{command.value} needs a recipe", self.state)
        try:
            if command is Command.PREPARE_RECIPE:
                self.recipes.load(request.recipe_id)
                self.recipe = request.recipe_id
            elif command is Command.ADD_RECIPE:
                self.recipes.add(request.recipe_id, request.content)
            else:
                if request.recipe_id == self.recipe:
                    raise InvalidState(command, f"recipe {request.recipe_id!r} is prepared: unprepare it first")
                self.recipes.remove(request.recipe_id)
        except RecipeError as e:
            raise BadArgument(command, str(e), self.state) from None

    def snapshot(self) -> Snapshot:
        with self._lock:
            return Snapshot(
                vision_state=self.state,
                cell_state="IDLE",
                paused=False,
                waiting_for_parts=False,
                counters=Counters(),
                parts_per_min=0.0,
                last_picks=(),
                alarm=None,
                calibration=None,
                heartbeat=0,
                allowed=allowed(self.state),
                job_id=self._job_id,
                recipe=self.recipe,
            )

    def subscribe(
        self,
        name: str,
        handler: Callable[[Event], None],
        *,
        kinds: Iterable[type[Event]] | None = None,
        maxsize: int = 1024,
        frames: bool = False,
        batch_s: float = 0.0,
    ) -> Subscription:
        return self.bus.subscribe(name, handler, kinds=kinds, maxsize=maxsize, frames=frames, batch_s=batch_s)

    def unsubscribe(self, subscription: Subscription) -> None:
        self.bus.unsubscribe(subscription)

    # ---- the job ----
    def _emit(self, event: Event) -> None:
        self.bus.emit(event)

    def _enter(self, state: VisionState, reason: str) -> None:
        if state is not self.state:
            source, self.state = self.state, state
            self._emit(VisionStateChanged(source=source.value, target=state.value, reason=reason))

    def _start(self, command: Command, origin: Origin, request: JobRequest) -> str:
        if request.recipe_id:
            try:
                self.recipes.load(request.recipe_id)
            except RecipeError as e:
                raise BadArgument(command, str(e), self.state) from None
        job_id = new_job_id()
        mode = "single" if command is Command.START_SINGLE else "continuous"
        self._job_id = job_id
        self._emit(
            JobStarted(
                job_id=job_id,
                mode=mode,
                origin=origin,
                recipe=request.recipe_id or self.recipe,
                arguments=request.as_json(),
            )
        )
        self._enter(
            VisionState.SINGLE_EXECUTION if mode == "single" else VisionState.CONTINUOUS_EXECUTION, command.value
        )
        self._stop.clear()
        self._job = threading.Thread(target=self._run, args=(job_id, mode), daemon=True)
        self._job.start()
        return job_id

    def _run(self, job_id: str, mode: str) -> None:
        n = 0
        while not self._stop.wait(self.pick_interval_s):
            n += 1
            self._pick(job_id, n)
            if mode == "single" and n >= self.single_picks:
                with self._lock:
                    if self._job_id == job_id:
                        self._emit(
                            JobEnded(
                                job_id=job_id, mode=mode, outcome="done", reason="table clear", counts={"picked": n}
                            )
                        )
                        self._job_id = ""
                        self._enter(VisionState.READY, "table clear")
                return

    def _pick(self, job_id: str, n: int) -> None:
        pid = pick_id(job_id, n)
        cls = "bolt" if n % 2 else "nut"
        table, robot = (10.0 * n, 20.0), (10.0 * n - 132.0, 60.0, 3.5)
        with self._lock:
            if self._job_id != job_id:
                return
            self._emit(
                TargetChosen(
                    job_id=job_id,
                    pick_id=pid,
                    track=n,
                    cls=cls,
                    attempt=1,
                    pixel=(100.0, 200.0),
                    table_mm=table,
                    robot_mm=robot,
                    approach_z_mm=40.0,
                    jaw_angle_deg=30.0 if cls == "bolt" else None,
                    bin_robot_mm=(-200.0, 60.0, 60.0),
                    calibration_id="cal-1",
                )
            )
            self._emit(
                PickVerified(
                    job_id=job_id,
                    pick_id=pid,
                    track=n,
                    cls=cls,
                    attempt=1,
                    result="picked",
                    pixel=(100.0, 200.0),
                    table_mm=table,
                    robot_mm=robot,
                    jaw_angle_deg=30.0 if cls == "bolt" else None,
                    still_at_mm=(),
                    calibration_id="cal-1",
                    cycle_ms=42.0,
                    time_utc=datetime.now(UTC),
                )
            )

    def _end_job(self, outcome: str) -> None:
        if self.state not in RUNNING:
            return
        self._stop.set()
        job_id, self._job_id = self._job_id, ""
        mode = "single" if self.state is VisionState.SINGLE_EXECUTION else "continuous"
        self._emit(JobEnded(job_id=job_id, mode=mode, outcome=outcome, reason=outcome, counts={}))

    def close(self) -> None:
        self._stop.set()
        if self._job is not None:
            self._job.join(timeout=5)
        self.bus.close()

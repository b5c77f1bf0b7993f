"""The line service's interface: what OPC UA, the web screen, MQTT, signals and the CLI may ask of
the cell, and the one command table they all obey.

Every interface holds a `LineServiceAPI` and nothing else: a command goes in with its
`Origin` (interface, user, role, address) and comes back accepted (a `CommandResult`) or
refused (`CommandRefused` with a `Refusal` code and the reason in words). The same command
in the same state gets the same answer whoever sends it. State comes out as immutable
`Snapshot`s; what happens comes out as typed events (cell.core.events) to which interfaces
subscribe, each on its own thread (cell.core.eventbus). No interface touches the runner, the arm
or the camera directly.

The outward state follows OPC 40100-1 (Machine Vision): Preoperational, Halted, Error,
and inside Operational: Initialized, Ready, SingleExecution, ContinuousExecution.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, NoReturn, Protocol

import numpy as np

from cell.core.commands import (
    Command,
    CommandResult,
    Request,
)
from cell.core.eventbus import Subscription
from cell.core.events import SERVICE_ORIGIN, Event, Origin
from cell.core.parts import PartRegistry
from cell.core.records import CalibrationInfo, LiveFrame, PartImage, RecipeInfo, Snapshot


class RecipeCatalog(Protocol):
    """The recipe files as an interface lists them (cell.recipes.RecipeBook has it); changes go
    through the command table (AddRecipe, PrepareRecipe ...), never through this."""

    def list(self) -> list[RecipeInfo]: ...

    def info(self, recipe_id: str) -> RecipeInfo: ...

    def sha256(self, recipe_id: str) -> str: ...


class LineServiceAPI(Protocol):
    """What every interface may call. All methods are thread-safe and return quickly, except
    `capture_plate_image`, `capture_part_image` and `preview_frame` (a camera frame)."""

    @property
    def parts(self) -> PartRegistry:
        """The part classes the cell tells apart and counts (cell.core.parts)."""
        ...

    @property
    def recipes(self) -> RecipeCatalog:
        """The recipe files, for listing (changes go through PrepareRecipe / AddRecipe ...)."""
        ...

    def command(
        self, command: Command, origin: Origin = SERVICE_ORIGIN, request: Request | None = None
    ) -> CommandResult:
        """Accept the command or raise CommandRefused; the work happens in the service's own thread."""
        ...

    def snapshot(self) -> Snapshot: ...

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
        """`handler` gets every event (of `kinds`), on its own thread behind its own bounded queue;
        with `frames` the images events carry too (otherwise `ref` is None); with `batch_s` it wakes at
        most once a batch_s and takes the events of the meantime in one go (a screen: fewer wakes of
        a thread beside the control thread); `unsubscribe(subscription)` ends it."""
        ...

    def unsubscribe(self, subscription: Subscription) -> None: ...

    def hold(self, reason: str, origin: Origin = SERVICE_ORIGIN) -> Callable[[], None]:
        """Hold starts and resumes (e.g. a recalibration awaiting its answer) until the returned
        function is called; every interface then gets InvalidState with `reason`."""
        ...

    def authorize(
        self,
        command: Command,
        origin: Origin,
        action: str = "",
        *,
        state: bool = True,
        arguments: dict[str, Any] | None = None,
    ) -> None:
        """Check `command`'s role (and with `state` its states and guards) in the command table for `origin`,
        before an interface's own step does anything (an uploaded plate's fit, a report's answer): refused,
        CommandRefused is raised and recorded; allowed, nothing happens but, with `action`, a record of it."""
        ...

    def refuse(
        self, command: Command, origin: Origin, action: str, message: str, arguments: dict[str, Any] | None = None
    ) -> NoReturn:
        """An interface's own rule refused `action`, a step of `command` (another engineer's teaching session):
        recorded as refused (access_denied, `message`) as the command table's refusals are, and raised
        (AccessDenied): nothing was done."""
        ...

    def capture_plate_image(self, origin: Origin = SERVICE_ORIGIN) -> np.ndarray:
        """A frame from the cell's camera for recalibration; only at rest (Ready, Halted, or a job
        paused at a safe point), and Resume and Start wait until it is taken."""
        ...

    def capture_part_image(self, origin: Origin = SERVICE_ORIGIN) -> PartImage:
        """A frame of example parts from the cell's camera for teaching a part type, with the calibration in use
        (CapturePartImage: the engineer's role, the cell idle: no job, paused or not); Start waits until it is
        taken. Refused: CommandRefused, recorded."""
        ...

    def preview_frame(self, origin: Origin = SERVICE_ORIGIN) -> LiveFrame | None:
        """A frame from the cell's camera for a live view, taken only while the cell is at rest (Ready,
        Halted, Error, or a job paused at a safe point) under the device lock; None otherwise (a job's
        own frames are the view then). Not a command: nothing moves, nothing is recorded."""
        ...

    def install_calibration(self, calibration: Any, info: CalibrationInfo, origin: Origin = SERVICE_ORIGIN) -> None:
        """Use a calibration that passed the quality gate and was written atomically to the active
        path: locate and the drift watch change together; only at rest."""
        ...

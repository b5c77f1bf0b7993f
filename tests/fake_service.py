"""A line service for the screen's tests: the LineServiceAPI contract, the real command table
(`state_refusal()`, roles, holds), the real event bus, a ticking thread that "captures" frames
and "picks" parts, and the real simulated plate for recalibration. It stands above the driver
layer: no camera, no arm, no runner."""

from __future__ import annotations

import functools
import threading
import time
from collections import deque
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import NoReturn

import cv2
import numpy as np

from cell.core.commands import (
    AccessDenied,
    BadArgument,
    Command,
    CommandResult,
    InvalidState,
    RecipeRequest,
    Rest,
    VisionState,
    allowed,
    needed_role,
    state_refusal,
)
from cell.core.eventbus import EventBus
from cell.core.events import (
    SERVICE_ORIGIN,
    FrameLocated,
    FrameRef,
    Origin,
    PickOrderChosen,
    PickVerified,
    SnapshotChanged,
)
from cell.core.parts import BUILT_IN_PARTS
from cell.core.records import Alarm, CalibrationInfo, Counters, LiveFrame, PartImage, PickRecord, Snapshot
from cell.recipes import RecipeBook, RecipeError
from cell.vision.types import LocatedPart, LocateResult

V = VisionState
_NEXT = {
    Command.START_SINGLE: V.SINGLE_EXECUTION,
    Command.START_CONTINUOUS: V.CONTINUOUS_EXECUTION,
    Command.STOP: V.READY,
    Command.HALT: V.HALTED,
    Command.RESET: V.READY,
}


@functools.lru_cache(maxsize=2)
def plate_image(size=(1920, 1080)) -> np.ndarray:
    """The built-in plate as the simulated camera sees it (rendered once: it takes seconds)."""
    from cell.config import CellConfig
    from cell.sim.render import render_plate
    from cell.sim.rig import default_camera

    image = render_plate(default_camera(*size), CellConfig().plate)
    image.setflags(write=False)
    return image


@functools.lru_cache(maxsize=2)
def part_image(size=(960, 540)):
    """Three L brackets (cell.sim.flatparts, seed 3) rendered through a camera looking down, and its calibration."""
    from cell.calibration.models import CameraMap
    from cell.calibration.store import Calibration
    from cell.camera_model import CameraModel
    from cell.sim.flatparts import random_types
    from cell.sim.parts import render_scene

    w, h = size
    cam = CameraModel.looking_down(w, h, 0.3 * 960 / w, (144.0, 81.0), tilt_deg=4.0, k1=-0.04)
    bracket = random_types(seed=3)["l-bracket"]
    poses = ((60.0, 50.0, 20.0), (200.0, 110.0, 145.0), (120.0, 120.0, 280.0))
    image = render_scene(cam, [bracket.placed(*p) for p in poses], seed=0)
    image.setflags(write=False)
    return image, Calibration("camera", CameraMap(cam), (w, h), cam)


def _now() -> datetime:
    return datetime.now(UTC)


class FakeLineService:
    def __init__(self, frame_size=(960, 540), interval_s: float = 0.1, plate_size=(1920, 1080), recipes_dir=None):
        self.frame_size, self.interval_s, self.plate_size = frame_size, interval_s, plate_size
        self.recipes = RecipeBook(Path(recipes_dir or "/nonexistent/recipes"))
        self.parts = BUILT_IN_PARTS
        self.recipe = ""
        self.previews = 0
        self._lock = threading.RLock()
        self.bus = EventBus()
        self.holds: dict[int, str] = {}
        self.state, self.paused = V.READY, False
        self.counters = Counters()
        self.picks: deque[PickRecord] = deque(maxlen=20)
        self.alarm: Alarm | None = None
        self.calibration = CalibrationInfo("polynomial", 0.0101, 0.0212, _now(), "rendered plate at start")
        self.installed: list = []
        self.commands: list[Command] = []
        self.steps: list[tuple[str, str, bool]] = []  # authorize(): (action or command, user, accepted)
        self.heartbeat = 0
        self._seq = 0
        self.refused: list[tuple[Command, str, str]] = []  # refuse(): (command, action, message)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="fake-service", daemon=True)
        self._thread.start()

    # ---- the contract ---------------------------------------------------------------
    def refuse(self, command: Command, origin: Origin, action: str, message: str, arguments=None) -> NoReturn:
        """LineServiceAPI.refuse: an interface's own rule refused a step; kept, raised."""
        with self._lock:
            self.refused.append((command, action, message))
        raise AccessDenied(command, f"{action} refused: {message}")

    def command(self, command: Command, origin: Origin = SERVICE_ORIGIN, request=None) -> CommandResult:
        with self._lock:
            if not origin.may(needed_role(command)):
                raise AccessDenied(command, f"{command.value} needs the {needed_role(command).value} role")
            why = state_refusal(command, Rest(self.state, self.paused, self.paused), self._hold())
            if why is not None:
                raise InvalidState(command, why, self.state)
            recipe = self._prepared(request) if command is Command.PREPARE_RECIPE else ""
            self.commands.append(command)
            if command in (Command.PREPARE_RECIPE, Command.UNPREPARE_RECIPE):
                self.recipe = recipe
            elif command in (Command.PAUSE, Command.RESUME):
                self.paused = command is Command.PAUSE
            else:
                self.state, self.paused = _NEXT[command], False
                if command is Command.RESET:
                    self.alarm = None
        self._emit("state")
        return CommandResult(command)

    def snapshot(self) -> Snapshot:
        with self._lock:
            c = self.counters
            return Snapshot(
                vision_state=self.state,
                cell_state=self._cell_state(),
                paused=self.paused,
                waiting_for_parts=False,
                counters=c,
                parts_per_min=60.0 * c.picked_total / max(self.heartbeat, 1),
                last_picks=tuple(self.picks),
                alarm=self.alarm,
                calibration=self.calibration,
                heartbeat=self.heartbeat,
                allowed=allowed(self.state, self.paused, self.paused, self._hold()),
                pausing=False,
                hold=self._hold(),
                subscribers=self.bus.stats(),
                recipe=self.recipe,
            )

    def subscribe(self, name, handler, *, kinds=None, maxsize=1024, frames=False, batch_s=0.0):
        return self.bus.subscribe(name, handler, kinds=kinds, maxsize=maxsize, frames=frames, batch_s=batch_s)

    def unsubscribe(self, subscription) -> None:
        self.bus.unsubscribe(subscription)

    def hold(self, reason: str, origin: Origin = SERVICE_ORIGIN):
        with self._lock:
            n = len(self.holds) + 1 + max(self.holds, default=0)
            self.holds[n] = reason

        def release():
            with self._lock:
                self.holds.pop(n, None)
            self._emit("hold")

        self._emit("hold")
        return release

    def authorize(self, command: Command, origin: Origin, action: str = "", *, state=True, arguments=None) -> None:
        """The service's check before a screen's own step: the role, then (with `state`) the states and guards;
        refusals and, with `action`, acceptances are kept in `steps` as (name, user, accepted)."""
        name = action or command.value
        with self._lock:
            try:
                if not origin.may(needed_role(command)):
                    raise AccessDenied(command, f"{command.value} needs the {needed_role(command).value} role")
                why = (
                    state_refusal(command, Rest(self.state, self.paused, self.paused), self._hold()) if state else None
                )
                if why is not None:
                    raise InvalidState(command, why, self.state)
            except (AccessDenied, InvalidState):
                self.steps.append((name, origin.user, False))
                raise
            if action:
                self.steps.append((name, origin.user, True))

    def capture_plate_image(self, origin: Origin = SERVICE_ORIGIN) -> np.ndarray:
        self._check_recalibration(Command.CAPTURE_PLATE, origin)
        return plate_image(self.plate_size)

    def capture_part_image(self, origin: Origin = SERVICE_ORIGIN) -> PartImage:
        """Three L brackets seen from above (cell.sim.flatparts), at rest only, with a camera's calibration."""
        self._check_recalibration(Command.CAPTURE_PART_IMAGE, origin)
        image, calibration = part_image(self.frame_size)
        return PartImage(image, calibration, _now())

    def preview_frame(self, origin: Origin = SERVICE_ORIGIN) -> LiveFrame | None:
        """The table as the camera sees it, at rest only (as the service's)."""
        with self._lock:
            if self.state in _RUNNING and not self.paused:
                return None
            self.previews += 1
            image, _ = self._draw(self._seq)
        cv2.putText(image, f"live {self.previews}", (20, 40), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (0, 0, 0), 2)
        return LiveFrame(image, time.monotonic(), _now())

    def install_calibration(self, calibration, info: CalibrationInfo, origin: Origin = SERVICE_ORIGIN) -> None:
        self._check_recalibration(Command.INSTALL_CALIBRATION, origin)
        with self._lock:
            self.installed.append(calibration)
            self.calibration = info
        self._emit("calibration")

    # ---- for tests ------------------------------------------------------------------
    def fault(self, reason: str, hint: str) -> None:
        with self._lock:
            self.state, self.paused = V.ERROR, False
            self.alarm = Alarm(reason, hint, _now())
        self._emit("alarm")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.bus.close()

    @property
    def listeners(self) -> int:
        return len(self.bus.stats())

    # ---- inside -----------------------------------------------------------------------
    def _prepared(self, request) -> str:
        """The recipe PrepareRecipe names, loaded and validated as the service does (BadArgument if not)."""
        if not isinstance(request, RecipeRequest):
            raise BadArgument(Command.PREPARE_RECIPE, "PrepareRecipe needs a recipe id", self.state)
        try:
            self.recipes.load(request.recipe_id)
        except RecipeError as e:
            raise BadArgument(Command.PREPARE_RECIPE, str(e), self.state) from None
        return request.recipe_id

    def _check_recalibration(self, command: Command, origin: Origin) -> None:
        with self._lock:
            if not origin.may(needed_role(command)):
                raise AccessDenied(command, f"{command.value} needs the {needed_role(command).value} role")
            why = state_refusal(command, Rest(self.state, self.paused, self.paused))
            if why is not None:
                raise InvalidState(command, why, self.state)

    def _hold(self) -> str:
        return next(iter(self.holds.values()), "")

    def _cell_state(self) -> str:
        if self.state is V.ERROR:
            return "FAULT"
        if self.paused:
            return "PAUSED"
        return "CAPTURE" if self.state in _RUNNING else "STOPPED"

    def _emit(self, what: str) -> None:
        self.bus.emit(SnapshotChanged(what=what))

    def _loop(self) -> None:
        last_beat = time.monotonic()
        while not self._stop.wait(self.interval_s):
            with self._lock:
                if time.monotonic() - last_beat >= 1.0:
                    last_beat += 1.0
                    self.heartbeat += 1
                if self.state in _RUNNING and not self.paused:
                    self._capture_and_pick()

    def _capture_and_pick(self) -> None:
        self._seq += 1
        t = time.monotonic()
        image, result = self._draw(self._seq)
        self.bus.emit(
            FrameLocated(
                frame=self._seq, locate_ms=1.0, warnings=(), detections=(), ref=FrameRef(self._seq, image, result, t)
            )
        )
        self.bus.emit(PickOrderChosen(frame=self._seq, order=(1,)))
        if self._seq % 3:
            return
        cls = "bolt" if self._seq % 2 else "nut"
        picked = dict(self.counters.picked)
        picked[cls] = picked.get(cls, 0) + 1
        self.counters = replace(self.counters, picked=tuple(sorted(picked.items())))
        pick = PickRecord(
            _now(),
            self._seq // 3,
            cls,
            (10.0 + self._seq, 20.0),
            (-122.0 + self._seq, 60.0, 5.0),
            30.0 if cls == "bolt" else None,
            "picked",
        )
        self.picks.append(pick)
        self.bus.emit(
            PickVerified(
                pick_id=f"fake/{self._seq}",
                track=pick.track_id,
                cls=cls,
                attempt=1,
                result="picked",
                pixel=(0.0, 0.0),
                table_mm=pick.table_mm,
                robot_mm=pick.robot_mm,
                jaw_angle_deg=pick.angle_deg,
                still_at_mm=(),
            )
        )
        self._emit("pick")
        if self.state is V.SINGLE_EXECUTION and self._seq % 30 == 0:
            self.state = V.READY
            self._emit("state")

    def _draw(self, seq: int) -> tuple[np.ndarray, LocateResult]:
        """A grey table with one nut, and what a locate would report for it."""
        w, h = self.frame_size
        image = np.full((h, w, 3), 235, np.uint8)
        x = 60 + (seq * 23) % (w - 120)
        cv2.circle(image, (x, h // 2), 30, (40, 40, 40), -1)
        outline = np.asarray(cv2.ellipse2Poly((x, h // 2), (30, 30), 0, 0, 360, 10)).reshape(-1, 1, 2).astype(np.int32)
        part = LocatedPart(1, "nut", "hexagonal", (float(x), float(h // 2)), (10.0 + seq, 20.0), None, True)
        part.outline_px = outline
        return image, LocateResult([part], (w, h), 1.0)


_RUNNING = frozenset({V.SINGLE_EXECUTION, V.CONTINUOUS_EXECUTION})

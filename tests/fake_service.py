"""A line service for the screen's tests: the LineServiceAPI contract, the real command table
(`allowed()`), a ticking thread that "captures" frames and "picks" parts, and the real
simulated plate for recalibration. It stands above the driver layer: no camera, no arm."""

from __future__ import annotations

import functools
import threading
import time
from collections import deque
from dataclasses import replace
from datetime import UTC, datetime

import cv2
import numpy as np

from cell.service.api import (
    Alarm,
    CalibrationInfo,
    Command,
    Counters,
    FrameView,
    InvalidState,
    PickRecord,
    ServiceEvent,
    Snapshot,
    VisionState,
    allowed,
)

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


def _now() -> datetime:
    return datetime.now(UTC)


class FakeLineService:
    def __init__(self, frame_size=(960, 540), interval_s: float = 0.1, plate_size=(1920, 1080)):
        self.frame_size, self.interval_s, self.plate_size = frame_size, interval_s, plate_size
        self._lock = threading.RLock()
        self._listeners: list = []
        self.state, self.paused = V.READY, False
        self.counters = Counters()
        self.picks: deque[PickRecord] = deque(maxlen=20)
        self.alarm: Alarm | None = None
        self.calibration = CalibrationInfo("polynomial", 0.0101, 0.0212, _now(), "rendered plate at start")
        self.installed: list = []
        self.commands: list[Command] = []
        self.heartbeat = 0
        self.frame: FrameView | None = None
        self._seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="fake-service", daemon=True)
        self._thread.start()

    # ---- the contract ---------------------------------------------------------------
    def command(self, command: Command) -> None:
        with self._lock:
            if command not in allowed(self.state, self.paused):
                raise InvalidState(command, self.state, self.paused)
            self.commands.append(command)
            if command in (Command.PAUSE, Command.RESUME):
                self.paused = command is Command.PAUSE
            else:
                self.state, self.paused = _NEXT[command], False
                if command is Command.RESET:
                    self.alarm = None
            self._emit("state")

    def snapshot(self) -> Snapshot:
        with self._lock:
            c = self.counters
            return Snapshot(
                vision_state=self.state,
                cell_state=self._cell_state(),
                paused=self.paused,
                waiting_for_parts=False,
                counters=c,
                parts_per_min=60.0 * (c.picked_bolts + c.picked_nuts) / max(self.heartbeat, 1),
                last_picks=tuple(self.picks),
                alarm=self.alarm,
                calibration=self.calibration,
                heartbeat=self.heartbeat,
                allowed=allowed(self.state, self.paused),
            )

    def latest_frame(self) -> FrameView | None:
        return self.frame

    def subscribe(self, listener):
        with self._lock:
            self._listeners.append(listener)

        def unsubscribe():
            with self._lock:
                if listener in self._listeners:
                    self._listeners.remove(listener)

        return unsubscribe

    def capture_plate_image(self) -> np.ndarray:
        self._check_recalibration("capture a plate image")
        return plate_image(self.plate_size)

    def install_calibration(self, calibration, info: CalibrationInfo) -> None:
        self._check_recalibration("install a calibration")
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

    @property
    def listeners(self) -> int:
        return len(self._listeners)

    # ---- inside -----------------------------------------------------------------------
    def _check_recalibration(self, what: str) -> None:
        with self._lock:
            if not (self.state in (V.READY, V.HALTED) or (self.paused and self.state in _RUNNING)):
                raise InvalidState(Command.PAUSE, self.state, self.paused)

    def _cell_state(self) -> str:
        if self.state is V.ERROR:
            return "FAULT"
        if self.paused:
            return "PAUSED"
        return "CAPTURE" if self.state in _RUNNING else "STOPPED"

    def _emit(self, kind: str, **extra) -> None:
        event = ServiceEvent(kind, self.snapshot(), **extra)
        for listener in list(self._listeners):
            listener(event)

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
        self.frame = FrameView(self._seq, t, self._draw(self._seq))
        self._emit("frame", frame=self.frame)
        if self._seq % 3:
            return
        cls = "bolt" if self._seq % 2 else "nut"
        field = "picked_bolts" if cls == "bolt" else "picked_nuts"
        self.counters = replace(self.counters, **{field: getattr(self.counters, field) + 1})
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
        self._emit("pick", pick=pick)
        if self.state is V.SINGLE_EXECUTION and self._seq % 30 == 0:
            self.state = V.READY
            self._emit("state")

    def _draw(self, seq: int) -> np.ndarray:
        w, h = self.frame_size
        image = np.full((h, w, 3), 235, np.uint8)
        x = 60 + (seq * 23) % (w - 120)
        cv2.circle(image, (x, h // 2), 30, (0, 180, 0), 3)
        cv2.putText(image, f"{seq} nut", (x + 35, h // 2 - 35), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 180, 0), 2)
        return image


_RUNNING = frozenset({V.SINGLE_EXECUTION, V.CONTINUOUS_EXECUTION})

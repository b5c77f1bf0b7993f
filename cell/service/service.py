"""The line service: one worker thread runs the cell's jobs through the Runner and its state
machine; every interface (OPC UA, the web screen, signals) only calls `command()`.

A command is checked against the command table (`api.allowed`) under the service's lock,
then becomes a job for the worker or a request on the running job's Controls: nothing
reaches the arm or the camera another way. The service watches the runner through its
audit stream (every event the runner writes), turns it into counters, pick records,
frames and alarms, and pushes them to subscribers from the worker thread.

Outward states (OPC 40100-1): Preoperational while starting; Ready between jobs (the last
job homed the arm); SingleExecution / ContinuousExecution while a job runs; Halted after a
Halt (the runner's safe stop: arm safe, torque released); Error after a fault. Both of
the last two need an explicit Reset.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime

import numpy as np

from cell.calibration.store import Calibration
from cell.config import CellConfig
from cell.planning import Planner, table_to_robot
from cell.runner import Runner
from cell.service.api import (
    Alarm,
    CalibrationInfo,
    Command,
    FrameView,
    InvalidState,
    PickRecord,
    ServiceEvent,
    Snapshot,
    VisionState,
    allowed,
)
from cell.service.counters import ShiftCounts
from cell.service.shiftlog import ShiftLog, iter_shift
from cell.signals import Controls
from cell.statemachine import State
from cell.vision.annotate import annotate
from drivers.arm.base import Arm
from drivers.cameras.base import Camera

log = logging.getLogger(__name__)

V = VisionState
_PICKS_KEPT = 20
_RATE_WINDOW = 20  # picks the parts-per-minute figure is taken over


@dataclass
class Devices:
    """What `run-cell` builds for a run (cell.commands.run._devices), owned by the service for its life."""

    camera: Camera
    arm: Arm
    calibration: Calibration
    expect_motion: bool
    sim: object | None = None  # cell.sim.cell.SimCell for the simulated cell
    plate_image: Callable[[], np.ndarray] | None = None  # the simulated cell renders its plate for recalibration


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
    )


def _split_hint(reason: str) -> tuple[str, str]:
    """CellError's text is 'what (hint: what to do)'; the alarm shows them apart."""
    if reason.endswith(")") and " (hint: " in reason:
        what, hint = reason[:-1].rsplit(" (hint: ", 1)
        return what, hint
    return reason, "remove the cause, then Reset"


class LineService:
    """Implements cell.service.api.LineServiceAPI."""

    def __init__(
        self,
        config: CellConfig,
        devices: Devices,
        audit: ShiftLog,
        locate: Callable[[np.ndarray, Calibration], object],
        camera: Camera | None = None,
        drift_watch: Callable[[Calibration], Callable | None] | None = None,
    ):
        self.config, self.devices, self.audit = config, devices, audit
        self._locate = locate
        self._drift_watch = drift_watch or (lambda calibration: None)  # per job, for the calibration in use
        self._camera = camera or devices.camera  # the simulated cell's is wrapped by its feeder
        self._planner = Planner(config.planning, table_to_robot(config.planning))
        self._calibration = devices.calibration
        self._cal_info = calibration_info(devices.calibration)
        self._lock = threading.RLock()  # guards the outward state below
        self._device_lock = threading.Lock()  # the camera between the runner and capture_plate_image
        self._vstate = V.PREOPERATIONAL
        self._cell_state = "IDLE"
        self._alarm: Alarm | None = None
        self._halt_requested = False
        self._controls: Controls | None = None
        self._runner: Runner | None = None
        self._counts = ShiftCounts.from_events(iter_shift(config.run.log_dir))  # the day's shift so far
        self._shift_day = datetime.now(UTC).date().isoformat()
        self._picks: deque[PickRecord] = deque(maxlen=_PICKS_KEPT)
        self._pick_times: deque[float] = deque(maxlen=_RATE_WINDOW)
        self._last_target: dict | None = None
        self._frame: FrameView | None = None
        self._frame_seq = 0
        self._located: tuple[np.ndarray, object, float] | None = None  # frame, result, capture time: awaiting PLAN
        self._job_camera: _Locked | None = None
        self._listeners: list[Callable[[ServiceEvent], None]] = []
        self._jobs: queue.Queue = queue.Queue()
        self._t0 = time.monotonic()
        self._closed = False
        self._worker = threading.Thread(target=self._work, name="cell-worker", daemon=True)
        interval = config.service.capture_interval_s
        self.capture_interval_s = interval / config.sim.speed_factor if devices.sim is not None else interval
        audit.listeners.append(self._on_audit)

    # ---- life -----------------------------------------------------------------------
    def start(self) -> None:
        c = self._counts.counters()
        self.audit.event(
            "service_start",
            counters=c.__dict__,
            calibration=self._cal_info.model,
            capture_interval_s=self.capture_interval_s,
        )
        self._worker.start()
        self._set_state(V.READY, "service started")
        self._publish("state")

    def close(self, timeout_s: float | None = None) -> None:
        """Halt any job (the safe stop), end the worker and write the last line; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._controls is not None:
                self._halt_requested = True
                self._controls.request(self._controls.stop, reason="the service is stopping")
        if self._worker.is_alive():
            self._jobs.put(None)
            self._worker.join(timeout_s or self.config.run.motion_timeout_s + 10)
        if self._worker.is_alive():
            log.error("the worker did not end within its timeout")
        self.audit.event("service_stop", counters=self._counts.counters().__dict__)

    # ---- LineServiceAPI -------------------------------------------------------------
    def command(self, command: Command) -> None:
        with self._lock:
            paused = self._paused()
            if command not in allowed(self._vstate, paused):
                raise InvalidState(command, self._vstate, paused)
            self.audit.event("command", command=command.value, vision_state=self._vstate.value)
            log.info("command %s in %s", command.value, self._vstate.value)
            getattr(self, "_cmd_" + command.name.lower())()
        self._publish("state")  # outside the lock: a listener never runs while the service is held

    def snapshot(self) -> Snapshot:
        with self._lock:
            paused = self._paused()
            rate = 0.0
            if len(self._pick_times) >= 2 and self._pick_times[-1] > self._pick_times[0]:
                rate = 60.0 * (len(self._pick_times) - 1) / (self._pick_times[-1] - self._pick_times[0])
            return Snapshot(
                self._vstate,
                self._cell_state,
                paused,
                self._cell_state == State.WAIT.name,
                self._counts.counters(),
                rate,
                tuple(self._picks),
                self._alarm,
                self._cal_info,
                self.heartbeat,
                allowed(self._vstate, paused),
            )

    @property
    def heartbeat(self) -> int:
        return int(time.monotonic() - self._t0)

    def latest_frame(self) -> FrameView | None:
        return self._frame

    def subscribe(self, listener: Callable[[ServiceEvent], None]) -> Callable[[], None]:
        with self._lock:
            self._listeners = [*self._listeners, listener]

        def unsubscribe() -> None:
            with self._lock:
                self._listeners = [x for x in self._listeners if x is not listener]

        return unsubscribe

    def capture_plate_image(self) -> np.ndarray:
        self._need_still("capture_plate_image")
        if self.devices.plate_image is not None:
            return self.devices.plate_image()
        with self._device_lock:
            cam = self.devices.camera
            if cam.is_connected:
                return cam.capture()
            with cam:
                return cam.capture()

    def install_calibration(self, calibration: Calibration, info: CalibrationInfo) -> None:
        self._need_still("install_calibration")
        with self._lock:
            self._calibration, self._cal_info = calibration, info
        self.audit.event(
            "calibration",
            model=info.model,
            cv_rms_mm=info.cv_rms_mm,
            cv_max_mm=info.cv_max_mm,
            source_image=info.source_image,
        )
        self._publish("calibration")

    # ---- commands (under the lock, already allowed) -----------------------------------
    def _cmd_start_single(self) -> None:
        self._start_job(V.SINGLE_EXECUTION)

    def _cmd_start_continuous(self) -> None:
        self._start_job(V.CONTINUOUS_EXECUTION)

    def _start_job(self, state: VisionState) -> None:
        self._controls = Controls()
        self._halt_requested = False
        self._jobs.put((state, self._controls))
        self._set_state(state, "job started")

    def _cmd_stop(self) -> None:
        self._controls.request(self._controls.finish)

    def _cmd_pause(self) -> None:
        self._controls.request(self._controls.pause)

    def _cmd_resume(self) -> None:
        self._controls.request(self._controls.pause, on=False)

    def _cmd_halt(self) -> None:
        if self._controls is None:  # between jobs the arm is already parked and at rest
            self._set_state(V.HALTED, "halted between jobs")
            return
        self._halt_requested = True
        self._controls.request(self._controls.stop, reason="Halt requested")

    def _cmd_reset(self) -> None:
        self._alarm = None
        self._set_state(V.READY, "reset")

    # ---- the worker -------------------------------------------------------------------
    def _work(self) -> None:
        while (job := self._jobs.get()) is not None:
            state, controls = job
            self._run_job(state, controls)

    def _run_job(self, state: VisionState, controls: Controls) -> None:
        sim = self.devices.sim
        self._job_camera = _Locked(self._camera, self._device_lock)
        try:
            self._runner = Runner(
                self._job_camera,
                self.devices.arm,
                lambda frame: self._locate(frame, self._calibration),
                self._planner,
                self.config.run,
                self.audit,
                controls,
                self.devices.expect_motion,
                progress=lambda line: log.info("%s", line),
                sim_motion_s=None if sim is None else sim.motion_time_s,
                drift_watch=self._drift_watch(self._calibration),
                continuous_interval_s=self.capture_interval_s if state == V.CONTINUOUS_EXECUTION else None,
            )
            summary = self._runner.run()
            outcome, reason = summary.outcome, summary.reason
        except Exception as e:  # a bug in the loop itself: the runner made the arm safe where it could
            log.exception("job ended by an internal error")
            outcome, reason = "fault", f"internal error: {type(e).__name__}: {e}"
        self._publish_frame()  # a frame located just before the job ended is still shown
        with self._lock:
            self._controls = self._runner = None
            if outcome == "fault":
                what, hint = _split_hint(reason)
                self._alarm = Alarm(what, hint, datetime.now(UTC))
                self._set_state(V.ERROR, reason)
            elif self._halt_requested:
                self._set_state(V.HALTED, reason)
            else:
                self._set_state(V.READY, reason)
        self._publish("alarm" if outcome == "fault" else "state")

    def _on_audit(self, e: dict) -> None:
        """The runner's events (worker thread): state, counters, picks, frames, alarms."""
        kind = e["kind"]
        if kind == "state":
            if State(e["target"]) not in (State.VERIFY, State.PLAN):  # PLAN ran, or will not for this frame
                self._publish_frame()
            with self._lock:
                self._cell_state = State(e["target"]).name
            self._publish("state")
        elif kind == "target":
            self._last_target = e
            self._publish_frame()  # PLAN chose: the frame goes out with its order before the arm moves
        elif kind == "frame":
            self._hold_frame()
        if kind in ("verify", "failed"):
            self._pick_event(e)
        with self._lock:
            if e["t_utc"][:10] != self._shift_day:  # 00:00 UTC: the log rolls to a new day's files, a new shift
                self._shift_day, self._counts = e["t_utc"][:10], ShiftCounts()
            changed = self._counts.apply(e)
        if changed:
            self._publish("counters")

    def _hold_frame(self) -> None:
        """A located frame waits for PLAN, so the screen can number the parts in the order picked."""
        runner = self._runner
        if runner is None or runner.frame is None or runner.result is None:
            return
        self._publish_frame()  # never more than one frame waiting
        captured_s = self._job_camera.captured_s if self._job_camera is not None else time.monotonic()
        self._located = (runner.frame, runner.result, captured_s)

    def _publish_frame(self) -> None:
        """The waiting frame, numbered with the runner's pick order if PLAN ran for it (else without numbers)."""
        if self._located is None:
            return
        (frame, result, captured_s), self._located = self._located, None
        order = None if self._runner is None else self._runner.pick_order
        order = tuple(order) if order is not None else ()
        self._frame_seq += 1
        self._frame = FrameView(self._frame_seq, captured_s, annotate(frame, result, order), order)
        self._publish("frame", frame=self._frame)

    def _pick_event(self, e: dict) -> None:
        t = self._last_target
        if t is None or t["track"] != e["track"]:
            return
        outcome = "failed" if e["kind"] == "failed" else e["result"]
        record = PickRecord(
            datetime.fromisoformat(e["t_utc"]),
            e["track"],
            t["cls"],
            tuple(t["table_mm"]),
            tuple(t["robot_mm"]),
            t["jaw_angle_deg"],
            outcome,
        )
        with self._lock:
            self._picks.append(record)
            if outcome == "picked":
                self._pick_times.append(time.monotonic())
        self._publish("pick", pick=record)

    # ---- helpers ----------------------------------------------------------------------
    def _paused(self) -> bool:
        return self._controls is not None and self._controls.pause.is_set()

    def _need_still(self, what: str) -> None:
        """Ready, Halted or a paused job: the camera is free and nothing moves."""
        with self._lock:
            paused = self._paused()
            if not (self._vstate in (V.READY, V.HALTED) or paused):
                raise InvalidState(_StillCommand(what), self._vstate, paused)

    def _set_state(self, state: VisionState, reason: str) -> None:
        """Under the lock; the caller publishes once it has let go of it."""
        with self._lock:
            if state == self._vstate:
                return
            self.audit.event("vision_state", source=self._vstate.value, target=state.value, reason=reason)
            log.info("vision state %s -> %s: %s", self._vstate.value, state.value, reason)
            self._vstate = state

    def _publish(self, kind: str, **kw) -> None:
        event = ServiceEvent(kind, self.snapshot(), **kw)
        for listener in self._listeners:
            try:
                listener(event)
            except Exception:  # a listener's bug must not stop the cell
                log.exception("service listener failed on a %s event", kind)


class _StillCommand:
    """Stands in for a Command in InvalidState for the two calls that are not commands."""

    def __init__(self, name: str):
        self.value = name


class _Locked(Camera):
    """The cell's camera with each capture under the service's device lock."""

    def __init__(self, camera: Camera, lock: threading.Lock):
        self.inner, self.lock = camera, lock
        self.captured_s = time.monotonic()
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

    def _grab(self):
        with self.lock:
            frame = self.inner.capture()
        self.captured_s = time.monotonic()  # the frame's capture time, for the screen's latency
        return frame

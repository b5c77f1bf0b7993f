"""The cell's loop: the side effects of each state, driven by the state machine.

Each handler does one state's work and returns the next state with its reason. Devices
come in through their interfaces (Camera, Arm, a locate function), so the same loop runs
the line, the dry run with a mock arm, and the simulated cell. Failures become FAULT,
a stop request or Ctrl-C becomes STOPPED; both first make the arm safe.

The safe stop comes first and nothing around it can prevent it: a stop signal may
interrupt a state's work but not the safe sequence or the end of the run (Controls), and
once the run is ending the audit log is best effort (a write that fails is dropped, never
raised), and what happened is logged after the arm is safe, not before.

Parts are tracked across frames by position (cell.tracking). Verify judges the part just
placed on the next frame: still there is a miss, retried up to max_retries, then the part
is marked failed and skipped.

Continuous mode (the line service): with nothing to pick, PLAN goes to WAIT instead of
DONE, and the cell captures again after the interval; only a stop ends the job. A
`finish` request ends it at the next safe point (no part in the gripper, the last pick
verified) with the arm homed and powered, ready for the next job.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from cell.core.events import (
    ArmCommanded,
    Event,
    FaultRaised,
    FrameLocated,
    FrameRef,
    PartFailed,
    PartUnreachable,
    PickOrderChosen,
    PickVerified,
    RobotReported,
    RunEnded,
    RunStarted,
    RunSummarized,
    SafeStepDone,
    SimTruth,
    StateChanged,
    TargetChosen,
    new_job_id,
    pick_id,
)
from cell.errors import REPORTED_ERRORS, CellError, ConfigError
from cell.planning import Planner, Target, Unreachable
from cell.run_config import RunConfig
from cell.signals import Controls, StopRequested
from cell.statemachine import State, StateMachine, Transition
from cell.summary import Summary
from cell.tracking import PartStatus, Track, Tracker
from cell.vision.types import LocatedPart, LocateResult
from cell.wording import plural
from drivers.arm.base import Arm, PickPlan
from drivers.arm.errors import OutOfReach, PickWithdrawn
from drivers.cameras.base import Camera

log = logging.getLogger(__name__)

S = State
PAUSABLE = frozenset({S.HOME, S.CAPTURE, S.LOCATE, S.VERIFY, S.PLAN, S.WAIT})  # HOME: before the first motion
EXIT_DONE, EXIT_INCOMPLETE, EXIT_FAULT, EXIT_STOPPED = 0, 1, 3, 130
Step = tuple[State, str]  # what a state handler returns: the next state and why


class EventSink(Protocol):
    """Where the runner's events go: the event bus (cell.core.eventbus), or an AuditLog alone.
    `emit` writes the record before returning (and raises when it cannot: the job faults);
    with `best_effort` set it never raises (making safe, ending)."""

    best_effort: bool

    def emit(self, event: Event) -> object: ...


class Runner:
    """One run of the cell, from connecting the devices to the summary.

    It owns the state machine, the summary, the part tracker, the last frame and its
    detections, the pick in progress (target and track) and whether the gripper holds a
    part; the devices, planner, config and audit log are lent to it by the caller.
    """

    def __init__(
        self,
        camera: Camera,
        arm: Arm,
        locate: Callable[[np.ndarray], LocateResult],
        planner: Planner,
        cfg: RunConfig,
        events: EventSink,
        controls: Controls | None = None,
        expect_motion: bool = True,
        progress: Callable[[str], None] | None = None,
        truth: Callable[[], dict[str, Any]] | None = None,
        sim_motion_s: Callable[[], float] | None = None,
        drift_watch: Callable[[np.ndarray], object] | None = None,
        continuous_interval_s: float | None = None,
        job_id: str | None = None,
        calibration_id: Callable[[], str] | None = None,
    ):
        self.camera, self.arm, self.locate, self.planner = camera, arm, locate, planner
        self.cfg = cfg
        self.events = events
        self.job_id = job_id or new_job_id()
        self.calibration_id = calibration_id or (lambda: "")  # the calibration locate used, for the record
        self.controls = controls or Controls()
        self.expect_motion = expect_motion  # False: a mock arm over a real table, nothing can move
        self.progress = progress or (lambda line: None)
        self.truth = truth  # the simulated world's account, logged before the summary
        self.sim_motion_s = sim_motion_s  # a simulated arm's motion time so far, reported apart from wall time
        self.drift_watch = drift_watch  # raises CameraMoved on a frame whose reference marks have moved
        self.continuous_interval_s = continuous_interval_s  # None: clear the table once and finish
        self._attempt_mark = 0  # continuous mode: the limit counts attempts since the last pick or wait
        self.sm = StateMachine([self._on_transition])
        if continuous_interval_s is not None:  # a shift's transitions live in the audit log, not in memory
            self.sm.history = deque(maxlen=1000)
        self.summary = Summary()
        self.tracker = Tracker(cfg.verify_radius_mm)
        self.frame: np.ndarray | None = None
        self.result: LocateResult | None = None
        self.frame_ref: FrameRef | None = None  # the last frame and what was found on it, for the record
        self._captured_s = 0.0
        self._target_t0 = 0.0
        self.pick_order: list[int] | None = None  # ids of the frame's parts in the order PLAN chose; None: not planned
        self.target: Target | None = None
        self.track: Track | None = None
        self.holding = False
        self.released = False  # the part of the attempt in progress was let go over its bin, not yet verified
        self.homed = False
        self.ending = False  # the run is ending (its safe stop or parking under way): requests can no longer act
        self.made_safe = False  # the safe stop released the arm's torque (not merely parked it)
        self._handlers = {
            S.IDLE: self._idle,
            S.HOME: self._home,
            S.CAPTURE: self._capture,
            S.LOCATE: self._locate,
            S.VERIFY: self._verify,
            S.PLAN: self._plan,
            S.PICK: self._pick,
            S.PLACE: self._place,
            S.PAUSED: self._paused,
            S.WAIT: self._wait,
        }

    # ---- the loop -------------------------------------------------------------------
    def run(self) -> Summary:
        """The loop until a terminal state; only a state's own work may be interrupted by a signal."""
        t0 = time.perf_counter()
        with self.controls.shielded():
            try:
                self._emit(
                    RunStarted,
                    expect_motion=self.expect_motion,
                    camera=self.camera.source,
                    arm=type(self.arm).__name__,
                    arm_port=self.arm.port,
                )
                while not self.sm.finished:
                    self._guarded_step()
            except CellError as e:  # the audit log failed before the first step
                self._finish(S.FAULT, f"{type(e).__name__}: {e}")
            finally:
                self.ending = True
                self.events.best_effort = True
                self._end(t0)
        return self.summary

    def _guarded_step(self) -> None:
        try:
            with self.controls.shielded(False):
                self._step()
        except StopRequested as e:
            self._finish(S.STOPPED, e.reason)
        except PickWithdrawn:  # a robot running its own program never took the pick: a stop came first
            c = self.controls
            self._finish(S.STOPPED, c.stop_reason if c.stop.is_set() else "stop requested: job ended at a safe point")
        except KeyboardInterrupt:
            self._finish(S.STOPPED, "Ctrl-C")
        except (*REPORTED_ERRORS, OSError) as e:
            self._finish(S.FAULT, f"{type(e).__name__}: {e}")
        except Exception as e:  # a bug must still leave the arm safe
            log.exception("internal error in %s", self.sm.state.name)
            self._finish(S.FAULT, f"internal error: {type(e).__name__}: {e}")

    def _end(self, t0: float) -> None:
        """Close the devices, total the summary, end the log (best effort: the arm is already safe)."""
        self.camera.disconnect()
        self.arm.disconnect()
        s = self.summary
        s.wall_s = time.perf_counter() - t0
        s.motion_sim_s = float(self.sim_motion_s()) if self.sim_motion_s else 0.0
        s.software_s = max(s.wall_s - s.capture_s - s.arm_s - s.paused_s, 0.0)
        if self.result is not None:
            s.unknown_left = sum(1 for o in self.result.objects if not o.pick)
        if self.sm.state == S.DONE:
            s.exit_code = EXIT_DONE if not (s.failed or s.unreachable) else EXIT_INCOMPLETE
        if self.truth is not None:
            self._emit(SimTruth, where=self.truth())
        self._emit(RunSummarized, summary=s.to_dict())
        self._emit(
            RunEnded,
            outcome=s.outcome,
            exit_code=s.exit_code,
            reason=s.reason,
            unknown_left=s.unknown_left,
            ref=self.frame_ref,
        )

    def _emit(self, kind: type[Event], **fields: Any) -> None:
        """One event of this job on the stream (its record written before this returns)."""
        self.events.emit(kind(job_id=self.job_id, **fields))

    def _step(self) -> None:
        state = self.sm.state
        if self.controls.stop.is_set():
            self._finish(S.STOPPED, self.controls.stop_reason)
            return
        if self.controls.pause.is_set() and state in PAUSABLE and not self.holding:
            self.sm.go(S.PAUSED, "pause requested")
            return
        if self.controls.finish.is_set() and state in PAUSABLE and not self.holding and self.track is None:
            self._finish(S.STOPPED, "stop requested: job ended at a safe point")
            return
        target, reason = self._handlers[state]()
        if target in (S.DONE, S.FAULT, S.STOPPED):
            self._finish(target, reason)
        else:
            self.sm.go(target, reason)

    def _on_transition(self, t: Transition) -> None:
        self._emit(StateChanged, source=t.source.value, target=t.target.value, reason=t.reason)
        log.info("%s -> %s: %s", t.source.name, t.target.name, t.reason)

    def _finish(self, state: State, reason: str) -> None:
        """Enter a terminal state: the arm is made safe first (unless the job is simply done),
        with stop signals held off and the log best effort, then what happened is logged."""
        if self.sm.finished:  # a signal that came as the last step ended
            return
        self.ending = True  # from here a request cannot act: the line service refuses them (Halt excepted)
        if state is S.STOPPED and self.controls.faulted:  # stopped for a failure outside the job
            state, reason = S.FAULT, self.controls.stop_reason
        with self.controls.shielded():
            self.events.best_effort = True
            where = self.sm.state.name
            s = self.summary
            s.outcome, s.reason = state.value, reason
            s.exit_code = {S.DONE: EXIT_DONE, S.FAULT: EXIT_FAULT, S.STOPPED: EXIT_STOPPED}[state]
            finishing = state == S.STOPPED and self.controls.finish.is_set()
            # a stop (Halt, Abort, a signal) that came while the last step ended the job still gets the safe stop
            park_only = (state == S.DONE or finishing) and not self.controls.stop.is_set()
            steps = self._make_safe(reason, park_only=park_only)
            self._settle_released(state)
            if state == S.FAULT:
                self._emit(FaultRaised, reason=reason, where=where, ref=self.frame_ref)
                log.error("fault in %s: %s", where, reason)
            for name, error in steps:
                self._emit(SafeStepDone, step=name, ok=error is None, error=error)
            self.sm.go(state, reason)

    def _make_safe(self, reason: str, park_only: bool) -> list[tuple[str, str | None]]:
        """Finish the move in flight, open the gripper over the bin (or at the part), home,
        release torque. Each step is tried even if an earlier one failed; returns (step, error)."""
        steps: list[tuple[str, Callable[[], None]]] = [
            ("finish motion", lambda: self.arm.wait_until_idle(self.cfg.motion_timeout_s)),
        ]
        if self.holding and (target := self.target) is not None:
            bx, by, bz = target.bin_robot_mm
            steps.append(("carry to bin", lambda: self.arm.move_to(bx, by, max(bz, target.approach_z_mm))))
            steps.append(("open gripper over bin", self._open_over_bin))
        elif not park_only:
            steps.append(("open gripper", self.arm.open_gripper))
        steps.append(("home", self._home_unless_position_lost))
        if not park_only:
            steps.append(("release torque", self.arm.stop))
        done = []
        for name, step in steps:
            done.append((name, self._safe_step(name, step, reason)))
        self.holding = False
        self.made_safe = not park_only and done[-1] == ("release torque", None)
        return done

    def _home_unless_position_lost(self) -> None:
        """Home as the last motion of the safe stop, except after a controller restart: homing
        then is motion started after a power interruption, which is the operator's to start
        (IEC 60204-1, 7.5), never the fault handler's."""
        if self.arm.position_lost:
            raise CellError(
                "not homed: the arm's controller restarted and its position is lost",
                hint="check the arm, then home it (`run-cell home`)",
            )
        self.arm.home()

    def _safe_step(self, name: str, step: Callable[[], None], reason: str) -> str | None:
        """One step of the safe sequence; its error as text (None: it worked). Never raises."""
        t0 = time.perf_counter()
        try:
            if not self.arm.is_connected:
                return "arm not connected"
            step()
            return None
        except (*REPORTED_ERRORS, OSError, KeyboardInterrupt) as e:
            log.warning("making safe after %s: %s failed: %s", reason, name, e)
            return f"{type(e).__name__}: {e}"
        except Exception as e:  # a driver bug must not skip the remaining steps
            log.exception("making safe after %s: %s failed", reason, name)
            return f"internal error: {type(e).__name__}: {e}"
        finally:
            self.summary.arm_s += time.perf_counter() - t0
            self._record_reports()

    # ---- devices, timed -------------------------------------------------------------
    def _arm(self, method: str, *args: float | None) -> None:
        self._emit(ArmCommanded, command=method, args=args)
        t0 = time.perf_counter()
        try:
            getattr(self.arm, method)(*args)
        finally:
            self.summary.arm_s += time.perf_counter() - t0
            self._record_reports()

    def _record_reports(self) -> None:
        """What the arm's own controller reported meanwhile (a robot's PICKED, PLACED, MISSED), recorded."""
        for report in self.arm.take_reports():
            self._emit(RobotReported, **report)

    def _release(self) -> None:
        self._arm("open_gripper")
        self.holding, self.released = False, True

    def _open_over_bin(self) -> None:
        """The safe sequence lets go of a held part over its bin: like a place, verified afterwards."""
        self.arm.open_gripper()
        self.released = True

    def _settle_released(self, state: State) -> None:
        """A part let go over its bin just before the job ended is verified on one more frame (the arm
        is parked out of view by now); where no frame can be had, it is recorded as placed, unverified."""
        if self.track is None or not self.released:
            return
        if state is not S.FAULT and self.expect_motion and self.camera.is_connected:
            try:
                self._capture()
                self._locate()
                self._verify()
                return
            except (*REPORTED_ERRORS, OSError) as e:
                log.warning("the part released before the end could not be verified: %s", e)
            except Exception:
                log.exception("verifying the part released before the end")
        track, target = self.track, self.target
        if track is None:  # the verification took it before it failed
            return
        self.track = None
        if target is not None:
            self._emit(
                PickVerified,
                pick_id=pick_id(self.job_id, self.summary.attempts),
                track=track.id,
                cls=track.cls,
                attempt=track.attempts,
                result="placed",
                pixel=target.pixel,
                table_mm=target.table_mm,
                robot_mm=target.robot_mm,
                jaw_angle_deg=target.jaw_angle_deg,
                still_at_mm=(),
                calibration_id=self.calibration_id(),
                cycle_ms=round(1e3 * (time.monotonic() - self._target_t0), 1),
            )

    # ---- state handlers -------------------------------------------------------------
    def _idle(self) -> Step:
        self.progress(f"connecting the camera {self.camera.source} and the arm on {self.arm.port or 'no port'}")
        self.camera.connect()
        self._arm("connect")
        problems = self.planner.bin_problems()
        for cls in ("bolt", "nut"):
            try:
                self.arm.check_target(*self.planner.cfg.for_class(cls).bin_robot_mm)
            except OutOfReach as e:
                problems.append(f"{cls} bin: {e}")
        if problems:
            raise ConfigError("bins out of reach: " + "; ".join(problems))
        return S.HOME, f"camera {self.camera.source} and arm {self.arm.port} connected"

    def _home(self) -> Step:
        self._arm("home")
        self._arm("open_gripper")
        self.homed = True
        return S.CAPTURE, "arm homed, gripper open"

    def _capture(self) -> Step:
        t0 = time.perf_counter()
        try:
            self.frame = self.camera.capture()
            self._captured_s = time.monotonic()
        finally:
            self.summary.capture_s += time.perf_counter() - t0
        self.summary.frames += 1
        return S.LOCATE, f"frame {self.summary.frames}"

    def _locate(self) -> Step:
        t0 = time.perf_counter()
        frame = self._last_frame()
        self.result = result = self.locate(frame)
        self.pick_order = None
        self.summary.locate_s += time.perf_counter() - t0
        objects, warnings = result.objects, result.warnings
        self.frame_ref = FrameRef(self.summary.frames, frame, result, self._captured_s)
        self._emit(
            FrameLocated,
            frame=self.summary.frames,
            locate_ms=round(result.elapsed_ms, 3),
            warnings=tuple(warnings),
            detections=tuple(_detection(o) for o in objects),
            calibration_id=self.calibration_id(),
            ref=self.frame_ref,
        )
        if warnings and not objects:  # blind, not empty: never "table clear" or "part gone"
            raise CellError("cannot see the table: " + "; ".join(warnings))
        n_pick = sum(o.pick for o in objects)
        why = f"{plural(len(objects), 'part')}, {n_pick} pickable"
        if self.track is not None:
            return S.VERIFY, f"{why}; checking part {self.track.id}"
        return S.PLAN, why

    def _verify(self) -> Step:
        target, track = self._attempt()
        self.track = None
        still = self.tracker.near(track, self._last_result().objects)
        if not self.expect_motion:
            track.status, result = PartStatus.REHEARSED, "rehearsed"
            self.summary.rehearsed += 1
        elif not still:
            track.status, result = PartStatus.PICKED, "picked"
            if self.continuous_interval_s is not None:  # a shift's limit counts attempts since the last pick
                self._attempt_mark = self.summary.attempts
            self.summary.picked[track.cls] = self.summary.picked.get(track.cls, 0) + 1
        else:
            result = "missed"
            self.summary.misses += 1
        self._emit(
            PickVerified,
            pick_id=pick_id(self.job_id, self.summary.attempts),
            track=track.id,
            cls=track.cls,
            attempt=track.attempts,
            result=result,
            pixel=target.pixel,
            table_mm=target.table_mm,
            robot_mm=target.robot_mm,
            jaw_angle_deg=target.jaw_angle_deg,
            still_at_mm=tuple(tuple(o.table_mm) for o in still),
            calibration_id=self.calibration_id(),
            cycle_ms=round(1e3 * (time.monotonic() - self._target_t0), 1),
            ref=self.frame_ref,
        )
        reason = f"part {track.id} {result}"
        if result == "missed" and track.attempts > self.cfg.max_retries:
            track.status = PartStatus.FAILED
            self.summary.failed += 1
            self._emit(
                PartFailed,
                track=track.id,
                cls=track.cls,
                attempts=track.attempts,
                pick_id=pick_id(self.job_id, self.summary.attempts),
                ref=self.frame_ref,
            )
            reason += f", failed after {plural(track.attempts, 'attempt')}"
        elif result == "missed":
            reason += ", will retry"
        self.progress(self._pick_line(target, track, result))
        return S.PLAN, reason

    def _plan(self) -> Step:
        if self.drift_watch is not None:  # the camera must still be where it was calibrated
            self.drift_watch(self._last_frame())
        if (n := self.summary.attempts - self._attempt_mark) >= self.cfg.max_attempts_total:
            since = " since the last pick or clear table" if self.continuous_interval_s is not None else ""
            return S.FAULT, f"safety stop: {plural(n, 'pick attempt')}{since} (run.max_attempts_total)"
        for part, track in self._choose():
            target = self._reachable(part, track)
            if target is not None:
                self._announce_order()
                self._start_attempt(track, target)
                return S.PICK, f"part {track.id} ({target.cls}), attempt {track.attempts}"
        self._announce_order()
        failed, unreachable = self.tracker.count(PartStatus.FAILED), self.tracker.count(PartStatus.UNREACHABLE)
        if self.continuous_interval_s is not None:
            self._attempt_mark = self.summary.attempts
            return S.WAIT, f"nothing to pick ({failed} failed, {unreachable} unreachable): waiting for parts"
        return S.DONE, f"no pickable part left ({failed} failed, {unreachable} unreachable)"

    def _choose(self) -> list[tuple[LocatedPart, Track]]:
        """The last frame's pickable parts still pending, in the planner's order from where the arm is."""
        pickable = [o for o in self._last_result().objects if o.pick]
        seen = [self.tracker.track_for(o) for o in pickable]
        pending = {id(o): (o, t) for o, t in zip(pickable, seen, strict=True) if t.status is PartStatus.PENDING}
        if self.continuous_interval_s is not None:  # forget parts gone from the table: a shift leaks nothing
            self.tracker.keep_only(seen)
        status = self.arm.status()
        here = (status.pose.x_mm, status.pose.y_mm) if status.pose is not None else None
        chosen = [pending[id(p)] for p in self.planner.order([o for o, _ in pending.values()], here)]
        self.pick_order = [o.id for o, _ in chosen]
        return chosen

    def _announce_order(self) -> None:
        """The frame's pick order as PLAN left it (unreachable parts taken out), for the screen."""
        if self.pick_order is not None:
            self._emit(PickOrderChosen, frame=self.summary.frames, order=tuple(self.pick_order))

    def _reachable(self, part: LocatedPart, track: Track) -> Target | None:
        """The part's target if the planner and the arm accept every point of it; else the
        part is marked unreachable (before any motion) and None returned."""
        try:
            target = self.planner.target(part)
            for point in target.pick_points():
                self.arm.check_target(*point, target.jaw_angle_deg)
            for point in target.place_points():  # as _place moves: a 4-axis arm's jaws turn with its base
                self.arm.check_target(*point)
            return target
        except (Unreachable, OutOfReach) as e:
            track.status = PartStatus.UNREACHABLE
            self.summary.unreachable += 1
            if self.pick_order is not None:
                self.pick_order.remove(part.id)  # skipped: it gets no number on the screen
            self._emit(PartUnreachable, track=track.id, cls=part.cls, table_mm=part.table_mm, reason=str(e))
            self.progress(
                f"part {track.id} {part.cls} at table ({part.table_mm[0]:.1f}, {part.table_mm[1]:.1f}) mm: "
                f"unreachable, skipped: {e}"
            )
            return None

    def _start_attempt(self, track: Track, target: Target) -> None:
        """Count the attempt and make it the pick in progress."""
        track.attempts += 1
        self.summary.attempts += 1
        self.summary.retries += track.attempts > 1
        self.target, self.track = target, track
        self.released = False
        self._target_t0 = time.monotonic()
        self._emit(
            TargetChosen,
            pick_id=pick_id(self.job_id, self.summary.attempts),
            track=track.id,
            cls=target.cls,
            attempt=track.attempts,
            pixel=target.pixel,
            table_mm=target.table_mm,
            robot_mm=target.robot_mm,
            approach_z_mm=target.approach_z_mm,
            jaw_angle_deg=target.jaw_angle_deg,
            bin_robot_mm=target.bin_robot_mm,
            calibration_id=self.calibration_id(),
        )

    def _pick(self) -> Step:
        t, track = self._attempt()
        x, y, z = t.robot_mm
        plan = PickPlan(pick_id(self.job_id, self.summary.attempts), t.cls, t.robot_mm, t.approach_z_mm,
                        t.jaw_angle_deg, t.bin_robot_mm, t.class_no)  # fmt: skip
        self.arm.announce(plan, lambda: self.controls.stop.is_set() or self.controls.finish.is_set())
        self._arm("move_to", x, y, t.approach_z_mm, t.jaw_angle_deg)
        self._arm("move_to", x, y, z, t.jaw_angle_deg)
        self._arm("close_gripper")
        self.holding = True
        self._arm("move_to", x, y, t.approach_z_mm, t.jaw_angle_deg)
        return S.PLACE, f"part {track.id} gripped at robot ({x:.1f}, {y:.1f}, {z:.1f}) mm"

    def _place(self) -> Step:
        t, track = self._attempt()
        bx, by, bz = t.bin_robot_mm
        self._arm("move_to", bx, by, max(bz, t.approach_z_mm))
        self._arm("move_to", bx, by, bz)
        self._release()
        self._arm("move_to", bx, by, max(bz, t.approach_z_mm))
        return S.CAPTURE, f"part {track.id} released over the {t.cls} bin"

    def _paused(self) -> Step:
        self.progress("paused at a safe point")
        t0 = time.perf_counter()
        c = self.controls
        while c.pause.is_set() and not c.stop.is_set() and not c.finish.is_set():
            time.sleep(0.05)
        self.summary.paused_s += time.perf_counter() - t0
        if c.stop.is_set():
            return S.STOPPED, f"{c.stop_reason} while paused"
        if c.finish.is_set():
            return S.STOPPED, "stop requested while paused: job ended"
        if not self.homed:
            return S.HOME, "resumed: homing first"
        return S.CAPTURE, "resumed: a fresh frame, the table may have changed"

    def _wait(self) -> Step:
        """Sleep one capture interval, cut short by any operator request; the arm does not move."""
        self.controls.wake.wait(self.continuous_interval_s)
        self.controls.wake.clear()
        return S.CAPTURE, f"waited up to {self.continuous_interval_s:g} s for parts"

    # ---- what a state needs from the ones before it ----------------------------------
    def _last_frame(self) -> np.ndarray:
        """The frame CAPTURE took (LOCATE and PLAN come after it)."""
        if self.frame is None:
            raise RuntimeError(f"{self.sm.state.name} before any frame was captured")
        return self.frame

    def _last_result(self) -> LocateResult:
        """What LOCATE found on the last frame (VERIFY and PLAN come after it)."""
        if self.result is None:
            raise RuntimeError(f"{self.sm.state.name} before any frame was located")
        return self.result

    def _attempt(self) -> tuple[Target, Track]:
        """The pick in progress, chosen by PLAN (PICK, PLACE and VERIFY come after it)."""
        if self.target is None or self.track is None:
            raise RuntimeError(f"{self.sm.state.name} without a pick in progress")
        return self.target, self.track

    def _pick_line(self, t: Target, track: Track, result: str) -> str:
        s = self.summary
        angle = "" if t.jaw_angle_deg is None else f", jaws {t.jaw_angle_deg:+.1f} deg"
        counts = ", ".join(plural(n, c) for c, n in sorted(s.picked.items())) or "none"
        return (
            f"pick {s.attempts:2d}: part {track.id:2d} {t.cls:4s} table ({t.table_mm[0]:6.1f}, {t.table_mm[1]:6.1f}) mm"
            f" -> robot ({t.robot_mm[0]:6.1f}, {t.robot_mm[1]:6.1f}, {t.robot_mm[2]:4.1f}) mm{angle}: {result}"
            f"  [picked {counts}; misses {s.misses}, failed {s.failed}]"
        )


def make_parked_arm_safe(
    arm: Arm, motion_timeout_s: float, events: EventSink, reason: str, job_id: str | None = None
) -> bool:
    """The safe stop with no job moving the arm (a Halt between jobs, or one that came as a job
    ended by parking the arm): a parked arm keeps its torque when its port is closed, so it is
    connected, told to finish any motion, open its gripper and release its torque, then
    disconnected. It is not homed: it is parked where the last job left it. Each step is tried
    even if one before failed and recorded after (best effort). True when the torque was released."""
    events.best_effort = True
    steps: list[tuple[str, Callable[[], None]]] = [
        ("connect", arm.connect),
        ("finish motion", lambda: arm.wait_until_idle(motion_timeout_s)),
        ("open gripper", arm.open_gripper),
        ("release torque", arm.stop),
    ]
    done: list[tuple[str, str | None]] = []
    for name, step in steps:
        error: str | None = None
        try:
            if name != "connect" and not arm.is_connected:
                error = "arm not connected"
            elif not (name == "connect" and arm.is_connected):
                step()
        except (*REPORTED_ERRORS, OSError, KeyboardInterrupt) as e:
            log.warning("making the parked arm safe after %s: %s failed: %s", reason, name, e)
            error = f"{type(e).__name__}: {e}"
        except Exception as e:  # a driver bug must not skip the remaining steps
            log.exception("making the parked arm safe after %s: %s failed", reason, name)
            error = f"internal error: {type(e).__name__}: {e}"
        done.append((name, error))
    try:
        arm.disconnect()
    except Exception:  # the torque is released or not by now; a port that will not close is logged
        log.exception("closing the arm's port after its safe stop")
    for name, error in done:
        events.emit(SafeStepDone(job_id=job_id, step=name, ok=error is None, error=error))
    return done[-1][1] is None


def _detection(o: LocatedPart) -> dict[str, Any]:
    return {
        "id": o.id,
        "cls": o.cls,
        "pick": o.pick,
        "table_mm": [round(v, 3) for v in o.table_mm],
        "pixel": [round(v, 2) for v in o.pixel],
        "angle_deg": None if o.angle_deg is None else round(o.angle_deg, 2),
        "reason": o.reason,
    }

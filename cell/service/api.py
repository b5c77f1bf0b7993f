"""The line service's interface: what OPC UA, the web screen and the CLI may ask of the cell.

Every interface holds a `LineServiceAPI` and nothing else: commands go in as `Command`
events, which the service checks against its command table (`allowed()`) and hands to the
one state machine; state comes out as immutable `Snapshot`s and pushed `ServiceEvent`s.
No interface touches the runner, the arm or the camera directly.

The outward state follows OPC 40100-1 (Machine Vision): Preoperational, Halted, Error,
and inside Operational: Initialized, Ready, SingleExecution, ContinuousExecution.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from enum import Enum
from typing import Protocol

import numpy as np


class VisionState(Enum):
    """OPC 40100-1 state shown to clients; the value is the spec's BrowseName."""

    PREOPERATIONAL = "Preoperational"
    """Starting: devices opening, calibration loading. No command is accepted."""
    HALTED = "Halted"
    """Safe-stopped on Halt (or a signal): arm safe, nothing runs until Reset."""
    ERROR = "Error"
    """A fault: arm made safe, the alarm says why; nothing runs until Reset."""
    INITIALIZED = "Initialized"
    """Operational, devices open, not yet homed for a job."""
    READY = "Ready"
    """Operational, arm homed, waiting for a start command."""
    SINGLE_EXECUTION = "SingleExecution"
    """Clearing the table once, as `run-cell` does; back to Ready when it is clear."""
    CONTINUOUS_EXECUTION = "ContinuousExecution"
    """Capturing at the configured interval and picking whatever appears, until Stop."""


class Command(Enum):
    """A client's request; the value is the OPC UA method's BrowseName."""

    START_SINGLE = "StartSingleJob"
    START_CONTINUOUS = "StartContinuous"
    STOP = "Stop"  # end the job at a safe point, arm homed, back to Ready
    PAUSE = "Pause"  # hold at a safe point with no part in the gripper
    RESUME = "Resume"
    HALT = "Halt"  # the safe stop, into Halted
    RESET = "Reset"  # from Halted or Error back to Ready


_RUNNING = frozenset({Command.STOP, Command.HALT})
_ALLOWED: dict[VisionState, frozenset[Command]] = {
    VisionState.PREOPERATIONAL: frozenset(),
    VisionState.HALTED: frozenset({Command.RESET}),
    VisionState.ERROR: frozenset({Command.RESET}),
    VisionState.INITIALIZED: frozenset({Command.HALT}),
    VisionState.READY: frozenset({Command.START_SINGLE, Command.START_CONTINUOUS, Command.HALT}),
    VisionState.SINGLE_EXECUTION: _RUNNING,
    VisionState.CONTINUOUS_EXECUTION: _RUNNING,
}


def allowed(state: VisionState, paused: bool) -> frozenset[Command]:
    """The command table every interface obeys (and tests check): a job may be paused or
    resumed, never both; Reset only clears Halted or Error."""
    extra = frozenset()
    if state in (VisionState.SINGLE_EXECUTION, VisionState.CONTINUOUS_EXECUTION):
        extra = frozenset({Command.RESUME if paused else Command.PAUSE})
    return _ALLOWED[state] | extra


class InvalidState(Exception):
    """The command is not allowed in the current state (OPC UA: BadInvalidState)."""

    def __init__(self, command: Command, state: VisionState, paused: bool):
        self.command, self.state, self.paused = command, state, paused
        where = f"{state.value}{' (paused)' if paused else ''}"
        super().__init__(f"{command.value} is not allowed in {where}")


@dataclass(frozen=True)
class Counters:
    picked_bolts: int = 0
    picked_nuts: int = 0
    misses: int = 0
    retries: int = 0
    failed: int = 0
    unreachable: int = 0
    unknown_left: int = 0


@dataclass(frozen=True)
class PickRecord:
    """One finished pick attempt, as the screen's table and OPC UA's LastPick* show it."""

    time_utc: datetime
    track_id: int
    cls: str  # bolt | nut
    table_mm: tuple[float, float]
    robot_mm: tuple[float, float, float]
    angle_deg: float | None  # jaw angle for bolts, None for nuts
    outcome: str  # picked | missed | failed | rehearsed


@dataclass(frozen=True)
class Alarm:
    reason: str  # what failed and where
    hint: str  # what the operator can do about it
    time_utc: datetime


@dataclass(frozen=True)
class CalibrationInfo:
    model: str
    cv_rms_mm: float
    cv_max_mm: float
    time_utc: datetime | None  # when it was made
    source_image: str  # which image it was made from (a name for display, never a path to open)


@dataclass(frozen=True)
class Snapshot:
    """Everything a client shows, consistent at one instant."""

    vision_state: VisionState
    cell_state: str  # the runner's State name, e.g. CAPTURE, PICK, PAUSED, FAULT, STOPPED
    paused: bool
    waiting_for_parts: bool  # continuous mode with an empty table
    counters: Counters
    parts_per_min: float
    last_picks: tuple[PickRecord, ...]  # newest last, at most 20
    alarm: Alarm | None
    calibration: CalibrationInfo | None
    heartbeat: int  # +1 a second while the service runs
    allowed: frozenset[Command]  # what the current state accepts (buttons enabled)


@dataclass(frozen=True)
class FrameView:
    """The latest captured frame with what the vision found, for the screen."""

    seq: int  # +1 per captured frame
    capture_monotonic_s: float  # time.monotonic() at capture, for latency measurement
    image_bgr: np.ndarray  # the annotated frame (outlines, class, pick order, jaw direction, reasons)
    pick_order: tuple[int, ...] = ()  # the drawn order: part ids as PLAN chose them; empty if not planned


@dataclass(frozen=True)
class ServiceEvent:
    kind: str  # state | pick | frame | alarm | counters | calibration
    snapshot: Snapshot
    pick: PickRecord | None = None
    frame: FrameView | None = None
    extra: dict = field(default_factory=dict)


class LineServiceAPI(Protocol):
    """What every interface may call. All methods are thread-safe and return quickly."""

    def command(self, command: Command) -> None:
        """Accept the command or raise InvalidState; the work happens in the service's own thread."""

    def snapshot(self) -> Snapshot: ...

    def latest_frame(self) -> FrameView | None: ...

    def subscribe(self, listener: Callable[[ServiceEvent], None]) -> Callable[[], None]:
        """Call `listener` on every event (from the service's thread: hand off, never block);
        returns the function that unsubscribes."""

    def capture_plate_image(self) -> np.ndarray:
        """A frame from the cell's camera for recalibration; only while Ready, paused or Halted
        (raises InvalidState otherwise). The cell stays where it is meanwhile."""

    def install_calibration(self, calibration, info: CalibrationInfo) -> None:
        """Use a calibration that already passed the quality gate and was written atomically to
        the active path; only while Ready, paused or Halted (raises InvalidState otherwise)."""

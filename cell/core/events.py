"""The cell's typed events: what happened, one dataclass per kind, on one stream.

The runner and the line service emit them; everything else listens (cell.core.eventbus): the
audit log (synchronously: the safety record is written before the next motion), and,
each on its own thread behind its own bounded queue, the shift counters, OPC UA, the
screen, the history store and plant telemetry.

Every event has a `kind` (the audit log's `kind` field), the UTC time it happened and the
job it belongs to (None outside a job). `record()` gives the fields the audit log writes;
fields marked `_NOT_RECORDED` (frames, located results) travel with the event only, by
reference: an event is immutable and nobody may change what it carries.

Frames in names: `*_px` pixels, `table_mm` the plate frame, `robot_mm` the arm's base frame.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass, field, fields
from datetime import UTC, datetime
from enum import Enum
from typing import Any, ClassVar

import numpy as np

from cell.core.parts import PartRegistry

_NOT_RECORDED = {"record": False}


def utc_now() -> datetime:
    return datetime.now(UTC)


def new_job_id(now: datetime | None = None) -> str:
    """Unique across jobs, restarts and cells' clocks alike: UTC time to the second and 16 random bits."""
    t = now or utc_now()
    return f"{t:%Y%m%d-%H%M%S}-{secrets.token_hex(2)}"


def pick_id(job_id: str, attempt_no: int) -> str:
    """A pick attempt's id, unique across jobs and restarts: its job and its number in the job."""
    return f"{job_id}/{attempt_no}"


class Interface(Enum):
    """Where a command came from."""

    OPCUA = "opcua"
    SCREEN = "screen"
    SIGNAL = "signal"
    CLI = "cli"
    MQTT = "mqtt"
    SERVICE = "service"  # the service itself (shutdown, start-up)


class Role(Enum):
    """What a user may do; each role may do everything the ones before it may."""

    VIEWER = "viewer"  # watch; and Halt, which every logged-in user may press
    OPERATOR = "operator"  # start, stop, pause, resume, reset, halt
    ENGINEER = "engineer"  # recalibrate, recipes, teach
    ADMIN = "admin"  # users

    @property
    def rank(self) -> int:
        return list(Role).index(self)

    def may(self, needed: Role) -> bool:
        return self.rank >= needed.rank


@dataclass(frozen=True)
class Origin:
    """Who asked, through which interface, from where (an address for display, never a path).

    Deny by default: an origin without a role (`role=None`, the default) may do nothing. Every
    interface names the role it found for its caller; none is assumed."""

    interface: Interface
    user: str = ""
    role: Role | None = None
    address: str = ""

    def may(self, needed: Role) -> bool:
        """Whether this origin's role allows what needs `needed`; never without a role."""
        return self.role is not None and self.role.may(needed)

    @property
    def role_name(self) -> str:
        return self.role.value if self.role is not None else "no role"

    def describe(self) -> str:
        who = self.user or "anonymous"
        where = f" from {self.address}" if self.address else ""
        return f"{who} ({self.role_name}) via {self.interface.value}{where}"

    def as_json(self) -> dict[str, Any]:
        role = self.role.value if self.role is not None else ""
        return {"interface": self.interface.value, "user": self.user, "role": role, "address": self.address}


SERVICE_ORIGIN = Origin(Interface.SERVICE, "service", Role.ADMIN)  # the service itself: start-up, shutdown
SIGNAL_ORIGIN = Origin(Interface.SIGNAL, "signal", Role.OPERATOR)


@dataclass(frozen=True)
class FrameRef:
    """A captured frame and what the vision found on it, shared by reference (never copied, never changed)."""

    frame_no: int
    image: np.ndarray  # BGR, pixels
    result: Any  # cell.vision.types.LocateResult
    captured_monotonic_s: float  # time.monotonic() at capture


def to_json(value: Any) -> Any:
    """JSON-safe copy: numpy scalars and arrays, tuples, enums, datetimes, paths, origins."""
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_json(value.tolist())
    if isinstance(value, np.generic):
        return to_json(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if isinstance(value, datetime):
        return value.isoformat(timespec="milliseconds")
    if isinstance(value, Origin):
        return value.as_json()
    if isinstance(value, Enum):
        return value.value
    return str(value)


@dataclass(frozen=True, kw_only=True)
class Event:
    kind: ClassVar[str] = "event"
    audited: ClassVar[bool] = True  # False: for live views only, the audit log skips it
    time_utc: datetime = field(default_factory=utc_now, metadata=_NOT_RECORDED)
    job_id: str | None = field(default=None, metadata=_NOT_RECORDED)

    def record(self) -> dict[str, Any]:
        """The fields the audit log writes for this event (besides seq, time, kind, state, job)."""
        return {
            f.name: to_json(getattr(self, f.name)) for f in fields(self) if f.metadata.get("record", True) is not False
        }


# ---- the runner: one job ----------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class RunStarted(Event):
    kind: ClassVar[str] = "run_start"
    expect_motion: bool
    camera: str
    arm: str
    arm_port: str | None


@dataclass(frozen=True, kw_only=True)
class StateChanged(Event):
    """The runner's state machine took a transition (cell.statemachine.State values)."""

    kind: ClassVar[str] = "state"
    source: str
    target: str
    reason: str


@dataclass(frozen=True, kw_only=True)
class ArmCommanded(Event):
    """A call into the arm's driver, recorded before it is made."""

    kind: ClassVar[str] = "arm"
    command: str
    args: tuple[float | None, ...] = ()  # the call's positional arguments (coordinates mm, angle deg)


@dataclass(frozen=True, kw_only=True)
class RobotReported(Event):
    """A robot running its own program (arm.kind robot-server) took a pick (`given`), reported it
    (`picked`, `placed`, `missed`), went silent (`unknown`), or the cell withdrew an offer it had not
    taken (`withdrawn`). A refused report (accepted false) carries its (-2,code) (docs/robots.md)."""

    kind: ClassVar[str] = "robot"
    report: str
    pick_no: int
    pick_id: str = ""
    peer: str = ""
    accepted: bool = True
    code: int = 0
    detail: str = ""


@dataclass(frozen=True, kw_only=True)
class FrameLocated(Event):
    """A frame was captured and the vision ran on it."""

    kind: ClassVar[str] = "frame"
    frame: int
    locate_ms: float
    warnings: tuple[str, ...]
    detections: tuple[dict[str, Any], ...]
    calibration_id: str = ""
    ref: FrameRef | None = field(default=None, metadata=_NOT_RECORDED)


@dataclass(frozen=True, kw_only=True)
class PickOrderChosen(Event):
    """PLAN ran on a frame: the ids of its parts in the order the arm will take them (the first is next)."""

    kind: ClassVar[str] = "plan"
    audited: ClassVar[bool] = False  # the targets that follow are the record
    frame: int
    order: tuple[int, ...]


@dataclass(frozen=True, kw_only=True)
class TargetChosen(Event):
    """A pick attempt begins: where the part is and where the arm goes for it."""

    kind: ClassVar[str] = "target"
    pick_id: str
    track: int
    cls: str
    attempt: int
    pixel: tuple[float, float]
    table_mm: tuple[float, float]
    robot_mm: tuple[float, float, float]
    approach_z_mm: float
    jaw_angle_deg: float | None
    bin_robot_mm: tuple[float, float, float]
    calibration_id: str = ""


@dataclass(frozen=True, kw_only=True)
class PickVerified(Event):
    """The frame after a place: the part gone (picked), still there (missed), or a dry run (rehearsed)."""

    kind: ClassVar[str] = "verify"
    pick_id: str
    track: int
    cls: str
    attempt: int
    result: str  # picked | missed | rehearsed
    pixel: tuple[float, float]
    table_mm: tuple[float, float]
    robot_mm: tuple[float, float, float]
    jaw_angle_deg: float | None
    still_at_mm: tuple[tuple[float, float], ...]
    calibration_id: str = ""
    cycle_ms: float = 0.0  # from the target to this verdict
    ref: FrameRef | None = field(default=None, metadata=_NOT_RECORDED)  # the frame that judged it


@dataclass(frozen=True, kw_only=True)
class PartFailed(Event):
    kind: ClassVar[str] = "failed"
    track: int
    cls: str
    attempts: int
    pick_id: str = ""  # the last attempt's
    ref: FrameRef | None = field(default=None, metadata=_NOT_RECORDED)


@dataclass(frozen=True, kw_only=True)
class PartUnreachable(Event):
    kind: ClassVar[str] = "unreachable"
    track: int
    cls: str
    table_mm: tuple[float, float]
    reason: str


@dataclass(frozen=True, kw_only=True)
class FaultRaised(Event):
    """A job faulted; the arm is being made safe. `where` is the runner state it faulted in."""

    kind: ClassVar[str] = "fault"
    reason: str
    where: str = ""
    ref: FrameRef | None = field(default=None, metadata=_NOT_RECORDED)  # the last frame, if any


@dataclass(frozen=True, kw_only=True)
class SafeStepDone(Event):
    kind: ClassVar[str] = "safe_step"
    step: str
    ok: bool
    error: str | None = None

    def record(self) -> dict[str, Any]:
        out = super().record()
        if self.error is None:
            out.pop("error")
        return out


@dataclass(frozen=True, kw_only=True)
class SimTruth(Event):
    kind: ClassVar[str] = "sim_truth"
    where: dict[str, Any]


@dataclass(frozen=True, kw_only=True)
class RunSummarized(Event):
    kind: ClassVar[str] = "summary"
    summary: dict[str, Any]

    def record(self) -> dict[str, Any]:
        return {str(k): to_json(v) for k, v in self.summary.items()}


@dataclass(frozen=True, kw_only=True)
class RunEnded(Event):
    kind: ClassVar[str] = "run_end"
    outcome: str  # done | fault | stopped
    exit_code: int
    reason: str
    unknown_left: int = 0
    ref: FrameRef | None = field(default=None, metadata=_NOT_RECORDED)  # the last frame


# ---- the line service ---------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class ConfigLoaded(Event):
    kind: ClassVar[str] = "config"
    source: str
    dry_run: bool
    config: dict[str, Any]


@dataclass(frozen=True, kw_only=True)
class ServiceStarted(Event):
    kind: ClassVar[str] = "service_start"
    counters: dict[str, Any]
    calibration: str
    capture_interval_s: float


@dataclass(frozen=True, kw_only=True)
class ServiceStopped(Event):
    kind: ClassVar[str] = "service_stop"
    counters: dict[str, Any]


@dataclass(frozen=True, kw_only=True)
class CommandHandled(Event):
    """A command from any interface: accepted, or refused and why (refusal is then set)."""

    kind: ClassVar[str] = "command"
    command: str
    origin: Origin
    accepted: bool
    vision_state: str
    refusal: str = ""  # the refusal's code (cell.core.api.Refusal value)
    message: str = ""  # why, in words
    arguments: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class VisionStateChanged(Event):
    """The outward (OPC 40100-1) state changed."""

    kind: ClassVar[str] = "vision_state"
    source: str
    target: str
    reason: str


@dataclass(frozen=True, kw_only=True)
class JobStarted(Event):
    kind: ClassVar[str] = "job_start"
    mode: str  # single | continuous
    origin: Origin
    recipe: str = ""
    arguments: dict[str, Any] = field(default_factory=dict)  # OPC 40100 MeasId, PartId, ProductId ...


@dataclass(frozen=True, kw_only=True)
class JobEnded(Event):
    kind: ClassVar[str] = "job_end"
    mode: str
    outcome: str  # done | fault | stopped | halted
    reason: str
    counts: dict[str, Any]


@dataclass(frozen=True, kw_only=True)
class AlarmRaised(Event):
    kind: ClassVar[str] = "alarm"
    alarm_id: str
    severity: str  # fault | warning
    reason: str
    hint: str
    source: str = ""  # what raised it: job, history, drift, login ...


@dataclass(frozen=True, kw_only=True)
class AlarmCleared(Event):
    kind: ClassVar[str] = "alarm_cleared"
    alarm_id: str
    origin: Origin  # who reset it


@dataclass(frozen=True, kw_only=True)
class CalibrationInstalled(Event):
    kind: ClassVar[str] = "calibration"
    calibration_id: str  # content hash
    model: str
    cv_rms_mm: float
    cv_max_mm: float
    source_image: str
    file: str = ""
    origin: Origin | None = None  # who accepted it (None: loaded at start)


@dataclass(frozen=True, kw_only=True)
class SnapshotChanged(Event):
    """The service's snapshot changed (`what`: state, counters, alarm, calibration, hold ...): an
    interface showing it should read `snapshot()` again. For live views only, never recorded."""

    kind: ClassVar[str] = "snapshot"
    audited: ClassVar[bool] = False
    what: str


@dataclass(frozen=True, kw_only=True)
class PartClassesChanged(Event):
    """The registry of part classes grew while the service runs: a recipe with taught types it did not count
    was added (AddRecipe), prepared (PrepareRecipe) or taught (AddPartType). `parts` is the whole registry
    now, in its order (never smaller than before: a counter shown stays); `added` the names new in it.
    OPC UA adds their Picked<Plural> variables, Sparkplug sends its births again, /metrics and the screen
    count them (cell.core.parts)."""

    kind: ClassVar[str] = "part_classes"
    recipe: str
    added: tuple[str, ...]
    parts: PartRegistry = field(metadata=_NOT_RECORDED)

    def record(self) -> dict[str, Any]:
        return {**super().record(), "classes": list(self.parts.names)}


EVENT_TYPES: tuple[type[Event], ...] = (
    RunStarted,
    StateChanged,
    ArmCommanded,
    RobotReported,
    FrameLocated,
    PickOrderChosen,
    TargetChosen,
    PickVerified,
    PartFailed,
    PartUnreachable,
    FaultRaised,
    SafeStepDone,
    SimTruth,
    RunSummarized,
    RunEnded,
    ConfigLoaded,
    ServiceStarted,
    ServiceStopped,
    CommandHandled,
    VisionStateChanged,
    JobStarted,
    JobEnded,
    AlarmRaised,
    AlarmCleared,
    CalibrationInstalled,
    SnapshotChanged,
    PartClassesChanged,
)
BY_KIND: dict[str, type[Event]] = {t.kind: t for t in EVENT_TYPES}

"""One mapping from the service's Snapshot to flat, named values: what OPC UA's Cell variables,
the Sparkplug device metrics and Prometheus's gauges all publish.

Each interface has its own names for the same value (OPC UA `PickedBolts`, Sparkplug
`Counters/Picked Bolts`, Prometheus `cell_shift_parts{counter="picked_bolts"}`) and its own way to
say "none" (OPC UA has no null: an empty string, 0 or its epoch; Sparkplug sends null), but the
values are decided here, once: an interface looks its names up by `key` and never reads the
Snapshot's fields itself. The counters of the part classes come from the registry
(cell.core.parts), so a class added there is published by every interface.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import Enum
from types import MappingProxyType
from typing import Any

from cell.core.parts import PartRegistry
from cell.core.records import PickRecord, Snapshot


class Kind(Enum):
    """What a value is, for each interface to choose its type."""

    TEXT = "text"
    FLAG = "flag"
    COUNT = "count"  # a whole number >= 0
    NUMBER = "number"  # a float; None where not known
    TIME = "time"  # a UTC datetime; None where not known
    NUMBERS = "numbers"  # a list of floats
    TEXTS = "texts"  # a list of strings


@dataclass(frozen=True)
class Value:
    key: str
    kind: Kind
    unit: str  # "" where it has none
    meaning: str


def _fixed_values() -> tuple[Value, ...]:
    V, K = Value, Kind
    return (
        V(
            "vision_state",
            K.TEXT,
            "",
            "OPC 40100-1 state: Preoperational, Ready, SingleExecution, ContinuousExecution, Halted, Error",
        ),
        V("cell_state", K.TEXT, "", "the runner's step (CAPTURE, LOCATE, PICK, WAIT, PAUSED ...); IDLE between jobs"),
        V("paused", K.FLAG, "", "a job paused at a safe point (nothing moves)"),
        V("pausing", K.FLAG, "", "a pause was asked for; the last motion is finishing"),
        V("waiting_for_parts", K.FLAG, "", "continuous mode with nothing on the table to pick"),
        V("job_id", K.TEXT, "", "the running job (YYYYMMDD-HHMMSS-xxxx); empty between jobs"),
        V("job_mode", K.TEXT, "", "single or continuous while a job runs; empty between jobs"),
        V("recipe", K.TEXT, "", "the prepared recipe's id"),
        V("hold", K.TEXT, "", "why starts are held (e.g. a recalibration awaiting its answer); empty if none"),
        V("picked", K.COUNT, "parts", "parts picked this shift, every class"),
    )


def _after_picked() -> tuple[Value, ...]:
    V, K = Value, Kind
    return (
        V("misses", K.COUNT, "picks", "picks that left the part on the table this shift"),
        V("retries", K.COUNT, "picks", "second and later attempts at a part this shift"),
        V("failed", K.COUNT, "parts", "parts given up after their last attempt this shift"),
        V("unreachable", K.COUNT, "parts", "parts the arm cannot reach this shift"),
        V("unknown_left", K.COUNT, "parts", "parts on the last frame that are not picked (unknown)"),
        V("parts_per_minute", K.NUMBER, "parts/min", "pick rate over the last 20 picks; 0 when no job runs"),
        V("fault", K.TEXT, "", "the fault alarm (needs Reset): reason (hint: ...); empty if none"),
        V("warnings", K.TEXTS, "", "the warning alarms: reason (hint: ...)"),
        V("alarm_active", K.FLAG, "", "an alarm is shown (the fault, else the newest warning)"),
        V("alarm_id", K.TEXT, "", "the shown alarm's id"),
        V("alarm_severity", K.TEXT, "", "fault (needs Reset) or warning"),
        V("alarm_reason", K.TEXT, "", "what failed and where"),
        V("alarm_hint", K.TEXT, "", "what the operator can do about it"),
        V("alarm_source", K.TEXT, "", "what raised it: job, history, telemetry, drift ..."),
        V("warnings_active", K.COUNT, "alarms", "warning alarms active"),
        V("heartbeat", K.COUNT, "", "+1 a second while the service runs"),
        V("calibration_id", K.TEXT, "", "content hash of the calibration in use"),
        V("calibration_model", K.TEXT, "", "the pixel-to-table model (quadratic, homography, polynomial, camera)"),
        V("calibration_cv_rms_mm", K.NUMBER, "mm", "its cross-validated RMS error"),
        V("calibration_cv_max_mm", K.NUMBER, "mm", "its cross-validated largest error"),
        V("calibration_time", K.TIME, "", "when the calibration in use was made"),
        V("dropped_events", K.COUNT, "events", "events the subscribers lost or failed on since start"),
        V("shift", K.TEXT, "", "the shift the counters count"),
    )


PICK_VALUES = (
    Value("last_pick_id", Kind.TEXT, "", "the pick attempt's id (JOB/N), unique across jobs and restarts"),
    Value("last_pick_class", Kind.TEXT, "", "the part's class"),
    Value("last_pick_outcome", Kind.TEXT, "", "picked, missed, failed (given up) or rehearsed (dry run)"),
    Value("last_pick_table_mm", Kind.NUMBERS, "mm", "where the part lay, table frame (x, y)"),
    Value("last_pick_robot_mm", Kind.NUMBERS, "mm", "the pick point in the arm's base frame (x, y, z)"),
    Value("last_pick_angle_deg", Kind.NUMBER, "deg", "the jaw angle; none where the class has no axis"),
    Value("last_pick_time", Kind.TIME, "", "when the attempt ended"),
)


def class_counter(part_key: str, plural_words: str) -> Value:
    return Value(part_key, Kind.COUNT, "parts", f"{plural_words} picked this shift")


@functools.lru_cache(maxsize=16)  # a registry never changes: its table is made once, not at every publish
def snapshot_table(parts: PartRegistry) -> tuple[Value, ...]:
    """Every value a snapshot gives, in a fixed order: the picked counter of each class after `picked`."""
    per_class = tuple(class_counter(p.counter_key, " ".join(p.words)) for p in parts)
    return _fixed_values() + per_class + _after_picked() + PICK_VALUES


@functools.lru_cache(maxsize=16)
def kinds(parts: PartRegistry) -> Mapping[str, Kind]:
    """Each value's kind by key (read-only: made once per registry)."""
    return MappingProxyType({v.key: v.kind for v in snapshot_table(parts)})


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _alarm_text(reason: str, hint: str) -> str:
    return f"{reason} (hint: {hint})"


def pick_values(p: PickRecord | None) -> dict[str, Any]:
    """The last_pick_* values of one finished attempt (None: no pick yet)."""
    if p is None:
        return {v.key: ([] if v.kind is Kind.NUMBERS else "" if v.kind is Kind.TEXT else None) for v in PICK_VALUES}
    return {
        "last_pick_id": p.pick_id,
        "last_pick_class": p.cls,
        "last_pick_outcome": p.outcome,
        "last_pick_table_mm": [float(v) for v in p.table_mm],
        "last_pick_robot_mm": [float(v) for v in p.robot_mm],
        "last_pick_angle_deg": None if p.angle_deg is None else float(p.angle_deg),
        "last_pick_time": p.time_utc,
    }


def counter_values(s: Snapshot, parts: PartRegistry) -> dict[str, int]:
    """The shift's counters by key, one picked_<plural> for every class of the registry."""
    c = s.counters
    out: dict[str, int] = {"picked": c.picked_total}
    out.update({p.counter_key: c.picked_of(p.name) for p in parts})
    out.update(
        misses=c.misses, retries=c.retries, failed=c.failed, unreachable=c.unreachable, unknown_left=c.unknown_left
    )
    return out


def snapshot_values(s: Snapshot, parts: PartRegistry) -> dict[str, Any]:
    """Every value of `snapshot_table(parts)`, by key; None where a number or time is not known."""
    shown = s.alarm or (s.warnings[-1] if s.warnings else None)
    cal = s.calibration
    values: dict[str, Any] = {
        "vision_state": s.vision_state.value,
        "cell_state": s.cell_state,
        "paused": s.paused,
        "pausing": s.pausing,
        "waiting_for_parts": s.waiting_for_parts,
        "job_id": s.job_id,
        "job_mode": s.job_mode,
        "recipe": s.recipe,
        "hold": s.hold,
        **counter_values(s, parts),
        "parts_per_minute": round(s.parts_per_min, 3),
        "fault": "" if s.alarm is None else _alarm_text(s.alarm.reason, s.alarm.hint),
        "warnings": [_alarm_text(w.reason, w.hint) for w in s.warnings],
        "alarm_active": shown is not None,
        "alarm_id": shown.alarm_id if shown else "",
        "alarm_severity": shown.severity if shown else "",
        "alarm_reason": shown.reason if shown else "",
        "alarm_hint": shown.hint if shown else "",
        "alarm_source": shown.source if shown else "",
        "warnings_active": len(s.warnings),
        "heartbeat": s.heartbeat,
        "calibration_id": cal.calibration_id if cal else "",
        "calibration_model": cal.model if cal else "",
        "calibration_cv_rms_mm": _finite(cal.cv_rms_mm) if cal else None,
        "calibration_cv_max_mm": _finite(cal.cv_max_mm) if cal else None,
        "calibration_time": cal.time_utc if cal else None,
        "dropped_events": sum(x.dropped + x.failed for x in s.subscribers),
        "shift": s.shift,
        **pick_values(s.last_picks[-1] if s.last_picks else None),
    }
    return values


def keys(table: Iterable[Value]) -> tuple[str, ...]:
    return tuple(v.key for v in table)

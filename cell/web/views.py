"""The service's snapshot as the JSON the page renders: what the operator sees, in their words."""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime
from typing import Any

from cell.core.commands import STATE_COMMANDS, VisionState
from cell.core.parts import BUILT_IN_PARTS, PartRegistry
from cell.core.records import Alarm, PickRecord, Snapshot
from cell.core.values import counter_values
from cell.web.words import alarm_words

V = VisionState
RUNNING = frozenset({V.SINGLE_EXECUTION, V.CONTINUOUS_EXECUTION})


def display_state(s: Snapshot) -> tuple[str, str]:
    """(key for the colour, words for the banner): running, waiting, paused, fault, halted, stopped, starting."""
    if s.vision_state is V.ERROR:
        return "fault", "Fault"
    if s.vision_state is V.HALTED:
        return "halted", "Halted"
    if s.vision_state is V.PREOPERATIONAL:
        return "starting", "Starting"
    if s.vision_state in RUNNING:
        if s.paused:
            return "paused", "Paused"
        if s.pausing:
            return "pausing", "Pausing: finishing the current motion"
        if s.waiting_for_parts:
            return "waiting", "Waiting for parts"
        job = "continuous" if s.vision_state is V.CONTINUOUS_EXECUTION else "single job"
        return "running", f"Running ({job})"
    return "stopped", "Stopped: ready to start" if s.vision_state is V.READY else "Stopped"


def next_action(s: Snapshot, key: str) -> str:
    """What the operator can do next, in the state shown (`key` from display_state)."""
    if key == "fault":
        if s.alarm is None:
            return "Fix the cause, then press Reset."
        words = alarm_words(s.alarm)
        return f"{words.say} {words.do}"
    held = f"{s.hold[:1].upper()}{s.hold[1:]}." if s.hold else ""
    return {
        "halted": "Nothing runs until you press Reset.",
        "starting": "Wait: the cell is starting.",
        "stopped": held or "Press Start to clear the table once, or Start continuous to keep picking.",
        "running": "Clearing the table once: Pause holds it at a safe point, Stop ends the job."
        if s.vision_state is V.SINGLE_EXECUTION
        else "Picking parts as they arrive: Pause holds it at a safe point, Stop ends the run.",
        "waiting": "The table is empty: put parts on it, or press Stop to end the run.",
        "pausing": "Finishing the current motion, then it holds: wait.",
        "paused": held or "Press Resume to go on, or Stop to end the job; Recalibrate is possible now.",
    }.get(key, "")


def _time(t: datetime | None) -> str | None:
    return None if t is None else t.isoformat(timespec="seconds")


def _round(values: Iterable[float], digits: int = 1) -> list[float]:
    return [round(float(v), digits) for v in values]


def pick_json(p: PickRecord) -> dict[str, Any]:
    return {
        "time": _time(p.time_utc),
        "part": p.track_id,
        "class": p.cls,
        "table_mm": _round(p.table_mm),
        "robot_mm": _round(p.robot_mm),
        "angle_deg": None if p.angle_deg is None else round(p.angle_deg, 1),
        "outcome": p.outcome,
    }


def alarm_json(a: Alarm) -> dict[str, Any]:
    """The alarm as the engine raised it (reason, hint) and in operator words (say, do, details)."""
    return {
        "reason": a.reason,
        "hint": a.hint,
        "time": _time(a.time_utc),
        "severity": a.severity,
        "source": a.source,
        **alarm_words(a).as_json(),
    }


def snapshot_json(
    s: Snapshot,
    recalibration_open: bool = False,
    calibration_pictures: bool = False,
    parts: PartRegistry = BUILT_IN_PARTS,
) -> dict[str, Any]:
    key, label = display_state(s)
    cal = s.calibration
    return {
        "display": {"key": key, "label": label, "next": next_action(s, key)},
        "vision_state": s.vision_state.value,
        "cell_state": s.cell_state,
        "paused": s.paused,
        "pausing": s.pausing,
        "job_id": s.job_id,
        "hold": s.hold,
        "dropped_events": {x.name: x.dropped + x.failed for x in s.subscribers if x.dropped or x.failed},
        "waiting_for_parts": s.waiting_for_parts,
        "counters": counter_values(s, parts),
        "part_classes": [{"key": p.counter_key, "label": " ".join(p.words).capitalize()} for p in parts],
        "parts_per_min": _rate(s),
        "last_picks": [pick_json(p) for p in reversed(s.last_picks)],  # newest first
        "alarm": None if s.alarm is None else alarm_json(s.alarm),
        "warnings": [alarm_json(w) for w in s.warnings],
        "recipe": s.recipe,
        "recipe_allowed": s.vision_state is V.READY,  # the command table's PrepareRecipe / UnprepareRecipe
        "calibration": None
        if cal is None
        else {
            "model": cal.model,
            "cv_rms_mm": round(cal.cv_rms_mm, 4),
            "cv_max_mm": round(cal.cv_max_mm, 4),
            "time": _time(cal.time_utc),
            "source_image": cal.source_image,
            "pictures": calibration_pictures,
        },
        "heartbeat": s.heartbeat,
        "shift": s.shift,
        "allowed": sorted(c.value for c in s.allowed),
        "recalibration_allowed": may_recalibrate(s),
        "recalibration_open": recalibration_open,
    }


def _rate(s: Snapshot) -> float | None:
    """Parts per minute while a job runs; None ("-") when none runs, it is paused, or its rate is not known
    yet (the ledger's 0 before a job's second pick)."""
    if s.vision_state not in RUNNING or s.paused or s.parts_per_min <= 0:
        return None
    return round(s.parts_per_min, 1)


def may_recalibrate(s: Snapshot) -> bool:
    """The service captures and installs only at rest: Ready, Halted, Error (e.g. the camera moved: recalibrate,
    then Reset), or a job paused at a safe point (the command table's CapturePlate / InstallCalibration)."""
    return s.vision_state in (V.READY, V.HALTED, V.ERROR) or (s.vision_state in RUNNING and s.paused)


COMMANDS = {c.value: c for c in STATE_COMMANDS}

"""The service's snapshot as the JSON the page renders: what the operator sees, in their words."""

from __future__ import annotations

from dataclasses import asdict
from datetime import datetime

from cell.service.api import STATE_COMMANDS, PickRecord, Snapshot, VisionState

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


def _time(t: datetime | None) -> str | None:
    return None if t is None else t.isoformat(timespec="seconds")


def _round(values, digits: int = 1) -> list[float]:
    return [round(float(v), digits) for v in values]


def pick_json(p: PickRecord) -> dict:
    return {
        "time": _time(p.time_utc),
        "part": p.track_id,
        "class": p.cls,
        "table_mm": _round(p.table_mm),
        "robot_mm": _round(p.robot_mm),
        "angle_deg": None if p.angle_deg is None else round(p.angle_deg, 1),
        "outcome": p.outcome,
    }


def snapshot_json(s: Snapshot, recalibration_open: bool = False, calibration_pictures: bool = False) -> dict:
    key, label = display_state(s)
    cal = s.calibration
    return {
        "display": {"key": key, "label": label},
        "vision_state": s.vision_state.value,
        "cell_state": s.cell_state,
        "paused": s.paused,
        "pausing": s.pausing,
        "job_id": s.job_id,
        "hold": s.hold,
        "dropped_events": {x.name: x.dropped + x.failed for x in s.subscribers if x.dropped or x.failed},
        "waiting_for_parts": s.waiting_for_parts,
        "counters": asdict(s.counters),
        "parts_per_min": round(s.parts_per_min, 1) if s.vision_state in RUNNING and not s.paused else None,
        "last_picks": [pick_json(p) for p in reversed(s.last_picks)],  # newest first
        "alarm": None
        if s.alarm is None
        else {"reason": s.alarm.reason, "hint": s.alarm.hint, "time": _time(s.alarm.time_utc)},
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


def may_recalibrate(s: Snapshot) -> bool:
    """The service captures and installs only while Ready, paused or Halted."""
    return s.vision_state in (V.READY, V.HALTED) or (s.vision_state in RUNNING and s.paused)


COMMANDS = {c.value: c for c in STATE_COMMANDS}

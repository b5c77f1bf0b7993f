"""From the cell's events to the history's rows.

One path for the live stream and for the audit files read back after a crash: an event in
its audit form (`{"kind", "time", "job", **event.record()}`) becomes row operations, each a
statement key and its parameters. Every insert is idempotent (ON CONFLICT on the row's id),
so a row written twice is there once.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from cell.history.db import parse_time

STATEMENTS: dict[str, str] = {
    "job_start": """INSERT INTO jobs (id, cell, start_utc, mode, interface, user_name, role, address, recipe, arguments)
        VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)
        ON CONFLICT (id) DO UPDATE SET mode = excluded.mode, interface = excluded.interface,
        user_name = excluded.user_name, role = excluded.role, address = excluded.address,
        recipe = excluded.recipe, arguments = excluded.arguments""",
    "run_start": """INSERT INTO jobs (id, cell, start_utc, mode, interface) VALUES (?, ?, ?, ?, ?)
        ON CONFLICT (id) DO NOTHING""",
    "run_end": """INSERT INTO jobs (id, cell, end_utc, outcome, reason, unknown_left) VALUES (?, ?, ?, ?, ?, ?)
        ON CONFLICT (id) DO UPDATE SET end_utc = excluded.end_utc,
        outcome = COALESCE(jobs.outcome, excluded.outcome), reason = COALESCE(jobs.reason, excluded.reason),
        unknown_left = excluded.unknown_left""",
    "job_end": """INSERT INTO jobs (id, cell, end_utc, mode, outcome, reason, picked, misses, failed, unreachable)
        VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)
        ON CONFLICT (id) DO UPDATE SET end_utc = excluded.end_utc, outcome = excluded.outcome,
        reason = excluded.reason, picked = excluded.picked, misses = excluded.misses, failed = excluded.failed,
        unreachable = excluded.unreachable""",
    "job_image": "UPDATE jobs SET image_id = ? WHERE id = ?",
    "pick": """INSERT INTO picks (id, job_id, cell, time_utc, class, track, attempt, pixel_x, pixel_y,
        table_x_mm, table_y_mm, robot_x_mm, robot_y_mm, robot_z_mm, jaw_angle_deg, calibration_id, outcome,
        cycle_ms, image_id) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)
        ON CONFLICT (id) DO NOTHING""",
    "pick_failed": "UPDATE picks SET outcome = 'failed', image_id = COALESCE(?, image_id) WHERE id = ?",
    "unreachable": """INSERT INTO unreachable (id, job_id, cell, time_utc, class, track, table_x_mm, table_y_mm,
        reason) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (id) DO NOTHING""",
    "alarm": """INSERT INTO alarms (id, cell, alarm_id, severity, raised_utc, reason, hint, source, job_id, image_id)
        VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (id) DO NOTHING""",
    "alarm_cleared": """UPDATE alarms SET cleared_utc = ?, cleared_interface = ?, cleared_user = ?,
        cleared_address = ? WHERE cell = ? AND alarm_id = ? AND cleared_utc IS NULL""",
    "alarms_closed": """UPDATE alarms SET cleared_utc = ?, cleared_interface = 'service', cleared_user = ?
        WHERE cell = ? AND cleared_utc IS NULL""",
    "command": """INSERT INTO commands (id, cell, time_utc, command, interface, user_name, role, address, accepted,
        refusal, message, vision_state, arguments) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)
        ON CONFLICT (id) DO NOTHING""",
    "calibration": """INSERT INTO calibrations (id, cell, first_utc, last_installed_utc, model, cv_rms_mm, cv_max_mm,
        source_image, file, accepted_interface, accepted_user, accepted_utc) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)
        ON CONFLICT (id) DO UPDATE SET last_installed_utc = excluded.last_installed_utc,
        accepted_interface = COALESCE(excluded.accepted_interface, calibrations.accepted_interface),
        accepted_user = COALESCE(excluded.accepted_user, calibrations.accepted_user),
        accepted_utc = COALESCE(excluded.accepted_utc, calibrations.accepted_utc)""",
    "state": """INSERT INTO states (id, cell, time_utc, source, target, reason) VALUES (?, ?, ?, ?, ?, ?)
        ON CONFLICT (id) DO NOTHING""",
    "image": """INSERT INTO images (id, cell, time_utc, kind, job_id, pick_id, frame_no, frame_file,
        annotated_file, bytes) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (id) DO NOTHING""",
    "image_deleted": "UPDATE images SET deleted_utc = ? WHERE id = ?",
    "mark": """INSERT INTO marks (cell, last_event_utc) VALUES (?, ?)
        ON CONFLICT (cell) DO UPDATE SET last_event_utc = excluded.last_event_utc""",
}

# Kinds whose rows carry ids from the cell itself: safe to read back from the audit after a crash.
KEYED_KINDS = frozenset({"job_start", "job_end", "run_start", "run_end", "verify", "failed", "unreachable"})
# Kinds the history listens to (the live stream).
KINDS = KEYED_KINDS | {
    "target",
    "fault",
    "alarm",
    "alarm_cleared",
    "command",
    "calibration",
    "vision_state",
    "service_start",
    "service_stop",
}


@dataclass(frozen=True)
class Op:
    key: str
    params: tuple


@dataclass(frozen=True)
class ImageWanted:
    """An image the event asks to keep: its id, kind and the rows that link to it (set once it is saved)."""

    image_id: str
    kind: str  # miss | failed | fault | unknown
    job_id: str
    pick_id: str


def image_id(job_id: str, frame_no: int) -> str:
    """Deterministic, so the same frame of the same job is one image (a miss, then its part failed)."""
    return uuid.uuid5(uuid.NAMESPACE_URL, f"pick-cell:{job_id}:{frame_no}").hex[:20]


def _f(v: Any) -> float | None:
    return None if v is None else float(v)


def _xy(v: Any, n: int) -> list[float | None]:
    vals = list(v) if v is not None else []
    return [_f(vals[i]) if i < len(vals) else None for i in range(n)]


class RowMaker:
    """Turns events (audit form) into Ops; keeps what links rows (a fault's image to its alarm)."""

    def __init__(self, cell: str, new_id: Callable[[], str] = lambda: uuid.uuid4().hex):
        self.cell, self.new_id = cell, new_id
        self._fault_image: tuple[str, str] | None = None  # (job_id, image id) of the last job fault

    def ops(self, e: dict, image: ImageWanted | None = None) -> list[Op]:
        kind = e.get("kind", "")
        handler = getattr(self, "_" + kind, None)
        if handler is None:
            return []
        t = parse_time(e.get("time") or e.get("t_utc")) or datetime.now(UTC)
        return handler(e, t, e.get("job") or "", image)

    # ---- jobs -------------------------------------------------------------------------------
    def _job_start(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        o = e.get("origin") or {}
        args = e.get("arguments") or {}
        params = (job, self.cell, t, e.get("mode", ""), o.get("interface", ""), o.get("user", ""))
        rest = (o.get("role", ""), o.get("address", ""), e.get("recipe", ""), json.dumps(args, sort_keys=True))
        return [Op("job_start", params + rest)]

    def _run_start(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        return [Op("run_start", (job, self.cell, t, "single", "cli"))] if job else []

    def _run_end(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        if not job:
            return []
        ops = [Op("run_end", (job, self.cell, t, e.get("outcome"), e.get("reason"), int(e.get("unknown_left") or 0)))]
        if image is not None:
            ops.append(Op("job_image", (image.image_id, job)))
        return ops

    def _job_end(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        c = e.get("counts") or {}
        picked = c.get("picked")
        if isinstance(picked, dict):
            picked = sum(int(v) for v in picked.values())
        params = (job, self.cell, t, e.get("mode", ""), e.get("outcome", ""), e.get("reason", ""))
        counts = (picked, c.get("misses"), c.get("failed"), c.get("unreachable"))
        return [Op("job_end", params + counts)]

    # ---- picks ------------------------------------------------------------------------------
    def _verify(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        px, py = _xy(e.get("pixel"), 2)
        tx, ty = _xy(e.get("table_mm"), 2)
        rx, ry, rz = _xy(e.get("robot_mm"), 3)
        params = (
            e["pick_id"],
            job,
            self.cell,
            t,
            e.get("cls", ""),
            int(e.get("track", 0)),
            int(e.get("attempt", 0)),
            px,
            py,
            tx,
            ty,
            rx,
            ry,
            rz,
            _f(e.get("jaw_angle_deg")),
            e.get("calibration_id") or "",
            e.get("result", ""),
            _f(e.get("cycle_ms")),
            None if image is None else image.image_id,
        )
        return [Op("pick", params)]

    def _failed(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        pick = e.get("pick_id") or ""
        return [Op("pick_failed", (None if image is None else image.image_id, pick))] if pick else []

    def _unreachable(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        tx, ty = _xy(e.get("table_mm"), 2)
        track = int(e.get("track", 0))
        params = (f"{job}/u{track}", job, self.cell, t, e.get("cls", ""), track, tx, ty, e.get("reason", ""))
        return [Op("unreachable", params)]

    def _fault(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        if image is None:
            self._fault_image = None
            return []
        self._fault_image = (job, image.image_id)
        return [Op("job_image", (image.image_id, job))] if job else []

    def _target(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        return []  # the verdict's row carries the same fields; kept for the stream's order only

    # ---- alarms, commands, calibrations, states -------------------------------------------------
    def _alarm(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        linked_job, linked_image = "", None
        if e.get("severity") == "fault" and e.get("source") == "job" and self._fault_image is not None:
            linked_job, linked_image = self._fault_image
            self._fault_image = None
        params = (self.new_id(), self.cell, e.get("alarm_id", ""), e.get("severity", ""), t, e.get("reason", ""))
        rest = (e.get("hint", ""), e.get("source", ""), job or linked_job, linked_image)
        return [Op("alarm", params + rest)]

    def _alarm_cleared(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        o = e.get("origin") or {}
        params = (t, o.get("interface", ""), o.get("user", ""), o.get("address", ""), self.cell, e.get("alarm_id", ""))
        return [Op("alarm_cleared", params)]

    def _service_start(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        """Alarm ids start again at A1: the alarms a previous run left open are closed by this start."""
        return [
            Op("alarms_closed", (t, "service restart", self.cell)),
            Op("state", (self.new_id(), self.cell, t, "Off", "Preoperational", "service started")),
        ]

    def _service_stop(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        return [Op("state", (self.new_id(), self.cell, t, "", "Off", "service stopped"))]

    def _command(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        o = e.get("origin") or {}
        args = json.dumps(e.get("arguments") or {}, sort_keys=True)
        params = (self.new_id(), self.cell, t, e.get("command", ""), o.get("interface", ""), o.get("user", ""))
        rest = (o.get("role", ""), o.get("address", ""), int(bool(e.get("accepted"))), e.get("refusal", ""))
        return [Op("command", params + rest + (e.get("message", ""), e.get("vision_state", ""), args))]

    def _calibration(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        cal_id = e.get("calibration_id") or ""
        if not cal_id:
            return []
        o = e.get("origin")
        who = (o.get("interface"), o.get("user"), t) if isinstance(o, dict) else (None, None, None)
        params = (cal_id, self.cell, t, t, e.get("model", ""), _f(e.get("cv_rms_mm")), _f(e.get("cv_max_mm")))
        return [Op("calibration", params + (e.get("source_image", ""), e.get("file", ""), *who))]

    def _vision_state(self, e: dict, t: datetime, job: str, image: ImageWanted | None) -> list[Op]:
        params = (self.new_id(), self.cell, t, e.get("source", ""), e.get("target", ""), e.get("reason", ""))
        return [Op("state", params)]

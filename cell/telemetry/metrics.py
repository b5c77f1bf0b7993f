"""The cell's Sparkplug metrics: every name, type, unit and meaning in one table (docs/plant.md lists
the same; tests/test_plant_doc.py keeps the two in step), and their values from the line
service's snapshot and from each finished pick."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from cell.core.commands import Command
from cell.core.records import PickRecord, Snapshot
from cell.telemetry.sparkplug import DataType

D = DataType


@dataclass(frozen=True)
class Spec:
    name: str
    dtype: DataType
    unit: str  # "" where the value has none
    meaning: str


BD_SEQ = "bdSeq"
REBIRTH = "Node Control/Rebirth"
DROPPED = "Telemetry/Dropped Messages"

NODE = (
    Spec(BD_SEQ, D.INT64, "", "birth/death sequence: the NDEATH with the same bdSeq ends this NBIRTH's session"),
    Spec(REBIRTH, D.BOOLEAN, "", "write true (NCMD) to have the cell publish NBIRTH and DBIRTH again"),
    Spec(DROPPED, D.UINT64, "messages", "updates not published since start (broker away, queue full)"),
)

DEVICE = (
    Spec(
        "State",
        D.STRING,
        "",
        "OPC 40100-1 state: Preoperational, Ready, SingleExecution, ContinuousExecution, Halted, Error",
    ),
    Spec("Cell State", D.STRING, "", "the runner's step (CAPTURE, LOCATE, PICK, WAIT, PAUSED ...); IDLE between jobs"),
    Spec("Paused", D.BOOLEAN, "", "a job paused at a safe point (nothing moves)"),
    Spec("Waiting For Parts", D.BOOLEAN, "", "continuous mode with nothing on the table to pick"),
    Spec("Job/Id", D.STRING, "", "the running job (YYYYMMDD-HHMMSS-xxxx); empty between jobs"),
    Spec("Job/Mode", D.STRING, "", "single or continuous while a job runs; empty between jobs"),
    Spec("Recipe", D.STRING, "", "the prepared recipe's id"),
    Spec("Hold", D.STRING, "", "why starts are held (e.g. a recalibration awaiting its answer); empty if none"),
    Spec("Counters/Picked", D.UINT64, "parts", "parts picked this shift (bolts and nuts)"),
    Spec("Counters/Picked Bolts", D.UINT64, "parts", "bolts picked this shift"),
    Spec("Counters/Picked Nuts", D.UINT64, "parts", "nuts picked this shift"),
    Spec("Counters/Misses", D.UINT64, "picks", "picks that left the part on the table this shift"),
    Spec("Counters/Retries", D.UINT64, "picks", "second and later attempts at a part this shift"),
    Spec("Counters/Failed", D.UINT64, "parts", "parts given up after their last attempt this shift"),
    Spec("Counters/Unreachable", D.UINT64, "parts", "parts the arm cannot reach this shift"),
    Spec("Counters/Unknown Left", D.UINT64, "parts", "parts on the last frame that are not picked (unknown)"),
    Spec("Rate/Parts Per Minute", D.DOUBLE, "parts/min", "pick rate over the last 20 picks; 0 when no job runs"),
    Spec("Last Pick/Id", D.STRING, "", "the pick attempt's id (JOB/N), unique across jobs and restarts"),
    Spec("Last Pick/Class", D.STRING, "", "bolt or nut"),
    Spec("Last Pick/Outcome", D.STRING, "", "picked, missed, failed (given up) or rehearsed (dry run)"),
    Spec("Last Pick/Table X mm", D.DOUBLE, "mm", "where the part lay, table frame (the plate's)"),
    Spec("Last Pick/Table Y mm", D.DOUBLE, "mm", "where the part lay, table frame"),
    Spec("Last Pick/Robot X mm", D.DOUBLE, "mm", "the pick point in the arm's base frame"),
    Spec("Last Pick/Robot Y mm", D.DOUBLE, "mm", "the pick point in the arm's base frame"),
    Spec("Last Pick/Robot Z mm", D.DOUBLE, "mm", "the pick point in the arm's base frame"),
    Spec("Last Pick/Jaw Angle deg", D.DOUBLE, "deg", "jaw angle for a bolt; null for a nut"),
    Spec("Last Pick/Cycle ms", D.DOUBLE, "ms", "from choosing the target to the verdict; null for failed"),
    Spec("Alarm/Active", D.BOOLEAN, "", "an alarm is shown (the fault, else the newest warning)"),
    Spec("Alarm/Id", D.STRING, "", "the shown alarm's id"),
    Spec("Alarm/Severity", D.STRING, "", "fault (needs Reset) or warning"),
    Spec("Alarm/Reason", D.STRING, "", "what failed and where"),
    Spec("Alarm/Hint", D.STRING, "", "what the operator can do about it"),
    Spec("Alarm/Source", D.STRING, "", "what raised it: job, history, telemetry, drift ..."),
    Spec("Alarm/Warnings", D.UINT64, "alarms", "warning alarms active"),
    Spec("Calibration/Id", D.STRING, "", "content hash of the calibration in use"),
    Spec("Calibration/Model", D.STRING, "", "the pixel-to-table model (quadratic, homography, polynomial, camera)"),
    Spec("Calibration/CV RMS mm", D.DOUBLE, "mm", "its cross-validated RMS error"),
    Spec("Calibration/CV Max mm", D.DOUBLE, "mm", "its cross-validated largest error"),
)

# Commands over MQTT (with telemetry.mqtt.commands): a host writes true to one of these (DCMD); the
# answer comes back in the Command/Last metrics. Only these four verbs (and both starts) are offered.
MQTT_COMMANDS = {
    "Command/StartSingleJob": Command.START_SINGLE,
    "Command/StartContinuous": Command.START_CONTINUOUS,
    "Command/Stop": Command.STOP,
    "Command/Pause": Command.PAUSE,
    "Command/Resume": Command.RESUME,
}
COMMANDS = tuple(
    Spec(name, D.BOOLEAN, "", f"write true (DCMD) to send {command.value}; always reads false")
    for name, command in MQTT_COMMANDS.items()
) + (
    Spec("Command/Last Name", D.STRING, "", "the last MQTT command (StartSingleJob, Stop ...)"),
    Spec("Command/Last Accepted", D.BOOLEAN, "", "whether the cell accepted it"),
    Spec(
        "Command/Last Refusal",
        D.STRING,
        "",
        "why not: invalid_state, access_denied, shutting_down, internal_error ...; empty if accepted",
    ),
    Spec("Command/Last Message", D.STRING, "", "the refusal in words (as OPC UA and the screen give it)"),
    Spec("Command/Last Job Id", D.STRING, "", "the job a start command began"),
)
COMMAND_RESULT_NAMES = tuple(s.name for s in COMMANDS if s.name not in MQTT_COMMANDS)


def device_specs(commands: bool) -> tuple[Spec, ...]:
    return DEVICE + (COMMANDS if commands else ())


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def snapshot_values(s: Snapshot) -> dict[str, Any]:
    """Every device metric the snapshot decides (all but Last Pick and Command)."""
    c = s.counters
    alarm = s.alarm or (s.warnings[-1] if s.warnings else None)
    cal = s.calibration
    return {
        "State": s.vision_state.value,
        "Cell State": s.cell_state,
        "Paused": s.paused,
        "Waiting For Parts": s.waiting_for_parts,
        "Job/Id": s.job_id,
        "Job/Mode": s.job_mode,
        "Recipe": s.recipe,
        "Hold": s.hold,
        "Counters/Picked": c.picked_bolts + c.picked_nuts,
        "Counters/Picked Bolts": c.picked_bolts,
        "Counters/Picked Nuts": c.picked_nuts,
        "Counters/Misses": c.misses,
        "Counters/Retries": c.retries,
        "Counters/Failed": c.failed,
        "Counters/Unreachable": c.unreachable,
        "Counters/Unknown Left": c.unknown_left,
        "Rate/Parts Per Minute": round(s.parts_per_min, 3),
        "Alarm/Active": alarm is not None,
        "Alarm/Id": alarm.alarm_id if alarm else "",
        "Alarm/Severity": alarm.severity if alarm else "",
        "Alarm/Reason": alarm.reason if alarm else "",
        "Alarm/Hint": alarm.hint if alarm else "",
        "Alarm/Source": alarm.source if alarm else "",
        "Alarm/Warnings": len(s.warnings),
        "Calibration/Id": cal.calibration_id if cal else "",
        "Calibration/Model": cal.model if cal else "",
        "Calibration/CV RMS mm": _finite(cal.cv_rms_mm) if cal else None,
        "Calibration/CV Max mm": _finite(cal.cv_max_mm) if cal else None,
    }


def pick_values(p: PickRecord, cycle_ms: float | None) -> dict[str, Any]:
    """The Last Pick metrics of one finished attempt (or a part given up)."""
    return {
        "Last Pick/Id": p.pick_id,
        "Last Pick/Class": p.cls,
        "Last Pick/Outcome": p.outcome,
        "Last Pick/Table X mm": round(p.table_mm[0], 3),
        "Last Pick/Table Y mm": round(p.table_mm[1], 3),
        "Last Pick/Robot X mm": round(p.robot_mm[0], 3),
        "Last Pick/Robot Y mm": round(p.robot_mm[1], 3),
        "Last Pick/Robot Z mm": round(p.robot_mm[2], 3),
        "Last Pick/Jaw Angle deg": None if p.angle_deg is None else round(float(p.angle_deg), 3),
        "Last Pick/Cycle ms": None if cycle_ms is None else round(float(cycle_ms), 1),
    }


NO_PICK = {
    "Last Pick/Id": "",
    "Last Pick/Class": "",
    "Last Pick/Outcome": "",
    **{f"Last Pick/{k}": None for k in ("Table X mm", "Table Y mm", "Robot X mm", "Robot Y mm", "Robot Z mm")},
    "Last Pick/Jaw Angle deg": None,
    "Last Pick/Cycle ms": None,
}
NO_COMMAND = {
    **dict.fromkeys(MQTT_COMMANDS, False),
    "Command/Last Name": "",
    "Command/Last Accepted": False,
    "Command/Last Refusal": "",
    "Command/Last Message": "",
    "Command/Last Job Id": "",
}

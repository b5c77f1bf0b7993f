"""The cell's Sparkplug metrics: every name, type, unit and meaning in one table (docs/plant.md lists
the same; tests/test_plant_doc.py keeps the two in step), and their values from the line
service's snapshot and from each finished pick."""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from cell.core.commands import Command
from cell.core.parts import BUILT_IN_PARTS, PartRegistry
from cell.core.records import PickRecord, Snapshot
from cell.core.values import snapshot_table
from cell.core.values import snapshot_values as core_values
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

# The metrics the snapshot decides: name, the value's key in cell.core.values (one mapping from the
# Snapshot, and one meaning and unit, for OPC UA, Sparkplug and /metrics), type. The part classes'
# counters go between the two (class_specs).
_BEFORE_CLASSES_KEYS = (
    ("State", "vision_state", D.STRING),
    ("Cell State", "cell_state", D.STRING),
    ("Paused", "paused", D.BOOLEAN),
    ("Waiting For Parts", "waiting_for_parts", D.BOOLEAN),
    ("Job/Id", "job_id", D.STRING),
    ("Job/Mode", "job_mode", D.STRING),
    ("Recipe", "recipe", D.STRING),
    ("Hold", "hold", D.STRING),
    ("Counters/Picked", "picked", D.UINT64),
)
_AFTER_CLASSES_KEYS = (
    ("Counters/Misses", "misses", D.UINT64),
    ("Counters/Retries", "retries", D.UINT64),
    ("Counters/Failed", "failed", D.UINT64),
    ("Counters/Unreachable", "unreachable", D.UINT64),
    ("Counters/Unknown Left", "unknown_left", D.UINT64),
    ("Rate/Parts Per Minute", "parts_per_minute", D.DOUBLE),
)
_AFTER_PICK_KEYS = (
    ("Alarm/Active", "alarm_active", D.BOOLEAN),
    ("Alarm/Id", "alarm_id", D.STRING),
    ("Alarm/Severity", "alarm_severity", D.STRING),
    ("Alarm/Reason", "alarm_reason", D.STRING),
    ("Alarm/Hint", "alarm_hint", D.STRING),
    ("Alarm/Source", "alarm_source", D.STRING),
    ("Alarm/Warnings", "warnings_active", D.UINT64),
    ("Calibration/Id", "calibration_id", D.STRING),
    ("Calibration/Model", "calibration_model", D.STRING),
    ("Calibration/CV RMS mm", "calibration_cv_rms_mm", D.DOUBLE),
    ("Calibration/CV Max mm", "calibration_cv_max_mm", D.DOUBLE),
)
# Last Pick: one metric per coordinate, from each finished pick (pick_values), not the snapshot
LAST_PICK = (
    Spec("Last Pick/Id", D.STRING, "", "the pick attempt's id (JOB/N), unique across jobs and restarts"),
    Spec("Last Pick/Class", D.STRING, "", "the part's class (bolt, nut, a taught type)"),
    Spec("Last Pick/Outcome", D.STRING, "", "picked, missed, failed (given up) or rehearsed (dry run)"),
    Spec("Last Pick/Table X mm", D.DOUBLE, "mm", "where the part lay, table frame (the plate's)"),
    Spec("Last Pick/Table Y mm", D.DOUBLE, "mm", "where the part lay, table frame"),
    Spec("Last Pick/Robot X mm", D.DOUBLE, "mm", "the pick point in the arm's base frame"),
    Spec("Last Pick/Robot Y mm", D.DOUBLE, "mm", "the pick point in the arm's base frame"),
    Spec("Last Pick/Robot Z mm", D.DOUBLE, "mm", "the pick point in the arm's base frame"),
    Spec("Last Pick/Jaw Angle deg", D.DOUBLE, "deg", "the jaw angle; null where the class has no axis (a nut)"),
    Spec("Last Pick/Cycle ms", D.DOUBLE, "ms", "from choosing the target to the verdict; null for failed"),
)


def _from_core(table: tuple[tuple[str, str, DataType], ...]) -> tuple[Spec, ...]:
    """Specs whose unit and meaning are the core value's (cell.core.values), under Sparkplug's names."""
    meaning = {v.key: v for v in snapshot_table(BUILT_IN_PARTS)}
    return tuple(Spec(name, dtype, meaning[key].unit, meaning[key].meaning) for name, key, dtype in table)


_BEFORE_CLASSES = _from_core(_BEFORE_CLASSES_KEYS)
_AFTER_CLASSES = _from_core(_AFTER_CLASSES_KEYS) + LAST_PICK + _from_core(_AFTER_PICK_KEYS)


def class_specs(parts: PartRegistry) -> tuple[Spec, ...]:
    """A picked counter for each part class of the registry (Counters/Picked Bolts ...)."""
    return tuple(Spec(p.sparkplug_name, D.UINT64, "parts", f"{' '.join(p.words)} picked this shift") for p in parts)


def device_table(parts: PartRegistry) -> tuple[Spec, ...]:
    """The device metrics the snapshot decides, the part classes' counters among them."""
    return _BEFORE_CLASSES + class_specs(parts) + _AFTER_CLASSES


DEVICE = device_table(BUILT_IN_PARTS)  # with the built-in part classes (documented in docs/plant.md)

# metric name -> the value's key in cell.core.values (one mapping from the Snapshot for OPC UA,
# Sparkplug and /metrics)
_KEYS = {name: key for name, key, _ in _BEFORE_CLASSES_KEYS + _AFTER_CLASSES_KEYS + _AFTER_PICK_KEYS}

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


def device_specs(commands: bool, parts: PartRegistry = BUILT_IN_PARTS) -> tuple[Spec, ...]:
    return device_table(parts) + (COMMANDS if commands else ())


def snapshot_values(s: Snapshot, parts: PartRegistry = BUILT_IN_PARTS) -> dict[str, Any]:
    """Every device metric the snapshot decides (all but Last Pick and Command)."""
    values = core_values(s, parts)
    return {name: values[key] for name, key in _names(parts).items()}


@functools.lru_cache(maxsize=16)  # made once per registry, not at every update
def _names(parts: PartRegistry) -> Mapping[str, str]:
    """Metric name -> the value's key, the part classes' counters among them."""
    return MappingProxyType({**_KEYS, **{p.sparkplug_name: p.counter_key for p in parts}})


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

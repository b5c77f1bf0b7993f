"""The domain core (cell/core): deny by default, the registry of part classes, and the one mapping
from a Snapshot to the values OPC UA, Sparkplug and /metrics publish."""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime

import pytest

from cell.core.commands import Command, VisionState, needed_role
from cell.core.events import SERVICE_ORIGIN, Interface, Origin, Role
from cell.core.parts import BUILT_IN_PARTS, PartClass, PartRegistry, UnknownPartClass
from cell.core.records import Alarm, CalibrationInfo, Counters, PickRecord, Snapshot
from cell.core.values import Kind, snapshot_table, snapshot_values
from cell.service import opcua
from cell.telemetry import metrics as sparkplug_metrics

BRACKET = PartClass("l-bracket", "l-brackets")
TAUGHT = BUILT_IN_PARTS.with_classes([BRACKET])


def snapshot(**changes) -> Snapshot:
    base = Snapshot(
        vision_state=VisionState.READY,
        cell_state="IDLE",
        paused=False,
        waiting_for_parts=False,
        counters=Counters(picked=(("bolt", 4), ("l-bracket", 2)), misses=1),
        parts_per_min=0.0,
        last_picks=(),
        alarm=None,
        calibration=None,
        heartbeat=7,
        allowed=frozenset(),
    )
    return replace(base, **changes)


# ---- deny by default -----------------------------------------------------------------------
def test_an_origin_without_a_role_may_do_nothing():
    nobody = Origin(Interface.OPCUA, "someone", address="10.0.0.9")
    assert nobody.role is None
    assert not any(nobody.may(needed_role(c)) for c in Command)
    assert "no role" in nobody.describe() and nobody.as_json()["role"] == ""


def test_roles_may_what_the_table_gives_them():
    viewer, operator = Origin(Interface.SCREEN, "v", Role.VIEWER), Origin(Interface.SCREEN, "o", Role.OPERATOR)
    assert viewer.may(needed_role(Command.HALT)) and not viewer.may(needed_role(Command.START_SINGLE))
    assert operator.may(needed_role(Command.START_SINGLE)) and not operator.may(needed_role(Command.ADD_RECIPE))
    assert all(SERVICE_ORIGIN.may(needed_role(c)) for c in Command)  # the service itself names its role


# ---- the registry of part classes ----------------------------------------------------------
def test_the_registry_names_each_class_for_every_interface():
    assert BUILT_IN_PARTS.names == ("bolt", "nut")
    bolt = BUILT_IN_PARTS.get("bolt")
    assert (bolt.counter_key, bolt.opcua_name, bolt.sparkplug_name) == (
        "picked_bolts",
        "PickedBolts",
        "Counters/Picked Bolts",
    )
    assert (BRACKET.counter_key, BRACKET.opcua_name, BRACKET.sparkplug_name) == (
        "picked_l_brackets",
        "PickedLBrackets",
        "Counters/Picked L Brackets",
    )
    assert TAUGHT.names == ("bolt", "nut", "l-bracket") and "l-bracket" in TAUGHT
    with pytest.raises(UnknownPartClass, match="'washer'.*known: bolt, nut"):
        BUILT_IN_PARTS.get("washer")


@pytest.mark.parametrize("name", ["", "Bolt", "bolt/../x", "1bolt", "a" * 33, "bolt nut"])
def test_a_class_name_must_be_safe_in_a_path_a_topic_and_a_label(name):
    with pytest.raises(ValueError, match="lower-case letters"):
        PartClass(name, "things")


def test_a_registry_refuses_a_name_twice_and_counters_that_collide():
    with pytest.raises(ValueError, match="twice"):
        PartRegistry([PartClass("bolt", "bolts"), PartClass("bolt", "screws")])
    with pytest.raises(ValueError, match="share a counter"):
        PartRegistry([PartClass("clip", "clip-s"), PartClass("clips", "clip_s")])
    assert TAUGHT.with_classes([BRACKET]).names == TAUGHT.names  # each name once


# ---- one mapping from the snapshot -----------------------------------------------------------
def test_counters_are_kept_per_class():
    c = Counters(picked=(("bolt", 4), ("l-bracket", 2)))
    assert c.picked_of("bolt") == 4 and c.picked_of("nut") == 0 and c.picked_total == 6
    assert c.as_json()["picked"] == {"bolt": 4, "l-bracket": 2}


def test_snapshot_values_follow_the_registry():
    values = snapshot_values(snapshot(), TAUGHT)
    assert set(values) == {v.key for v in snapshot_table(TAUGHT)}
    assert (values["picked"], values["picked_bolts"], values["picked_nuts"], values["picked_l_brackets"]) == (
        6,
        4,
        0,
        2,
    )
    assert values["calibration_time"] is None and values["last_pick_angle_deg"] is None  # unknown: None
    assert values["fault"] == "" and values["alarm_active"] is False


def test_the_shown_alarm_is_the_fault_else_the_newest_warning():
    t = datetime(2026, 12, 3, tzinfo=UTC)
    warning = Alarm("disk nearly full", "free space", t, "w1", "warning", "history")
    values = snapshot_values(snapshot(warnings=(warning,)), BUILT_IN_PARTS)
    assert (values["alarm_active"], values["alarm_id"], values["fault"]) == (True, "w1", "")
    assert values["warnings"] == ["disk nearly full (hint: free space)"]
    fault = Alarm("arm stalled", "Reset", t, "f1")
    values = snapshot_values(snapshot(alarm=fault, warnings=(warning,)), BUILT_IN_PARTS)
    assert (values["alarm_id"], values["fault"]) == ("f1", "arm stalled (hint: Reset)")


def test_opcua_sparkplug_and_metrics_publish_a_taught_class():
    t = datetime(2026, 12, 3, tzinfo=UTC)
    pick = PickRecord(t, 1, "l-bracket", (1.0, 2.0), (3.0, 4.0, 5.0), None, "picked", "job/1", "job")
    cal = CalibrationInfo("camera", float("nan"), 0.02, None, "plate.png", "abc")
    s = snapshot(last_picks=(pick,), calibration=cal)
    ua_types = opcua.variables(TAUGHT)
    assert list(ua_types)[5:8] == ["PickedBolts", "PickedNuts", "PickedLBrackets"]
    assert opcua.browse_names(TAUGHT)["PickedLBrackets"] == "picked_l_brackets"
    kinds = {v.key: v.kind for v in snapshot_table(TAUGHT)}
    assert kinds["picked_l_brackets"] is Kind.COUNT
    specs = {spec.name for spec in sparkplug_metrics.device_specs(False, TAUGHT)}
    assert "Counters/Picked L Brackets" in specs
    values = sparkplug_metrics.snapshot_values(s, TAUGHT)
    assert values["Counters/Picked L Brackets"] == 2 and values["Counters/Picked"] == 6
    assert values["Calibration/CV RMS mm"] is None  # not finite: null in Sparkplug
    assert set(values) <= specs


def test_the_documented_tables_are_those_of_the_built_in_classes():
    assert opcua.VARIABLES == opcua.variables(BUILT_IN_PARTS)
    assert sparkplug_metrics.DEVICE == sparkplug_metrics.device_table(BUILT_IN_PARTS)
    assert {"PickedBolts", "PickedNuts"} <= set(opcua.VARIABLES)

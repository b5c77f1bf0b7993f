"""docs/opcua-machinevision.md says what the Machine Vision model does: every method served,
the state mapping, the refusal codes and the settings."""

from __future__ import annotations

import re
from pathlib import Path

from cell.core.commands import VisionState
from cell.service.machinevision import METHODS, REFUSAL_STATUS, STATE_PLACE, SYSTEM_STATE
from cell.service.mv_config import MachineVisionConfig

DOC = (Path(__file__).resolve().parents[1] / "docs" / "opcua-machinevision.md").read_text(encoding="utf-8")
E10 = {1: "PRD_1", 2: "SBY_2", 3: "ENG_3", 4: "SDT_4", 5: "UDT_5", 6: "NST_6"}


def test_every_method_served_is_documented() -> None:
    for path in METHODS:
        assert re.search(rf"`{path[-1]}\b", DOC), path[-1]


def test_the_state_table_is_the_mapping() -> None:
    for state in VisionState:
        row = re.search(rf"^\| {state.value}\b[^|]* \| (\w+) \| ([^|]+) \| ([^|]+) \|$", DOC, re.M)
        assert row, state
        top, sub = STATE_PLACE[state]
        assert row.group(1) == top
        assert row.group(2).strip() == (sub or "(empty)")
        assert row.group(3).startswith(E10[SYSTEM_STATE[state]])


def test_every_refusal_code_and_setting_is_documented() -> None:
    from asyncua import ua

    names = {v: k for k, v in vars(ua.StatusCodes).items() if isinstance(v, int)}
    for status in REFUSAL_STATUS.values():
        assert f"`{names[status]}`" in DOC
    for key in MachineVisionConfig.model_fields:
        assert f"| `{key}` |" in DOC, key

"""docs/opcua.md says what the server does: every node it serves, and the command table."""

from __future__ import annotations

import re
from pathlib import Path

from cell.core.commands import Command, VisionState, allowed
from cell.service.opcua import VARIABLES

DOC = (Path(__file__).resolve().parents[1] / "docs" / "opcua.md").read_text(encoding="utf-8")


def test_every_variable_is_documented_with_its_type():
    rows = {}
    for line in DOC.splitlines():
        m = re.match(r"^\| (`\w+`(?:, `\w+`)*) \| (\w+)(\[\d*\])? \|", line)
        if m:
            for name in re.findall(r"`(\w+)`", m.group(1)):
                rows[name] = m.group(2)
    assert set(rows) == set(VARIABLES)
    for name, (vtype, _) in VARIABLES.items():
        assert rows[name] == vtype.name, name


def test_the_method_table_is_the_command_table():
    for state in VisionState:
        row = re.search(rf"^\| {state.value} \| (.*) \|$", DOC, re.M).group(1)
        documented = {c for c in Command if re.search(rf"\b{c.value}\b", row)}
        if state in (VisionState.SINGLE_EXECUTION, VisionState.CONTINUOUS_EXECUTION):
            assert documented == allowed(state, False) | allowed(state, True)
        else:
            assert documented == allowed(state, False) == allowed(state, True)

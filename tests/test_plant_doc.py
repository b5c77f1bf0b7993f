"""docs/plant.md lists every Sparkplug metric (name, type, unit) and every Prometheus metric the
code publishes, and nothing else: this test keeps the page and the code in step."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from cell.telemetry import metrics as M
from cell.web.metrics import CellMetrics
from tests.fake_service import FakeLineService

pytestmark = pytest.mark.timeout(30)
DOC = Path(__file__).resolve().parents[1] / "docs" / "plant.md"
TYPE_NAMES = {
    "Int64": "INT64",
    "Boolean": "BOOLEAN",
    "UInt64": "UINT64",
    "UInt32": "UINT32",
    "String": "STRING",
    "Double": "DOUBLE",
}


def table_after(heading: str) -> list[list[str]]:
    """The rows of the first table after a line starting with `heading` (header and rule left out)."""
    lines = DOC.read_text(encoding="utf-8").splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(heading))
    rows, seen = [], False
    for line in lines[start:]:
        if line.startswith("|"):
            seen = True
            rows.append([c.strip() for c in line.strip().strip("|").split("|")])
        elif seen:
            break
    return rows[2:]  # the header and its rule


@pytest.mark.parametrize(
    "heading, specs",
    [
        ("Node metrics", M.NODE),
        ("Device metrics", M.DEVICE),
        ("Command metrics", M.COMMANDS),
    ],
)
def test_every_sparkplug_metric_is_documented_with_its_type_and_unit(heading, specs):
    documented = [(r[0].strip("`"), TYPE_NAMES.get(r[1], r[1]), r[2]) for r in table_after(heading)]
    assert documented == [(s.name, s.dtype.name, s.unit) for s in specs]


def test_every_prometheus_metric_is_documented():
    service = FakeLineService()
    try:
        metrics = CellMetrics(service)
        published = {}
        for family in metrics.registry.collect():
            name = family.name + ("_total" if family.type == "counter" else "")
            published[name] = family.type.replace("stateset", "state set")
    finally:
        service.close()
    documented = {re.sub(r"\{.*\}", "", r[0].strip("`")): r[1] for r in table_after("| metric | type |")}
    assert documented == published

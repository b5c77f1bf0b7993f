"""The audit log: one valid JSON object per line, readable while the run is still going."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from cell.audit import AuditLog, read_events
from cell.summary import Summary, counts_from_log

pytestmark = pytest.mark.timeout(60)  # runs a subprocess


def test_each_event_is_one_flushed_json_line_with_state(tmp_path):
    path = tmp_path / "a.jsonl"
    log = AuditLog(path)
    log.event("frame", detections=[{"table_mm": np.array([1.5, 2.0]), "n": np.int64(3)}], t=(1, 2))
    log.state = "plan"
    log.event("target", robot_mm=(1.0, 2.0, 3.0), bad=float("nan"))
    lines = path.read_text().splitlines()  # before close: flushed per line
    assert len(lines) == 2
    first, second = (json.loads(line) for line in lines)
    assert first["detections"] == [{"table_mm": [1.5, 2.0], "n": 3}] and first["state"] == "idle"
    assert second["state"] == "plan" and second["bad"] is None and second["seq"] == 2
    log.close()


def test_a_killed_writer_leaves_a_readable_log(tmp_path):
    path = tmp_path / "a.jsonl"
    code = (
        "import os\nfrom cell.audit import AuditLog\n"
        f"log = AuditLog({str(path)!r})\n"
        "log.state = 'pick'\nlog.event('target', robot_mm=[1, 2, 3])\n"
        "log._file.write('{\"seq\": 2, \"kind\": \"ver')\nlog._file.flush()\nos._exit(9)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=False)
    events = read_events(path)
    assert [e["kind"] for e in events] == ["target"] and events[-1]["state"] == "pick"


def test_counts_from_log_match_a_summary():
    events = [
        {"kind": "target", "attempt": 1}, {"kind": "verify", "result": "missed", "cls": "nut"},
        {"kind": "target", "attempt": 2}, {"kind": "verify", "result": "picked", "cls": "nut"},
        {"kind": "unreachable"}, {"kind": "frame", "detections": [{"pick": False}, {"pick": True}]},
    ]
    s = Summary(picked={"nut": 1}, misses=1, retries=1, unreachable=1, attempts=2, unknown_left=1)
    assert counts_from_log(events) == s.counts()
    assert any("1 misses" in line for line in s.lines())

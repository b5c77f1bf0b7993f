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
        f"fd = os.open({str(path)!r}, os.O_WRONLY | os.O_APPEND)\n"  # the second line, torn by the kill
        'os.write(fd, b\'{"seq": 2, "kind": "ver\')\nos._exit(9)\n'
    )
    subprocess.run([sys.executable, "-c", code], check=False)
    events = read_events(path)
    assert [e["kind"] for e in events] == ["target"] and events[-1]["state"] == "pick"


def test_counts_from_log_match_a_summary():
    events = [
        {"kind": "target", "attempt": 1},
        {"kind": "verify", "result": "missed", "cls": "nut"},
        {"kind": "target", "attempt": 2},
        {"kind": "verify", "result": "picked", "cls": "nut"},
        {"kind": "unreachable"},
        {"kind": "frame", "detections": [{"pick": False}, {"pick": True}]},
    ]
    s = Summary(picked={"nut": 1}, misses=1, retries=1, unreachable=1, attempts=2, unknown_left=1)
    assert counts_from_log(events) == s.counts()
    lines = s.lines()
    assert "picked 1 nut; 1 miss, 1 retry, 0 failed, 1 unreachable, 1 unknown part left" in lines
    assert "2 pick attempts in" in lines[2]
    two = Summary(picked={"nut": 2, "bolt": 1}, misses=2, retries=2, unknown_left=2, attempts=5).lines()[1]
    assert two == "picked 1 bolt, 2 nuts; 2 misses, 2 retries, 0 failed, 0 unreachable, 2 unknown parts left"


def test_two_runs_started_in_the_same_second_write_two_logs(tmp_path):
    """Each run's log is created exclusively under its own name (time, pid): never shared."""
    code = (
        "import sys\nfrom pathlib import Path\nfrom cell.audit import AuditLog\n"
        "from cell.recordfile import unique_stem\n"
        f"log = AuditLog(f\"{{unique_stem(Path({str(tmp_path)!r}), 'run', ('.jsonl', '.log'))}}.jsonl\")\n"
        "for i in range(200):\n    log.event('frame', i=i)\n"
    )
    procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(2)]
    assert [p.wait(timeout=60) for p in procs] == [0, 0]
    logs = sorted(tmp_path.glob("run-*.jsonl"))
    assert len(logs) == 2
    for path in logs:
        assert [e["seq"] for e in read_events(path)] == list(range(1, 201))


def test_an_audit_log_never_opens_an_existing_file(tmp_path, monkeypatch):
    from datetime import datetime

    import pytest

    import cell.recordfile
    from cell.recordfile import unique_stem

    path = tmp_path / "a.jsonl"
    path.write_text("another run's\n")
    with pytest.raises(FileExistsError):
        AuditLog(path)

    class Frozen(datetime):  # both names asked for in the same second
        @classmethod
        def now(cls, tz=None):
            return datetime(2026, 1, 1, 12, 0, 0, tzinfo=tz)

    monkeypatch.setattr(cell.recordfile, "datetime", Frozen)
    first = unique_stem(tmp_path, "run", (".jsonl", ".log"))
    AuditLog(f"{first}.jsonl").close()
    second = unique_stem(tmp_path, "run", (".jsonl", ".log"))
    assert second.name == first.name + "-2"

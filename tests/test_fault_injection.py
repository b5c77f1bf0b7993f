"""The fault-injection matrix on the simulated cell, in-process, through the real drivers and
their emulators: a full disk at an audit write, a stop or pause signal at a point of the run.

Whatever fails, the run must end with the arm safe (gripper open, no part held, torque per
the arm's policy, the emulator's pty gone) and the documented exit code. The default suite
takes one write of every (event kind, state) the run produces, and the write right after
the gripper closed on both arms; `-m slow` sweeps every write of a whole run.
"""
from __future__ import annotations

import itertools
import os
import signal

import pytest

from cell.cli import main
from tests.faults import FullDiskAt, assert_arm_safe, audit_events, capture_sim, fast_config

KINDS = ("dynamixel", "serial")


def run_cell(tmp_path, kind: str, max_attempts: int | None = None) -> int:
    cfg = fast_config(tmp_path, kind, max_attempts)
    return main(["--config", str(cfg), "--log-dir", str(tmp_path / "logs")])


@pytest.fixture(scope="module")
def writes(tmp_path_factory):
    """(kind, state) of each audit write: of a normal run's first picks (cut short by a full
    disk at write 40) and of a run that faults after its first pick (run.max_attempts_total), per arm."""
    out = {}
    with pytest.MonkeyPatch.context() as mp:
        for kind in KINDS:
            d = tmp_path_factory.mktemp(f"ref-{kind}")
            FullDiskAt(40).install(mp)
            assert run_cell(d / "a", kind) == 3
            FullDiskAt(None).install(mp)
            assert run_cell(d / "b", kind, max_attempts=1) == 3
            out[kind] = {"normal": [(e["kind"], e["state"]) for e in audit_events(d / "a" / "logs")],
                         "fault": [(e["kind"], e["state"]) for e in audit_events(d / "b" / "logs")]}
    return out


def firsts(seq: list[tuple[str, str]]) -> dict[tuple[str, str], int]:
    """Write number (1-based) of the first write of each (kind, state)."""
    out = {}
    for n, pair in enumerate(seq, start=1):
        out.setdefault(pair, n)
    return out


# Which writes the default suite fails: every (kind, state) pair once, arms taking turns; the
# runs are chosen by name here and resolved against the reference runs in the test.
NORMAL_PAIRS = [("config", "idle"), ("run_start", "idle"), ("arm", "idle"), ("state", "idle"), ("arm", "home"),
                ("state", "home"), ("state", "capture"), ("frame", "locate"), ("state", "locate"),
                ("target", "plan"), ("state", "plan"), ("arm", "pick"), ("state", "pick"), ("arm", "place"),
                ("state", "place"), ("verify", "verify"), ("state", "verify")]
FAULT_PAIRS = [("fault", "plan"), ("safe_step", "plan"), ("state", "plan"), ("sim_truth", "fault"),
               ("summary", "fault"), ("run_end", "fault")]
CASES = ([("normal", pair, KINDS[i % 2]) for i, pair in enumerate(NORMAL_PAIRS)]
         + [("fault", pair, KINDS[i % 2]) for i, pair in enumerate(FAULT_PAIRS)]
         + [("normal", "after close_gripper", kind) for kind in KINDS])


def write_number(writes, kind: str, run: str, what) -> int:
    seq = writes[kind][run]
    if what == "after close_gripper":  # the case: the disk fills as the jaws hold a nut
        return seq.index(("arm", "pick"), 13) + 1 + 4  # approach, down, close, then the lift's write
    return firsts(seq[: -1 if run == "normal" else None])[tuple(what)]


@pytest.mark.parametrize("run,what,kind", CASES, ids=lambda v: "-".join(v) if isinstance(v, tuple) else str(v))
def test_a_full_disk_at_an_audit_write_leaves_the_arm_safe_and_exits_3(writes, run, what, kind, tmp_path,
                                                                        monkeypatch, capsys):
    n = write_number(writes, kind, run, what)
    disk = FullDiskAt(n).install(monkeypatch)
    sim = capture_sim(monkeypatch)
    assert run_cell(tmp_path, kind, max_attempts=1 if run == "fault" else None) == 3
    err = capsys.readouterr().err
    assert disk.failed_line is not None and '"seq":%d,' % n in disk.failed_line
    assert "write failed (No space left on device)" in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("run-cell run: ") and "exit 3" in last or "cannot write event 1 (config)" in last
    events = audit_events(tmp_path / "logs")
    assert [e["seq"] for e in events] == list(range(1, n))  # everything before the full disk kept, in order
    if sim.cell is None:  # the first write failed before any device was opened
        assert n == 1
        return
    assert_arm_safe(sim.cell, tmp_path / "logs")
    assert "the audit log is incomplete; the run's summary:" in err

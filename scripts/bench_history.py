"""The history store's costs: what it adds to the control thread, how many rows a second its
writer sustains, and `run-cell report` over a million picks.

1. Control thread: the bus with the audit log as its record (as in the service) emits a pick's
   events (target, the arm's commands, state changes, the verdict, a frame) with and without
   the history subscriber, alternating rounds; the emitting thread's own CPU time
   (time.thread_time) per pick, median over the rounds.
2. Writer: picks handed to the store as fast as they come; rows per second until written
   (wall) and per CPU second of the whole process.
3. Report: a SQLite store of 1,000,000 picks over one plant day (plus states and alarms), then
   `run-cell report --day` as a subprocess: its CPU time (user + system) and wall time; and
   build_report in-process (CPU time).

    .venv/bin/python scripts/bench_history.py [--rounds 7] [--picks 2000] [--report-picks 1000000]
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from cell.audit import AuditLog  # noqa: E402
from cell.core.eventbus import EventBus  # noqa: E402
from cell.core.events import ArmCommanded, Event, FrameLocated, FrameRef, PickVerified, StateChanged, TargetChosen  # noqa: E402
from cell.history.config import HistoryConfig  # noqa: E402
from cell.history.store import EVENT_TYPES, HistoryStore  # noqa: E402

JOB = "20261201-060000-beef"


def pick_events(n: int, image: np.ndarray) -> list[Event]:
    pid = f"{JOB}/{n}"
    common: dict[str, Any] = {
        "job_id": JOB,
        "track": n,
        "cls": "nut",
        "attempt": 1,
        "pixel": (100.0, 200.0),
        "table_mm": (10.0, 20.0),
    }
    out: list[Event] = [
        StateChanged(job_id=JOB, source="plan", target="pick", reason="next"),
        TargetChosen(
            **common,
            pick_id=pid,
            robot_mm=(-122.0, 60.0, 2.0),
            approach_z_mm=40.0,
            jaw_angle_deg=None,
            bin_robot_mm=(200.0, 60.0, 60.0),
            calibration_id="c0ffee",
        ),
    ]
    out += [ArmCommanded(job_id=JOB, command="move_to", args=(1.0, 2.0, 3.0)) for _ in range(6)]
    out += [StateChanged(job_id=JOB, source="pick", target="place", reason="gripped")]
    out.append(
        FrameLocated(job_id=JOB, frame=n, locate_ms=5.0, warnings=(), detections=(), ref=FrameRef(n, image, None, 0.0))
    )
    out.append(
        PickVerified(
            **common,
            pick_id=pid,
            result="picked",
            robot_mm=(-122.0, 60.0, 2.0),
            jaw_angle_deg=None,
            still_at_mm=(),
            calibration_id="c0ffee",
            cycle_ms=800.0,
            ref=FrameRef(n, image, None, 0.0),
        )
    )
    out += [StateChanged(job_id=JOB, source="verify", target="plan", reason="picked")]
    return out


def control_thread(rounds: int, picks: int) -> tuple[float, float]:
    image = np.zeros((540, 960, 3), np.uint8)
    with_us: list[float] = []
    without_us: list[float] = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for r in range(rounds):
            for history in (False, True):
                bus = EventBus()
                audit = AuditLog(tmp / f"audit-{r}-{history}.jsonl")
                bus.add_record(audit.record, owner=audit)
                store = None
                if history:
                    cfg = HistoryConfig(data_dir=tmp / f"data-{r}", cell_name="bench", images=False)
                    store = HistoryStore(cfg, tmp / "logs")
                    bus.subscribe("history", store.handle, kinds=EVENT_TYPES, maxsize=200_000)
                events = [pick_events(r * picks + n, image) for n in range(picks)]
                t0 = time.thread_time()
                for group in events:
                    for e in group:
                        bus.emit(e)
                dt = time.thread_time() - t0
                (with_us if history else without_us).append(1e6 * dt / picks)
                bus.close(60)
                if store is not None:
                    store.close(60)
                audit.close()
    return statistics.median(without_us), statistics.median(with_us)


def writer_rate(picks: int) -> tuple[float, float]:
    image = np.zeros((8, 8, 3), np.uint8)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = HistoryConfig(data_dir=Path(tmp), cell_name="bench", images=False)
        store = HistoryStore(cfg, Path(tmp) / "logs")
        verdicts = [g[-2] for g in (pick_events(n, image) for n in range(picks))]
        c0, t0 = time.process_time(), time.monotonic()
        for e in verdicts:
            store.handle(e)
        assert store.wait_idle(600)
        wall, cpu = time.monotonic() - t0, time.process_time() - c0
        store.close()
    return picks / wall, picks / cpu


def make_million(path: Path, n: int) -> None:
    import sqlite3

    from cell.history.db import open_sqlite, sqlite_time
    from cell.history.schema import migrate

    db = open_sqlite(path)
    migrate(db)
    db.close()
    conn = sqlite3.connect(path)
    start = datetime(2026, 12, 1, 6, 0, tzinfo=UTC)
    step = 86_400 / n
    outcomes = ["picked"] * 47 + ["missed", "missed", "failed"]
    rows = (
        (
            f"{JOB}/{i}",
            JOB,
            "bench",
            sqlite_time(start + timedelta(seconds=i * step)),
            "bolt" if i % 2 else "nut",
            i,
            1,
            100.0,
            200.0,
            10.0,
            20.0,
            -122.0,
            60.0,
            2.0,
            None,
            "c0ffee",
            outcomes[i % 50],
            800.0,
            None,
        )
        for i in range(n)
    )
    conn.executemany(f"INSERT INTO picks VALUES ({', '.join('?' * 19)})", rows)
    states = [
        (f"s{i}", "bench", sqlite_time(start + timedelta(minutes=10 * i)), "", s, "bench")
        for i, s in enumerate(["Ready", "ContinuousExecution", "Error", "Ready", "ContinuousExecution"] * 29)
    ]
    conn.executemany("INSERT INTO states VALUES (?, ?, ?, ?, ?, ?)", states)
    alarms = [
        (f"a{i}", "bench", f"A{i}", "fault", sqlite_time(start + timedelta(minutes=10 * (5 * i + 2))), None)
        + (f"reason {i % 3}", "hint", "job", JOB, "screen", "anna", "", None)
        for i in range(29)
    ]
    conn.executemany(f"INSERT INTO alarms VALUES ({', '.join('?' * 14)})", alarms)
    conn.commit()
    conn.close()


def report_time(n: int) -> tuple[float, float, float]:
    from cell.history.query import open_reader
    from cell.history.report import build_report
    from cell.shifts import ShiftCalendar

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "history.sqlite"
        t0 = time.monotonic()
        make_million(path, n)
        print(f"  ({n} picks written in {time.monotonic() - t0:.0f} s)", flush=True)
        url = f"sqlite:///{path}"
        (Path(tmp) / "cell.toml").write_text(f'[history]\nurl = "{url}"\ncell_name = "bench"\n')
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.monotonic()
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "cell.cli",
                "report",
                "--config",
                str(Path(tmp) / "cell.toml"),
                "--day",
                "2026-12-01",
            ],
            capture_output=True,
            text=True,
            cwd=REPO,
        )
        wall = time.monotonic() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if out.returncode != 0:
            raise SystemExit(out.stderr)
        print("  " + "\n  ".join(out.stdout.splitlines()[:5]))
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        from cell.config import CellConfig

        cfg = CellConfig()
        cfg.history.url, cfg.history.cell_name = url, "bench"
        start, end = ShiftCalendar(cfg.shifts).day(datetime(2026, 12, 1).date())
        reader = open_reader(cfg)
        c0 = time.process_time()
        build_report(reader, "bench", start, end)
        inproc = time.process_time() - c0
        reader.close()
    return cpu, wall, inproc


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--picks", type=int, default=2000)
    ap.add_argument("--report-picks", type=int, default=1_000_000)
    args = ap.parse_args()
    without, with_ = control_thread(args.rounds, args.picks)
    print(
        f"control thread, CPU per pick (13 events: audit line each): without history {without:.1f} us, "
        f"with {with_:.1f} us ({with_ - without:+.1f} us, {100 * (with_ / without - 1):+.1f} %)",
        flush=True,
    )
    wall_rate, cpu_rate = writer_rate(20 * args.picks)
    print(f"writer: {wall_rate:.0f} picks/s of wall time, {cpu_rate:.0f} picks per CPU second", flush=True)
    cpu, wall, inproc = report_time(args.report_picks)
    print(
        f"run-cell report --day over {args.report_picks} picks: {cpu:.2f} s CPU ({wall:.2f} s wall) for the "
        f"whole command; build_report alone {inproc:.2f} s CPU"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

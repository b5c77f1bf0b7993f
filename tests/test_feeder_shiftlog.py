"""The simulated feeder (seeded, free spots only, never overlapping, tidy) and the shift's
rolling audit log (whole lines, by day and size, read back as one shift)."""

from __future__ import annotations

import json

import pytest

from cell.core.events import PartFailed, PartUnreachable, ServiceStarted
from cell.run_config import FeederConfig
from cell.service.counters import ShiftCounts
from cell.service.shiftlog import ShiftLog, read_shift, shift_files
from cell.sim.cell import MIN_GAP_MM, outline_gap_mm
from cell.sim.feeder import Feeder
from cell.sim.world import Bin, Truth, World
from cell.summary import counts_from_log


def world() -> World:
    return World(
        [], Truth(0.0, -132.0, 40.0, 0.0), [Bin("bolt", (-200.0, 60.0), 40.0), Bin("nut", (200.0, 60.0), 40.0)]
    )


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_parts_arrive_at_the_rate_on_free_spots_inside_the_area():
    w, clock = world(), Clock()
    cfg = FeederConfig(parts_per_minute=30, max_on_table=25, seed=3)
    feeder = Feeder(w, cfg, clock)
    clock.t = 40.0  # 20 parts due
    feeder.tick()
    specs = [p.spec for p in w.on_table()]
    assert feeder.dropped + feeder.skipped == 20 and feeder.dropped >= 18
    kinds = {s.kind for s in specs}
    assert kinds <= {"bolt", "nut", "washer"} and len(kinds) >= 2
    x0, y0, x1, y1 = cfg.area_mm
    for i, a in enumerate(specs):
        o = a.top_view_outline_mm()
        assert x0 <= o[:, 0].min() and o[:, 0].max() <= x1 and y0 <= o[:, 1].min() and o[:, 1].max() <= y1
        for b in specs[i + 1 :]:
            assert outline_gap_mm(a, b) >= MIN_GAP_MM
    clock.t = 120.0  # 40 more due, but at most 25 on the table
    feeder.tick()
    assert len(w.on_table()) <= 25 and feeder.skipped >= 15


def test_the_same_seed_gives_the_same_shift():
    runs = []
    for _ in range(2):
        w, clock = world(), Clock()
        feeder = Feeder(w, FeederConfig(parts_per_minute=12, seed=7), clock)
        clock.t = 30.0
        feeder.tick()
        runs.append([(p.spec.kind, p.spec.x_mm, p.spec.y_mm) for p in w.on_table()])
    assert runs[0] == runs[1] and len(runs[0]) == 6


def test_binned_parts_leave_the_world_and_vacated_spots_stay_free():
    w, clock = world(), Clock()
    feeder = Feeder(w, FeederConfig(parts_per_minute=60, seed=1, washer_share=0.0), clock)
    clock.t = 5.0
    feeder.tick()
    taken = w.on_table()[0]
    taken.where = "bin:nut"
    spot = (taken.spec.x_mm, taken.spec.y_mm)
    clock.t = 60.0
    feeder.tick()
    assert taken not in w.parts and sum(feeder.binned.values()) == 1
    for p in w.on_table():
        assert min(((x - spot[0]) ** 2 + (y - spot[1]) ** 2) ** 0.5 for x, y in p.spec.top_view_outline_mm()) >= 12.0


def test_parts_left_too_long_are_cleared():
    w, clock = world(), Clock()
    feeder = Feeder(w, FeederConfig(parts_per_minute=6, clear_after_s=30.0), clock)
    clock.t = 20.0
    feeder.tick()
    assert len(w.on_table()) == 2
    clock.t = 55.0
    feeder.tick()  # the two from t = 0-20 s are past 30 s; three new ones arrived
    assert feeder.cleared == 2 and len(w.on_table()) == 3


def test_the_shift_log_rolls_by_size_between_whole_lines(tmp_path):
    log = ShiftLog(tmp_path, max_bytes=4096, day=lambda: "20261201")
    for i in range(200):
        log.record(PartUnreachable(track=i, cls="nut", table_mm=(1.0, 2.0), reason="x" * (i % 50)))
    log.close()
    files = shift_files(tmp_path, "20261201")
    assert len(files) > 5
    for f in files:
        text = f.read_text()
        assert text.endswith("\n") and all(json.loads(line) for line in text.splitlines())
        assert f.stat().st_size < 4096 + 400
    events = read_shift(tmp_path, "20261201")
    assert [e["track"] for e in events] == list(range(200))


def test_the_shift_log_rolls_at_a_new_day_and_a_restart_takes_the_next_file(tmp_path):
    day = {"d": "20261201"}
    log = ShiftLog(tmp_path, max_bytes=10**6, day=lambda: day["d"])
    log.record(ServiceStarted(counters={}, calibration="a", capture_interval_s=1.0))
    day["d"] = "20261202"
    log.record(ServiceStarted(counters={}, calibration="b", capture_interval_s=1.0))
    log.close()
    again = ShiftLog(tmp_path, max_bytes=10**6, day=lambda: day["d"])
    again.record(ServiceStarted(counters={}, calibration="c", capture_interval_s=1.0))
    again.close()
    assert [e["calibration"] for e in read_shift(tmp_path, "20261201")] == ["a"]
    assert [e["calibration"] for e in read_shift(tmp_path, "20261202")] == ["b", "c"]
    assert [f.name for f in shift_files(tmp_path, "20261202")] == ["cell-20261202-000.jsonl", "cell-20261202-001.jsonl"]


def test_shift_counts_agree_with_the_summary_recount():
    events = [
        {"kind": "target", "attempt": 1},
        {"kind": "verify", "result": "missed", "cls": "bolt"},
        {"kind": "target", "attempt": 2},
        {"kind": "verify", "result": "picked", "cls": "bolt"},
        {"kind": "target", "attempt": 1},
        {"kind": "verify", "result": "picked", "cls": "nut"},
        {"kind": "unreachable"},
        {"kind": "failed"},
        {"kind": "frame", "detections": [{"pick": False}, {"pick": True}]},
    ]
    c = ShiftCounts.from_events(events)
    ref = counts_from_log(events)
    assert (c.picked, c.misses, c.retries, c.failed, c.unreachable, c.unknown_left, c.attempts) == (
        ref["picked"],
        ref["misses"],
        ref["retries"],
        ref["failed"],
        ref["unreachable"],
        ref["unknown_left"],
        ref["attempts"],
    )
    assert c.counters().picked_of("bolt") == 1 and c.counters().retries == 1


def test_a_torn_last_line_is_skipped_when_the_shift_is_read_back(tmp_path):
    log = ShiftLog(tmp_path, max_bytes=10**6, day=lambda: "20261201")
    log.record(PartFailed(track=1, cls="nut", attempts=3))
    log.close()
    with open(shift_files(tmp_path, "20261201")[-1], "a") as f:
        f.write('{"seq":2,"kind":"verify","result":"pick')  # the writer killed mid-line
    assert [e["kind"] for e in read_shift(tmp_path, "20261201")] == ["failed"]
    again = ShiftLog(tmp_path, max_bytes=10**6, day=lambda: "20261201")  # the restarted service: a new file
    again.record(ServiceStarted(counters={}, calibration="c", capture_interval_s=1.0))
    again.close()
    assert [e["kind"] for e in read_shift(tmp_path, "20261201")] == ["failed", "service_start"]


def test_a_day_may_have_more_than_a_thousand_files(tmp_path):
    for n in range(1000):
        (tmp_path / f"cell-20261201-{n:03d}.jsonl").write_text("")
    log = ShiftLog(tmp_path, max_bytes=10**6, day=lambda: "20261201")
    log.record(PartFailed(track=1, cls="nut", attempts=3))
    log.close()
    files = shift_files(tmp_path, "20261201")
    assert files[-1].name == "cell-20261201-1000.jsonl" and len(files) == 1001
    again = ShiftLog(tmp_path, max_bytes=10**6, day=lambda: "20261201")  # and a restart after it
    again.record(PartFailed(track=2, cls="nut", attempts=3))
    again.close()
    assert shift_files(tmp_path, "20261201")[-1].name == "cell-20261201-1001.jsonl"
    assert [e["track"] for e in read_shift(tmp_path, "20261201")] == [1, 2]


def test_after_a_failed_write_the_next_event_goes_to_a_new_file_or_raises(tmp_path, monkeypatch):
    import errno
    import os

    from cell.audit import AuditWriteFailed
    from cell.recordfile import RecordFile

    full = {"on": False}

    class MaybeFull(RecordFile):
        def _write(self, data):
            if full["on"]:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return super()._write(data)

    monkeypatch.setattr("cell.audit.RecordFile", MaybeFull)
    log = ShiftLog(tmp_path, max_bytes=10**6, day=lambda: "20261201")
    log.record(PartFailed(track=1, cls="nut", attempts=3))
    full["on"] = True
    with pytest.raises(AuditWriteFailed, match="No space left on device"):
        log.record(PartFailed(track=2, cls="nut", attempts=3))
    with pytest.raises(AuditWriteFailed):  # never silently dropped while not making safe
        log.ensure_writable() or log.record(PartFailed(track=3, cls="nut", attempts=3))
    full["on"] = False  # space freed: the next event opens the day's next file
    log.record(PartFailed(track=4, cls="nut", attempts=3))
    log.close()
    assert [e["track"] for e in read_shift(tmp_path, "20261201")] == [1, 4]

"""Continuous mode: WAIT instead of DONE, parts that appear get picked, `finish` ends the job
at a safe point with the arm homed (not released), and a shift's tracks do not pile up."""

from __future__ import annotations

import threading
import time

import pytest

from cell.audit import AuditLog
from cell.planning import Planner
from cell.run_config import RunConfig
from cell.runner import Runner
from cell.signals import Controls
from cell.statemachine import State
from tests.doubles import PLANNING, TRUE_FRAME, FakeArm, FakeCamera, FakeTable, fake_locator

pytestmark = pytest.mark.timeout(60)  # the runner in a thread: a stuck wait must not hang the suite

ONE_NUT = [("nut", 20.0, 30.0, None)]


def continuous_runner(tmp_path, parts=ONE_NUT, interval_s=0.05, run: RunConfig | None = None):
    table = FakeTable(parts)
    arm, camera, controls = FakeArm(table), FakeCamera(), Controls()
    runner = Runner(
        camera,
        arm,
        fake_locator(table),
        Planner(PLANNING, TRUE_FRAME),
        run or RunConfig(),
        AuditLog(tmp_path / "audit.jsonl"),
        controls,
        continuous_interval_s=interval_s,
    )
    return runner, table, arm, camera, controls


def run_in_thread(runner) -> threading.Thread:
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    return t


def wait_for(cond, timeout_s=5.0):
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.01)


def test_empty_table_waits_then_picks_what_appears_and_stop_parks_the_arm(tmp_path):
    runner, table, arm, camera, controls = continuous_runner(tmp_path)
    thread = run_in_thread(runner)
    wait_for(lambda: runner.sm.state == State.WAIT and table.bins == [1])
    table.parts[7] = ("bolt", 100.0, 60.0, 30.0)  # a part arrives
    wait_for(lambda: 7 in table.bins)
    controls.request(controls.finish)
    thread.join(5)
    assert not thread.is_alive() and runner.sm.state == State.STOPPED
    assert runner.summary.picked == {"nut": 1, "bolt": 1}
    names = [c[0] for c in arm.calls]
    assert names[-2:] == ["home", "disconnect"] and "stop" not in names  # homed, torque kept: ready for the next job
    assert State.DONE not in [t.target for t in runner.sm.history]


def test_waiting_does_not_busy_loop_or_move_the_arm(tmp_path):
    """Each WAIT is one blocking wait of the capture interval (no busy loop), then one frame; the
    arm is not moved meanwhile. Counted, not timed: the test lets each wait end when it says so."""
    runner, table, arm, camera, controls = continuous_runner(tmp_path, parts=[], interval_s=30.0)
    waits, ends = [], threading.Semaphore(0)

    class CountedWake(threading.Event):
        def wait(self, timeout=None):
            waits.append(timeout)
            ends.acquire()  # the interval elapses when the test says so
            return False

    controls.wake = CountedWake()
    thread = run_in_thread(runner)
    wait_for(lambda: len(waits) == 1)
    frames, calls = camera.frames, len(arm.calls)
    for n in range(2, 7):
        ends.release()
        wait_for(lambda: len(waits) == n)
    assert camera.frames - frames == 5  # one frame per wait, nothing in between
    assert set(waits) == {30.0}  # each wait blocks for the whole interval
    assert [c for c in arm.calls[calls:] if c[0] != "status"] == []
    controls.request(controls.stop)
    ends.release()
    thread.join(5)
    assert runner.sm.state == State.STOPPED


def test_a_request_cuts_the_wait_short(tmp_path):
    # The wait is an hour: a job that ends at all after the request was woken by it, whatever the machine's load.
    runner, table, arm, camera, controls = continuous_runner(tmp_path, parts=[], interval_s=3600.0)
    thread = run_in_thread(runner)
    wait_for(lambda: runner.sm.state == State.WAIT)
    controls.request(controls.finish)
    thread.join(60)
    assert not thread.is_alive() and runner.sm.state == State.STOPPED


def test_halt_while_waiting_releases_the_arm(tmp_path):
    runner, table, arm, camera, controls = continuous_runner(tmp_path, parts=[])
    thread = run_in_thread(runner)
    wait_for(lambda: runner.sm.state == State.WAIT)
    controls.request(controls.stop)
    thread.join(5)
    assert [c[0] for c in arm.calls[-3:]] == ["home", "stop", "disconnect"]


def test_finish_during_a_pick_waits_for_its_verification(tmp_path):
    runner, table, arm, camera, controls = continuous_runner(tmp_path)
    runner.sm.listeners.append(lambda t: controls.request(controls.finish) if t.target == State.PICK else None)
    runner.run()
    targets = [t.target for t in runner.sm.history]
    assert targets[-3:] == [State.VERIFY, State.PLAN, State.STOPPED]
    assert runner.summary.picked == {"nut": 1} and table.bins == [1]


def test_finish_while_paused_ends_without_releasing(tmp_path):
    runner, table, arm, camera, controls = continuous_runner(tmp_path, parts=[])
    thread = run_in_thread(runner)
    wait_for(lambda: runner.sm.state == State.WAIT)
    controls.request(controls.pause)
    wait_for(lambda: runner.sm.state == State.PAUSED)
    controls.request(controls.finish)
    thread.join(5)
    assert [t.target for t in runner.sm.history][-2:] == [State.PAUSED, State.STOPPED]
    assert "stop" not in [c[0] for c in arm.calls]


def test_a_shift_forgets_parts_gone_from_the_table(tmp_path):
    runner, table, arm, camera, controls = continuous_runner(tmp_path, parts=[], interval_s=0.01)
    thread = run_in_thread(runner)
    for i in range(30):
        table.parts[100 + i] = ("nut", 20.0 + i % 5 * 30, 30.0, None)
        wait_for(lambda: 100 + i in table.bins)
    controls.request(controls.finish)
    thread.join(5)
    assert runner.summary.picked == {"nut": 30}
    assert len(runner.tracker.tracks) <= 1


def test_the_attempt_limit_counts_from_the_last_pick(tmp_path):
    runner, table, arm, camera, controls = continuous_runner(
        tmp_path, parts=[], interval_s=0.01, run=RunConfig(max_attempts_total=3)
    )
    thread = run_in_thread(runner)
    for i in range(6):  # more picks than the limit, each one successful
        table.parts[100 + i] = ("nut", 50.0, 30.0 + 20 * i, None)
        wait_for(lambda: 100 + i in table.bins)
    controls.request(controls.finish)
    thread.join(5)
    assert runner.sm.state == State.STOPPED and runner.summary.attempts == 6


def test_a_shift_keeps_a_bounded_transition_history(tmp_path):
    runner, table, arm, camera, controls = continuous_runner(tmp_path, parts=[], interval_s=0.0005)
    thread = run_in_thread(runner)
    wait_for(lambda: camera.frames > 400)  # > 1200 transitions: capture, locate, plan, wait
    controls.request(controls.finish)
    thread.join(5)
    assert len(runner.sm.history) == 1000 and runner.sm.history[-1].target == State.STOPPED


def test_endless_misses_still_hit_the_safety_limit(tmp_path):
    from cell.planning import TableToRobot

    table = FakeTable([("nut", 20.0, 30.0, None)])
    shifted = TableToRobot(0.0, TRUE_FRAME.tx_mm - 3.0, TRUE_FRAME.ty_mm, 0.0)  # every grip misses
    arm, camera = FakeArm(table, shifted), FakeCamera()
    runner = Runner(
        camera,
        arm,
        fake_locator(table),
        Planner(PLANNING, TRUE_FRAME),
        RunConfig(max_retries=10, max_attempts_total=4),
        AuditLog(tmp_path / "audit.jsonl"),
        Controls(),
        continuous_interval_s=0.01,
    )
    summary = runner.run()
    assert runner.sm.state == State.FAULT and summary.attempts == 4
    assert "4 pick attempts since the last pick" in summary.reason

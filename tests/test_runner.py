"""The runner with the fakes above the driver layer (tests/doubles.py): a fake table,
camera, locator and arm; misses come from geometry as in the simulated cell."""

from __future__ import annotations

import math

import pytest

from cell.audit import AuditLog, read_events
from cell.planning import Planner, TableToRobot
from cell.run_config import RunConfig
from cell.runner import EXIT_DONE, EXIT_FAULT, EXIT_INCOMPLETE, EXIT_STOPPED, Controls, Runner
from cell.statemachine import TERMINAL, State
from cell.summary import counts_from_log
from cell.vision.types import LocateResult
from tests.doubles import PLANNING, TRUE_FRAME, FakeArm, FakeCamera, FakeTable, fake_locator

PARTS = [
    ("nut", 20.0, 30.0, None),
    ("bolt", 100.0, 60.0, 30.0),
    ("nut", 200.0, 120.0, None),
    ("unknown", 150.0, 150.0, None),
]


def make_runner(
    tmp_path,
    parts=PARTS,
    truth=TRUE_FRAME,
    arm_fail=None,
    arm_restart=None,
    camera_fail=None,
    locate_fail=None,
    run=None,
    controls=None,
    expect_motion=True,
):
    table = FakeTable(parts)
    arm = FakeArm(table, truth, arm_fail, arm_restart)
    camera = FakeCamera(camera_fail)
    audit = AuditLog(tmp_path / "audit.jsonl")
    runner = Runner(
        camera,
        arm,
        fake_locator(table, locate_fail),
        Planner(PLANNING, TRUE_FRAME),
        run or RunConfig(),
        audit,
        controls,
        expect_motion,
    )
    return runner, table, arm, audit


def test_clears_the_table_and_leaves_unknown_parts(tmp_path):
    runner, table, arm, audit = make_runner(tmp_path)
    summary = runner.run()
    assert runner.sm.state == State.DONE and summary.exit_code == EXIT_DONE
    assert summary.picked == {"nut": 2, "bolt": 1}
    assert [cls for cls, *_ in table.parts.values()] == ["unknown"]
    assert sorted(table.bins) == [1, 2, 3]
    assert summary.unknown_left == 1
    states = [t.target for t in runner.sm.history]
    assert states[:6] == [State.HOME, State.CAPTURE, State.LOCATE, State.PLAN, State.PICK, State.PLACE]
    assert states[6:9] == [State.CAPTURE, State.LOCATE, State.VERIFY]
    audit.close()
    events = read_events(audit.path)
    assert counts_from_log(events) == summary.counts()
    assert events[-1]["kind"] == "run_end" and events[-1]["state"] == "done"
    assert arm.calls[-1] == ("disconnect",) and not runner.camera.is_connected


def test_wrong_offset_misses_retries_then_fails_and_ends(tmp_path):
    shifted = TableToRobot(0.0, TRUE_FRAME.tx_mm - 3.0, TRUE_FRAME.ty_mm, 0.0)  # the cell's offset is 3 mm off
    runner, table, arm, audit = make_runner(tmp_path, truth=shifted, run=RunConfig(max_retries=2))
    summary = runner.run()
    assert runner.sm.state == State.DONE
    assert summary.exit_code == EXIT_INCOMPLETE
    assert summary.failed == 3 and summary.picked == {}
    assert summary.attempts == 9 and summary.misses == 9 and summary.retries == 6
    audit.close()
    assert counts_from_log(read_events(audit.path)) == summary.counts()


def test_unreachable_part_is_refused_before_motion(tmp_path):
    far = [("nut", 20.0, 30.0, None), ("nut", 900.0, 30.0, None)]
    runner, table, arm, audit = make_runner(tmp_path, parts=far)
    summary = runner.run()
    assert summary.unreachable == 1 and summary.picked == {"nut": 1}
    assert summary.exit_code == EXIT_INCOMPLETE
    assert all(abs(c[1] - (900.0 + TRUE_FRAME.tx_mm)) > 1 for c in arm.calls if c[0] == "move_to")


def test_rehearsal_without_motion_plans_each_part_once(tmp_path):
    class StillArm(FakeArm):
        def close_gripper(self):
            self._record("close_gripper")

    table = FakeTable(PARTS)
    audit = AuditLog(tmp_path / "a.jsonl")
    runner = Runner(
        FakeCamera(),
        StillArm(table),
        fake_locator(table),
        Planner(PLANNING, TRUE_FRAME),
        RunConfig(),
        audit,
        expect_motion=False,
    )
    summary = runner.run()
    assert summary.rehearsed == 3 and summary.attempts == 3 and summary.exit_code == EXIT_DONE


def test_a_4_axis_arm_rehearses_a_bolt_square_to_its_base_and_its_bin_moves(tmp_path):
    """The jaw angle is checked where the jaws turn (at the part), not over the bin: the
    place moves send no angle, and a 4-axis arm's jaws point wherever its base does there."""
    from drivers.arm.config import ArmConfig
    from drivers.arm.mock import MockArm

    robot_xy = (100.0, 150.0)
    base_deg = math.degrees(math.atan2(robot_xy[1], robot_xy[0] - 12.0))  # yaw axis at x = 12 mm
    ((x, y),) = TRUE_FRAME.to_table([robot_xy])
    table = FakeTable([("bolt", float(x), float(y), base_deg - 90.0)])  # jaws close across the axis
    audit = AuditLog(tmp_path / "a.jsonl")
    planning = PLANNING.model_copy(
        update={"bolt": PLANNING.bolt.model_copy(update={"bin_robot_mm": (60.0, -200.0, 60.0)})}
    )
    runner = Runner(
        FakeCamera(),
        MockArm(ArmConfig(kind="mock", mock_of="dynamixel")),
        fake_locator(table),
        Planner(planning, TRUE_FRAME),
        RunConfig(),
        audit,
        expect_motion=False,
    )
    summary = runner.run()
    assert summary.unreachable == 0 and summary.rehearsed == 1 and summary.exit_code == EXIT_DONE


# ---- faults raised in each state ---------------------------------------------------------
FAULTS = {
    State.IDLE: dict(arm_fail={"connect": 1}),
    State.HOME: dict(arm_fail={"home": 1}),
    State.CAPTURE: dict(camera_fail=1),
    State.LOCATE: dict(locate_fail=1),
    State.PLAN: dict(arm_fail={"status": 1}),
    State.PICK: dict(arm_fail={"close_gripper": 1}),
    State.PLACE: dict(arm_fail={"open_gripper": 2}),  # 1st open is at home
}


@pytest.mark.parametrize("state", list(FAULTS), ids=lambda s: s.name)
def test_fault_in_each_state_ends_in_fault_with_reason(tmp_path, state):
    runner, table, arm, audit = make_runner(tmp_path, **FAULTS[state])
    summary = runner.run()
    assert runner.sm.state == State.FAULT and summary.exit_code == EXIT_FAULT
    assert "injected" in summary.reason or "no frame" in summary.reason
    assert runner.sm.history[-1].source == state
    audit.close()
    events = read_events(audit.path)
    assert [e for e in events if e["kind"] == "fault"][0]["reason"] == summary.reason
    assert events[-1]["kind"] == "run_end" and events[-1]["state"] == "fault"


def test_fault_while_holding_opens_the_gripper_over_the_bin(tmp_path):
    runner, table, arm, audit = make_runner(tmp_path, arm_fail={"move_to": 4})  # moving to the bin
    runner.run()
    assert runner.sm.state == State.FAULT
    i = max(i for i, c in enumerate(arm.calls) if c[0] == "open_gripper")
    bins_xy = [PLANNING.nut.bin_robot_mm[:2], PLANNING.bolt.bin_robot_mm[:2]]
    assert arm.calls[i - 1][0] == "move_to" and arm.calls[i - 1][1:3] in bins_xy
    assert len(table.bins) == 1 and table.held is None
    assert ("stop",) in arm.calls


def test_a_controller_restart_faults_and_the_safe_stop_moves_nothing_not_even_home(tmp_path):
    runner, table, arm, audit = make_runner(tmp_path, arm_restart={"close_gripper": 2})
    summary = runner.run()
    assert runner.sm.state == State.FAULT and summary.exit_code == EXIT_FAULT
    assert summary.reason.startswith("PositionLost: controller restarted: position lost; home before moving")
    audit.close()
    events = read_events(audit.path)
    steps = {e["step"]: e for e in events if e["kind"] == "safe_step"}
    assert "not homed: the arm's controller restarted" in steps["home"]["error"]
    assert steps["release torque"]["ok"] and not steps["finish motion"]["ok"]
    restart = [i for i, c in enumerate(arm.calls) if c[0] == "close_gripper"][1]
    assert [c[0] for c in arm.calls[restart + 1 :]] == ["stop", "disconnect"]
    assert arm.position_lost  # for the operator to home or unlock


def test_a_blind_frame_is_a_fault_not_a_clear_table_or_a_verified_pick(tmp_path):
    runner, table, arm, audit = make_runner(tmp_path)
    seen = runner.locate

    def blind_after_first_pick(frame):
        result = seen(frame)
        if table.bins or table.held is not None:
            return LocateResult([], result.image_size, 0.1, ["frame too dark (backlight level 3 < 40)"])
        return result

    runner.locate = blind_after_first_pick
    summary = runner.run()
    assert runner.sm.state == State.FAULT and "frame too dark" in summary.reason
    assert runner.sm.history[-1].source == State.LOCATE and summary.picked == {}


def test_plan_fault_from_the_safety_limit(tmp_path):
    shifted = TableToRobot(0.0, TRUE_FRAME.tx_mm - 3.0, TRUE_FRAME.ty_mm, 0.0)
    runner, *_ = make_runner(tmp_path, truth=shifted, run=RunConfig(max_retries=5, max_attempts_total=4))
    summary = runner.run()
    assert runner.sm.history[-1].source == State.PLAN and runner.sm.state == State.FAULT
    assert summary.attempts == 4


# ---- a stop request in each state --------------------------------------------------------
@pytest.mark.parametrize(
    "state", [s for s in State if s not in TERMINAL and s not in (State.PAUSED, State.WAIT)], ids=lambda s: s.name
)
def test_stop_request_in_each_state_makes_the_arm_safe(tmp_path, state):
    controls = Controls()
    runner, table, arm, audit = make_runner(tmp_path, controls=controls)
    if state == State.IDLE:
        controls.stop.set()
    else:
        runner.sm.listeners.append(lambda t: controls.stop.set() if t.target == state else None)
    summary = runner.run()
    assert runner.sm.state == State.STOPPED and summary.exit_code == EXIT_STOPPED
    assert runner.sm.history[-1].source == state
    if state != State.IDLE:
        tail = [c[0] for c in arm.calls[-4:]]
        assert tail[-3:] == ["home", "stop", "disconnect"]
    assert table.held is None


def test_stop_request_while_paused(tmp_path):
    controls = Controls()
    controls.pause.set()
    runner, *_ = make_runner(tmp_path, controls=controls)
    runner.sm.listeners.append(lambda t: controls.stop.set() if t.target == State.PAUSED else None)
    runner.run()
    assert [t.target for t in runner.sm.history][-2:] == [State.PAUSED, State.STOPPED]


def test_pause_then_resume_takes_a_fresh_frame(tmp_path):
    controls = Controls()
    runner, *_ = make_runner(tmp_path, controls=controls)

    def on(t):
        if t.target == State.PLAN and not any(h.target == State.PAUSED for h in runner.sm.history):
            controls.pause.set()
        if t.target == State.PAUSED:
            controls.pause.clear()

    runner.sm.listeners.append(on)
    summary = runner.run()
    targets = [t.target for t in runner.sm.history]
    i = targets.index(State.PAUSED)
    assert targets[i + 1] == State.CAPTURE and summary.outcome == "done"


def test_ctrl_c_during_pick_opens_at_bin_homes_and_releases(tmp_path):
    runner, table, arm, audit = make_runner(tmp_path)
    real_move = arm.move_to

    def interrupted(*a, **k):
        real_move(*a, **k)
        if table.held is not None and not any(c[0] == "wait_until_idle" for c in arm.calls):
            raise KeyboardInterrupt

    arm.move_to = interrupted
    summary = runner.run()
    assert runner.sm.state == State.STOPPED and summary.reason == "Ctrl-C"
    assert table.held is None and len(table.bins) == 1
    assert [c[0] for c in arm.calls[-3:]] == ["home", "stop", "disconnect"]
    audit.close()
    assert read_events(audit.path)[-1]["state"] == "stopped"


def test_fault_in_verify_ends_in_fault_with_the_arm_safe(tmp_path):
    """Verify's own failure (here: the audit log cannot be written, disk full) is a Fault, not a crash."""
    runner, table, arm, audit = make_runner(tmp_path)
    write = audit.event

    def event(kind, **fields):
        if kind == "verify":
            raise OSError(28, "No space left on device (injected)")
        return write(kind, **fields)

    audit.event = event
    summary = runner.run()
    assert runner.sm.state == State.FAULT and summary.exit_code == EXIT_FAULT
    assert runner.sm.history[-1].source == State.VERIFY
    assert "No space left on device" in summary.reason
    assert ("stop",) in arm.calls and table.held is None


# ---- the audit log fails (a full disk): at every write of a whole run ------------------------------
def _run_writes(tmp_path) -> int:
    runner, *_ = make_runner(tmp_path / "ref")
    runner.run()
    runner.events.close()
    return len(read_events(runner.events.path))


def test_a_full_disk_at_every_audit_write_faults_with_the_arm_safe(tmp_path, monkeypatch):
    """The runner alone (fakes above the drivers), so every write of a whole run is cheap to fail."""
    import errno
    import os

    from cell.recordfile import RecordFile

    (tmp_path / "ref").mkdir()
    total = _run_writes(tmp_path)
    assert total > 50
    for n in range(1, total + 1):
        writes = {"n": 0}

        class Full(RecordFile):
            def _write(self, data):
                writes["n"] += 1
                if writes["n"] >= n:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                return super()._write(data)

        monkeypatch.setattr("cell.audit.RecordFile", Full)
        (tmp_path / str(n)).mkdir()
        runner, table, arm, audit = make_runner(tmp_path / str(n))
        summary = runner.run()
        audit.close()
        assert audit.failed is not None, n
        assert table.held is None, n
        names = [c[0] for c in arm.calls]
        assert names[-1] == "disconnect", n
        if summary.outcome == "fault":  # failed during the loop: made safe, torque released
            assert summary.exit_code == EXIT_FAULT and "No space left on device" in summary.reason
            assert "connect" not in names or names[-2] == "stop", (n, names[-4:])
        else:  # failed while ending a finished run: the job was done, the record is what is lost
            assert summary.outcome == "done", n
        assert [e["seq"] for e in read_events(audit.path)] == list(range(1, n)), n


def test_the_safe_stop_runs_before_the_fault_is_logged(tmp_path):
    runner, table, arm, audit = make_runner(tmp_path, arm_fail={"close_gripper": 1})
    order = []
    real_event = audit.event
    audit.event = lambda kind, **f: (order.append(("log", kind)), real_event(kind, **f))[1]
    real_stop = arm.stop
    arm.stop = lambda: (order.append(("arm", "stop")), real_stop())[1]
    runner.run()
    assert order.index(("arm", "stop")) < order.index(("log", "fault"))


def test_a_fault_requested_from_outside_ends_the_job_as_a_fault_with_the_arm_safe(tmp_path):
    controls = Controls()
    runner, table, arm, audit = make_runner(tmp_path, controls=controls)
    runner.sm.listeners.append(
        lambda t: controls.request_fault("history cannot be written: disk full") if t.target == State.PICK else None
    )
    summary = runner.run()
    assert summary.outcome == "fault" and summary.exit_code == EXIT_FAULT
    assert summary.reason == "history cannot be written: disk full"
    assert table.held is None and ("stop",) in arm.calls

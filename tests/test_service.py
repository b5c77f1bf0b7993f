"""The line service in-process over the simulated cell (960 x 540 camera, to keep frames cheap):
the command table, continuous mode, pause/resume, stop, halt/reset, a fault, events, counters
carried over a restart, and nothing left running after close."""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest

from cell.audit import read_events
from cell.commands.serve import open_service
from cell.config import CellConfig
from cell.service.api import Command, InvalidState, VisionState
from cell.service.shiftlog import read_shift, shift_files
from cell.summary import counts_from_log

pytestmark = pytest.mark.timeout(120)  # the simulated cell in-process; one case opens a pty with emulated GRBL

V = VisionState


def small_config(tmp_path, **sim) -> CellConfig:
    cfg = CellConfig()
    cfg.camera.width_px, cfg.camera.height_px = 960, 540
    cfg.sim.reference_marks_mm = []  # the drift watch does not find its marks at 960 x 540 (run-cell neither)
    cfg.run.log_dir = tmp_path / "logs"
    cfg.service.capture_interval_s = 0.2
    for k, v in sim.items():
        setattr(cfg.sim, k, v)
    return cfg


@contextlib.contextmanager
def running(cfg: CellConfig):
    with contextlib.ExitStack() as stack:
        service = open_service(cfg, True, stack)
        service.start()
        yield service


def wait_for(cond, timeout_s=30.0, what="condition"):
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.05)


def picked(service) -> int:
    c = service.snapshot().counters
    return c.picked_bolts + c.picked_nuts


def test_commands_outside_the_table_are_refused_and_change_nothing(tmp_path):
    with running(small_config(tmp_path)) as service:
        assert service.snapshot().vision_state == V.READY
        for command in (Command.RESET, Command.PAUSE, Command.RESUME, Command.STOP):
            with pytest.raises(InvalidState, match=f"{command.value} is not allowed in Ready"):
                service.command(command)
        assert service.snapshot().vision_state == V.READY
        assert service.snapshot().allowed == {Command.START_SINGLE, Command.START_CONTINUOUS, Command.HALT}


def test_continuous_picks_pauses_resumes_and_stops_into_ready(tmp_path):
    no_feeder = CellConfig().sim.feeder.model_copy(update={"parts_per_minute": 0})
    with running(small_config(tmp_path, feeder=no_feeder)) as service:
        kinds = []
        service.subscribe(lambda e: kinds.append(e.kind))
        service.command(Command.START_CONTINUOUS)
        assert service.snapshot().vision_state == V.CONTINUOUS_EXECUTION
        with pytest.raises(InvalidState):
            service.command(Command.START_SINGLE)
        wait_for(lambda: picked(service) >= 3, what="3 picks")
        service.command(Command.PAUSE)
        wait_for(lambda: service.snapshot().cell_state == "PAUSED", what="PAUSED")
        snap = service.snapshot()
        assert snap.paused and Command.RESUME in snap.allowed and Command.PAUSE not in snap.allowed
        held = picked(service)
        time.sleep(0.5)
        assert picked(service) == held  # nothing picked while paused
        service.command(Command.RESUME)
        wait_for(lambda: service.snapshot().waiting_for_parts, what="the table cleared and the cell waiting")
        assert picked(service) == 17  # the built-in table: 9 bolts, 8 nuts; the washer stays
        service.command(Command.STOP)
        wait_for(lambda: service.snapshot().vision_state == V.READY, what="Ready")
        snap = service.snapshot()
        assert snap.cell_state == "STOPPED" and snap.counters.unknown_left == 1
        assert {"state", "pick", "frame", "counters"} <= set(kinds)
        frame = service.latest_frame()
        assert frame.image_bgr.shape == (540, 960, 3) and frame.seq >= 18
        assert frame.seq == sum(e["kind"] == "frame" for e in read_shift(tmp_path / "logs"))  # one per frame, pause too
        assert [p.outcome for p in snap.last_picks] == ["picked"] * len(snap.last_picks)
        assert len(snap.last_picks) == 17 and snap.last_picks[-1].cls in ("bolt", "nut")


def test_the_frame_numbers_the_parts_in_the_order_the_runner_picks_them(tmp_path):
    no_feeder = CellConfig().sim.feeder.model_copy(update={"parts_per_minute": 0})
    with running(small_config(tmp_path, feeder=no_feeder)) as service:
        seen = []  # audit frames, the screen's frames and the runner's targets, in the worker's order
        service.subscribe(lambda e: e.kind == "frame" and seen.append(("view", e.frame)))
        service.audit.listeners.append(lambda e: e["kind"] in ("frame", "target") and seen.append((e["kind"], e)))
        service.command(Command.START_CONTINUOUS)
        wait_for(lambda: service.snapshot().waiting_for_parts, what="the table cleared and the cell waiting")
        service.command(Command.STOP)
        wait_for(lambda: service.snapshot().vision_state == V.READY, what="Ready")
    frames = [e for kind, e in seen if kind == "frame"]
    views = [v for kind, v in seen if kind == "view"]
    assert len(views) == len(frames) >= 18 and [v.seq for v in views] == list(range(1, len(views) + 1))
    targets = 0
    for i, (kind, e) in enumerate(seen):
        if kind != "target":
            continue
        targets += 1
        (_, view), (_, frame) = seen[i - 1], seen[i - 2]  # the frame goes out as PLAN chose, before the arm moves
        parts = {d["id"]: d for d in frame["detections"]}
        assert view.pick_order and all(parts[n]["pick"] for n in view.pick_order)
        nearest = min(parts.values(), key=lambda d: math.dist(d["table_mm"], e["table_mm"]))
        assert nearest["id"] == view.pick_order[0], f"the arm goes for part {nearest['id']}, numbered 1 is another"
    assert targets == 17 and views[-1].pick_order == ()  # the last frame: nothing left to pick


def test_halt_then_reset_and_nothing_but_reset_in_halted(tmp_path):
    with running(small_config(tmp_path)) as service:
        service.command(Command.START_CONTINUOUS)
        wait_for(lambda: picked(service) >= 1, what="a pick")
        service.command(Command.HALT)
        wait_for(lambda: service.snapshot().vision_state == V.HALTED, what="Halted")
        assert service.snapshot().cell_state == "STOPPED"
        for command in (Command.START_CONTINUOUS, Command.START_SINGLE, Command.STOP, Command.HALT):
            with pytest.raises(InvalidState):
                service.command(command)
        service.command(Command.RESET)
        assert service.snapshot().vision_state == V.READY
    events = read_shift(tmp_path / "logs")
    safe = [e["step"] for e in events if e["kind"] == "safe_step"]
    assert safe[-2:] == ["home", "release torque"]


def test_a_fault_raises_an_alarm_and_needs_a_reset(tmp_path):
    # the table is 10 mm higher than the planner thinks: the first descent drives the tool into it
    with running(small_config(tmp_path, truth_table_z_mm=10.0)) as service:
        alarms = []
        service.subscribe(lambda e: alarms.append(e.snapshot.alarm) if e.kind == "alarm" else None)
        service.command(Command.START_SINGLE)
        wait_for(lambda: service.snapshot().vision_state == V.ERROR, what="Error")
        snap = service.snapshot()
        assert "into the table" in snap.alarm.reason and snap.alarm.hint and alarms
        assert snap.allowed == {Command.RESET} and snap.cell_state == "FAULT"
        service.command(Command.RESET)
        snap = service.snapshot()
        assert snap.vision_state == V.READY and snap.alarm is None


def test_single_job_counters_survive_a_restart_and_match_the_log(tmp_path):
    cfg = small_config(tmp_path)
    with running(cfg) as service:
        service.command(Command.START_SINGLE)
        wait_for(lambda: service.snapshot().vision_state == V.READY and picked(service) == 17, what="the job")
        before = service.snapshot().counters
    with running(cfg) as again:
        assert again.snapshot().counters == before
    counts = counts_from_log(read_shift(tmp_path / "logs"))
    assert counts["picked"] == {"bolt": before.picked_bolts, "nut": before.picked_nuts}


def open_fds() -> set[str]:
    return set(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else set()


@pytest.mark.parametrize("arm", ["mock", "serial"])
def test_close_leaves_no_thread_or_fd_behind(tmp_path, arm):
    cfg = small_config(tmp_path)
    if arm == "serial":  # the real driver on a pty against the emulated GRBL: threads and fds to leak
        from cell.config import load_config

        cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "sim-grbl.toml")
        cfg.camera.width_px, cfg.camera.height_px = 960, 540
        cfg.sim.reference_marks_mm = []
        cfg.run.log_dir = tmp_path / "logs"
    before_threads, before_fds = {t.ident for t in threading.enumerate()}, open_fds()
    with running(cfg) as service:
        service.command(Command.START_CONTINUOUS)
        wait_for(lambda: picked(service) >= 1, what="a pick", timeout_s=60)
    assert {t.ident for t in threading.enumerate()} - before_threads == set()
    assert open_fds() - before_fds == set()
    files = shift_files(tmp_path / "logs", read_shift.__defaults__[0] or time.strftime("%Y%m%d", time.gmtime()))
    assert read_events(files[-1])[-1]["kind"] == "service_stop"


def test_plate_image_and_a_new_calibration_only_while_still(tmp_path):
    with running(small_config(tmp_path)) as service:
        seen = []
        service.subscribe(lambda e: seen.append(e) if e.kind == "calibration" else None)
        plate = service.capture_plate_image()  # Ready: the simulated cell renders its plate
        assert plate.shape == (540, 960, 3)
        cal = service.devices.calibration
        service.command(Command.START_CONTINUOUS)
        with pytest.raises(InvalidState, match="capture_plate_image is not allowed in ContinuousExecution"):
            service.capture_plate_image()
        info = service.snapshot().calibration
        with pytest.raises(InvalidState):
            service.install_calibration(cal, info)
        service.command(Command.PAUSE)
        new = replace(info, model="homography", source_image="plate-2.png")
        service.install_calibration(cal, new)  # paused: allowed
        assert service.snapshot().calibration == new and seen[-1].snapshot.calibration == new
        service.command(Command.STOP)
        wait_for(lambda: service.snapshot().vision_state == V.READY, what="Ready")


def test_counters_start_again_with_the_next_days_shift(tmp_path):
    with running(small_config(tmp_path)) as service:
        service.command(Command.START_SINGLE)
        wait_for(lambda: service.snapshot().vision_state == V.READY and picked(service) == 17, what="the job")
        today = service._shift_day
        service._on_audit(
            {"kind": "unreachable", "t_utc": "2999-01-01T00:00:00.001+00:00"}
        )  # the first event after midnight
        c = service.snapshot().counters
        assert (c.unreachable, c.picked_nuts, c.picked_bolts) == (1, 0, 0)
        assert today != service._shift_day

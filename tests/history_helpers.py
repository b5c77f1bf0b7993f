"""Events of a small made-up shift for the history tests: a job with picks, a miss, a failed part,
an unreachable part, an alarm raised and reset, a command, a calibration."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from cell.config import CellConfig
from cell.core.events import (
    AlarmCleared,
    AlarmRaised,
    CalibrationInstalled,
    CommandHandled,
    FrameRef,
    Interface,
    JobEnded,
    JobStarted,
    Origin,
    PartFailed,
    PartUnreachable,
    PickVerified,
    Role,
    VisionStateChanged,
)

JOB = "20261201-061500-ab12"
T0 = datetime(2026, 12, 1, 6, 15, tzinfo=UTC)
OPERATOR = Origin(Interface.SCREEN, "anna", Role.OPERATOR, "10.0.0.7")


def history_config(tmp_path: Path, **history) -> CellConfig:
    cfg = CellConfig()
    cfg.run.log_dir = tmp_path / "logs"
    cfg.history.data_dir = tmp_path / "data"
    cfg.history.cell_name = "cell-a"
    cfg.history.min_free_mb = 1
    for k, v in history.items():
        setattr(cfg.history, k, v)
    return cfg


def frame(n: int) -> FrameRef:
    image = np.full((60, 80, 3), 200, np.uint8)
    image[20:40, 30:50] = n % 255
    return FrameRef(n, image, None, 0.0)


def verify(n: int, result: str = "picked", cls: str = "nut", attempt: int = 1, track: int | None = None, **kw):
    return PickVerified(
        job_id=kw.pop("job_id", JOB),
        time_utc=kw.pop("time_utc", T0 + timedelta(seconds=n)),
        pick_id=f"{kw.pop('job', JOB)}/{n}",
        track=track if track is not None else n,
        cls=cls,
        attempt=attempt,
        result=result,
        pixel=(100.0 + n, 50.0),
        table_mm=(10.0 + n, 20.0),
        robot_mm=(-122.0 + n, 60.0, 2.0),
        jaw_angle_deg=None if cls == "nut" else 30.0,
        still_at_mm=(),
        calibration_id="cal0001",
        cycle_ms=900.0,
        ref=kw.pop("ref", None),
    )


def shift_events() -> list:
    """A job: 3 picks, a part missed twice and failed, one unreachable; an alarm reset by an operator."""
    t = T0
    return [
        CalibrationInstalled(
            time_utc=t - timedelta(minutes=5),
            calibration_id="cal0001",
            model="polynomial",
            cv_rms_mm=0.01,
            cv_max_mm=0.02,
            source_image="plate.png",
            file="calibration/active.json",
            origin=OPERATOR,
        ),
        VisionStateChanged(time_utc=t - timedelta(minutes=5), source="Preoperational", target="Ready", reason="up"),
        CommandHandled(time_utc=t, command="StartSingleJob", origin=OPERATOR, accepted=True, vision_state="Ready"),
        CommandHandled(
            time_utc=t,
            command="Reset",
            origin=OPERATOR,
            accepted=False,
            vision_state="Ready",
            refusal="invalid_state",
            message="Reset is not allowed in Ready",
        ),
        JobStarted(time_utc=t, job_id=JOB, mode="single", origin=OPERATOR),
        VisionStateChanged(time_utc=t, source="Ready", target="SingleExecution", reason="job started"),
        verify(1),
        verify(2, cls="bolt"),
        verify(3, "missed", track=9, ref=frame(3)),
        verify(4, "missed", attempt=2, track=9, ref=frame(4)),
        PartFailed(
            time_utc=T0 + timedelta(seconds=4),
            job_id=JOB,
            track=9,
            cls="nut",
            attempts=2,
            pick_id=f"{JOB}/4",
            ref=frame(4),
        ),
        PartUnreachable(
            time_utc=T0 + timedelta(seconds=5),
            job_id=JOB,
            track=11,
            cls="bolt",
            table_mm=(300.0, 1.0),
            reason="out of reach",
        ),
        verify(6),
        JobEnded(
            time_utc=T0 + timedelta(seconds=7),
            job_id=JOB,
            mode="single",
            outcome="done",
            reason="table clear",
            counts={"picked": {"nut": 2, "bolt": 1}, "misses": 2, "failed": 1, "unreachable": 1},
        ),
        VisionStateChanged(time_utc=T0 + timedelta(seconds=7), source="SingleExecution", target="Ready", reason="done"),
        AlarmRaised(
            time_utc=T0 + timedelta(minutes=1),
            alarm_id="A1",
            severity="fault",
            reason="arm stalled",
            hint="check the arm",
            source="history",
        ),
        VisionStateChanged(time_utc=T0 + timedelta(minutes=1), source="Ready", target="Error", reason="arm stalled"),
        AlarmCleared(time_utc=T0 + timedelta(minutes=3), alarm_id="A1", origin=OPERATOR),
        VisionStateChanged(time_utc=T0 + timedelta(minutes=3), source="Error", target="Ready", reason="reset"),
    ]

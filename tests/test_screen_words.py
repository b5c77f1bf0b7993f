"""The screen's words: alarms and calibration refusals as the cell really raises them (the drift
watch on a bumped simulated camera, the calibration pipeline on a plate cut, covered or missing)
become operator sentences pointing to the screen's own buttons, with the technical text kept as
their details; each state says what to do next."""

from __future__ import annotations

from datetime import UTC, datetime

import cv2
import numpy as np
import pytest

from cell.calibration.drift import DriftWatch
from cell.calibration.gates import change_problems
from cell.calibration.lattice import number_lattice
from cell.calibration.models import CameraMap
from cell.calibration.pipeline import calibrate
from cell.calibration.recalibrate import gate_failure
from cell.calibration.store import Calibration
from cell.config import CellConfig, DriftConfig
from cell.core.commands import VisionState, allowed
from cell.core.records import Alarm, Counters, Snapshot
from cell.errors import CameraMoved, PlateNotFound
from cell.service.service import split_hint
from cell.sim.cell import bumped
from cell.sim.render import render_plate
from cell.sim.rig import default_camera
from cell.sim.sim_camera import SimCamera
from cell.sim.world import Truth, World
from cell.web.views import display_state, next_action, snapshot_json
from cell.web.words import alarm_words, calibration_words

pytestmark = pytest.mark.timeout(60)

V = VisionState
MARKS = [(-6.0, -6.0), (270.0, -6.0), (-6.0, 182.0), (270.0, 182.0)]


def job_alarm(error: Exception) -> Alarm:
    """The alarm the service raises for a job that ended on `error` (the runner's reason, split as the service does)."""
    what, hint = split_hint(f"{type(error).__name__}: {error}")
    return Alarm(what, hint, datetime.now(UTC))


def drift_error(marks=MARKS, shift=(0.8, 0.0)) -> CameraMoved:
    model = default_camera(1280, 720)
    watch = DriftWatch(Calibration("camera", CameraMap(model), (1280, 720), model), DriftConfig(marks_mm=MARKS))
    world = World([], Truth(0.0, -132.0, 40.0, 0.0), [])
    camera = SimCamera(world, bumped(model, shift), seed=0, marks_mm=np.array(marks))
    camera.connect()
    with pytest.raises(CameraMoved) as caught:
        watch(camera.capture())
    return caught.value


def test_the_drift_alarm_points_to_recalibrate_and_reset_with_the_cli_text_as_details():
    words = alarm_words(job_alarm(drift_error()))
    assert words.say.startswith("The camera has moved since calibration (by 0.8")
    assert words.do == "Check it is fixed, then use Recalibrate, then press Reset."
    assert "run-cell" not in words.say + words.do and "drift.limit_mm" not in words.say + words.do
    assert "drift.limit_mm" in words.details and "run-cell check-calibration" in words.details  # the CLI's own text


def test_covered_reference_marks_say_uncover_them():
    words = alarm_words(job_alarm(drift_error(marks=MARKS[:3], shift=(0.0, 0.0))))
    assert words.say == "The reference marks at the table's edge cannot be seen."
    assert words.do.startswith("Uncover them") and words.do.endswith("then press Reset.")
    assert "not found where the calibration puts them" in words.details


def test_an_unknown_alarm_is_shown_as_raised_with_a_terminal_hint_kept_in_the_details():
    plain = alarm_words(
        Alarm("history store: cannot write rows", "free space on the disk, then Reset", datetime.now(UTC))
    )
    assert (plain.say, plain.do, plain.details) == (
        "History store: cannot write rows.",
        "Free space on the disk, then Reset.",
        "",
    )
    terminal = alarm_words(Alarm("telemetry: broker gone", "check mqtt.host in the .toml", datetime.now(UTC)))
    assert (
        terminal.do == "Fix the cause, then press Reset." and terminal.details == "hint: check mqtt.host in the .toml"
    )


@pytest.fixture(scope="module")
def plate() -> np.ndarray:
    return render_plate(default_camera(960, 540), CellConfig().plate)


def refusal(image: np.ndarray, config: CellConfig | None = None) -> str:
    with pytest.raises(PlateNotFound) as caught:
        calibrate(image, config or CellConfig())
    return str(caught.value)


def test_a_plate_cut_by_the_image_edge_says_move_it_towards_the_centre(plate):
    cut = plate.copy()
    cut[:, 600:] = 230  # three columns out of view
    words = calibration_words(refusal(cut))
    assert (
        words.say == "Only part of the plate is in view (10 x 12 of its 13 x 12 circles): move it towards the centre."
    )
    assert "10 x 12 lattice, expected 13 x 12" in words.details


def test_blobs_that_form_no_lattice_say_the_plate_is_not_fully_in_view():
    points = np.array([[0, 0], [10, 3], [25, 40], [7, 90]], float)
    with pytest.raises(PlateNotFound) as caught:
        number_lattice(points, CellConfig().plate, 0.2)
    assert str(caught.value) == "found 4 blobs, none form a consistent lattice"
    words = calibration_words(str(caught.value))
    assert words.say == "The plate is not fully in view: move it towards the centre."
    assert words.details == "found 4 blobs, none form a consistent lattice"


def test_a_covered_plate_and_an_empty_table(plate):
    covered = plate.copy()
    cv2.rectangle(covered, (400, 200), (560, 330), (230, 230, 230), -1)
    words = calibration_words(refusal(covered))
    assert words.say == "12 circles of the plate are hidden or cannot be read."
    assert words.do.startswith("Clear anything lying on the plate")
    assert calibration_words(refusal(np.full_like(plate, 230))).say == "No plate in view."


def test_fits_refused_by_the_gates_say_why_in_operator_words(plate):
    strict = CellConfig()
    strict.calibration.max_cv_rms_mm = 1e-6
    result = calibrate(plate, strict)
    assert calibration_words(gate_failure(result, strict)).say == "The calibration is not accurate enough."
    wrong_pitch = CellConfig()
    wrong_pitch.plate.pitch_x_mm = 20.0  # a 22 mm plate configured as 20 mm
    failure = gate_failure(calibrate(plate, wrong_pitch), wrong_pitch)
    assert failure is not None
    assert calibration_words(failure).say == "The plate does not match the plate the cell is set up for."
    model = default_camera(960, 540)
    moved = calibrate(render_plate(bumped(model, (8.0, 0.0)), CellConfig().plate), CellConfig()).calibration
    problems = change_problems(moved, result.calibration, CellConfig().calibration)
    words = calibration_words("; ".join(problems))
    assert words.say == "The camera or the plate is not where it was at the last calibration."
    assert "--accept-change" in words.do  # the screen cannot accept a move: an engineer, in the terminal


@pytest.mark.parametrize(
    "message, say",
    [
        ("upload: empty file", "The file is empty."),
        ("upload: not a PNG or JPEG image", "This file is not a picture the cell can read."),
        (
            "upload: image is 640 x 480 px but the camera is configured for 1920 x 1080 px",
            "The picture is 640 x 480 pixels; this cell's camera takes 1920 x 1080.",
        ),
        ("upload: cannot decode the image (corrupt or truncated)", "The picture is damaged and cannot be read."),
        ("upload too large: at most 25600 KiB", "The file is too large (at most 25 MB)."),
        ("recalibrate only while stopped (Ready), paused, halted or after a fault", "The cell is running."),
    ],
)
def test_refused_images_in_operator_words(message, say):
    assert calibration_words(message).say == say


def snapshot(state: VisionState, **kw) -> Snapshot:
    base = dict(
        vision_state=state,
        cell_state="IDLE",
        paused=False,
        waiting_for_parts=False,
        counters=Counters(),
        parts_per_min=12.0,
        last_picks=(),
        alarm=None,
        calibration=None,
        heartbeat=1,
        allowed=allowed(state),
    )
    return Snapshot(**{**base, **kw})


@pytest.mark.parametrize(
    "snap, label, action",
    [
        (snapshot(V.READY), "Stopped: ready to start", "Press Start to clear the table once, or Start continuous"),
        (snapshot(V.HALTED), "Halted", "Nothing runs until you press Reset."),
        (snapshot(V.CONTINUOUS_EXECUTION, pausing=True), "Pausing", "Finishing the current motion"),
        (snapshot(V.CONTINUOUS_EXECUTION, paused=True), "Paused", "Press Resume to go on, or Stop"),
        (snapshot(V.CONTINUOUS_EXECUTION, waiting_for_parts=True), "Waiting for parts", "The table is empty"),
        (snapshot(V.SINGLE_EXECUTION), "Running (single job)", "Clearing the table once"),
        (snapshot(V.CONTINUOUS_EXECUTION), "Running (continuous)", "Picking parts as they arrive"),
        (snapshot(V.PREOPERATIONAL), "Starting", "Wait: the cell is starting."),
        (snapshot(V.READY, hold="a recalibration report is waiting"), "Stopped", "A recalibration report is waiting."),
    ],
)
def test_every_state_says_what_to_do_next(snap, label, action):
    key, shown = display_state(snap)
    assert shown.startswith(label) and next_action(snap, key).startswith(action)


def test_error_says_the_alarm_and_then_reset_and_rates_are_a_dash_when_not_running():
    alarm = job_alarm(drift_error())
    state = snapshot_json(snapshot(V.ERROR, alarm=alarm))
    assert state["display"]["next"] == (
        f"{state['alarm']['say']} Check it is fixed, then use Recalibrate, then press Reset."
    )
    assert state["parts_per_min"] is None and state["recalibration_allowed"]  # recalibrate, then Reset
    assert snapshot_json(snapshot(V.CONTINUOUS_EXECUTION))["parts_per_min"] == 12.0
    assert snapshot_json(snapshot(V.CONTINUOUS_EXECUTION, paused=True))["parts_per_min"] is None
    assert snapshot_json(snapshot(V.CONTINUOUS_EXECUTION, parts_per_min=0.0))["parts_per_min"] is None  # not known yet

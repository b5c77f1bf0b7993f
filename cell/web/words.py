"""The screen's words for what the cell reports in an engineer's terms: alarms and calibration
refusals become a short sentence an operator can act on, pointing to the screen's own buttons;
the technical text stays available behind the page's "details" toggle.

The CLI keeps the technical wording (it names commands and config keys, which suit a terminal);
these mappings are for the screen only. Each is a regular expression over the message the cell
raises (cell/calibration/lattice.py, pipeline.py, gates.py, recalibrate.py, drift.py, the
drivers' errors) and the sentence it becomes; a message no pattern knows is shown as it is.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

from cell.core.records import Alarm

# A hint written for the terminal: a command, an option, a config key (drift.limit_mm), code quotes.
TECHNICAL = re.compile(r"run-cell|scripts/|`|--[a-z]|\b[a-z]+\.[a-z]+_[a-z_]+\b|\.toml\b")


@dataclass(frozen=True)
class Words:
    """What happened and what to do, in operator words; `details`: the technical text (may be empty)."""

    say: str
    do: str
    details: str

    def as_json(self) -> dict[str, str]:
        return {"say": self.say, "do": self.do, "details": self.details}


Rule = tuple[re.Pattern[str], Callable[[re.Match[str]], tuple[str, str]]]


def _rules(*pairs: tuple[str, Callable[[re.Match[str]], tuple[str, str]]]) -> list[Rule]:
    return [(re.compile(pattern), make) for pattern, make in pairs]


# ---- alarms: a job's fault reason is "<ExceptionType>: <message>" (cell.runner) ----------------
_JOB_ALARMS = _rules(
    (
        r"^CameraMoved: camera moved ([\d.]+) mm since calibration",
        lambda m: (
            f"The camera has moved since calibration (by {m[1]} mm).",
            "Check it is fixed, then use Recalibrate, then press Reset.",
        ),
    ),
    (
        r"^CameraMoved: reference marks .* not found",
        lambda m: (
            "The reference marks at the table's edge cannot be seen.",
            "Uncover them; if the camera has moved, use Recalibrate; then press Reset.",
        ),
    ),
    (
        r"^CameraError: .*(no frame|ran out|cannot open|could not open)",
        lambda m: (
            "The camera gives no picture.",
            "Check its cable and power, and that no other program uses it, then press Reset.",
        ),
    ),
    (r"^CameraError: ", lambda m: ("The camera failed.", "Check its cable and power, then press Reset.")),
    (r"^NoResponse: ", lambda m: ("The arm does not answer.", "Check the arm's power and cable, then press Reset.")),
    (
        r"^ConnectionLost: ",
        lambda m: ("The connection to the arm was lost.", "Check the arm's USB cable, then press Reset."),
    ),
    (
        r"^AlarmResponse: ",
        lambda m: (
            "The arm's controller stopped in alarm (a limit switch, the emergency stop or a blocked move).",
            "Clear the cause, then press Reset. If it comes back, call an engineer.",
        ),
    ),
    (
        r"^HardwareFault: ",
        lambda m: (
            "A servo of the arm reported a fault (overload or overheating).",
            "Remove what blocks the arm, let it cool, switch the arm off and on, then press Reset.",
        ),
    ),
    (
        r"^PositionLost: |^CellError: not homed",
        lambda m: (
            "The arm's controller restarted and lost its position.",
            "Check the arm is clear and have an engineer home it, then press Reset.",
        ),
    ),
    (
        r"^OutOfReach: ",
        lambda m: ("A part lies where the arm cannot reach.", "Move it into the working area, then press Reset."),
    ),
    (
        r"^safety stop: .*pick attempt",
        lambda m: (
            "Too many picks failed.",
            "Check the gripper and the parts on the table, then press Reset.",
        ),
    ),
    (
        r"^AuditWriteFailed: |No space left on device",
        lambda m: (
            "The cell cannot write its record (the disk is full or failing).",
            "Free space on the disk or call an engineer, then press Reset.",
        ),
    ),
    (
        r"^internal error",
        lambda m: (
            "The cell's software failed.",
            "Press Reset to go on; if it happens again, call an engineer (the details are in the log).",
        ),
    ),
    (
        r"^(ArmError|ErrorResponse|NotConnected): ",
        lambda m: ("The arm refused a command.", "Check the arm, then press Reset."),
    ),
    (
        r"^ConfigError: ",
        lambda m: ("The cell's settings are wrong.", "Call an engineer: the details say which setting."),
    ),
)


def alarm_words(alarm: Alarm) -> Words:
    """An alarm as the screen shows it. A fault's `do` always ends in Reset; a warning needs none."""
    technical = alarm.reason + (f" (hint: {alarm.hint})" if alarm.hint else "")
    for pattern, make in _JOB_ALARMS:
        if m := pattern.search(alarm.reason):
            say, do = make(m)
            return Words(say, do, technical)
    # not known here: the reason as it is; its hint too, unless it speaks of commands and config keys
    plain = bool(alarm.hint) and not TECHNICAL.search(alarm.hint)
    if plain:
        return Words(_sentence(alarm.reason), _sentence(alarm.hint), "")
    do = "" if alarm.severity == "warning" else "Fix the cause, then press Reset."
    return Words(_sentence(alarm.reason), do, f"hint: {alarm.hint}" if alarm.hint else "")


# ---- calibration refusals ---------------------------------------------------------------------
_CALIBRATION = _rules(
    (
        r"none form a consistent lattice",
        lambda m: (
            "The plate is not fully in view: move it towards the centre.",
            "Clear anything lying on it, then try again.",
        ),
    ),
    (
        r"(\d+) fit a (\d+) x (\d+) lattice, expected (\d+) x (\d+)",
        lambda m: (
            (
                f"Only part of the plate is in view ({m[2]} x {m[3]} of its {m[4]} x {m[5]} circles): "
                "move it towards the centre."
            )
            if int(m[2]) * int(m[3]) < int(m[4]) * int(m[5])
            else f"This plate has more circles than the cell's plate ({m[4]} x {m[5]}): use the cell's plate.",
            "Every circle must be in the picture; then try again.",
        ),
    ),
    (
        r"(\d+) circles missing(?: or covered)? \(at most (\d+) allowed\)",
        lambda m: (
            f"{m[1]} circles of the plate are hidden or cannot be read.",
            "Clear anything lying on the plate, wipe it, check the light from below, then try again.",
        ),
    ),
    (
        r"no plate in view|too few for a \d+ x \d+ plate|plate points: too few",
        lambda m: (
            "No plate in view.",
            "Put the calibration plate on the lit table under the camera, then try again.",
        ),
    ),
    (
        r"paper preset found",
        lambda m: (
            "Not every circle of the plate was found.",
            "Put the whole plate in view, lit evenly from below, then try again.",
        ),
    ),
    (
        (
            r"physical camera model fits|fitted camera is .* above the table|no finite camera pose"
            r"|circles are round only if pitch_x_mm / pitch_y_mm|the plate puts the camera .* above the table"
        ),
        lambda m: (
            "The plate does not match the plate the cell is set up for.",
            "Use the cell's calibration plate; if it is the right one, call an engineer to check its settings.",
        ),
    ),
    (
        r"cross-validated error .* exceeds",
        lambda m: (
            "The calibration is not accurate enough.",
            "Check the plate lies flat and still, the camera is focused and fixed, then try again.",
        ),
    ),
    (
        r"^scale .* against the active|image centre maps .* from where the active calibration",
        lambda m: (
            "The camera or the plate is not where it was at the last calibration.",
            "Put the plate in its fixture and check the camera is fixed. If the camera was moved on purpose, "
            "an engineer accepts the change with run-cell recalibrate --accept-change.",
        ),
    ),
    (
        r"image is (\d+) x (\d+) px but the camera is configured for (\d+) x (\d+) px",
        lambda m: (
            f"The picture is {m[1]} x {m[2]} pixels; this cell's camera takes {m[3]} x {m[4]}.",
            "Upload a picture taken by this cell's camera.",
        ),
    ),
    (r"empty file", lambda m: ("The file is empty.", "Choose a PNG or JPEG picture of the plate.")),
    (
        r"not a PNG or JPEG|not an image this cell reads",
        lambda m: ("This file is not a picture the cell can read.", "Choose a PNG or JPEG picture of the plate."),
    ),
    (
        r"cannot decode|corrupt|decoder failed|decoding took longer|not valid compressed data",
        lambda m: ("The picture is damaged and cannot be read.", "Take or upload the picture again."),
    ),
    (
        r"upload too large: at most (\d+) KiB",
        lambda m: (f"The file is too large (at most {int(m[1]) // 1024} MB).", "Upload a smaller picture."),
    ),
    (
        r"^camera .*(no frame|cannot open)|no camera to capture",
        lambda m: ("The camera gives no picture.", "Check its cable and power, or upload a picture instead."),
    ),
    (
        r"recalibrate only while|the cell is moving|(CapturePlate|InstallCalibration) is not allowed",
        lambda m: ("The cell is running.", "Press Pause or Stop first, then Recalibrate."),
    ),
    (
        r"needs the (\w+) role; (.*) is (\w+)$",
        lambda m: (
            f"Recalibrating needs the {m[1]} role; {m[2]} is logged in as {m[3]}.",
            f"Ask someone with the {m[1]} role to log in and recalibrate.",
        ),
    ),
)


def calibration_words(message: str) -> Words:
    """A refused recalibration (or a fit that fails the gate) in operator words, the message behind it."""
    for pattern, make in _CALIBRATION:
        if m := pattern.search(message):
            say, do = make(m)
            return Words(say, do, message)
    return Words(_sentence(message), "", "")


def _sentence(text: str) -> str:
    text = text.strip()
    return text[:1].upper() + text[1:] + ("" if text.endswith((".", "!", "?")) else ".")

"""The one command table every interface obeys: the commands, the states each is allowed in, the
least role that may send it, the guards, and the refusals (each with a code an interface maps to
its own status: OPC UA, HTTP, MQTT). The outward state follows OPC 40100-1 (Machine Vision).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from enum import Enum
from typing import Any

from cell.core.events import Role


class VisionState(Enum):
    """OPC 40100-1 state shown to clients; the value is the spec's BrowseName."""

    PREOPERATIONAL = "Preoperational"
    """Starting: devices opening, calibration loading. No command is accepted."""
    HALTED = "Halted"
    """Safe-stopped on Halt (or a signal): arm safe, nothing runs until Reset."""
    ERROR = "Error"
    """A fault: arm made safe, the alarm says why; nothing runs until Reset."""
    INITIALIZED = "Initialized"
    """Operational, devices open, not yet homed for a job."""
    READY = "Ready"
    """Operational, arm homed, waiting for a start command."""
    SINGLE_EXECUTION = "SingleExecution"
    """Clearing the table once, as `run-cell` does; back to Ready when it is clear."""
    CONTINUOUS_EXECUTION = "ContinuousExecution"
    """Capturing at the configured interval and picking whatever appears, until Stop."""


V = VisionState


RUNNING = frozenset({V.SINGLE_EXECUTION, V.CONTINUOUS_EXECUTION})


class Command(Enum):
    """A client's request; the value is the OPC UA method's BrowseName."""

    START_SINGLE = "StartSingleJob"
    START_CONTINUOUS = "StartContinuous"
    STOP = "Stop"  # end the job at a safe point, arm homed, back to Ready
    ABORT = "Abort"  # end the job now: the safe stop (arm safe), back to Ready without a Reset
    PAUSE = "Pause"  # hold at a safe point with no part in the gripper
    RESUME = "Resume"
    HALT = "Halt"  # the safe stop, into Halted
    RESET = "Reset"  # from Halted or Error back to Ready
    CAPTURE_PLATE = "CapturePlate"  # a frame for recalibration; the cell stays at rest meanwhile
    INSTALL_CALIBRATION = "InstallCalibration"  # use a calibration that passed the gate
    PREPARE_RECIPE = "PrepareRecipe"  # make a recipe the active one
    UNPREPARE_RECIPE = "UnprepareRecipe"  # back to the built-in recipe
    ADD_RECIPE = "AddRecipe"
    REMOVE_RECIPE = "RemoveRecipe"
    CAPTURE_PART_IMAGE = "CapturePartImage"  # a frame of example parts for teaching a part type; the cell idle
    ADD_PART_TYPE = "AddPartType"  # a taught part type's model added to a recipe file


class Refusal(Enum):
    """Why a command was refused (OPC UA maps each to a status code, the screen to an HTTP status)."""

    INVALID_STATE = "invalid_state"  # not in this state, or a guard holds (a recalibration awaiting its answer)
    ACCESS_DENIED = "access_denied"  # the user's role may not
    SHUTTING_DOWN = "shutting_down"  # the service is stopping: it takes no more commands
    BAD_ARGUMENT = "bad_argument"  # e.g. an unknown recipe
    NOT_RECORDED = "not_recorded"  # the record could not be written, so nothing is done


# The command table: the states each command is allowed in (pausing and guards below), and the
# least role that may send it.
_AT_REST = frozenset({V.READY, V.HALTED, V.ERROR})  # the arm parked or made safe
_IDLE = _AT_REST  # no job at all (a paused job is at rest but not idle): where a part type is taught


_TABLE: dict[Command, tuple[frozenset[VisionState], Role]] = {
    Command.START_SINGLE: (frozenset({V.READY}), Role.OPERATOR),
    Command.START_CONTINUOUS: (frozenset({V.READY}), Role.OPERATOR),
    Command.STOP: (RUNNING, Role.OPERATOR),
    Command.ABORT: (RUNNING, Role.OPERATOR),
    Command.PAUSE: (RUNNING, Role.OPERATOR),
    Command.RESUME: (RUNNING, Role.OPERATOR),
    Command.HALT: (frozenset({V.INITIALIZED, V.READY}) | RUNNING, Role.VIEWER),
    Command.RESET: (frozenset({V.HALTED, V.ERROR}), Role.OPERATOR),
    Command.CAPTURE_PLATE: (_AT_REST | RUNNING, Role.ENGINEER),
    Command.INSTALL_CALIBRATION: (_AT_REST | RUNNING, Role.ENGINEER),
    Command.PREPARE_RECIPE: (frozenset({V.READY}), Role.ENGINEER),
    Command.UNPREPARE_RECIPE: (frozenset({V.READY}), Role.ENGINEER),
    Command.ADD_RECIPE: (_AT_REST | RUNNING, Role.ENGINEER),
    Command.REMOVE_RECIPE: (_AT_REST | RUNNING, Role.ENGINEER),
    Command.CAPTURE_PART_IMAGE: (_IDLE, Role.ENGINEER),
    Command.ADD_PART_TYPE: (_IDLE, Role.ENGINEER),
}


# Commands that need the cell at rest: Ready, Halted, Error, or a job paused at a safe point (not pausing).
STILL_COMMANDS = frozenset({Command.CAPTURE_PLATE, Command.INSTALL_CALIBRATION})


# Commands a hold (a recalibration awaiting its answer) refuses: nothing may start or move on.
HELD_COMMANDS = frozenset({Command.START_SINGLE, Command.START_CONTINUOUS, Command.RESUME})


# Commands a plate capture in progress refuses: each would move the arm (Stop and Abort home it from a
# paused job) into the plate image. Halt is never refused: the safe stop comes before any image.
CAPTURE_REFUSES = HELD_COMMANDS | {Command.STOP, Command.ABORT}


JOB_COMMANDS = frozenset({Command.START_SINGLE, Command.START_CONTINUOUS})


STATE_COMMANDS = (
    Command.START_SINGLE,
    Command.START_CONTINUOUS,
    Command.STOP,
    Command.ABORT,
    Command.PAUSE,
    Command.RESUME,
    Command.HALT,
    Command.RESET,
)


def needed_role(command: Command) -> Role:
    return _TABLE[command][1]


@dataclass(frozen=True)
class Rest:
    """Where the cell stands for the command table: the outward state, whether a pause was asked
    for (`pausing`) and whether the job has reached it (`paused`: at rest, nothing moves)."""

    state: VisionState
    pausing: bool = False
    paused: bool = False
    ending: bool = False  # the job has ended (the arm parked or made safe) or a Halt's safe stop runs: only Halt acts
    capturing: bool = False  # a plate image is being captured for recalibration: nothing may move into it


# What a cell coming to rest (`Rest.ending`) still takes: Halt (its safe stop follows whatever the job
# did) and the recipe files (nothing moves); anything else could only be recorded and then do nothing.
WHILE_ENDING = frozenset({Command.HALT, Command.ADD_RECIPE, Command.REMOVE_RECIPE})


def allowed(
    state: VisionState,
    pausing: bool = False,
    paused: bool | None = None,
    hold: str = "",
    ending: bool = False,
    capturing: bool = False,
) -> frozenset[Command]:
    """The commands the state accepts (any role), as every interface shows them (buttons enabled)."""
    rest = Rest(state, pausing, pausing if paused is None else paused, ending, capturing)
    return frozenset(c for c in STATE_COMMANDS if state_refusal(c, rest, hold) is None)


def state_refusal(command: Command, rest: Rest, hold: str = "") -> str | None:
    """Why the command is not allowed where the cell stands (None: it is)."""
    states, _ = _TABLE[command]
    where = f"{rest.state.value}{' (paused)' if rest.paused else ' (pausing)' if rest.pausing else ''}"
    if rest.state not in states:
        return f"{command.value} is not allowed in {where}"
    if rest.ending and command not in WHILE_ENDING:
        return f"{command.value} is not allowed in {where}: the cell is coming to rest (wait until it is)"
    if command is Command.PAUSE and rest.pausing:
        return f"{command.value} is not allowed in {where}: already pausing"
    if command is Command.RESUME and not rest.pausing:
        return f"{command.value} is not allowed in {where}: not paused"
    if command in STILL_COMMANDS and rest.state in RUNNING and not rest.paused:
        why = "wait until it is paused" if rest.pausing else "pause or stop it first"
        return f"{command.value} is not allowed in {where}: the cell is moving ({why})"
    if command in CAPTURE_REFUSES and rest.capturing:
        return f"{command.value} is not allowed now: a plate image is being captured for recalibration (wait for it)"
    if command in HELD_COMMANDS and hold:
        return f"{command.value} is not allowed now: {hold}"
    return None


class CommandRefused(Exception):
    """A command the service did not accept; nothing changed. `reason` says which rule refused it."""

    reason = Refusal.INVALID_STATE

    def __init__(self, command: Command | str, message: str, state: VisionState | None = None):
        self.command = command
        self.state = state
        super().__init__(message)


class InvalidState(CommandRefused):
    """Not allowed in the current state, or held by a guard (OPC UA: BadInvalidState; screen: 409)."""

    reason = Refusal.INVALID_STATE


class AccessDenied(CommandRefused):
    """The user's role may not send this command (OPC UA: BadUserAccessDenied; screen: 403)."""

    reason = Refusal.ACCESS_DENIED


class ShuttingDown(CommandRefused):
    """The service is stopping and takes no more commands (OPC UA: BadShutdown; screen: 503)."""

    reason = Refusal.SHUTTING_DOWN


class BadArgument(CommandRefused):
    """An argument the command cannot take (OPC UA: BadInvalidArgument; screen: 422)."""

    reason = Refusal.BAD_ARGUMENT


class NotRecorded(CommandRefused):
    """The command could not be recorded, so it was not carried out (OPC UA: BadResourceUnavailable)."""

    reason = Refusal.NOT_RECORDED


@dataclass(frozen=True)
class JobRequest:
    """OPC 40100-1 StartSingleJob / StartContinuous inputs; all optional. An empty recipe_id means
    the prepared (active) recipe."""

    recipe_id: str = ""
    product_id: str = ""
    part_id: str = ""
    meas_id: str = ""
    parameters: tuple[tuple[str, str], ...] = ()

    def as_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {k: v for k, v in self.__dict__.items() if v and k != "parameters"}
        if self.parameters:
            out["parameters"] = dict(self.parameters)
        return out


@dataclass(frozen=True)
class RecipeRequest:
    """PrepareRecipe / UnprepareRecipe / RemoveRecipe name a recipe; AddRecipe also brings its TOML text."""

    recipe_id: str
    content: str = ""

    def as_json(self) -> dict[str, Any]:
        return {"recipe_id": self.recipe_id, **({"content_bytes": len(self.content)} if self.content else {})}


@dataclass(frozen=True)
class PartTypeRequest:
    """AddPartType: a taught type's shape model (its JSON text, as cell.vision.shapes writes it) for a recipe
    file (created if absent); the type's name is the model's; its bin given, another class's, or none."""

    recipe_id: str
    name: str
    model_json: str
    bin_robot_mm: tuple[float, float, float] | None = None  # where it goes (robot mm); none: left on the table
    bin_of: str = ""  # or the bin of another class of the recipe (bolt, nut, a taught type)

    def as_json(self) -> dict[str, Any]:
        digest = hashlib.sha256(self.model_json.encode("utf-8")).hexdigest()
        out: dict[str, Any] = {"recipe_id": self.recipe_id, "name": self.name, "model_sha256": digest}
        if self.bin_robot_mm is not None:
            out["bin_robot_mm"] = list(self.bin_robot_mm)
        if self.bin_of:
            out["bin_of"] = self.bin_of
        return out


Request = JobRequest | RecipeRequest | PartTypeRequest  # what a command may carry


@dataclass(frozen=True)
class CommandResult:
    command: Command
    job_id: str | None = None  # a start command's new job
    said: tuple[str, ...] = ()  # what the command tells whoever sent it (AddPartType: the bin, the class_no)

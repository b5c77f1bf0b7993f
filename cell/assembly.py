"""The one place a cell is assembled from its config: camera, arm, calibration, drift watch,
device locks and, for a dry run, the simulated world.

Every command that touches a device (run, serve, teach, jog, home, recalibrate,
check-calibration) and the line service get their devices here, so a rule about devices
(which arm a dry run gets, what is locked, which calibration is loaded) holds everywhere.
What must be shut down afterwards (an emulated arm's pty, the locks) goes on the caller's
ExitStack.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, get_args

import numpy as np

from cell.calibration.drift import DriftWatch
from cell.calibration.store import Calibration
from cell.config import CellConfig, load_config
from cell.core.eventbus import EventBus
from cell.core.parts import PartRegistry
from cell.errors import ConfigError
from cell.locks import device_locks
from cell.planning import Planner, table_to_robot
from cell.recipes import Recipe, load_recipe_file
from cell.run_config import ClassPlan
from cell.signals import Controls
from cell.vision.locate import locate
from cell.vision.shapes import ShapeModel
from cell.vision.types import LocateResult
from drivers.arm.base import Arm
from drivers.arm.config import ArmConfig, DeviceKind
from drivers.arm.factory import make_arm, with_overrides
from drivers.arm.robot_server import RobotServerArm
from drivers.cameras.base import Camera
from drivers.cameras.factory import make_camera

if TYPE_CHECKING:  # a real cell never loads cell.sim; the store is built where it is configured
    from cell.history.store import HistoryStore
    from cell.sim.cell import SimCell
    from cell.telemetry.publisher import SparkplugPublisher

log = logging.getLogger(__name__)

# `--dry-run --arm KIND` with no --config: the shipped simulated cell laid out for that arm
# (the built-in one is out of a gantry's reach and lays bolts a 4-axis arm cannot grip).
SIM_CONFIGS = {"serial": "sim-grbl.toml", "dynamixel": "sim-dynamixel.toml"}
CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


@dataclass(frozen=True)
class Overrides:
    """What the command line may change in a config (every field optional)."""

    arm: str | None = None
    port: str | None = None
    log_dir: Path | None = None
    offset_x_mm: float = 0.0
    offset_y_mm: float = 0.0


def config_path(path: Path | None, dry_run: bool, arm: str | None) -> Path | None:
    """The config file a run uses: the one given, or for `--dry-run --arm serial|dynamixel` the shipped
    simulated cell for that arm; None: the built-in simulated cell."""
    if path is None and not dry_run:
        raise ConfigError("give --config FILE to run the cell, or --dry-run to rehearse on the built-in simulated cell")
    if path is None and arm in SIM_CONFIGS:
        return CONFIG_DIR / SIM_CONFIGS[arm]
    return path


def cell_config(path: Path | None, dry_run: bool, overrides: Overrides = Overrides()) -> CellConfig:
    """The config a run or the service uses (see config_path), with the command line's overrides."""
    return apply_overrides(load_config(config_path(path, dry_run, overrides.arm)), overrides)


def apply_overrides(config: CellConfig, o: Overrides) -> CellConfig:
    if o.offset_x_mm or o.offset_y_mm:
        if config.planning.frame != "offset":
            raise ConfigError("--offset-x-mm/--offset-y-mm change planning.offset_*, but planning.frame is 'taught'")
        config.planning.offset_x_mm += o.offset_x_mm
        config.planning.offset_y_mm += o.offset_y_mm
    if o.log_dir:
        config.run.log_dir = o.log_dir
    if o.arm or o.port:
        config.arm = with_overrides(config.arm, o.arm, o.port)
    return config


@dataclass(frozen=True)
class RunRecipe:
    """A recipe a run uses: its handling, its taught types' shape models (the finder of
    `run-cell locate --recipe`) and the part classes it counts."""

    recipe: Recipe
    shapes: tuple[ShapeModel, ...] = ()
    name: str = ""

    @classmethod
    def load(cls, path: Path) -> RunRecipe:
        recipe, shapes = load_recipe_file(path)
        return cls(recipe, tuple(shapes), Path(path).stem)

    @property
    def taught_plans(self) -> dict[str, ClassPlan]:
        return self.recipe.taught_plans()

    @property
    def parts(self) -> PartRegistry:
        return self.recipe.registry()

    def unbinned_words(self) -> str | None:
        """The recipe's taught types without a bin, in words (they are found and left on the table), or None."""
        return self.recipe.unbinned_words(self.name)

    def leave_unpicked(self, result: LocateResult) -> LocateResult:
        """Parts of a class the recipe does not pick stay on the table, saying so."""
        for part in result.objects:
            if part.pick and part.cls not in self.recipe.classes:
                part.pick, part.reason = False, f"{part.reason}; not picked by recipe {self.name}"
        return result


@dataclass
class Cell:
    """A cell's devices and how it sees, for one run or one service's life."""

    config: CellConfig
    camera: Camera  # the simulated cell's is fed by its feeder when assembled for a shift
    arm: Arm
    calibration: Calibration
    expect_motion: bool  # False: a mock arm over a real table, nothing can move
    sim: SimCell | None = None  # the simulated cell's world, when there is one
    plate_image: Callable[[], np.ndarray] | None = None  # how a plate frame is taken for recalibration
    notes: list[str] = field(default_factory=list)  # what the operator should be told about the set-up
    recipe: RunRecipe | None = None  # `run-cell --recipe FILE`: its taught types found and picked

    def planner(self) -> Planner:
        if self.recipe is None:
            return Planner(self.config.planning, table_to_robot(self.config.planning))
        plans, numbers = self.recipe.taught_plans, self.recipe.recipe.class_numbers()
        return Planner(self.config.planning, table_to_robot(self.config.planning), plans, numbers)

    def locate(self, frame: np.ndarray, calibration: Calibration) -> LocateResult:
        if self.recipe is None:
            return locate(frame, calibration, self.config)
        return self.recipe.leave_unpicked(locate(frame, calibration, self.config, self.recipe.shapes))

    def drift_watch(self, calibration: Calibration) -> DriftWatch | None:
        """The reference-mark watch for this calibration: the configured marks, else those printed on
        the simulated table; None when there are none."""
        sim_marks = self.sim.marks_mm if self.sim is not None else []
        marks = self.config.drift.marks_mm or sim_marks
        if not marks:
            return None
        return DriftWatch(calibration, self.config.drift.model_copy(update={"marks_mm": list(marks)}))

    def motion_time_s(self) -> float:
        return float(self.sim.motion_time_s()) if self.sim is not None else 0.0


def assemble(
    config: CellConfig,
    dry_run: bool,
    resources: contextlib.ExitStack,
    *,
    shift: bool = False,
    progress: Callable[[str], None] = lambda line: None,
    recipe: RunRecipe | None = None,
) -> Cell:
    """The cell's devices, opened lazily by the runner (connect); locks and emulators go on
    `resources`. `shift`: the simulated cell gets its feeder (the line service's dry run).
    `recipe`: the run's recipe (its taught types found, planned and, simulated, laid out)."""
    if config.camera.source == "sim":
        cell = _simulated(config, resources, shift, progress, recipe)
        cell.recipe = recipe
        return cell
    progress(f"loading the calibration {config.calibration.active_path}")
    calibration = Calibration.load(config.calibration.active_path)
    arm_cfg = config.arm
    if dry_run and arm_cfg.kind in get_args(DeviceKind):  # the mock checks every command as the real driver would
        arm_cfg = arm_cfg.model_copy(update={"kind": "mock", "mock_of": arm_cfg.kind})
    resources.enter_context(device_locks(arm_cfg, config.camera.source))  # this process's alone until it ends
    camera = make_camera(config.camera)
    arm = make_arm(arm_cfg, config.robot_server)
    if isinstance(arm, RobotServerArm):  # listens for the cell's life, across jobs
        resources.enter_context(arm.serving())
    cell = Cell(config, camera, arm, calibration, not dry_run, recipe=recipe)
    cell.plate_image = lambda: _capture(camera)
    if isinstance(arm, RobotServerArm):
        cell.notes.append(f"robot server on {arm.port.removeprefix('tcp://')} (protocol: docs/robots.md)")
    doubt = calibration.height_doubt(config.parts.tallest_centre_height_mm, config.calibration.max_height_cost_mm)
    if doubt is not None:
        cell.notes.append(f"warning: {doubt[0]} (hint: {doubt[1]})")
    return cell


def _simulated(
    config: CellConfig,
    resources: contextlib.ExitStack,
    shift: bool,
    progress: Callable[[str], None],
    recipe: RunRecipe | None = None,
) -> Cell:
    from cell.sim.cell import sim_arm_kind, sim_cell
    from cell.sim.feeder import FedCamera, Feeder, SimClock
    from cell.sim.parts import ExtrudedPart
    from cell.sim.render import render_plate

    taught: list[tuple[ExtrudedPart, tuple[float, float, float] | None]] = []
    if recipe is not None:  # each taught type, its model extruded, on the simulated table (those without a bin stay)
        plans = recipe.taught_plans
        for m in recipe.shapes:
            part = ExtrudedPart(m.name, np.asarray(m.outline_mm), tuple(np.asarray(h) for h in m.holes_mm), m.height_mm)
            taught.append((part, plans[m.name].bin_robot_mm if m.name in plans else None))

    if sim_arm_kind(config.arm) != "sim" and config.arm.port:
        log.warning(
            "camera.source is 'sim': the emulated %s arm gets a pseudo-terminal; arm.port %r is not used",
            config.arm.kind,
            config.arm.port,
        )
    progress("rendering the simulated plate and calibrating on it")
    sim = resources.enter_context(sim_cell(config, taught))
    camera: Camera = sim.camera
    if shift:
        feeder = Feeder(sim.world, config.sim.feeder, SimClock(config.sim.speed_factor))
        camera = FedCamera(sim.camera, feeder)
    if config.sim.camera_source != "sim":  # the rendered frames through Aravis's Fake GenICam camera
        from cell.sim.genicam_feed import fed_genicam

        camera = fed_genicam(camera, make_camera(config.camera.model_copy(update={"source": config.sim.camera_source})))
    cell = Cell(config, camera, sim.arm, sim.calibration, True, sim)
    cell.plate_image = lambda: render_plate(sim.camera.model, config.plate, seed=config.sim.seed)
    cell.notes.append(f"simulated cell: {len(sim.world.parts)} parts; plate calibrated: {sim.calibration_note}")
    if sim.world_arm is not None:
        host, port = sim.arm.port.removeprefix("tcp://").rsplit(":", 1)
        robot = "a simulated robot asks over it" if config.robot_server.simulated_robot else "waiting for a robot"
        cell.notes.append(f"robot server on {host}:{port} ({robot}; protocol: docs/robots.md)")
    if sim.emulated is not None:
        emu = sim.emulated
        cell.notes.append(
            f"arm: the real {type(sim.arm).__name__} driver against an emulated {emu.firmware} on {emu.port} "
            f"(motion {emu.speed_scale:g}x faster than the arm's)"
        )
    return cell


def _capture(camera: Camera) -> np.ndarray:
    if camera.is_connected:
        return camera.capture()
    with camera:
        return camera.capture()


def capture_plate(config: CellConfig) -> np.ndarray:
    """One frame of the plate from the configured camera (the simulated camera renders the built-in plate)."""
    if config.camera.source.strip() == "sim":
        from cell.sim.render import render_plate
        from cell.sim.rig import default_camera

        log.info("capturing the plate from the simulated camera")
        return render_plate(default_camera(config.camera.width_px, config.camera.height_px), config.plate)
    with contextlib.ExitStack() as stack:
        stack.enter_context(device_locks(None, config.camera.source))
        return _capture(make_camera(config.camera))


class CellHooks(Protocol):
    """What a consumer of the event stream (the history store, plant telemetry) may ask of the cell
    it records: stop it safely with a fault, or show and clear a warning alarm."""

    def fault(self, reason: str, hint: str, source: str) -> None: ...

    def raise_warning(self, key: str, reason: str, hint: str, source: str) -> None: ...

    def clear_warning(self, key: str) -> None: ...


class RunHooks:
    """CellHooks for one `run-cell` job: a fault stops the job safely (exit 3 with its reason);
    warnings are logged (the operator sees them in the log and the audit)."""

    def __init__(self, controls: Controls):
        self.controls = controls
        self.fault_reason: str | None = None

    def fault(self, reason: str, hint: str, source: str) -> None:
        if self.fault_reason is None:
            self.fault_reason = f"{reason} (hint: {hint})"
            log.error("%s: %s", source, self.fault_reason)
            self.controls.request_fault(self.fault_reason)

    def raise_warning(self, key: str, reason: str, hint: str, source: str) -> None:
        log.warning("%s: %s (%s)", source, reason, hint)

    def clear_warning(self, key: str) -> None:
        log.info("warning %s cleared", key)


@dataclass
class Consumers:
    """What attach_consumers built (None where the config leaves it out)."""

    history: HistoryStore | None = None
    telemetry: SparkplugPublisher | None = None


def rehearsal_config(config: CellConfig) -> CellConfig:
    """The config a rehearsal (`--dry-run`, `make demo`) runs: the same, but its history goes to a
    store of its own (cell.history.config.rehearsal_history), apart from production's. The one place a
    rehearsal's store is chosen, for `run-cell --dry-run` and `run-cell serve --dry-run` alike."""
    from cell.history.config import rehearsal_history

    return config.model_copy(update={"history": rehearsal_history(config.history, config.run.log_dir)})


def attach_consumers(
    config: CellConfig, bus: EventBus, resources: contextlib.ExitStack, hooks: CellHooks, *, rehearsal: bool = False
) -> Consumers:
    """The event stream's consumers a config asks for (the history store, plant telemetry), each a
    subscriber of `bus` on its own thread, closed with `resources`. The one place they are built,
    for `run-cell` and `run-cell serve` alike. `rehearsal`: a dry run, whose config is
    rehearsal_config's; its store reads back only the audit lines marked as a rehearsal's."""
    consumers = Consumers()
    if config.history.enabled:
        from cell.history.store import EVENT_TYPES, HistoryStore

        store = HistoryStore(config.history, config.run.log_dir, hooks, rehearsal=rehearsal)
        resources.callback(store.close)
        # a large queue: the subscriber only turns events into rows (fast); it must lose none
        sub = bus.subscribe(
            "history", store.handle, kinds=EVENT_TYPES, maxsize=200_000, frames=HistoryStore.wants_frame
        )
        resources.callback(bus.unsubscribe, sub)  # first: the queued events are handed over, then the store closes
        consumers.history = store
    if config.telemetry.mqtt.enabled:  # Sparkplug B to the plant's broker (paho-mqtt is imported only then)
        from cell.telemetry.publisher import attach_mqtt

        consumers.telemetry = attach_mqtt(config.telemetry.mqtt, bus, resources, hooks, log_dir=config.run.log_dir)
    return consumers


def commissioning_camera(config: CellConfig) -> Camera:
    """The configured camera alone, for commissioning (`run-cell camera`); 'sim' is the simulated
    camera looking at the calibration plate. The caller locks and connects it."""
    if config.camera.source.strip() == "sim":
        from cell.sim.cell import sim_plate_camera

        return sim_plate_camera(config)
    return make_camera(config.camera)


@contextlib.contextmanager
def arm_only(config: CellConfig, kind: str | None = None, port: str | None = None) -> Iterator[Arm]:
    """The configured arm (with the command line's kind and port), its port locked for this process,
    not yet connected (`with arm:` connects); for teach, jog and home."""
    arm_cfg: ArmConfig = with_overrides(config.arm, kind, port)
    if arm_cfg.kind == "robot-server":
        raise ConfigError(
            "arm.kind 'robot-server': the robot runs its own program; the cell does not jog, home or teach it",
            hint="jog and home the robot from its pendant; teach with --point and positions read there",
        )
    with device_locks(arm_cfg):
        yield make_arm(arm_cfg)

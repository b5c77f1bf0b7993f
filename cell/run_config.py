"""Config sections of the running cell: planning (table -> robot, per-class motion), the run
loop, and the built-in simulated cell. Robot-frame values are mm in the arm's base frame;
heights named *_above_table_mm are relative to the table surface.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from drivers.arm.config import Workspace
from drivers.config import Strict


class ClassPlan(Strict):
    """How one class of part is picked and where it goes."""

    pick_above_table_mm: float = Field(ge=0, le=100, description="tool point height when the jaws close")
    approach_above_table_mm: float = Field(40.0, gt=0, le=300, description="height of moves above the table")
    jaw_across_axis: bool = Field(
        False, description="turn the jaws to close across the part's axis (bolts); else leave the angle"
    )
    bin_robot_mm: tuple[float, float, float] = Field(description="where the gripper opens over the bin, robot frame")


class RobotWorkspace(Workspace):
    """Where the planner lets the tool go, robot frame: the arm's workspace box (ordered
    there) plus a reach ring about the base axis; checked before anything moves."""

    x_min_mm: float = Field(
        -300.0, description="smallest X of a pick, approach or bin point, robot mm (the arm's base frame)"
    )
    x_max_mm: float = Field(
        300.0, description="largest X of a pick, approach or bin point, robot mm (the arm's base frame)"
    )
    y_min_mm: float = Field(
        -300.0, description="smallest Y of a pick, approach or bin point, robot mm (the arm's base frame)"
    )
    y_max_mm: float = Field(
        300.0, description="largest Y of a pick, approach or bin point, robot mm (the arm's base frame)"
    )
    z_min_mm: float = Field(
        -5.0, description="lowest Z of a pick, approach or bin point, robot mm (the arm's base frame)"
    )
    z_max_mm: float = Field(
        200.0, description="highest Z of a pick, approach or bin point, robot mm (the arm's base frame)"
    )
    reach_min_mm: float = Field(60.0, ge=0, description="closest the tool may come to the base axis (XY)")
    reach_max_mm: float = Field(380.0, gt=0, description="farthest the tool may reach from the base axis (XY)")

    @model_validator(mode="after")
    def _reach_ordered(self) -> RobotWorkspace:
        if self.reach_min_mm >= self.reach_max_mm:
            raise ValueError(
                f"reach_min_mm ({self.reach_min_mm:g} mm) must be below reach_max_mm ({self.reach_max_mm:g} mm)"
            )
        return self


class PlanningConfig(Strict):
    """Table mm -> robot mm, and the per-class pick and place moves."""

    frame: Literal["offset", "taught"] = Field(
        "offset",
        description="'offset': the fixed offset below (the paper's way); 'taught': the fit of `run-cell teach`",
    )
    offset_x_mm: float = Field(-132.0, description="robot X of the table origin (plate point 1)")
    offset_y_mm: float = Field(40.0, description="robot Y of the table origin")
    table_z_mm: float = Field(0.0, description="robot Z of the table surface")
    taught_path: Path = Field(Path("calibration/robot_frame.json"), description="written by `run-cell teach`")
    teach_max_residual_mm: float = Field(1.0, gt=0, description="a teach fit with a larger residual is refused")
    teach_fit_scale: bool = Field(False, description="also fit a scale (a similarity instead of a rigid transform)")
    pick_order: Literal["nearest", "rows", "as-found"] = Field(
        "nearest", description="nearest to the gripper first; rows: table Y then X; as-found: vision's order"
    )
    workspace: RobotWorkspace = RobotWorkspace()
    bolt: ClassPlan = ClassPlan(pick_above_table_mm=3.5, jaw_across_axis=True, bin_robot_mm=(-200.0, 60.0, 60.0))
    nut: ClassPlan = ClassPlan(pick_above_table_mm=2.0, bin_robot_mm=(200.0, 60.0, 60.0))

    def for_class(self, cls: str) -> ClassPlan:
        return {"bolt": self.bolt, "nut": self.nut}[cls]


class RunConfig(Strict):
    """The pick loop."""

    max_retries: int = Field(2, ge=0, le=20, description="further attempts at a part still there after a place")
    verify_radius_mm: float = Field(
        5.0, gt=0, le=50, description="a part seen this close to where one was picked is taken as still there"
    )
    max_attempts_total: int = Field(200, ge=1, description="safety stop: never more pick attempts than this per run")
    log_dir: Path = Field(Path("logs"), description="audit (JSON lines) and operator logs, one pair per run")
    motion_timeout_s: float = Field(30.0, gt=0, le=600, description="longest wait for the arm to finish a move")


class FeederConfig(Strict):
    """The dry run's parts supply for continuous mode: parts dropped onto free spots of the table."""

    parts_per_minute: float = Field(6.0, ge=0, le=600, description="arrival rate in simulated minutes; 0 = none")
    bolt_share: float = Field(0.45, ge=0, le=1, description="fraction of arrivals that are bolts")
    nut_share: float = Field(0.45, ge=0, le=1, description="fraction that are nuts")
    washer_share: float = Field(0.10, ge=0, le=1, description="fraction that are washers (the cell must leave them)")
    seed: int = Field(1, ge=0, description="random seed of the arrivals: each part's kind, size, place and turn")
    area_mm: tuple[float, float, float, float] = Field(
        (15.0, 25.0, 255.0, 170.0),
        description="table rectangle parts land in: x_min, y_min, x_max, y_max (table mm); "
        "the default keeps clear of the arm's base (reach_min_mm)",
    )
    max_on_table: int = Field(40, ge=1, le=500, description="a part due when this many lie on the table is not dropped")
    clear_after_s: float = Field(
        600.0,
        ge=0,
        description="a part left on the table this long (simulated s) is cleared away, as an operator "
        "clears rejects (washers); 0 = never",
    )

    @model_validator(mode="after")
    def _some_mix(self) -> FeederConfig:
        if self.bolt_share + self.nut_share + self.washer_share <= 0:
            raise ValueError("sim.feeder: bolt_share + nut_share + washer_share must be above 0")
        x0, y0, x1, y1 = self.area_mm
        if x0 >= x1 or y0 >= y1:
            raise ValueError(f"sim.feeder.area_mm {self.area_mm}: x_min < x_max and y_min < y_max, please")
        return self


class SimConfig(Strict):
    """The built-in simulated cell: the truth the planner's config should agree with."""

    truth_offset_x_mm: float = Field(-132.0, description="true robot X of the table origin")
    truth_offset_y_mm: float = Field(40.0, description="true robot Y of the table origin")
    truth_rotation_deg: float = Field(0.0, ge=-180, le=180, description="true rotation table -> robot")
    truth_table_z_mm: float = Field(0.0, description="true robot Z of the table surface")
    layout: Literal["paper", "paper-square-to-base", "paper-fixed-jaws", "random"] = Field(
        "paper",
        description="paper: Table IV's 9 bolts and 8 nuts plus a washer; paper-square-to-base: the same with "
        "every bolt square to the line from the Dynamixel arm's base (what a 4-axis arm can grip); "
        "paper-fixed-jaws: every bolt across arm.serial.fixed_jaw_angle_deg (what a 3-axis gantry can grip)",
    )
    taught_parts_per_type: int = Field(
        3,
        ge=1,
        le=20,
        description="with a recipe of taught types (`run-cell --dry-run --recipe FILE`): how many of each type "
        "the simulated table holds, laid out at random (sim.seed) in place of the layout above",
    )
    teach_family: str = Field(
        "",
        pattern=r"^[a-z0-9-]{0,32}$",
        description="rehearsing teaching on the screen (docs/operator-screen.md, 'Teach a part type'): the "
        "simulated table holds sim.taught_parts_per_type parts of this flat part family alone (l-bracket, "
        "t-bracket, plate-4h, spacer, tab-washer, clip, gear, ...: cell/sim/flatparts.py, drawn with sim.seed), "
        "in place of the layout above; empty: the layout",
    )
    seed: int = Field(
        0,
        ge=0,
        description="random seed of the simulated cell: part turns (layout random: the whole scene), the camera's sensor noise",
    )
    perfect_calibration: bool = Field(
        False, description="use the camera model itself instead of calibrating the rendered plate"
    )
    plate_cache: bool = Field(
        True,
        description="keep the rendered plate's fitted calibration in $XDG_CACHE_HOME/pick-cell/sim ($CACHE_DIRECTORY/sim under systemd), keyed by the "
        "camera, the plate, the settings and the code that fit it: later dry runs start without fitting it again",
    )
    camera_bumped_mm: tuple[float, float] = Field(
        (0.0, 0.0),
        description="move the camera this far (table X, Y) after the plate was calibrated: a stale calibration",
    )
    camera_bumped_at_pick: int = Field(
        0,
        ge=0,
        description="when: 0 before the run starts; N the camera moves just before the frame that pick N "
        "is planned from",
    )
    reference_marks_mm: list[tuple[float, float]] = Field(
        default_factory=lambda: [(-6.0, -6.0), (270.0, -6.0), (-6.0, 182.0), (270.0, 182.0)],
        description="dark dots printed on the simulated table (drift.mark_diameter_mm across), just outside the "
        "plate's corners; the run watches them unless drift.marks_mm names others",
    )
    jaw_across_tolerance_mm: float = Field(
        1.5, gt=0, le=20, description="error allowed along the jaws' closing direction"
    )
    jaw_along_tolerance_mm: float = Field(
        1.0, gt=0, le=20, description="error allowed along the jaw faces (nuts, washers)"
    )
    bolt_end_margin_mm: float = Field(
        2.0, ge=0, le=50, description="the jaws must close on a bolt's body at least this far from either end"
    )
    bolt_angle_tolerance_deg: float = Field(
        5.0, gt=0, le=90, description="a bolt is gripped only with the jaws within this of square to its axis"
    )
    bin_half_size_mm: float = Field(40.0, gt=0, le=500, description="a part released within this of a bin lands in it")
    speed_mm_s: float = Field(150.0, gt=0, description="arm.kind sim (the simulated arm): tool speed")
    gripper_s: float = Field(0.4, ge=0, description="arm.kind sim: time to open or close the gripper")
    realtime: bool = Field(False, description="arm.kind sim: sleep for the simulated motion time")
    emulator_speed_scale: float = Field(
        50.0,
        gt=0,
        le=10000,
        description="arm.kind serial/dynamixel (the real driver against an emulated arm): "
        "the emulator moves this many times faster than the arm would; 1 = real time",
    )
    speed_factor: float = Field(
        1.0,
        gt=0,
        le=10000,
        description="run-cell serve: simulated time runs this many times faster than the wall "
        "clock (the feeder, the capture interval): rehearse a shift in minutes",
    )
    camera_source: str = Field(
        "sim",
        pattern=r"^(sim|genicam:Fake_\d+)$",
        description="the simulated camera's frames reach the cell straight (\"sim\") or through Aravis's "
        'in-process Fake GenICam camera ("genicam:Fake_1"), fed each rendered frame: the GenICam driver\'s '
        "whole path (trigger, stream, buffers, camera.genicam's settings) without a camera (docs/cameras.md)",
    )
    feeder: FeederConfig = FeederConfig()
    arm_fault_after_grips: int = Field(
        0,
        ge=0,
        description="arm.kind serial/dynamixel: rehearse a fault (sim.arm_fault) after this many grips; 0 = never",
    )
    arm_fault: Literal["alarm", "restart"] = Field(
        "alarm",
        description="what arm_fault_after_grips rehearses: alarm (GRBL ALARM:1 on the next move; the Dynamixel "
        "gripper servo overloads) or restart (the controller restarts at once: GRBL's banner, all servos' supply dips)",
    )

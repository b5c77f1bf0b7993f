"""The built-in simulated cell: a webcam over the paper's plate, calibrated from its own
rendered image, then a table laid out like the paper's Table IV (9 bolts, 8 nuts) plus a
washer the cell must leave alone, an arm and its two bins.

The calibration is fitted, not copied from the camera model, so the dry run carries the
same mapping error the line would. The arm is the geometric SimArm (arm.kind sim), or
the real serial or Dynamixel driver against its emulated firmware on a pseudo-terminal.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import json
import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from cell.calibration.models import CameraMap
from cell.calibration.pipeline import calibrate
from cell.calibration.store import Calibration
from cell.camera_model import CameraModel
from cell.config import CellConfig
from cell.errors import ConfigError
from cell.sim.emulated_arm import EmulatedArm, emulated_arm
from cell.sim.flatparts import layout as flat_layout
from cell.sim.flatparts import random_types
from cell.sim.parts import ExtrudedPart, PartSpec, random_scene
from cell.sim.platefit import cached_fit, default_dir
from cell.sim.render import plate_centres_mm, render_plate
from cell.sim.rig import default_camera
from cell.sim.sim_arm import SimArm
from cell.sim.sim_camera import SimCamera
from cell.sim.world import Bin, JawTolerance, Truth, World
from drivers.arm.base import Arm
from drivers.arm.config import ArmConfig

log = logging.getLogger(__name__)

# The paper's Table IV: object class and world position (mm), rows 1-17.
PAPER_TABLE4_MM = [
    ("nut", 259.809, 14.600),
    ("bolt", 61.768, 27.991),
    ("bolt", 174.146, 23.477),
    ("nut", 226.089, 48.039),
    ("nut", 86.853, 54.084),
    ("nut", 157.383, 60.966),
    ("bolt", 255.871, 79.293),
    ("bolt", 73.889, 90.566),
    ("bolt", 186.030, 87.026),
    ("nut", 205.624, 117.387),
    ("nut", 54.439, 127.731),
    ("nut", 127.538, 128.567),
    ("bolt", 262.846, 124.786),
    ("nut", 255.676, 137.408),
    ("bolt", 67.780, 158.343),
    ("bolt", 234.450, 164.004),
    ("bolt", 130.297, 167.991),
]
_NUT_SIZES = ["M6", "M8", "M5", "M10"]
MIN_GAP_MM = 3.0  # between part outlines in a layout: closer, the camera may see one blob
_BOLTS = [("M6", 20.0), ("M5", 16.0), ("M8", 25.0), ("M5", 20.0)]


@dataclass
class SimCell:
    world: World
    camera: SimCamera
    arm: Arm
    calibration: Calibration
    calibration_note: str
    emulated: EmulatedArm | None  # None: the arm is the geometric SimArm
    marks_mm: list[tuple[float, float]]  # reference marks printed on the simulated table
    world_arm: SimArm | None = None  # arm.kind robot-server: the simulated robot's arm (self.arm is the server)

    def motion_time_s(self) -> float:
        """Motion time so far: the emulator's motion model, or SimArm's distance / speed estimate."""
        if self.emulated is not None:
            return self.emulated.motion_time_s()
        if self.world_arm is not None:
            return self.world_arm.motion_time_s
        return self.arm.motion_time_s if isinstance(self.arm, SimArm) else 0.0


_EDGE_STEPS = np.linspace(0, 1, 8, endpoint=False)[:, None, None]


@functools.lru_cache(maxsize=256)
def _dense_outline(p: PartSpec | ExtrudedPart) -> np.ndarray:
    """The top-view outline with 8 samples along each edge (read-only; a part's is kept while it is used)."""
    poly = p.top_view_outline_mm()
    nxt = np.roll(poly, -1, axis=0)
    dense = (poly + _EDGE_STEPS * (nxt - poly)).reshape(-1, 2)
    dense.flags.writeable = False
    return dense


def outline_gap_mm(a: PartSpec | ExtrudedPart, b: PartSpec | ExtrudedPart) -> float:
    """Smallest distance between two top-view outlines (sampled), mm."""
    return nearest_outline_mm(a, [b])


def nearest_outline_mm(a: PartSpec | ExtrudedPart, others: Sequence[PartSpec | ExtrudedPart]) -> float:
    """Smallest distance between a's top-view outline and any of the others' (sampled), mm: the
    least of outline_gap_mm(a, q) over them, in one step."""
    pa, pb = _dense_outline(a), np.concatenate([_dense_outline(q) for q in others])
    dx = pa[:, 0, None] - pb[None, :, 0]
    dy = pa[:, 1, None] - pb[None, :, 1]
    dx *= dx
    dy *= dy
    dx += dy
    return float(np.sqrt(dx.min()))  # the square root of the least square: the least distance


_ACROSS_FIXED_JAWS_DEG = (0.0, -2.0, 2.0)  # well within a fixed-jaw arm's tolerance (5 deg by default)


def paper_layout(
    seed: int = 0, base_table_mm: tuple[float, float] | None = None, jaws_table_deg: float | None = None
) -> list[PartSpec]:
    """Table IV's 17 parts at their published positions, plus an M8 washer in the widest gap.

    Sizes cycle through common M5-M10 parts; each bolt is turned to the angle (of 12 tried)
    that leaves the most room to its neighbours, so no two outlines touch. Given the arm's
    base (table frame), each bolt is instead laid square to the line from the base (see
    _square_to_base): a 4-axis arm closes its jaws along that line, so it grips no other bolt. Given
    a fixed jaw angle (`jaws_table_deg`, table frame: a 3-axis gantry's jaws less the table's rotation),
    each bolt lies across it (within 2 deg), head one way or the other, whichever leaves most room.
    """
    rng = np.random.default_rng(seed)
    parts: list[PartSpec] = []
    for i, (kind, x, y) in enumerate(PAPER_TABLE4_MM):
        if kind == "nut":
            parts.append(PartSpec("nut", _NUT_SIZES[i % 4], x, y, float(rng.uniform(0, 60))))
        else:
            parts.append(PartSpec("bolt", _BOLTS[i % 4][0], x, y, 0.0, _BOLTS[i % 4][1]))
    jitter = float(rng.uniform(0, 15))
    for i, p in enumerate(parts):
        if p.kind != "bolt":
            continue
        others = [q for j, q in enumerate(parts) if j != i]

        def room(c: PartSpec) -> float:
            return nearest_outline_mm(c, others)

        if jaws_table_deg is not None:
            axis = jaws_table_deg - 90.0  # the jaws close across the bolt's axis
            parts[i] = max(
                (
                    PartSpec("bolt", p.size, p.x_mm, p.y_mm, axis + turn + a, p.length_mm)
                    for turn in (0.0, 180.0)
                    for a in _ACROSS_FIXED_JAWS_DEG
                ),
                key=room,
            )
        elif base_table_mm is None:
            parts[i] = max(
                (PartSpec("bolt", p.size, p.x_mm, p.y_mm, a + jitter, p.length_mm) for a in range(0, 360, 30)), key=room
            )
        else:
            parts[i] = _square_to_base(p, base_table_mm, room)
    grid = itertools.product(np.arange(20.0, 250.0, 5.0), np.arange(15.0, 165.0, 5.0))
    centres = np.array([(p.x_mm, p.y_mm) for p in parts])
    wx, wy = max(grid, key=lambda g: np.hypot(*(centres - g).T).min())
    parts.append(PartSpec("washer", "M8", float(wx), float(wy)))
    return parts


def _square_to_base(bolt: PartSpec, base_mm: tuple[float, float], room) -> PartSpec:
    """The bolt with the middle of its shaft (where the cell grips) on the line from the base
    through its position and its axis square to that line, pointing whichever way leaves more
    room. Where that crowds a neighbour (Table IV's bolt 13 would touch nut 14), it is slid
    along the line by the least 2 mm step that keeps MIN_GAP_MM between outlines."""
    dx, dy = bolt.x_mm - base_mm[0], bolt.y_mm - base_mm[1]
    rho = math.hypot(dx, dy)
    ux, uy = dx / rho, dy / rho
    bearing = math.degrees(math.atan2(uy, ux))
    middle = bolt.shaft_middle_offset_mm
    if middle is None:
        raise ValueError(f"a {bolt.kind} is not a bolt")
    candidates = []
    for shift_mm in range(-12, 13, 2):
        for a in (bearing + 90.0, bearing - 90.0):
            ar = math.radians(a)
            centre = (
                bolt.x_mm + shift_mm * ux - middle * math.cos(ar),
                bolt.y_mm + shift_mm * uy - middle * math.sin(ar),
            )
            spec = PartSpec("bolt", bolt.size, *centre, a, bolt.length_mm)
            candidates.append((room(spec), shift_mm, spec))
    return max(candidates, key=lambda c: (c[0] >= MIN_GAP_MM, -abs(c[1]), c[0]))[2]


def bumped(model: CameraModel, shift_mm: tuple[float, float]) -> CameraModel:
    """The same camera moved parallel to the table: its calibration no longer holds."""
    t = model.tvec - model.rotation @ np.array([shift_mm[0], shift_mm[1], 0.0])
    return CameraModel(model.width_px, model.height_px, model.camera_matrix, model.dist_coeffs, model.rvec, t)


def sim_arm_kind(arm: ArmConfig) -> str:
    """The simulated cell's arm: 'sim' (SimArm), or 'serial'/'dynamixel' against an emulator.

    'mock' is the documented old spelling of 'sim' here (docs/running-the-cell.md, `make
    demo`): a recording mock arm has no table to act on, so in the simulated cell it means SimArm.
    """
    return "sim" if arm.kind in ("sim", "mock") else arm.kind


# A few fits of the simulated plate, each a few kB: see plate_calibration.
_PLATE_FITS: dict[str, tuple[Calibration, str]] = {}


def plate_calibration(config: CellConfig, model: CameraModel) -> tuple[Calibration, str]:
    """The simulated plate rendered and calibrated as the line's would be: (calibration, why).

    The fit depends only on the camera, the seed and the plate, detection and calibration
    settings, so a process that builds the cell again (a line service starting job after
    job, the test suite) renders and fits it once, and with `sim.plate_cache` later processes
    load it from the user's cache folder (cell/sim/platefit.py).
    """
    key = json.dumps(
        [
            model.to_dict(),
            config.sim.seed,
            config.plate.model_dump(mode="json"),
            config.detection.model_dump(mode="json"),
            config.calibration.model_dump(mode="json"),
        ]
    )
    if key not in _PLATE_FITS:

        def fit() -> tuple[Calibration, str]:
            result = calibrate(render_plate(model, config.plate, seed=config.sim.seed), config)
            model.cache.clear()  # the plate's ray maps are not needed again
            return result.calibration, result.why

        if len(_PLATE_FITS) >= 4:
            _PLATE_FITS.pop(next(iter(_PLATE_FITS)))
        _PLATE_FITS[key] = cached_fit(key, default_dir() if config.sim.plate_cache else None, fit)
    return _PLATE_FITS[key]


TAUGHT_AREA_MM = (0.0, 0.0, 264.0, 176.0)  # where taught parts are laid out: the plate's area
TAUGHT_GAP_MM = 8.0  # between their outlines seen from above (room for parallax and the jaws)


def taught_layout(types: Sequence[ExtrudedPart], per_type: int, seed: int) -> list[ExtrudedPart]:
    """`per_type` of each taught type at random positions and turns on the plate's area, apart."""
    rng = np.random.default_rng(seed)
    order = [t for t in types for _ in range(per_type)]
    return flat_layout([order[i] for i in rng.permutation(len(order))], rng, TAUGHT_AREA_MM, TAUGHT_GAP_MM)


def teach_family(name: str, seed: int) -> ExtrudedPart:
    """The flat part of family `name` (cell.sim.flatparts.random_types(seed)) to rehearse teaching with."""
    types = random_types(seed)
    if name not in types:
        raise ConfigError(f"sim.teach_family {name!r}: no such flat part family", hint=f"one of {', '.join(types)}")
    return types[name]


@contextlib.contextmanager
def sim_cell(
    config: CellConfig, taught: Sequence[tuple[ExtrudedPart, tuple[float, float, float] | None]] = ()
) -> Iterator[SimCell]:
    """Camera, plate calibration, world and arm of the simulated cell, for a `with` block: an
    emulated arm's pty and emulator run until the block ends, however it ends. `taught`: a
    recipe's taught types (each its extruded stand-in and its bin, robot mm, or None: a type the
    recipe leaves on the table): the table holds sim.taught_parts_per_type of each in place of the
    configured layout."""
    sim = config.sim
    model = default_camera(config.camera.width_px, config.camera.height_px)
    if sim.perfect_calibration:
        calibration = Calibration("camera", CameraMap(model), (model.width_px, model.height_px), model)
        note = "perfect (the camera model itself)"
    else:
        calibration, note = plate_calibration(config, model)
    bump = None
    if any(sim.camera_bumped_mm) and sim.camera_bumped_at_pick == 0:
        model = bumped(model, sim.camera_bumped_mm)
        note += f"; camera since moved by {sim.camera_bumped_mm} mm"
    elif any(sim.camera_bumped_mm):
        bump = (sim.camera_bumped_at_pick, bumped(model, sim.camera_bumped_mm))
        note += f"; camera to be moved by {sim.camera_bumped_mm} mm before pick {sim.camera_bumped_at_pick}"
    truth = Truth(sim.truth_rotation_deg, sim.truth_offset_x_mm, sim.truth_offset_y_mm, sim.truth_table_z_mm)
    parts: list[PartSpec | ExtrudedPart]
    if taught:
        parts = list(taught_layout([t for t, _ in taught], sim.taught_parts_per_type, sim.seed))
    elif sim.teach_family:
        parts = list(taught_layout([teach_family(sim.teach_family, sim.seed)], sim.taught_parts_per_type, sim.seed))
    elif sim.layout == "random":
        parts = list(random_scene(sim.seed))
    elif sim.layout == "paper-fixed-jaws":
        parts = list(paper_layout(sim.seed, jaws_table_deg=config.arm.serial.fixed_jaw_angle_deg - truth.rotation_deg))
    elif sim.layout == "paper-square-to-base":
        parts = list(paper_layout(sim.seed, truth.robot_to_table(config.arm.dynamixel.geometry.yaw_axis_x_mm, 0.0)))
    else:
        parts = list(paper_layout(sim.seed))
    plan = config.planning
    bins = [
        Bin("bolt", plan.bolt.bin_robot_mm[:2], sim.bin_half_size_mm),
        Bin("nut", plan.nut.bin_robot_mm[:2], sim.bin_half_size_mm),
    ]
    own = [Bin(t.name, where[:2], sim.bin_half_size_mm) for t, where in taught if where is not None]
    bins = own + bins  # a type's own bin first
    tolerance = JawTolerance(
        sim.jaw_across_tolerance_mm,
        sim.jaw_along_tolerance_mm,
        sim.bolt_end_margin_mm,
        sim.bolt_angle_tolerance_deg,
        config.parts.jaw_face_width_mm,
        config.parts.jaw_max_opening_mm,
    )
    world = World(parts, truth, bins, tolerance)
    marks = config.drift.marks_mm or sim.reference_marks_mm
    camera = SimCamera(
        world, model, seed=sim.seed, marks_mm=np.array(marks), mark_diameter_mm=config.drift.mark_diameter_mm, bump=bump
    )
    log.info("simulated cell: %d parts on the table, calibration %s", len(parts), note)
    if config.arm.kind == "robot-server":
        yield from _robot_server_cell(config, world, camera, calibration, note, marks)
        return
    if sim_arm_kind(config.arm) != "sim":
        with emulated_arm(
            config.arm, world, sim.emulator_speed_scale, sim.arm_fault_after_grips, sim.arm_fault
        ) as emulated:
            yield SimCell(world, camera, emulated.arm, calibration, note, emulated, marks)
        return
    arm = SimArm(
        world,
        plan.workspace,
        speed_mm_s=sim.speed_mm_s,
        gripper_s=sim.gripper_s,
        realtime=sim.realtime,
    )
    yield SimCell(world, camera, arm, calibration, note, None, marks)


def _robot_server_cell(
    config: CellConfig, world: World, camera: SimCamera, calibration: Calibration, note: str, marks: list
) -> Iterator[SimCell]:
    """arm.kind robot-server in the simulated cell: the cell's arm is the robot server, listening on its
    real socket; the simulated arm is the robot's, moved by a simulated robot program over that socket
    (robot_server.simulated_robot) or by an outside client's reports (cell.sim.robot)."""
    from cell.sim.robot import robot_for
    from drivers.arm.factory import make_arm
    from drivers.arm.robot_server import RobotServerArm

    sim = config.sim
    world_arm = SimArm(
        world, config.planning.workspace, speed_mm_s=sim.speed_mm_s, gripper_s=sim.gripper_s, realtime=sim.realtime
    )
    arm = make_arm(config.arm, config.robot_server)
    assert isinstance(arm, RobotServerArm)
    with arm.serving() as server:
        with robot_for(world_arm, server.address, config.robot_server.simulated_robot, arm.board.observers):
            yield SimCell(world, camera, arm, calibration, note, None, marks, world_arm)


def sim_plate_camera(config: CellConfig) -> SimCamera:
    """The simulated camera over the calibration plate, nothing else on the table: what
    `run-cell camera` looks through with camera.source 'sim' (fresh sensor noise each frame)."""
    model = default_camera(config.camera.width_px, config.camera.height_px)
    world = World([], Truth(0.0, 0.0, 0.0, 0.0), [])
    return SimCamera(
        world,
        model,
        seed=config.sim.seed,
        marks_mm=plate_centres_mm(config.plate),
        mark_diameter_mm=config.plate.diameter_mm,
    )

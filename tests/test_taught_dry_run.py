"""A taught recipe end to end: two part types taught from rendered images into a recipe with their
bins (`run-cell part teach --bin-robot-mm X Y Z`, no file edited by hand), then `run-cell --dry-run --recipe FILE` lays those parts out on the simulated table (each
rendered from its model, extruded with its holes), finds them by shape, plans the jaws along each
model's grip and clears the table; the run's summary and history name the types."""

from __future__ import annotations

import contextlib
import json
import shutil
import sqlite3

import cv2
import numpy as np
import pytest

from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.camera_model import CameraModel
from cell.cli import main
from cell.core.parts import BUILT_IN_PARTS
from cell.planning import Planner, TableToRobot, Unreachable
from cell.recipes import RecipeError, load_recipe_file, parse_recipe
from cell.run_config import PlanningConfig
from cell.sim.flatparts import random_types
from cell.sim.parts import PartSpec, render_scene
from cell.sim.world import SimPart
from cell.vision.types import LocatedPart

W, H = 960, 540
TYPES = random_types(seed=3)
KINDS = ("l-bracket", "plate-4h")
BINS = {"l-bracket": (200.0, 60.0, 60.0), "plate-4h": (200.0, 160.0, 60.0)}

SIM_CONFIG = f"""
[camera]
source = "sim"
width_px = {W}
height_px = {H}

[sim]
perfect_calibration = true
taught_parts_per_type = 3

[drift]
mark_diameter_mm = 3.0  # the table's marks seen at this small camera size
"""


POSES = [((60.0, 50.0, 20.0), (200.0, 110.0, 145.0)), ((230.0, 40.0, 280.0), (80.0, 120.0, 75.0))]


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """Two rendered images of each type (two parts each) and the camera's calibration."""
    d = tmp_path_factory.mktemp("taught-images")
    cam = CameraModel.looking_down(W, H, 0.3, (144.0, 81.0), tilt_deg=4.0, k1=-0.04)
    Calibration("camera", CameraMap(cam), (W, H), cam).save(d / "cal.json")
    for name in KINDS:
        for k, pose in enumerate(POSES):
            cv2.imwrite(str(d / f"{name}-{k}.png"), render_scene(cam, [TYPES[name].placed(*p) for p in pose], seed=k))
    return d


def teach_argv(images, name: str, recipe, *extra: str) -> list[str]:
    argv = ["part", "teach", name, "--calibration", str(images / "cal.json")]
    argv += ["--height-mm", str(TYPES[name].height_mm), "--recipe", str(recipe), *extra]
    for k in range(len(POSES)):
        argv += ["--image", str(images / f"{name}-{k}.png")]
    return argv


@pytest.fixture(scope="module")
def recipe(images, tmp_path_factory):
    """Both types taught from two rendered images each, each with its bin on the command line."""
    d = tmp_path_factory.mktemp("taught-run")
    path = d / "taught.toml"
    for name in KINDS:
        assert main(teach_argv(images, name, path, "--bin-robot-mm", *(str(v) for v in BINS[name]))) == 0
    (d / "sim.toml").write_text(SIM_CONFIG, encoding="utf-8")
    return path


def test_a_dry_run_with_a_taught_recipe_clears_the_table(recipe, tmp_path, capsys):
    logs = tmp_path / "logs"
    code = main(
        ["--config", str(recipe.parent / "sim.toml"), "--dry-run", "--recipe", str(recipe), "--log-dir", str(logs)]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    truth = next(line for line in out.splitlines() if line.startswith("simulated truth:"))
    assert "table" not in truth, truth  # nothing left on it
    for name in KINDS:
        assert f"bin:{name}: 3 {name}" in truth, truth  # each part in its own type's bin
    summary = next(line for line in out.splitlines() if line.startswith("picked "))
    assert "0 misses" in summary and "0 unreachable" in summary, summary
    for name in KINDS:
        assert f"3 {name}" in summary, summary
    targets = [json.loads(line) for line in next(logs.glob("run-*.jsonl")).read_text().splitlines()]
    jaws = [e for e in targets if e["kind"] == "arm" and e["command"] == "move_to" and e["state"] == "pick"]
    assert jaws and all(len(e["args"]) == 4 for e in jaws)  # every pick turns the jaws to the model's grip
    stores = list(tmp_path.rglob("history.sqlite"))
    assert len(stores) == 1, f"one rehearsal history store under {tmp_path}: {stores}"
    with sqlite3.connect(stores[0]) as db:
        rows = list(db.execute("select class, outcome, count(*) from picks group by class, outcome"))
    assert sorted(rows) == [("l-bracket", "picked", 3), ("plate-4h", "picked", 3)]


def test_the_recipe_names_its_types_bins_and_the_planner_checks_them(recipe):
    loaded, shapes = load_recipe_file(recipe)
    assert loaded.classes == frozenset(KINDS)
    assert {n: t.bin_robot_mm for n, t in loaded.types.items()} == BINS  # written by part teach
    assert loaded.class_numbers() == {"bolt": 1, "nut": 2, "l-bracket": 3, "plate-4h": 4}
    parts = loaded.registry()
    assert [c.opcua_name for c in parts][len(BUILT_IN_PARTS) :] == ["PickedLBrackets", "PickedPlate4hs"]
    plans = loaded.taught_plans()
    bracket = next(m for m in shapes if m.name == "l-bracket")
    assert plans["l-bracket"].pick_above_table_mm == pytest.approx(bracket.height_mm / 2)
    planner = Planner(PlanningConfig.model_validate(_planning()), TableToRobot(0.0, -132.0, 40.0, 0.0), plans)
    assert planner.bin_problems() == []
    centre = np.array([100.0, 80.0])
    grasp, jaw = bracket.grip_on_table(centre, 30.0)
    part = LocatedPart(
        1, "l-bracket", "", (0.0, 0.0), (100.0, 80.0), 30.0, True, tuple(grasp), features={"jaw_angle_deg": jaw}
    )
    t = planner.target(part)
    assert t.robot_mm[:2] == pytest.approx((grasp[0] - 132.0, grasp[1] + 40.0))
    assert t.jaw_angle_deg == pytest.approx(((jaw + 90.0) % 180.0) - 90.0)
    assert t.bin_robot_mm == BINS["l-bracket"]
    far = Planner(
        PlanningConfig.model_validate(_planning()),
        TableToRobot(0.0, -132.0, 40.0, 0.0),
        {"l-bracket": plans["l-bracket"].model_copy(update={"bin_robot_mm": (900.0, 0.0, 60.0)})},
    )
    assert any("types.l-bracket.bin_robot_mm" in p for p in far.bin_problems())
    with pytest.raises(Unreachable, match="without its grip"):
        planner.target(LocatedPart(2, "plate-4h", "", (0.0, 0.0), (100.0, 80.0), None, True))


def _planning() -> dict:
    bins = {"pick_above_table_mm": 3.0, "bin_robot_mm": (-200.0, 60.0, 60.0)}
    return {"bolt": bins, "nut": bins}


@pytest.mark.parametrize(
    "extra, says",
    [
        ("pick_above_table_mm = 50.0", "jaws would close above the part"),
        ("approach_above_table_mm = 0.5", "not above the part"),
        ("bin_robot_mm = [1.0, 2.0]", "bin_robot_mm"),
    ],
)
def test_a_taught_types_moves_are_validated(extra, says):
    text = f'[types.a]\nmodel = "m.json"\nmodel_sha256 = "{"0" * 64}"\nheight_mm = 3.0\n{extra}\n'
    with pytest.raises(RecipeError, match=says):
        parse_recipe(text, "r.toml")


@pytest.mark.parametrize("added_later", [False, True])
def test_the_line_service_picks_a_prepared_taught_recipe_and_names_its_types(recipe, tmp_path, added_later):
    """The service's part registry holds the taught types of the recipes in its folder (so OPC UA,
    Sparkplug and /metrics have their counters from start-up); a job of the prepared recipe finds
    them by shape and picks them into their bins, the shift's counters by type. A recipe put in the
    folder after start-up is picked and counted by name too; the interfaces' counters, made at
    start-up, stay as they were (a Sparkplug birth names every metric it will send)."""
    from cell.commands.serve import open_service
    from cell.core.commands import Command, RecipeRequest, VisionState
    from cell.core.values import counter_values
    from cell.service.opcua import browse_names
    from cell.sim.world import Bin
    from cell.telemetry.metrics import class_specs
    from tests.test_service import small_config, wait_for

    cfg = small_config(tmp_path, perfect_calibration=True)
    recipes = tmp_path / "recipes"
    recipes.mkdir()
    cfg.service.machine_vision.recipes_dir = recipes

    def add_recipe() -> None:
        shutil.copy(recipe, recipes / "taught.toml")
        shutil.copytree(recipe.parent / "models", recipes / "models")

    if not added_later:
        add_recipe()
    with contextlib.ExitStack() as stack:
        service = open_service(cfg, True, stack)
        if added_later:
            add_recipe()
            assert [c.name for c in service.parts] == ["bolt", "nut"]
        else:
            assert [c.name for c in service.parts] == ["bolt", "nut", *KINDS]
            assert {"PickedLBrackets", "PickedPlate4hs"} <= set(browse_names(service.parts))
            assert {"Counters/Picked L Brackets", "Counters/Picked Plate 4hs"} <= {
                s.name for s in class_specs(service.parts)
            }
        world = service.cell.sim.world  # the simulated table: two taught parts and a nut this recipe leaves
        _, shapes = load_recipe_file(recipe)
        poses = [(60.0, 60.0, 30.0), (200.0, 110.0, 200.0)]
        placed = [TYPES[m.name].placed(*pose) for m, pose in zip(shapes, poses, strict=True)]
        world.parts[:] = [SimPart(i + 1, p) for i, p in enumerate([*placed, PartSpec("nut", "M8", 130.0, 150.0)])]
        world.bins[:0] = [Bin(name, BINS[name][:2], 40.0) for name in KINDS]
        world.version += 1
        service.start()
        service.command(Command.PREPARE_RECIPE, request=RecipeRequest("taught"))
        service.command(Command.START_SINGLE)
        wait_for(
            lambda: (
                service.snapshot().vision_state == VisionState.READY and service.snapshot().counters.picked_total >= 2
            ),
            what="the job to pick both taught parts",
        )
        counters = service.snapshot().counters
        assert dict(counters.picked) == {"l-bracket": 1, "plate-4h": 1}
        values = counter_values(service.snapshot(), service.parts)
        if not added_later:
            assert values["picked_l_brackets"] == 1 and values["picked_plate_4hs"] == 1
        assert [p.spec.kind for p in world.on_table()] == [
            "nut"
        ]  # the shift's feeder empties the bins; the nut: not its


def test_the_simulated_jaws_hold_a_taught_part_only_along_its_grip(recipe):
    """The simulated world holds a flat part of any shape where its model's grip says, and refuses
    jaws turned across it (wider than the jaws open) or off its centre."""
    from cell.sim.parts import ExtrudedPart
    from cell.sim.world import JawTolerance, Truth, World

    _, shapes = load_recipe_file(recipe)
    m = next(s for s in shapes if s.name == "plate-4h")
    part = ExtrudedPart(m.name, m.outline_mm, tuple(m.holes_mm), m.height_mm).placed(100.0, 80.0, 30.0)
    grasp, jaw = m.grip_on_table(np.array([100.0, 80.0]), 30.0)
    z = m.height_mm / 2

    def grip(dx: float, dy: float, turn_deg: float) -> str:
        world = World([part], Truth(0.0, 0.0, 0.0, 0.0), [], JawTolerance(jaw_max_opening_mm=30.0))
        return world.grip((grasp[0] + dx, grasp[1] + dy, z), jaw + turn_deg).reason

    assert grip(0.0, 0.0, 0.0).endswith("held")
    assert "wide across the jaws" in grip(0.0, 0.0, 90.0)
    off = 3.0 * np.array([np.cos(np.radians(jaw)), np.sin(np.radians(jaw))])
    assert "off centre between the jaws" in grip(*off, 0.0)


def test_a_type_taught_without_a_bin_is_named_in_words_and_left_on_the_table(images, tmp_path, capsys):
    """Teach now, place later: a type with no bin is written (the recipe valid), the teacher is told it stays on
    the table, and the dry run says so once before the job; its parts are found, counted and left, while a type
    sharing the nut's bin (--bin-of nut) is cleared into it. The job itself is not faulted for it."""
    path = tmp_path / "later.toml"
    assert main(teach_argv(images, "l-bracket", path)) == 0
    out = capsys.readouterr().out
    assert "l-bracket: no bin: found and counted, left on the table; the robot is told class_no 3" in out, out
    assert main(teach_argv(images, "plate-4h", path, "--bin-of", "nut")) == 0
    out = capsys.readouterr().out
    assert "plate-4h: into the bin at robot (200, 60, 60) mm; the robot is told class_no 4" in out, out
    assert "recipe later: l-bracket has no bin either: left on the table" in out, out
    loaded, _ = load_recipe_file(path)
    assert loaded.unbinned() == ["l-bracket"] and loaded.types["plate-4h"].bin_robot_mm == (200.0, 60.0, 60.0)
    (tmp_path / "sim.toml").write_text(SIM_CONFIG, encoding="utf-8")
    code = main(["--config", str(tmp_path / "sim.toml"), "--dry-run", "--recipe", str(path)])
    out = capsys.readouterr().out
    assert code == 0, out
    said = "recipe later: l-bracket has no bin: found and counted but left on the table"
    assert out.count(said) == 1, out
    truth = next(line for line in out.splitlines() if line.startswith("simulated truth:"))
    assert "table: 3 l-bracket" in truth and "3 plate-4h" in truth and "table: 3 plate-4h" not in truth, truth


def test_a_bin_outside_the_workspace_or_of_an_unknown_type_is_refused_in_words(images, tmp_path, capsys):
    path = tmp_path / "r.toml"
    assert main(teach_argv(images, "l-bracket", path, "--bin-robot-mm", "900", "0", "60")) != 0
    err = capsys.readouterr().err
    assert "--bin-robot-mm (900, 0, 60) mm: robot x = 900.0 mm is outside the workspace" in err, err
    assert not path.exists()  # nothing written
    assert main(teach_argv(images, "l-bracket", path, "--bin-of", "washer")) != 0
    err = capsys.readouterr().err
    assert "--bin-of washer: the recipe has no type 'washer'" in err and "bolt, nut" in err, err
    assert main(teach_argv(images, "l-bracket", path)) == 0  # no bin: allowed
    assert main(teach_argv(images, "plate-4h", path, "--bin-of", "l-bracket")) != 0
    assert "--bin-of l-bracket: 'l-bracket' has no bin itself" in capsys.readouterr().err


def test_teaching_a_type_again_keeps_its_bin_and_class_no(images, tmp_path, capsys):
    path = tmp_path / "again.toml"
    assert main(teach_argv(images, "plate-4h", path, "--bin-robot-mm", "200", "160", "60")) == 0
    assert main(teach_argv(images, "l-bracket", path, "--bin-robot-mm", "200", "60", "60")) == 0
    text = path.read_text(encoding="utf-8")
    path.write_text(text.replace("[types.plate-4h]\n", "[types.plate-4h]\napproach_above_table_mm = 50.0\n"))
    assert main(teach_argv(images, "plate-4h", path)) == 0  # no bin given: the one it had stays
    capsys.readouterr()
    loaded, _ = load_recipe_file(path)
    plate = loaded.types["plate-4h"]
    assert (plate.bin_robot_mm, plate.class_no, plate.approach_above_table_mm) == ((200.0, 160.0, 60.0), 3, 50.0)
    assert loaded.class_numbers()["l-bracket"] == 4
    assert list(loaded.types) == ["plate-4h", "l-bracket"]  # in place, not appended

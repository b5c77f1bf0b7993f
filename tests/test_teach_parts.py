"""Taught part types: `run-cell part teach` from rendered images, then `run-cell locate --recipe`.

The images come from the simulated world (cell/sim/parts.py renders any extruded outline with
holes through a tilted, distorted camera); the truth is where the renderer put each part.
"""

from __future__ import annotations

import json
import os
import re

import cv2
import numpy as np
import pytest

from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.camera_model import CameraModel
from cell.cli import main
from cell.recipes import RecipeBook, RecipeError, load_recipe_file
from cell.sim.flatparts import random_types
from cell.sim.parts import PartSpec, render_scene
from cell.vision.shapes import Footprint, ShapeModelError
from tests.helpers import DATA, need

W, H = 960, 540
TYPES = random_types(seed=3)
BRACKET, MIRROR, PLATE4, PLATE3 = (TYPES[n] for n in ("l-bracket", "l-bracket-mirror", "plate-4h", "plate-3h"))


@pytest.fixture(scope="module")
def cam() -> CameraModel:
    return CameraModel.looking_down(W, H, 0.3, (144.0, 81.0), tilt_deg=4.0, k1=-0.04)


@pytest.fixture(scope="module")
def files(tmp_path_factory, cam):
    d = tmp_path_factory.mktemp("teach")
    Calibration("camera", CameraMap(cam), (W, H), cam).save(d / "cal.json")
    poses = [((60.0, 50.0, 20.0), (200.0, 110.0, 145.0)), ((230.0, 40.0, 280.0), (80.0, 120.0, 75.0))]
    for part in (BRACKET, MIRROR, PLATE4, PLATE3):
        for k, pose in enumerate(poses):
            frame = render_scene(cam, [part.placed(*p) for p in pose], seed=k)
            cv2.imwrite(str(d / f"{part.name}-{k}.png"), frame)
    return d


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def teach(capsys, files, name, images, recipe="recipe.toml", *extra):
    args = [
        "part",
        "teach",
        name,
        "--calibration",
        files / "cal.json",
        "--height-mm",
        TYPES.get(name, BRACKET).height_mm,
    ]
    for image in images:
        args += ["--image", files / image]
    return run(capsys, *args, "--recipe", files / recipe, *extra)


@pytest.fixture(scope="module")
def taught(files):
    """The four types taught into one recipe (the module's capsys is not available: a plain call)."""
    for part in (BRACKET, MIRROR, PLATE4, PLATE3):
        argv = ["part", "teach", part.name, "--calibration", str(files / "cal.json")]
        argv += ["--height-mm", str(part.height_mm), "--recipe", str(files / "recipe.toml")]
        argv += ["--image", str(files / f"{part.name}-0.png"), "--image", str(files / f"{part.name}-1.png")]
        assert main(argv) == 0
    return files / "recipe.toml"


def angle_offset(name: str, recipe) -> float:
    """The model frame's angle in the part's design frame (teaching picks its own frame)."""
    model = next(m for m in load_recipe_file(recipe)[1] if m.name == name)
    part = TYPES[name]
    return model.match(Footprint(part.outline_mm, list(part.holes_mm))).angle_deg


def test_teach_then_locate_tells_mirror_images_and_a_missing_hole_apart(taught, files, cam, capsys):
    scene = [
        BRACKET.placed(70.0, 45.0, 200.0),
        MIRROR.placed(200.0, 50.0, 35.0),
        PLATE4.placed(60.0, 120.0, 310.0),
        PLATE3.placed(215.0, 120.0, 100.0),
        PartSpec("nut", "M8", 140.0, 85.0, 10.0),
        PartSpec("washer", "M8", 140.0, 140.0),
    ]
    cv2.imwrite(str(files / "scene.png"), render_scene(cam, scene, seed=7))
    code, out, err = run(
        capsys,
        "locate",
        "--image",
        files / "scene.png",
        "--calibration",
        files / "cal.json",
        "--recipe",
        taught,
        "--json",
    )
    assert code == 0, err
    objs = json.loads(out)["objects"]
    assert len(objs) == len(scene)
    for part in scene:
        o = min(objs, key=lambda o: np.hypot(o["world_mm"][0] - part.x_mm, o["world_mm"][1] - part.y_mm))
        if part.kind == "extruded":
            assert o["class"] == part.name, o["reason"]
            assert np.hypot(o["world_mm"][0] - part.x_mm, o["world_mm"][1] - part.y_mm) < 0.2
            expected = part.angle_deg + angle_offset(part.name, taught)
            assert abs((o["angle_deg"] - expected + 180.0) % 360.0 - 180.0) < 1.0
            assert 0.95 < o["score"] <= 1.0 and o["pick"] is True
        elif part.kind == "nut":
            assert o["class"] == "nut"
        else:
            assert o["class"] == "unknown" and o["pick"] is False and "taught" in o["reason"]


def test_touching_parts_and_a_part_cut_by_the_edge_stay_unknown(taught, files, cam, capsys):
    width = float(np.ptp(PLATE4.outline_mm[:, 0]))
    scene = [
        PLATE4.placed(100.0, 80.0, 0.0),
        PLATE4.placed(100.0 + width - 1.0, 80.0, 0.0),
        BRACKET.placed(2.0, 60.0, 0.0),
    ]
    cv2.imwrite(str(files / "crowded.png"), render_scene(cam, scene, seed=8))
    code, out, err = run(
        capsys,
        "locate",
        "--image",
        files / "crowded.png",
        "--calibration",
        files / "cal.json",
        "--recipe",
        taught,
        "--json",
    )
    assert code == 0, err
    objs = json.loads(out)["objects"]
    assert len(objs) == 2 and all(o["class"] == "unknown" for o in objs)
    reasons = sorted(o["reason"] for o in objs)
    assert any("border" in r for r in reasons) and any("touching" in r for r in reasons), reasons


def test_the_teach_report_and_the_recipe(taught, files):
    text = taught.read_text()
    assert "[types.l-bracket]" in text and "[types.plate-3h]" in text
    recipe, models = load_recipe_file(taught)
    assert set(recipe.types) == {"l-bracket", "l-bracket-mirror", "plate-4h", "plate-3h"}
    by_name = {m.name: m for m in models}
    assert by_name["l-bracket"].mirror_distinct and by_name["l-bracket"].symmetry == 1
    assert by_name["plate-4h"].examples == 4  # two images of two examples each
    assert by_name["l-bracket"].grip.opening_mm <= 30.0
    assert not [p for p in files.iterdir() if p.name.startswith(".") or "tmp" in p.name]  # no temporary files left


def test_symmetry_found_from_the_shape(tmp_path, cam, capsys):
    Calibration("camera", CameraMap(cam), (W, H), cam).save(tmp_path / "cal.json")
    for name, says in (("gear", "symmetry: 6-fold"), ("spacer", "symmetry: round"), ("tab-washer", "symmetry: 3-fold")):
        part = TYPES[name]
        frame = render_scene(cam, [part.placed(80.0, 60.0, 10.0), part.placed(200.0, 100.0, 77.0)], seed=1)
        cv2.imwrite(str(tmp_path / f"{name}.png"), frame)
        code, out, err = run(
            capsys, "part", "teach", name, "--image", tmp_path / f"{name}.png", "--calibration", tmp_path / "cal.json",
            "--height-mm", part.height_mm, "--recipe", tmp_path / "r.toml",
        )  # fmt: skip
        assert code == 0, err
        assert says in out and "consistency: worst misfit" in out


@pytest.mark.parametrize(
    "images, says",
    [
        (["l-bracket-0.png", "plate-4h-1.png"], "the examples disagree"),
        (["l-bracket-0.png", "l-bracket-mirror-1.png"], "a mirror image?"),
        (["plate-4h-0.png", "plate-3h-1.png"], "4 against 3 holes"),
        (["touching.png", "l-bracket-1.png"], "parts touching?"),
        (["at-edge.png"], "leaves the image"),
    ],
)
def test_teaching_refuses_in_words(files, cam, capsys, images, says):
    if "touching.png" in images:
        frame = render_scene(cam, [BRACKET.placed(100.0, 80.0, 0.0), BRACKET.placed(100.0, 80.0 + 18.0, 0.0)], seed=2)
        cv2.imwrite(str(files / "touching.png"), frame)
    if "at-edge.png" in images:
        cv2.imwrite(str(files / "at-edge.png"), render_scene(cam, [BRACKET.placed(3.0, 60.0, 0.0)], seed=3))
    before = (files / "refused.toml").exists()
    code, out, err = teach(capsys, files, "l-bracket", images, "refused.toml")
    assert code != 0 and says in err, err
    assert "Traceback" not in err and "hint:" in err
    assert not before and not (files / "refused.toml").exists()


def test_a_part_the_jaws_cannot_open_for_is_refused(files, capsys):
    (files / "small-jaws.toml").write_text("[parts]\njaw_max_opening_mm = 6.0\n")
    code, _, err = teach(
        capsys, files, "l-bracket", ["l-bracket-0.png"], "jaws.toml", "--config", files / "small-jaws.toml"
    )
    assert code != 0 and "cannot be gripped" in err and "6 mm" in err


def test_a_model_that_does_not_match_its_hash_is_refused(taught, files, capsys, tmp_path):
    recipe, _ = load_recipe_file(taught)
    copy = tmp_path / "recipes"
    (copy / "models").mkdir(parents=True)
    (copy / "r.toml").write_text(taught.read_text())
    for t in recipe.types.values():
        (copy / t.model).write_bytes((files / t.model).read_bytes())
    model = copy / recipe.types["plate-3h"].model
    model.write_text(model.read_text().replace('"symmetry": 1', '"symmetry": 2'))
    code, _, err = run(
        capsys, "locate", "--image", files / "plate-3h-0.png", "--calibration", files / "cal.json", "--recipe",
        copy / "r.toml",
    )  # fmt: skip
    assert code != 0 and "changed since the recipe named it" in err
    with pytest.raises(ShapeModelError, match="changed since the recipe named it"):
        RecipeBook(copy).load("r")
    # The recipe's height must be the model's.
    model.write_bytes((files / recipe.types["plate-3h"].model).read_bytes())
    RecipeBook(copy).load("r")
    text = (copy / "r.toml").read_text()
    at = text.index("[types.plate-3h]")
    (copy / "r.toml").write_text(text[:at] + re.sub(r"height_mm = \S+", "height_mm = 9.5", text[at:], count=1))
    with pytest.raises(RecipeError, match="taught at"):
        RecipeBook(copy).load("r")


def test_the_recipe_is_kept_and_a_type_taught_again_is_replaced(files, capsys):
    recipe = files / "kept.toml"
    original = (
        "# nuts and one taught bracket\n"
        'description = "kit 17"\n\n'
        "[pick.nut]  # to the right\n"
        "pick_above_table_mm = 2.0\n"
        "bin_robot_mm = [200.0, 60.0, 60.0]\n"
    )
    recipe.write_text(original)
    assert teach(capsys, files, "l-bracket", ["l-bracket-0.png"], "kept.toml")[0] == 0
    first = recipe.read_text()
    assert first.startswith(original) and first.count("[types.l-bracket]") == 1
    assert teach(capsys, files, "l-bracket", ["l-bracket-1.png"], "kept.toml")[0] == 0
    second = recipe.read_text()
    assert second.startswith(original) and second.count("[types.l-bracket]") == 1 and second != first
    r, models = load_recipe_file(recipe)
    assert set(r.pick) == {"nut"} and [m.name for m in models] == ["l-bracket"]
    # A recipe that is not valid is not touched.
    recipe.write_text("speed = 3\n")
    code, _, err = teach(capsys, files, "l-bracket", ["l-bracket-0.png"], "kept.toml")
    assert code != 0 and "speed" in err and recipe.read_text() == "speed = 3\n"
    assert not [p for p in os.listdir(files) if p.startswith("kept.toml.") or p.endswith(".tmp")]


def test_real_photos_a_taught_type_is_told_from_the_others(tmp_path, capsys):
    """Types taught from two real front-lit photos each are found in the other photos of the same
    camera, and never given to another kind of part (the other parts fall to the built-in rules or
    stay unknown)."""
    photos = need(DATA / "parts-photos")
    taught = {"ring": ("arandela_0000", "arandela_0030"), "screw": ("tornillo_0000", "tornillo_0040")}
    taught["nut-real"] = ("tuerca_0000", "tuerca_0020")
    for name, shots in taught.items():
        images = [a for s in shots for a in ("--image", next(photos.glob(f"packt_*_{s}.png")))]
        code, _, err = run(
            capsys,
            "part",
            "teach",
            name,
            *images,
            "--mm-per-px",
            0.3,
            "--height-mm",
            2,
            "--recipe",
            tmp_path / "r.toml",
        )
        assert code == 0, err
    kinds = {"tuerca": "nut-real", "arandela": "ring", "tornillo": "screw"}
    found = {k: 0 for k in kinds.values()}
    for photo in sorted(photos.glob("packt_*_0*.png")):
        kind = kinds[photo.stem.split("_")[2]]
        code, out, err = run(
            capsys, "locate", "--image", photo, "--mm-per-px", 0.3, "--recipe", tmp_path / "r.toml", "--json"
        )
        assert code == 0, err
        classes = [o["class"] for o in json.loads(out)["objects"]]
        assert not set(classes) & (set(kinds.values()) - {kind}), (photo.name, classes)
        found[kind] += classes.count(kind)
    assert found["nut-real"] >= 8 and found["ring"] >= 4 and found["screw"] >= 4, found


def test_a_part_whose_jaws_would_touch_a_neighbour_waits(taught, files, cam, capsys):
    """The L bracket's jaws close across its narrow width; a nut put right where a jaw goes makes it
    wait (not picked, saying which part is in the way); the same nut further off does not."""
    model = next(m for m in load_recipe_file(taught)[1] if m.name == "l-bracket")
    centre, angle = np.array([140.0, 80.0]), 30.0
    grasp, jaw_deg = model.grip_on_table(centre, angle + angle_offset("l-bracket", taught))
    d = np.array([np.cos(np.radians(jaw_deg)), np.sin(np.radians(jaw_deg))])
    results = {}
    for name, reach in (
        ("crowded", model.grip.opening_mm / 2 + 5.0 + 2.5),
        ("clear", model.grip.opening_mm / 2 + 14.0),
    ):
        nut = grasp + reach * d
        scene = [BRACKET.placed(*centre, angle), PartSpec("nut", "M5", float(nut[0]), float(nut[1]))]
        cv2.imwrite(str(files / f"{name}.png"), render_scene(cam, scene, seed=4))
        code, out, err = run(
            capsys, "locate", "--image", files / f"{name}.png", "--calibration", files / "cal.json", "--recipe", taught,
            "--json",
        )  # fmt: skip
        assert code == 0, err
        results[name] = next(o for o in json.loads(out)["objects"] if o["class"] == "l-bracket")
    assert results["crowded"]["pick"] is False and "jaws would touch part" in results["crowded"]["reason"]
    assert results["clear"]["pick"] is True, results["clear"]["reason"]

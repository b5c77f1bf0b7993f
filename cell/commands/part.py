"""`run-cell part teach`: a part type learnt from example images, added to a recipe."""

from __future__ import annotations

import argparse
from pathlib import Path

from cell.calibration.store import Calibration
from cell.commands.argtypes import finite_float
from cell.config import load_config
from cell.errors import InputError
from cell.imageio import read_image
from cell.recipes import add_taught_type, bin_of, check_bin, read_recipe_if_any
from cell.vision.locate import PixelScale
from cell.vision.teaching import check_height_mm, check_type_name, examples_in, teach_examples


def register(sub) -> None:
    p = sub.add_parser(
        "part",
        help="teach a part type from example images",
        description="Part types a recipe picks beside bolts and nuts (docs/parts.md, 'Teaching a part type').",
    )
    verbs = p.add_subparsers(dest="part_command", metavar="VERB", required=True)
    t = verbs.add_parser(
        "teach",
        help="learn a part type from images of examples, each alone on the backlit table",
        description="Learn a part type's shape from one or more images, each showing one or more examples of "
        "the part alone on the backlit table; write its model beside the recipe (models/NAME-<sha>.json) and "
        "name it in the recipe ([types.NAME], the recipe created if absent). Prints how consistent the examples "
        "were, the symmetry found and the grip; refuses when the examples disagree, touch, leave the image or "
        "cannot be gripped.",
    )
    t.add_argument("name", help="the part type's name: 1-32 lower-case letters, digits, - and _ (e.g. bracket-l)")
    t.add_argument("--image", required=True, action="append", type=Path, help="an image of examples (repeat)")
    where = t.add_mutually_exclusive_group(required=True)
    where.add_argument("--calibration", type=Path, help="calibration JSON (table mm, height correction)")
    where.add_argument("--mm-per-px", type=finite_float, help="a plain scale for an uncalibrated camera")
    t.add_argument("--height-mm", required=True, type=finite_float, help="the part's height lying on the table")
    t.add_argument("--recipe", required=True, type=Path, help="recipe TOML to add the type to (created if absent)")
    t.add_argument(
        "--config", type=Path, help="cell config TOML (its [parts]: segmentation, jaws; its planning.workspace)"
    )
    bins = t.add_mutually_exclusive_group()
    bins.add_argument(
        "--bin-robot-mm",
        nargs=3,
        type=finite_float,
        metavar=("X", "Y", "Z"),
        help="where the gripper opens over this type's bin, robot frame (inside planning.workspace); "
        "without a bin the type is found and counted but left on the table",
    )
    bins.add_argument(
        "--bin-of",
        metavar="TYPE",
        help="the same bin as another class of the recipe (bolt, nut, or a taught type that has one)",
    )
    t.set_defaults(func=cmd_teach)


def cmd_teach(args: argparse.Namespace) -> int:
    name = check_type_name(args.name)
    try:
        height_mm = check_height_mm(args.height_mm)
    except InputError:
        raise InputError(f"--height-mm {args.height_mm:g}: the part's height, more than 0 and at most 200 mm") from None
    config = load_config(args.config)
    parts = config.parts
    where, note = None, ""  # the bin, checked before any image is read
    if args.bin_robot_mm is not None:
        where = check_bin("--bin-robot-mm", args.bin_robot_mm, config.planning)
    elif args.bin_of is not None:
        recipe = read_recipe_if_any(args.recipe)
        where = check_bin(f"--bin-of {args.bin_of}", bin_of(recipe, config.planning, args.bin_of), config.planning)
        note = f"the bin of {args.bin_of}"
    mapper: Calibration | PixelScale
    mapper = Calibration.load(args.calibration) if args.calibration is not None else PixelScale(args.mm_per_px)
    examples = []
    for path in args.image:
        image = read_image(path, config.camera.max_image_px, mapper.image_size)
        examples += examples_in(image, mapper, parts, height_mm, path.name)
    report = teach_examples(name, examples, height_mm, parts)
    added = add_taught_type(args.recipe, report.model, where, note)
    for line in report.lines:
        print(line)
    print(f"wrote {added.model_path} (sha256 {added.sha256[:12]}...) and [types.{name}] in {args.recipe}")
    for line in added.lines(name, args.recipe.stem):
        print(line)
    return 0

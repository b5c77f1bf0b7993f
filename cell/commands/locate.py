"""`run-cell locate`: find, classify and locate the parts in one image (the paper's Table IV, Fig. 6)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import get_args

import numpy as np

from cell.calibration.store import Calibration
from cell.commands.argtypes import finite_float
from cell.config import load_config
from cell.imageio import check_image_path, read_image, write_image_atomic
from cell.recipes import load_recipe_file
from cell.vision.annotate import annotate
from cell.vision.config import Preset
from cell.vision.locate import PixelScale, locate
from cell.vision.types import LocateResult


def register(sub) -> None:
    p = sub.add_parser(
        "locate",
        help="find, classify and locate bolts, nuts and taught part types in an image",
        description="Find the parts in one image, classify each (bolt, nut, or unknown with the reason) and give "
        "its table position through a calibration or a plain mm-per-pixel scale. Prints a table (--json: "
        "JSON); --annotate writes the image with each part outlined, numbered and labelled.",
    )
    p.add_argument("--image", required=True, type=Path, help="the table seen by the calibrated camera")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--calibration", type=Path, help="calibration JSON (table mm, height correction)")
    where.add_argument(
        "--mm-per-px", type=finite_float, help="a plain scale for an uncalibrated image (no height correction)"
    )
    p.add_argument("--config", type=Path, help="cell config TOML (its [parts] table)")
    p.add_argument(
        "--recipe", type=Path, help="recipe TOML whose taught part types are found too (run-cell part teach)"
    )
    p.add_argument("--preset", choices=get_args(Preset), help="override parts.preset")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument(
        "--annotate", type=Path, metavar="OUT.png", help="write the image with each part outlined and labelled"
    )
    p.set_defaults(func=cmd_locate)


def cmd_locate(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    parts = config.parts
    if args.preset:
        parts = parts.model_copy(update={"preset": args.preset})
    mapper: Calibration | PixelScale
    if args.calibration is not None:
        mapper = Calibration.load(args.calibration)
    else:
        mapper = PixelScale(args.mm_per_px)
    if args.annotate is not None:
        check_image_path(args.annotate)  # refuse before the work, not after it
    shapes = load_recipe_file(args.recipe)[1] if args.recipe is not None else []  # refused before the image
    image = read_image(args.image, config.camera.max_image_px, mapper.image_size)
    result = locate(image, mapper, parts, shapes)
    if args.annotate:
        write_image_atomic(args.annotate, annotate(image, result))
    if args.json:
        print(json.dumps(to_json(result), allow_nan=False))
    else:
        print(format_table(result))
    return 0


def _round(values, digits: int = 3):
    """Rounded floats; a number that is not finite becomes null (JSON has no NaN)."""
    if values is None:
        return None
    return [round(float(v), digits) if np.isfinite(v) else None for v in values]


def _number(value, digits: int):
    return None if value is None or not np.isfinite(value) else round(float(value), digits)


def to_json(result: LocateResult) -> dict:
    objects = []
    for p in result.objects:
        objects.append(
            {
                "id": p.id,
                "class": p.cls,
                "reason": p.reason,
                "pixel": _round(p.pixel),
                "world_mm": _round(p.table_mm),  # the documented key tools read (table mm)
                "angle_deg": _number(p.angle_deg, 2),
                "pick": p.pick,
                "grasp_mm": _round(p.grasp_mm),
                "jaw_opening_mm": _number(p.jaw_opening_mm, 2),
                "head_mm": _round(p.head_mm),
                "score": _number(p.score, 4),
            }
        )
    return {
        "objects": objects,
        "image_size": list(result.image_size),
        "elapsed_ms": round(result.elapsed_ms, 2),
        "warnings": result.warnings,
    }


def format_table(result: LocateResult) -> str:
    w, h = result.image_size
    lines = [f"{len(result.objects)} objects in a {w} x {h} image ({result.elapsed_ms:.1f} ms)"]
    lines += [f"warning: {text}" for text in result.warnings]
    wide = max([8, *(len(p.cls) + 1 for p in result.objects)])
    lines.append(
        f"{'No.':>4}  {'Object':<{wide}}{'x (px)':>9}{'y (px)':>9}{'X (mm)':>10}{'Y (mm)':>10}{'Angle':>8}  Pick  Reason"
    )
    for p in result.objects:
        angle = "" if p.angle_deg is None else f"{p.angle_deg:.1f}"
        lines.append(
            f"{p.id:>4}  {p.cls.capitalize():<{wide}}{p.pixel[0]:>9.1f}{p.pixel[1]:>9.1f}"
            f"{p.table_mm[0]:>10.3f}{p.table_mm[1]:>10.3f}{angle:>8}  {'yes' if p.pick else 'no ':<4}  {p.reason}"
        )
    return "\n".join(lines)

"""`run-cell locate`: find, classify and locate the parts in one image (the paper's Table IV, Fig. 6)."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import get_args

import cv2
import numpy as np

from cell.calibration.store import Calibration
from cell.commands.argtypes import finite_float
from cell.config import load_config
from cell.imageio import check_image_path, read_image, write_image_atomic
from cell.vision.config import Preset
from cell.vision.locate import PixelScale, locate
from cell.vision.types import LocateResult

_COLOURS_BGR = {"bolt": (0, 140, 255), "nut": (0, 180, 0), "unknown": (0, 0, 230)}


def register(sub) -> None:
    p = sub.add_parser("locate", help="find, classify and locate bolts and nuts in an image")
    p.add_argument("--image", required=True, type=Path, help="the table seen by the calibrated camera")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--calibration", type=Path, help="calibration JSON (table mm, height correction)")
    where.add_argument(
        "--mm-per-px", type=finite_float, help="a plain scale for an uncalibrated image (no height correction)"
    )
    p.add_argument("--config", type=Path, help="cell config TOML (its [parts] table)")
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
    if args.calibration is not None:
        mapper = Calibration.load(args.calibration)
    else:
        mapper = PixelScale(args.mm_per_px)
    if args.annotate is not None:
        check_image_path(args.annotate)  # refuse before the work, not after it
    image = read_image(args.image, config.camera.max_image_px, mapper.image_size)
    result = locate(image, mapper, parts)
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
    lines.append(
        f"{'No.':>4}  {'Object':<8}{'x (px)':>9}{'y (px)':>9}{'X (mm)':>10}{'Y (mm)':>10}{'Angle':>8}  Pick  Reason"
    )
    for p in result.objects:
        angle = "" if p.angle_deg is None else f"{p.angle_deg:.1f}"
        lines.append(
            f"{p.id:>4}  {p.cls.capitalize():<8}{p.pixel[0]:>9.1f}{p.pixel[1]:>9.1f}"
            f"{p.table_mm[0]:>10.3f}{p.table_mm[1]:>10.3f}{angle:>8}  {'yes' if p.pick else 'no ':<4}  {p.reason}"
        )
    return "\n".join(lines)


def annotate(image: np.ndarray, result: LocateResult, order: Sequence[int] | None = None) -> np.ndarray:
    """The image with each part outlined, numbered and labelled (the paper's Fig. 6): bolts with
    the line the jaws close along, unknown parts with the reason they are left. `order` (part
    ids in the order the cell will pick them) puts a badge 1, 2, 3... beside those parts."""
    out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    scale = max(out.shape[1] / 1280, 0.6)
    thick = max(1, round(2 * scale))
    rank = {part_id: n for n, part_id in enumerate(order or (), start=1)}
    for p in result.objects:
        colour = _COLOURS_BGR[p.cls]
        if p.outline_px is not None:
            cv2.drawContours(out, [p.outline_px], -1, colour, thick, cv2.LINE_AA)
        x, y = (int(round(v)) for v in p.pixel)
        cv2.drawMarker(out, (x, y), colour, cv2.MARKER_CROSS, max(6, round(12 * scale)), thick)
        if p.cls == "bolt" and p.outline_px is not None:
            _draw_jaws(out, p, thick)
        label = f"{p.id} {p.cls}" + (f": {_short(p.reason)}" if p.cls == "unknown" else "")  # red: never picked
        org = (x + round(8 * scale), y - round(8 * scale))
        cv2.putText(out, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, (255, 255, 255), thick + 2, cv2.LINE_AA)
        cv2.putText(out, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, colour, thick, cv2.LINE_AA)
        if p.id in rank:
            _draw_rank(out, (x, y), rank[p.id], scale, thick)
    return out


def _draw_rank(out: np.ndarray, centre: tuple[int, int], n: int, scale: float, thick: int) -> None:
    """The pick order as a white disc with a black number, up and left of the part's centre."""
    r = round(13 * scale)
    c = (centre[0] - round(1.6 * r), centre[1] - round(1.6 * r))
    cv2.circle(out, c, r, (255, 255, 255), -1, cv2.LINE_AA)
    cv2.circle(out, c, r, (0, 0, 0), max(1, thick // 2), cv2.LINE_AA)
    text = str(n)
    size = 0.55 * scale if n < 10 else 0.42 * scale
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, size, thick)
    org = (c[0] - w // 2, c[1] + h // 2)
    cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, size, (0, 0, 0), thick, cv2.LINE_AA)


def _draw_jaws(out: np.ndarray, part, thick: int) -> None:
    """A line across the bolt's axis through its centre, with a bar at each end: where the jaws close."""
    points = part.outline_px.reshape(-1, 2).astype(np.float32)
    vx, vy = cv2.fitLine(points, cv2.DIST_L2, 0, 0.01, 0.01).ravel()[:2]
    nx, ny = -vy, vx  # across the axis
    width = np.ptp(points @ np.array([nx, ny], np.float32))
    half = 0.5 * width + 6 * thick
    c = np.array(part.pixel, np.float32)
    ends = [c + s * half * np.array([nx, ny]) for s in (-1, 1)]
    colour = (255, 80, 0)
    cv2.line(out, _pt(ends[0]), _pt(ends[1]), colour, thick, cv2.LINE_AA)
    for e in ends:
        bar = 4 * thick * np.array([vx, vy])
        cv2.line(out, _pt(e - bar), _pt(e + bar), colour, thick + 1, cv2.LINE_AA)


def _pt(v) -> tuple[int, int]:
    return int(round(float(v[0]))), int(round(float(v[1])))


def _short(text: str, limit: int = 48) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."

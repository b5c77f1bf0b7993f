"""`run-cell map` (pixels -> table mm), `run-cell check-calibration` (a fresh plate image through
the calibration in use) and `run-cell calibrate-demo` (a rendered plate, calibrated)."""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
from pathlib import Path

import numpy as np

from cell.atomicfile import ensure_folder
from cell.calibration.check import check_calibration, check_text
from cell.calibration.pipeline import calibrate
from cell.calibration.report import summary_text, write_report
from cell.calibration.store import Calibration
from cell.config import CellConfig, load_config
from cell.errors import InputError
from cell.imageio import read_image, write_image_atomic
from cell.oplog import log_to_file
from cell.sim.render import render_plate
from cell.sim.rig import default_camera

log = logging.getLogger(__name__)

CHECK_FAILED = 3  # exit code of check-calibration when a point is over calibration.check_max_mm


def register(sub) -> None:
    p = sub.add_parser(
        "map",
        help="map pixel points to table mm through a calibration",
        description="Map pixel points to table millimetres through a calibration file: one point as X Y, "
        "or a CSV with header x_px,y_px (--pixels). Pixels outside the calibrated image are refused.",
    )
    p.add_argument("--calibration", required=True, type=Path, help="calibration JSON")
    p.add_argument("--pixels", type=Path, help="CSV with header x_px,y_px")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("point", nargs="*", type=str, help="X Y: one pixel point")
    p.set_defaults(func=cmd_map)

    c = sub.add_parser(
        "check-calibration",
        help="map a fresh plate image through the calibration in use and report the error per point",
        description="Exit 0 when every plate point maps within calibration.check_max_mm of where it lies, "
        "3 when one does not, 2 on bad input.",
    )
    c.add_argument("--image", required=True, type=Path, help="plate image, the plate in its fixture")
    c.add_argument("--calibration", type=Path, help="calibration JSON (default: calibration.active_path)")
    c.add_argument("--config", type=Path, help="cell config TOML (default: built-in)")
    c.add_argument("--log", type=Path, default=Path("logs/cell.log"), help="operator log (default: logs/cell.log)")
    c.set_defaults(func=cmd_check_calibration)

    d = sub.add_parser(
        "calibrate-demo",
        help="render the built-in plate, calibrate it, print the report",
        description="Render the built-in simulated plate, calibrate it with the default pipeline and with the "
        "paper's preset, print both reports and write them (Table III CSV, numbered plate, deviation plot) "
        "under --out-dir.",
    )
    d.add_argument("--out-dir", type=Path, default=Path("demo-out"), help="report folder (default demo-out)")
    d.set_defaults(func=cmd_calibrate_demo)


def read_pixels_csv(path: Path) -> np.ndarray:
    """Pixel points from a CSV with header x_px,y_px; every bad cell named by line."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: pixels file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read pixels file: {e}") from None
    reader = csv.reader(text.splitlines())
    header = next(reader, None)
    if header is None or [h.strip() for h in header] != ["x_px", "y_px"]:
        raise InputError(f"{path}: line 1: header must be 'x_px,y_px', found {','.join(header or [])!r}")
    points = []
    for line_no, row in enumerate(reader, start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != 2:
            raise InputError(f"{path}: line {line_no}: expected 2 values, found {len(row)}")
        try:
            x, y = float(row[0]), float(row[1])
        except ValueError:
            raise InputError(f"{path}: line {line_no}: not a number: {','.join(row)!r}") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise InputError(f"{path}: line {line_no}: not a finite number: {','.join(row)!r}")
        points.append((x, y))
    return np.array(points, dtype=np.float64).reshape(-1, 2)


def cmd_map(args: argparse.Namespace) -> int:
    cal = Calibration.load(args.calibration)
    if args.pixels and args.point:
        raise InputError("give either --pixels FILE or one point X Y, not both")
    if args.pixels:
        pixels = read_pixels_csv(args.pixels)
    elif len(args.point) == 2:
        try:
            pixels = np.array([[float(args.point[0]), float(args.point[1])]])
        except ValueError:
            raise InputError(f"point must be two numbers X Y, got {' '.join(args.point)!r}") from None
        if not np.all(np.isfinite(pixels)):
            raise InputError(f"point must be finite, got {' '.join(args.point)!r}")
    else:
        raise InputError("give --pixels FILE or one point as X Y (pixels)")
    _check_inside(pixels, cal.image_size, args.pixels)
    table = cal.pixel_to_table_mm(pixels) if len(pixels) else np.zeros((0, 2))
    if not np.all(np.isfinite(table)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(table), axis=1))[0])
        raise InputError(
            f"{args.calibration}: maps pixel ({pixels[bad][0]:g}, {pixels[bad][1]:g}) to no finite "
            "table position (a corrupt calibration?)"
        )
    rows = [
        {"x_px": float(p[0]), "y_px": float(p[1]), "X_mm": float(t[0]), "Y_mm": float(t[1])}
        for p, t in zip(pixels, table, strict=True)
    ]
    if args.json:
        print(json.dumps(rows))
    else:
        print(f"{'x_px':>10}{'y_px':>10}{'X_mm':>12}{'Y_mm':>12}")
        for r in rows:
            print(f"{r['x_px']:>10.2f}{r['y_px']:>10.2f}{r['X_mm']:>12.4f}{r['Y_mm']:>12.4f}")
    return 0


def _check_inside(pixels: np.ndarray, image_size: tuple[int, int], source: Path | None) -> None:
    """A pixel outside the calibrated image maps to nothing real (a polynomial there is wild)."""
    w, h = image_size
    outside = ~((pixels[:, 0] >= -0.5) & (pixels[:, 0] <= w - 0.5) & (pixels[:, 1] >= -0.5) & (pixels[:, 1] <= h - 0.5))
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        where = f"{source}: point {i + 1}: " if source else ""
        raise InputError(
            f"{where}pixel ({pixels[i][0]:g}, {pixels[i][1]:g}) is outside the calibrated "
            f"{w} x {h} px image; {int(outside.sum())} such point(s)"
        )


def cmd_check_calibration(args: argparse.Namespace) -> int:
    try:
        log_to_file(args.log)
    except OSError as e:
        raise InputError(f"cannot open log {args.log}: {e}") from None
    config = load_config(args.config)
    path = args.calibration or config.calibration.active_path
    calibration = Calibration.load(path)
    image = read_image(args.image, config.camera.max_image_px, calibration.image_size)  # header checked first
    result = check_calibration(image, calibration, config)
    print(check_text(result, str(args.image)))
    log.info(
        "calibration check of %s on %s: RMS %.4f mm, max %.4f mm, %s",
        path,
        args.image,
        result.rms_mm,
        result.max_mm,
        "pass" if result.passed else "FAIL",
    )
    return 0 if result.passed else CHECK_FAILED


def cmd_calibrate_demo(args: argparse.Namespace) -> int:
    """The calibration part of the job on built-in defaults: both presets on one rendered plate."""
    config = CellConfig()
    camera = default_camera()
    image = render_plate(camera, config.plate)
    ensure_folder(args.out_dir)
    write_image_atomic(args.out_dir / "plate.png", image)
    print(f"rendered the built-in plate: {args.out_dir / 'plate.png'}")
    result = calibrate(image, config)
    print("\n== default pipeline ==")
    print(summary_text(result, table=False))
    write_report(image, result, args.out_dir / "default")
    result.calibration.save(args.out_dir / "calibration.json")
    paper = config.model_copy(deep=True)
    paper.detection.preset = "paper"
    paper_result = calibrate(image, paper, "quadratic")
    print("\n== paper preset (HSV threshold, whole-pixel moments, quadratic) ==")
    print(summary_text(paper_result, table=False))
    write_report(image, paper_result, args.out_dir / "paper")
    print(
        f"\nreports in {args.out_dir}/default and {args.out_dir}/paper; calibration: {args.out_dir / 'calibration.json'}"
    )
    return 0

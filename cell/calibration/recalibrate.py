"""Recalibration as the operator runs it: fit, report, and only then replace the active file.

Exit codes: 0 replaced; 2 bad input (file, config, plate not found, size mismatch);
3 fit rejected by the configured limits. In every failure the active file is untouched.
"""
from __future__ import annotations

import argparse
import logging
import shutil
import sys
from datetime import datetime
from pathlib import Path
from typing import get_args

from cell.calibration.pipeline import calibrate
from cell.calibration.report import summary_text, write_report
from cell.config import ModelName, load_config
from cell.errors import REPORTED_ERRORS, CalibrationRejected, InputError, exit_code
from cell.imageio import read_image
from cell.oplog import log_to_file, quiet_terminal
from cell.sim.render import render_plate
from cell.sim.rig import default_camera
from cell.vision.config import Preset
from drivers.cameras.factory import make_camera

log = logging.getLogger(__name__)
DESCRIPTION = "Fit a new pixel -> table calibration from a plate image and make it active."


def build_parser() -> argparse.ArgumentParser:
    """scripts/recalibrate.py's own parser; `run-cell recalibrate` takes the same options."""
    p = argparse.ArgumentParser(prog="recalibrate.py", description=DESCRIPTION)
    add_arguments(p)
    return p


def register(sub) -> None:
    """`run-cell recalibrate`: the same command as scripts/recalibrate.py."""
    p = sub.add_parser("recalibrate", help="fit a new calibration from a plate image and make it active",
                       description=DESCRIPTION)
    add_arguments(p)
    p.set_defaults(func=cmd_recalibrate)


def cmd_recalibrate(args: argparse.Namespace) -> int:
    """As the script: the report on stdout, a failure as run-cell's one line (details in --log)."""
    if not args.verbose:
        quiet_terminal(logging.CRITICAL)
    return recalibrate(args)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--image", type=Path, help="plate image (default: capture from the configured camera)")
    p.add_argument("--out", type=Path, help="calibration file to replace (default: calibration.active_path)")
    p.add_argument("--config", type=Path, help="cell config TOML (default: built-in)")
    p.add_argument("--model", choices=get_args(ModelName))
    p.add_argument("--preset", choices=get_args(Preset), help="detector preset (overrides the config)")
    p.add_argument("--report-dir", type=Path, help="write table3.csv, plate_numbered.png, deviation.png, report.txt here")
    p.add_argument("--log", type=Path, default=Path("logs/cell.log"), help="operator log (default: logs/cell.log)")
    p.add_argument("--quiet", action="store_true", help="print the summary without the per-point table")


def capture_plate(config):
    """One frame from the configured camera; the simulated camera sees the built-in plate."""
    if config.camera.source.strip() == "sim":
        log.info("capturing the plate from the simulated camera")
        return render_plate(default_camera(config.camera.width_px, config.camera.height_px), config.plate)
    log.info("capturing the plate from camera %s", config.camera.source)
    with make_camera(config.camera) as camera:
        return camera.capture()


def check_image_size(image, config, source: str) -> None:
    """A plate image must be the camera's size: the calibration maps that camera's pixels."""
    h, w = image.shape[:2]
    want = (config.camera.width_px, config.camera.height_px)
    if (w, h) != want:
        raise InputError(
            f"{source}: image is {w} x {h} px but the camera is configured for "
            f"{want[0]} x {want[1]} px (camera.width_px, camera.height_px)"
        )


def gate_failure(result, limits) -> str | None:
    """Why a fit fails the configured limits (calibration.max_cv_*), or None when it passes."""
    cv = result.chosen.cv
    if cv.rms_mm <= limits.max_cv_rms_mm and cv.max_mm <= limits.max_cv_error_mm:
        return None
    return (
        f"cross-validated error RMS {cv.rms_mm:.4f} mm / max {cv.max_mm:.4f} mm exceeds "
        f"calibration.max_cv_rms_mm {limits.max_cv_rms_mm} mm / max_cv_error_mm {limits.max_cv_error_mm} mm"
    )


def replace_active(result, config, out: Path | None = None) -> tuple[Path, Path | None]:
    """The quality gate, then the atomic replacement (previous file kept as a dated backup).

    Every way of recalibrating (this script, the operator screen) goes through here; on any
    refusal the active file is untouched. Returns the file written and the backup, if any.
    """
    limits = config.calibration
    target = out or limits.active_path
    why = gate_failure(result, limits)
    if why:
        raise CalibrationRejected(f"{why}; {target} left unchanged")
    backup = None
    if target.exists():
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        backup_dir = limits.backup_dir if out is None else target.parent / "backups"
        backup_dir.mkdir(parents=True, exist_ok=True)
        backup = backup_dir / f"{target.stem}.{stamp}{target.suffix}"
        shutil.copy2(target, backup)
    result.calibration.save(target)
    cv = result.chosen.cv
    log.info(
        "recalibrated: %s written (%s; CV RMS %.4f mm, max %.4f mm)%s",
        target,
        result.chosen.label,
        cv.rms_mm,
        cv.max_mm,
        f"; previous kept as {backup}" if backup else "",
    )
    return target, backup


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    if args.preset:
        config.detection.preset = args.preset
    image = read_image(args.image) if args.image else capture_plate(config)
    check_image_size(image, config, str(args.image or "camera frame"))
    result = calibrate(image, config, args.model)
    print(summary_text(result, table=not args.quiet))
    if args.report_dir:
        for p in write_report(image, result, args.report_dir):
            print(f"wrote {p}")
    out, backup = replace_active(result, config, args.out)
    print(f"active calibration replaced: {out}" + (f" (previous kept as {backup})" if backup else ""))
    return 0


def recalibrate(args: argparse.Namespace) -> int:
    """Run with the operator log open; a failure is logged there, then raised for the caller
    to print as one line (exit 2, or 3 for a fit over the limits)."""
    try:
        log_to_file(args.log)
    except OSError as e:
        raise InputError(f"cannot open log {args.log}: {e}") from None
    try:
        return run(args)
    except CalibrationRejected as e:
        log.error("recalibration refused: %s", e)
        raise
    except REPORTED_ERRORS as e:
        log.error("recalibration failed: %s", e)
        raise


def main(argv: list[str] | None = None) -> int:
    """scripts/recalibrate.py: its messages start with `recalibrate:`."""
    args = build_parser().parse_args(argv)
    try:
        return recalibrate(args)
    except CalibrationRejected as e:
        print(f"recalibrate: refused: {e}", file=sys.stderr)
        return e.exit_code
    except REPORTED_ERRORS as e:
        print(f"recalibrate: error: {e}", file=sys.stderr)
        return exit_code(e)

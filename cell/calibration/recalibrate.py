"""Recalibration as the operator runs it: fit, report, and only then replace the active file.

Exit codes: 0 replaced; 2 bad input (file, config, plate not found, size mismatch, the
calibration file in use); 3 fit rejected (the configured limits, an implausible plate or
camera, a change beyond the limits without --accept-change) or a write failed; 130
stopped by a signal. In every failure the active file is untouched and no temporary file
is left. Recalibrations of one file are serialised by its lock; each keeps its own backup.
"""

from __future__ import annotations

import argparse
import logging
from datetime import datetime
from pathlib import Path
from typing import get_args

from cell.atomicfile import copy_unique, ensure_folder
from cell.calibration.gates import change_problems, plausibility_problems
from cell.calibration.pipeline import calibrate
from cell.calibration.report import summary_text, write_report
from cell.calibration.store import Calibration
from cell.config import ModelName, load_config
from cell.errors import REPORTED_ERRORS, CalibrationRejected, InputError, OutputError, describe_os_error, exit_code
from cell.imageio import read_image
from cell.locks import holding
from cell.oplog import log_to_file, quiet_terminal
from cell.recordfile import tell_stderr
from cell.signals import EXIT_STOPPED, Controls, StopRequested, handling_signals
from cell.sim.render import render_plate
from cell.sim.rig import default_camera
from cell.terminal import guarded_stdout
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
    p = sub.add_parser(
        "recalibrate", help="fit a new calibration from a plate image and make it active", description=DESCRIPTION
    )
    add_arguments(p)
    p.set_defaults(func=cmd_recalibrate)


def cmd_recalibrate(args: argparse.Namespace) -> int:
    """As the script: the report on stdout, a failure as run-cell's one line (details in --log)."""
    if not args.verbose:
        quiet_terminal(logging.CRITICAL)
    return recalibrate(args, getattr(args, "controls", None))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--image", type=Path, help="plate image (default: capture from the configured camera)")
    p.add_argument("--out", type=Path, help="calibration file to replace (default: calibration.active_path)")
    p.add_argument("--config", type=Path, help="cell config TOML (default: built-in)")
    p.add_argument(
        "--model",
        choices=get_args(ModelName),
        help="the mapping to fit (default: calibration.model; auto: the lowest cross-validated error)",
    )
    p.add_argument("--preset", choices=get_args(Preset), help="detector preset (overrides the config)")
    p.add_argument(
        "--report-dir", type=Path, help="write table3.csv, plate_numbered.png, deviation.png, report.txt here"
    )
    p.add_argument("--log", type=Path, default=Path("logs/cell.log"), help="operator log (default: logs/cell.log)")
    p.add_argument("--quiet", action="store_true", help="print the summary without the per-point table")
    p.add_argument(
        "--accept-change",
        action="store_true",
        help="replace the active calibration even if scale or origin move beyond the configured limits "
        "(the camera or plate was moved on purpose)",
    )


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


def gate_failure(result, config) -> str | None:
    """Why a fit fails the quality gate (calibration.max_cv_*, a plausible plate and camera), or None."""
    limits = config.calibration
    cv = result.chosen.cv
    problems = []
    if cv.rms_mm > limits.max_cv_rms_mm or cv.max_mm > limits.max_cv_error_mm:
        problems.append(
            f"cross-validated error RMS {cv.rms_mm:.4f} mm / max {cv.max_mm:.4f} mm exceeds "
            f"calibration.max_cv_rms_mm {limits.max_cv_rms_mm} mm / max_cv_error_mm {limits.max_cv_error_mm} mm"
        )
    problems += plausibility_problems(result, limits, config.plate)
    return "; ".join(problems) or None


def replace_active(
    result, config, out: Path | None = None, accept_change: bool = False, controls: Controls | None = None
) -> tuple[Path, Path | None]:
    """The quality gate, then under the file's lock the change check and the atomic replacement
    (the previous file kept as a backup of its own). Every way of recalibrating (the script,
    `run-cell recalibrate`, the operator screen) goes through here; on any refusal the active
    file is untouched. Returns the file written and the backup, if any."""
    limits = config.calibration
    target = out or limits.active_path
    if why := gate_failure(result, config):
        raise CalibrationRejected(f"{why}; {target} left unchanged")
    backup_dir = limits.backup_dir if out is None else target.parent / "backups"
    with holding(target, "calibration file", wait_s=limits.lock_wait_s):  # one recalibration of a file at a time
        backup = _replace(target, result.calibration, backup_dir, accept_change, limits, controls or Controls())
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


def run(args: argparse.Namespace, controls: Controls | None = None) -> int:
    config = load_config(args.config)
    if args.preset:
        config.detection.preset = args.preset
    out = args.out or config.calibration.active_path
    if out.is_dir():
        raise OutputError(
            f"{out}: is a folder; --out must name the calibration file", hint="e.g. --out cal/active.json"
        )
    want = (config.camera.width_px, config.camera.height_px)
    image = read_image(args.image, config.camera.max_image_px, want) if args.image else capture_plate(config)
    check_image_size(image, config, str(args.image or "camera frame"))
    result = calibrate(image, config, args.model)
    print(summary_text(result, table=not args.quiet))
    if args.report_dir:
        for p in write_report(image, result, args.report_dir):
            print(f"wrote {p}")
    out, backup = replace_active(result, config, args.out, args.accept_change, controls)
    print(f"active calibration replaced: {out}" + (f" (previous kept as {backup})" if backup else ""))
    return 0


def _replace(out: Path, new: Calibration, backup_dir: Path, accept_change: bool, limits, controls: Controls):
    """Under the file's lock: compare with the active file, back it up under a name of its own,
    write the new one; a signal waits until both are done. Returns the backup path or None."""
    if not out.exists():
        new.save(out)
        return None
    try:
        active = Calibration.load(out)
    except InputError as e:
        log.warning("the active calibration cannot be compared (%s); it is replaced and kept as a backup", e)
        active = None
    if active is not None and (problems := change_problems(new, active, limits)) and not accept_change:
        raise CalibrationRejected(
            "; ".join(problems) + f"; {out} left unchanged",
            hint="if the camera or plate was moved on purpose, rerun with --accept-change",
        )
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    with controls.shielded():
        backup = copy_unique(out, ensure_folder(backup_dir), f"{out.stem}.{stamp}", out.suffix)
        new.save(out)
    return backup


def recalibrate(args: argparse.Namespace, controls: Controls | None = None) -> int:
    """Run with the operator log open; a failure is logged there, then raised for the caller
    to print as one line (exit 2, or 3 for a refused fit or a failed write)."""
    try:
        log_to_file(args.log)
    except OSError as e:
        raise InputError(f"cannot open log {args.log}: {describe_os_error(e)}") from None
    try:
        return run(args, controls)
    except CalibrationRejected as e:
        log.error("recalibration refused: %s", e)
        raise
    except REPORTED_ERRORS as e:
        log.error("recalibration failed: %s", e)
        raise
    except StopRequested as e:
        log.warning("recalibration stopped: %s; the active calibration is unchanged", e.reason)
        raise
    except OSError as e:
        log.error("recalibration failed: %s", e)
        raise


def main(argv: list[str] | None = None) -> int:
    """scripts/recalibrate.py: its messages start with `recalibrate:`; signals handled from the start;
    a closed stdout (`| head`) does not stop the recalibration (cell.terminal)."""
    with guarded_stdout() as stdout:
        code = _main(argv)
    if stdout.lost is not None:
        tell_stderr(
            f"recalibrate: note: standard output was closed early ({stdout.lost.strerror or stdout.lost}); "
            f"the rest of the output was not shown, the command ran to its end (exit {code})"
        )
    return code


def _main(argv: list[str] | None) -> int:
    with handling_signals() as controls:
        args = build_parser().parse_args(argv)
        try:
            return recalibrate(args, controls)
        except CalibrationRejected as e:
            return _last_line(f"recalibrate: refused: {e}", e.exit_code)
        except REPORTED_ERRORS as e:
            return _last_line(f"recalibrate: error: {e}", exit_code(e))
        except StopRequested as e:
            return _last_line(f"recalibrate: stopped: {e.reason}; the active calibration is unchanged", EXIT_STOPPED)
        except KeyboardInterrupt:
            return _last_line("recalibrate: stopped: Ctrl-C; the active calibration is unchanged", EXIT_STOPPED)
        except OSError as e:
            return _last_line(f"recalibrate: error: {describe_os_error(e)}", 3)
        except Exception as e:  # a bug: one line for the operator, the traceback in the log
            log.exception("recalibration failed")
            return _last_line(f"recalibrate: internal error: {type(e).__name__}: {e} (details in {args.log})", 3)


def _last_line(text: str, code: int) -> int:
    tell_stderr(text)
    return code

"""`run-cell recalibrate` and scripts/recalibrate.py: fit, report, and only then replace the active file
(cell.calibration.recalibrate.replace_active).

Exit codes: 0 replaced; 2 bad input (file, config, plate not found, size mismatch, the
calibration file in use); 3 fit rejected (the configured limits, an implausible plate or
camera, a change beyond the limits without --accept-change) or a write failed; 130
stopped by a signal. In every failure the active file is untouched and no temporary file
is left. Recalibrations of one file are serialised by its lock; each keeps its own backup.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import get_args

from cell.assembly import capture_plate
from cell.calibration.pipeline import RaisedPlate, calibrate
from cell.calibration.recalibrate import check_image_size, replace_active
from cell.calibration.report import summary_text, write_report
from cell.commands.argtypes import positive_mm
from cell.config import ModelName, load_config
from cell.errors import REPORTED_ERRORS, CalibrationRejected, InputError, OutputError, describe_os_error, exit_code
from cell.imageio import read_image
from cell.oplog import log_to_file, quiet_terminal
from cell.recordfile import tell_stderr
from cell.signals import EXIT_STOPPED, Controls, StopRequested, handling_signals
from cell.terminal import guarded_stdout
from cell.vision.config import Preset

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
        "--raised-image",
        type=Path,
        help="a second image of the plate lying on a spacer (with --spacer-mm): it measures the camera's height, "
        "which one flat plate seen nearly straight down cannot (`run-cell camera --snapshot FILE` takes it)",
    )
    p.add_argument(
        "--spacer-mm", type=positive_mm, help="thickness of the spacer under the plate in --raised-image, in mm"
    )
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
    raised = None
    if (args.raised_image is None) != (args.spacer_mm is None):
        raise InputError(
            "--raised-image and --spacer-mm go together",
            hint="give the image of the plate on the spacer and the spacer's thickness, or neither",
        )
    if args.raised_image is not None:
        raised_image = read_image(args.raised_image, config.camera.max_image_px, want)
        raised = RaisedPlate(raised_image, args.spacer_mm, str(args.raised_image))
    result = calibrate(image, config, args.model, raised)
    print(summary_text(result, table=not args.quiet))
    if args.report_dir:
        for p in write_report(image, result, args.report_dir):
            print(f"wrote {p}")
    out, backup = replace_active(result, config, args.out, args.accept_change, controls)
    print(f"active calibration replaced: {out}" + (f" (previous kept as {backup})" if backup else ""))
    return 0


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


def main(argv: list[str] | None = None, controls: Controls | None = None) -> int:
    """scripts/recalibrate.py: its messages start with `recalibrate:`; signals handled from the start;
    a closed stdout (`| head`) does not stop the recalibration (cell.terminal)."""
    with guarded_stdout() as stdout:
        code = _main(argv, controls)
    if stdout.lost is not None:
        tell_stderr(
            f"recalibrate: note: standard output was closed early ({stdout.lost.strerror or stdout.lost}); "
            f"the rest of the output was not shown, the command ran to its end (exit {code})"
        )
    return code


def _main(argv: list[str] | None, controls: Controls | None = None) -> int:
    with handling_signals(controls, install=controls is None) as controls:
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

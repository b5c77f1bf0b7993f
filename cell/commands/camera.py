"""`run-cell camera`: look through the configured camera before calibrating: focus, exposure,
and the plate's coverage of the view and tilt, with what to adjust in words
(cell.vision.commissioning does the looking)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cell.config import CellConfig, load_config
from cell.errors import InputError
from cell.imageio import check_image_path, write_image_atomic
from cell.locks import camera_lock
from cell.signals import Controls, StopRequested
from cell.sim.cell import sim_plate_camera
from cell.vision.commissioning import FocusTracker, assess, live_line, report_text
from cell.wording import plural
from drivers.cameras.base import Camera
from drivers.cameras.factory import make_camera

DESCRIPTION = (
    "Look through the camera of the config (camera.source; 'sim' is the simulated camera over the "
    "calibration plate) and print its focus score (variance of the Laplacian), exposure (histogram, "
    "share of black and white pixels), the plate's coverage of the view and the camera's tilt when the "
    "plate is in view, and what to adjust. One frame by default; --live prints a line per frame until "
    "Ctrl-C (exit 0) or --frames N."
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "camera", help="look through the camera: focus, exposure, plate coverage and tilt", description=DESCRIPTION
    )
    p.add_argument(
        "--config", type=Path, metavar="FILE", default=argparse.SUPPRESS, help="cell config TOML (default: built-in)"
    )
    p.add_argument("--snapshot", type=Path, metavar="FILE", help="write the (last) frame to FILE (.png or .jpg)")
    p.add_argument("--live", action="store_true", help="a line per frame, the best focus so far in it, until Ctrl-C")
    p.add_argument("--frames", type=_positive_int, metavar="N", help="with --live: stop after N frames")
    p.set_defaults(func=cmd_camera)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more: {text!r}")
    return value


def open_camera(config: CellConfig) -> Camera:
    """The configured camera; 'sim' is the simulated camera looking at the calibration plate."""
    if config.camera.source.strip() == "sim":
        return sim_plate_camera(config)
    return make_camera(config.camera)


def cmd_camera(args: argparse.Namespace) -> int:
    config = load_config(getattr(args, "config", None) or getattr(args, "run_config", None))
    if args.frames is not None and not args.live:
        raise InputError("--frames N goes with --live")
    if args.snapshot is not None:
        check_image_path(args.snapshot)  # refuse before opening the camera, not after
    controls = getattr(args, "controls", None) or Controls()
    camera = open_camera(config)
    with camera_lock(config.camera.source), camera:
        if args.live:
            last = _live(camera, config, args.frames, controls)
        else:
            last = camera.capture()
            print(report_text(assess(last, config), camera.source), flush=True)
        if args.snapshot is not None and last is not None:
            with controls.shielded():  # a second Ctrl-C must not leave half a file
                write_image_atomic(args.snapshot, last)
            print(f"snapshot: {args.snapshot}", flush=True)
    return 0


def _live(camera: Camera, config: CellConfig, frames: int | None, controls: Controls) -> np.ndarray | None:
    """A line per frame until `frames` or a stop signal; the last frame."""
    tracker, last, n = FocusTracker(), None, 0
    ended = f"after {plural(frames, 'frame')}" if frames else ""
    try:
        while frames is None or n < frames:
            frame = camera.capture()
            n += 1
            view = assess(frame, config, tracker)
            last = frame
            print(live_line(n, view, tracker), flush=True)
    except StopRequested as e:
        ended = f"stopped by {e.reason} after {plural(n, 'frame')}"
    with controls.shielded():
        if n:
            print(f"{ended}; best focus {tracker.best:.1f} at frame {tracker.best_frame}", flush=True)
    return last

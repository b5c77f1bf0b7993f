#!/usr/bin/env python3
"""Calibration benchmark: default pipeline vs the paper's, on rendered webcam-like plates.

For each camera it renders the plate, calibrates it with both pipelines, and measures the
error over the whole plate field at dense points (every 2 mm, none of them used in the
fit) against the renderer's exact truth. Times are CPU times on one core, median of
--repeat runs, with cv2.findCirclesGrid timed on the same image as the reference.

    python scripts/bench_calibration.py [--repeat 5]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one core: no BLAS worker threads (set before numpy loads)

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.calibration.pipeline import calibrate  # noqa: E402
from cell.camera_model import CameraModel  # noqa: E402
from cell.config import CellConfig  # noqa: E402
from cell.sim.render import plate_field_error_mm, render_plate  # noqa: E402

# (label, width, height, mm/px, k1, k2, tilt_deg, tilt_azimuth_deg, roll_deg)
CAMERAS = [
    ("1080p barrel k1-.12 k2.08", 1920, 1080, 0.24, -0.12, 0.08, 6.0, 30.0, 4.0),
    ("1080p mild k1-.05", 1920, 1080, 0.25, -0.05, 0.02, 3.0, 120.0, -2.0),
    ("1080p pincushion k1+.08", 1920, 1080, 0.27, 0.08, 0.0, 5.0, 250.0, -4.0),
    ("1080p none, tilt 6", 1920, 1080, 0.26, 0.0, 0.0, 6.0, 0.0, 1.0),
    ("720p barrel k1-.10", 1280, 720, 0.30, -0.10, 0.05, 4.0, 60.0, 3.0),
    ("720p pincushion k1+.06", 1280, 720, 0.33, 0.06, 0.02, 6.0, 200.0, -3.0),
]


def camera_for(spec) -> CameraModel:
    _, w, h, mmpx, k1, k2, tilt, az, roll = spec
    return CameraModel.looking_down(
        w, h, mmpx, (132.0, 88.0), tilt_deg=tilt, tilt_azimuth_deg=az, roll_deg=roll, k1=k1, k2=k2
    )


def timed(fn, repeat: int):
    """(result, median CPU ms): CPU time, so that other jobs on a shared machine do not count."""
    times, out = [], None
    for _ in range(repeat):
        t = time.process_time()
        out = fn()
        times.append(1e3 * (time.process_time() - t))
    return out, statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5, help="timing repeats per image (median reported)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    config = CellConfig()
    paper = config.model_copy(deep=True)
    paper.detection.preset = "paper"
    print(
        f"{'camera':<28}{'default model':<16}{'RMS':>8}{'max':>8}{'ms':>7}   {'paper RMS':>9}{'max':>8}{'ms':>7}   {'findCirclesGrid ms':>18}"
    )
    worst_d_rms = worst_d_max = 0.0
    paper_rms: list[float] = []
    speed: list[float] = []
    for spec in CAMERAS:
        cam = camera_for(spec)
        image = render_plate(cam, config.plate, seed=7)
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        d_res, d_ms = timed(lambda: calibrate(image, config), args.repeat)
        p_res, p_ms = timed(lambda: calibrate(image, paper, "quadratic"), args.repeat)
        (found, _), g_ms = timed(
            lambda: cv2.findCirclesGrid(
                gray, (config.plate.columns, config.plate.rows), flags=cv2.CALIB_CB_SYMMETRIC_GRID
            ),
            args.repeat,
        )
        d_rms, d_max = plate_field_error_mm(cam, d_res.calibration, config.plate)
        p_rms, p_max = plate_field_error_mm(cam, p_res.calibration, config.plate)
        worst_d_rms = max(worst_d_rms, d_rms)
        worst_d_max = max(worst_d_max, d_max)
        paper_rms.append(p_rms)
        speed.append(d_ms / g_ms)
        print(
            f"{spec[0]:<28}{d_res.chosen.label[:15]:<16}{d_rms:>8.4f}{d_max:>8.4f}{d_ms:>7.1f}   "
            f"{p_rms:>9.4f}{p_max:>8.4f}{p_ms:>7.1f}   {g_ms:>12.1f}{'' if found else ' (not found)':>6}"
        )
    print(
        f"\nworst default over the plate field: RMS {worst_d_rms:.4f} mm, max {worst_d_max:.4f} mm "
        f"(target RMS <= 0.015, max <= 0.05)"
    )
    print(f"paper preset RMS over the plate field: {min(paper_rms):.3f}-{max(paper_rms):.3f} mm")
    print(
        f"default calibration (detect, number, fit five models, cross-validate, the camera pose's focal-length "
        f"profile, the pitch-ratio check) / findCirclesGrid alone: time ratio {min(speed):.2f}-"
        f"{max(speed):.2f} (errors in mm; times median of {args.repeat}, one core)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

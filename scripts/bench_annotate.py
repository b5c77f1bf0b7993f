#!/usr/bin/env python3
"""Annotation benchmark: CPU time to lay out and draw the operator's frame.

Renders random scenes of 15-20 parts through the built-in simulated camera at each size,
locates them on a perfect calibration, and times `layout()` (label placement alone) and
`annotate()` (copy, outlines, jaws, labels, legend) with the pick order given. CPU time
(time.process_time) on one core (cv2.setNumThreads(1)), median and 95th percentile over
--scenes scenes x --repeat runs; a loaded machine slows wall time, not these figures much.

    python scripts/bench_annotate.py [--scenes 6] [--repeat 20]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.calibration.models import CameraMap  # noqa: E402
from cell.calibration.store import Calibration  # noqa: E402
from cell.sim.parts import random_scene, render_scene  # noqa: E402
from cell.sim.rig import default_camera  # noqa: E402
from cell.vision.annotate import annotate, layout  # noqa: E402
from cell.vision.locate import locate  # noqa: E402

SIZES = [(3840, 2160), (1920, 1080), (1280, 720), (640, 480), (320, 240)]


def cpu_ms(fn, repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        out.append(1e3 * (time.process_time() - t0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"{'frame':>11}  {'parts':>5}  {'layout ms (median / p95)':>25}  {'annotate ms (median / p95)':>27}")
    for w, h in SIZES:
        camera = default_camera(w, h)
        calibration = Calibration("camera", CameraMap(camera), (w, h), camera)
        lay, ann, parts = [], [], []
        for seed in range(args.scenes):
            image = render_scene(camera, random_scene(seed), seed=seed)
            result = locate(image, calibration)
            order = [p.id for p in result.objects if p.pick]
            parts.append(len(result.objects))
            lay += cpu_ms(lambda r=result, o=order: layout(r, (w, h), o), args.repeat)
            ann += cpu_ms(lambda i=image, r=result, o=order: annotate(i, r, o), args.repeat)
        print(
            f"{w:>5} x {h:<4}  {min(parts):>2}-{max(parts):<2}  "
            f"{np.median(lay):>12.2f} / {np.percentile(lay, 95):<10.2f}  "
            f"{np.median(ann):>13.2f} / {np.percentile(ann, 95):<10.2f}"
        )


if __name__ == "__main__":
    main()

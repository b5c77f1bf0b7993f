#!/usr/bin/env python3
"""Parts benchmark: find, classify and locate bolts and nuts on rendered scenes.

For each camera it renders the plate, calibrates on it (the default pipeline, and the
paper's detection with its quadratic model), then renders random scenes of 15-20
non-touching parts (nuts M5-M10, bolts M5-M8 x 16-35 mm, two washers) through the same
camera and compares what locate() reports with the renderer's truth:

- default: default calibration, default preset, part-height correction;
- default, no height: the same without height correction (everything on the table plane);
- paper: the paper's calibration and segmentation, no height correction;
- perfect cal.: default preset on a perfect table-plane calibration (the vision alone).

Centre errors are footprint-centre errors (mm) over the parts picked and classified
right; bolt angle errors are in table degrees. Figures are given per frame size (1920 x 1080
and 1280 x 720 at 0.3 mm/px). Locate time is the median of --repeat runs per frame on one
core (cv2.setNumThreads(1)).

    python scripts/bench_parts.py [--scenes 8] [--repeat 5]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.calibration.models import CameraMap  # noqa: E402
from cell.calibration.pipeline import calibrate  # noqa: E402
from cell.calibration.store import Calibration  # noqa: E402
from cell.camera_model import CameraModel  # noqa: E402
from cell.config import CellConfig  # noqa: E402
from cell.sim.parts import PartSpec, random_scene, render_scene  # noqa: E402
from cell.sim.render import render_plate  # noqa: E402
from cell.vision.config import PartsConfig  # noqa: E402
from cell.vision.locate import locate  # noqa: E402
from cell.vision.types import LocateResult  # noqa: E402

# (label, width, height, mm/px, k1, k2, tilt_deg, tilt_azimuth_deg, roll_deg); hfov 70:
# the 1080p cameras are 330-370 mm above the table, the 720p ones (0.3 mm/px) about 270 mm.
CAMERAS = [
    ("1080p barrel k1-.12 tilt 6", 1920, 1080, 0.24, -0.12, 0.08, 6.0, 30.0, 4.0),
    ("1080p mild k1-.05 tilt 3", 1920, 1080, 0.25, -0.05, 0.02, 3.0, 120.0, -2.0),
    ("1080p pincushion k1+.08 tilt 5", 1920, 1080, 0.27, 0.08, 0.0, 5.0, 250.0, -4.0),
    ("720p barrel k1-.10 tilt 4", 1280, 720, 0.30, -0.10, 0.05, 4.0, 60.0, 3.0),
    ("720p mild k1-.05 tilt 2", 1280, 720, 0.30, -0.05, 0.02, 2.0, 160.0, -2.0),
    ("720p pincushion k1+.06 tilt 5", 1280, 720, 0.30, 0.06, 0.02, 5.0, 200.0, -3.0),
]
RUNS = ["default", "default, no height", "paper", "perfect cal."]


def camera_for(spec) -> CameraModel:
    _, w, h, mmpx, k1, k2, tilt, az, roll = spec
    return CameraModel.looking_down(
        w, h, mmpx, (132.0, 88.0), tilt_deg=tilt, tilt_azimuth_deg=az, roll_deg=roll, k1=k1, k2=k2
    )


def score(result: LocateResult, parts: list[PartSpec]) -> dict[str, Any]:
    """Match each located object to the nearest true footprint; count and measure."""
    truth = np.array([p.footprint_centre_mm for p in parts])
    out: dict[str, Any] = {
        "confusion": Counter(),
        "centre": [],
        "angle": [],
        "head": [],
        "wrong": [],
        "found": len(result.objects),
    }
    for obj in result.objects:
        d = np.hypot(*(truth - np.array(obj.table_mm)).T)
        part = parts[int(d.argmin())]
        expected = part.kind if part.kind in ("nut", "bolt") else "unknown"
        out["confusion"][(part.kind, obj.cls)] += 1
        if obj.cls != expected or (obj.pick and part.kind not in ("nut", "bolt")):
            out["wrong"].append(f"{part.kind} {part.size} -> {obj.cls} ({obj.reason})")
            continue
        if obj.pick:
            out["centre"].append(float(d.min()))
        if part.kind == "bolt":
            axis_deg, head_mm = part.axis_angle_deg, part.head_centre_mm
            if obj.angle_deg is None or obj.head_mm is None or axis_deg is None or head_mm is None:
                out["wrong"].append(f"bolt {part.size}: no axis or head reported")
                continue
            out["angle"].append(abs((obj.angle_deg - axis_deg + 90.0) % 180.0 - 90.0))
            # The head end is right when the reported head is nearer the true head than the tip.
            tip = 2 * np.array(part.footprint_centre_mm) - np.array(head_mm)
            out["head"].append(np.hypot(*(np.array(obj.head_mm) - head_mm)) < np.hypot(*(np.array(obj.head_mm) - tip)))
    return out


def report(size: str, n_scenes: int, n_cameras: int, totals: dict[str, dict[str, Any]], times_ms: list[float]) -> None:
    """Classes, centre and angle errors per pipeline, and locate time, for one frame size."""
    print(f"\n=== {size}: {n_scenes} scenes, {n_cameras} cameras, each calibrated on its own plate image ===")
    kinds = ["nut", "bolt", "washer"]
    for run in RUNS:
        tot = totals[run]
        conf = tot["confusion"]
        classes = ", ".join(
            f"{k}: " + "/".join(f"{conf[(k, c)]} {c}" for c in ("nut", "bolt", "unknown") if conf[(k, c)])
            for k in kinds
        )
        c, a = np.array(tot["centre"]), np.array(tot["angle"])
        print(f"\n[{run}]")
        print(f"  classes (truth: found): {classes}; misclassified or wrongly picked: {len(tot['wrong'])}")
        if c.size:
            print(f"  footprint-centre error: mean {c.mean():.3f} mm, max {c.max():.3f} mm over {c.size} parts")
        if a.size:
            print(
                f"  bolt angle error: mean {a.mean():.2f} deg, max {a.max():.2f} deg over {a.size} bolts; "
                f"head end right for {sum(tot['head'])}/{len(tot['head'])}"
            )
        for line in tot["wrong"][:5]:
            print(f"    {line}")
    t = np.array(times_ms)
    print(
        f"\nlocate time per {size} frame, default preset, one core: median {statistics.median(times_ms):.1f} ms, "
        f"p95 {np.percentile(t, 95):.1f} ms over {t.size} runs"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=8, help="scenes per camera")
    ap.add_argument("--repeat", type=int, default=5, help="timing repeats per frame (median reported)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    cell = CellConfig()
    paper_cell = cell.model_copy(deep=True)
    paper_cell.detection.preset = "paper"
    configs = {
        "default": PartsConfig(),
        "default, no height": PartsConfig(height_correction=False),
        "paper": PartsConfig(preset="paper"),
        "perfect cal.": PartsConfig(),
    }
    sizes = list(dict.fromkeys(f"{w} x {h}" for _, w, h, *_ in CAMERAS))
    totals: dict[str, dict[str, dict[str, Any]]] = {
        size: {run: {"confusion": Counter(), "centre": [], "angle": [], "head": [], "wrong": []} for run in RUNS}
        for size in sizes
    }
    times_ms: dict[str, list[float]] = {size: [] for size in sizes}
    n_scenes: Counter[str] = Counter()
    t_start = time.perf_counter()
    print(f"{'camera':<32}{'seed':>5}{'parts':>6}  " + "".join(f"{run + ' mean/max mm':>30}" for run in RUNS))
    for spec in CAMERAS:
        cam = camera_for(spec)
        size = f"{cam.width_px} x {cam.height_px}"
        plate = render_plate(cam, cell.plate, seed=7)
        cals = {
            "default": calibrate(plate, cell).calibration,
            "paper": calibrate(plate, paper_cell, "quadratic").calibration,
            "perfect": Calibration("camera", CameraMap(cam), (cam.width_px, cam.height_px), cam),
        }
        cal_for = {"default": "default", "default, no height": "default", "paper": "paper", "perfect cal.": "perfect"}
        for seed in range(args.scenes):
            parts = random_scene(seed=1000 + seed)
            frame = render_scene(cam, parts, seed=seed, exposure=float(np.random.default_rng(seed).uniform(0.8, 1.1)))
            n_scenes[size] += 1
            cells = []
            for run in RUNS:
                s = score(locate(frame, cals[cal_for[run]], configs[run]), parts)
                tot = totals[size][run]
                tot["confusion"].update(s["confusion"])
                for key in ("centre", "angle", "head", "wrong"):
                    tot[key] += s[key]
                c = s["centre"]
                cells.append(f"{np.mean(c):.3f}/{np.max(c):.3f} ({len(s['wrong'])} wrong)" if c else "-")
            for _ in range(args.repeat):
                times_ms[size].append(locate(frame, cals["default"], configs["default"]).elapsed_ms)
            print(f"{spec[0]:<32}{1000 + seed:>5}{len(parts):>6}  " + "".join(f"{c:>30}" for c in cells))

    for size in sizes:
        report(size, n_scenes[size], sum(size in f"{w} x {h}" for _, w, h, *_ in CAMERAS), totals[size], times_ms[size])
    print(
        "\ntargets: every bolt and nut right, no washer picked, angle <= 1.5 deg; centre mean <= 0.25 mm and max <= 0.7 mm "
        "at 1080p, mean <= 0.15 mm and max <= 0.5 mm at 720p (0.3 mm/px); locate median <= 15 ms at 1080p"
    )
    print(f"benchmark took {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

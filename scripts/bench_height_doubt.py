#!/usr/bin/env python3
"""Height-doubt benchmark: is the camera height's standard deviation honest, and does the predicted
cost of its doubt match what the parts suffer?

Each camera family (cell/sim/cameras.py, as scripts/bench_parts.py draws them) gets --cameras random
cameras; each renders its plate and is calibrated from the plate alone with the default pipeline.
Per camera: the fitted height against the renderer's truth in standard deviations (z), and the
part-height cost the calibration predicts (Calibration.height_cost_mm: the tallest configured part,
a height error of 3 standard deviations, the worst over the field) against the cost measured
through the true camera: a part's centre at the tallest part's height seen at each pixel of the
image's border and a 9 x 9 grid, located by the calibration, against where it lies (the error at
the part's height minus the error of the same pixel on the table: the height's share alone).

The reference in the same run: the fraction of |z| within 1 and 2 an honest standard deviation
gives (68 % and 95 %), and the predicted cost at the true height error (|z| sd) against the
measured one (their ratio should be near 1).

    python scripts/bench_height_doubt.py [--cameras 6] [--families "640 x 480,1280 x 720"]
    python scripts/bench_height_doubt.py --cameras 40     # the wide run (about 20 min on one core)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.calibration.pipeline import calibrate  # noqa: E402
from cell.calibration.store import HEIGHT_DOUBT_SDS  # noqa: E402
from cell.config import CellConfig  # noqa: E402
from cell.errors import CalibrationRejected, PlateNotFound  # noqa: E402
from cell.sim.cameras import FAMILIES, FAMILY, random_camera  # noqa: E402
from cell.sim.render import render_plate  # noqa: E402

SEED_BASE = 90_000  # no test and no other bench uses these


def field_pixels(w: int, h: int) -> np.ndarray:
    t = np.linspace(0.0, 1.0, 33)
    border = np.concatenate(
        [np.column_stack([t * (w - 1), np.full_like(t, e)]) for e in (0, h - 1)]
        + [np.column_stack([np.full_like(t, e), t * (h - 1)]) for e in (0, w - 1)]
    )
    g = np.linspace(0.0, 1.0, 9)
    gx, gy = np.meshgrid(g * (w - 1), g * (h - 1))
    return np.concatenate([border, np.column_stack([gx.ravel(), gy.ravel()])])


def measured_cost_mm(cal, truth_camera, part_mm: float) -> float:
    """The worst shift of a part's centre the height alone causes: through the true camera."""
    px = field_pixels(*cal.image_size)
    at_part = cal.pixel_to_table_mm(px, part_mm) - truth_camera.pixel_to_table(px, part_mm)
    on_table = cal.pixel_to_table_mm(px) - truth_camera.pixel_to_table(px)
    return float(np.max(np.hypot(*(at_part - on_table).T)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cameras", type=int, default=6, help="random cameras per family")
    ap.add_argument("--families", default=",".join(f.name for f in FAMILIES), help="comma-separated family names")
    ap.add_argument("--seed-base", type=int, default=SEED_BASE)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    names = [n.strip() for n in args.families.split(",")]
    unknown = [n for n in names if n not in FAMILY]
    if unknown:
        print(f"bench_height_doubt: unknown family {unknown[0]!r} (have: {', '.join(FAMILY)})", file=sys.stderr)
        return 2
    t0 = time.process_time()
    print(
        f"{'family':<12}{'seed':>7}{'mm/px':>7}{'tilt':>6}{'true H':>8}{'fit H':>8}{'sd':>6}{'z':>6}"
        f"{'pred@' + format(HEIGHT_DOUBT_SDS, 'g') + 'sd':>9}{'pred@|z|':>9}{'measured':>9}{'ratio':>7}  warns"
    )
    zs, ratios, missed, warned, unknown_sd = [], [], [], 0, 0
    by_family: dict[str, list[float]] = {}
    for name in names:
        index = [f.name for f in FAMILIES].index(name)
        for i in range(args.cameras):
            sim = random_camera(FAMILY[name], args.seed_base + 1000 * index + i)
            config = CellConfig(plate=sim.plate)
            part = config.parts.tallest_centre_height_mm
            image = render_plate(sim.camera, sim.plate, sim.optics, seed=sim.seed)
            try:
                result = calibrate(image, config)
            except (PlateNotFound, CalibrationRejected) as e:
                print(f"{name:<12}{sim.seed:>7}  calibration failed: {str(e)[:80]}")
                continue
            cal = result.calibration
            true_h = float(sim.camera.center_table_mm[2])
            fit_h, sd = float(result.plate_height_mm or 0.0), result.plate_height_sd_mm
            tilt = float(np.degrees(np.arccos(abs(sim.camera.rotation[2, 2]))))
            mmpx = cal.mm_per_px((cal.image_size[0] / 2, cal.image_size[1] / 2))
            if not np.isfinite(sd):
                unknown_sd += 1
                warned += cal.height_doubt() is not None
                print(f"{name:<12}{sim.seed:>7}{mmpx:>7.3f}{tilt:>6.1f}{true_h:>8.1f}{fit_h:>8.1f}  sd not known")
                continue
            z = (fit_h - true_h) / sd
            zs.append(z)
            by_family.setdefault(name, []).append(abs(z))
            predicted = cal.height_cost_mm(part, HEIGHT_DOUBT_SDS * sd)[0]
            at_truth = cal.height_cost_mm(part, abs(fit_h - true_h))[0]
            measured = measured_cost_mm(cal, sim.camera, part)
            ratio = at_truth / measured if measured > 1e-4 else float("nan")
            if measured > 1e-3:
                ratios.append(ratio)
            warns = cal.height_doubt() is not None
            warned += warns
            if measured > config.calibration.max_height_cost_mm and not warns:
                missed.append(f"{name} seed {sim.seed}: measured {measured:.3f} mm, no warning")
            print(
                f"{name:<12}{sim.seed:>7}{mmpx:>7.3f}{tilt:>6.1f}{true_h:>8.1f}{fit_h:>8.1f}{sd:>6.1f}{z:>6.2f}"
                f"{predicted:>9.3f}{at_truth:>9.3f}{measured:>9.3f}{ratio:>7.2f}  {'yes' if warns else 'no'}",
                flush=True,
            )
    a = np.abs(np.array(zs))
    if len(a):
        print(
            f"\nheight sd honesty over {len(a)} cameras: |z| <= 1: {np.mean(a <= 1):.0%} (honest: 68 %), "
            f"|z| <= 2: {np.mean(a <= 2):.0%} (honest: 95 %); median |z| {np.median(a):.2f} (honest: 0.67), "
            f"worst {a.max():.2f}"
        )
        for name, fz in by_family.items():
            f = np.array(fz)
            print(f"  {name:<12} {len(f):>3} cameras: |z| <= 1: {np.mean(f <= 1):.0%}, <= 2: {np.mean(f <= 2):.0%}")
    print(
        f"height not known at all (a flat profile): {unknown_sd} cameras; warned: {warned} of "
        f"{len(zs) + unknown_sd} (plate alone)"
    )
    if ratios:
        r = np.array(ratios)
        print(
            f"predicted cost at the true height error / measured: median {np.median(r):.2f}, "
            f"range {r.min():.2f}-{r.max():.2f} (1 = the formula is the camera's)"
        )
    print(f"cameras whose measured cost passes the tolerance without a warning: {len(missed)}")
    for m in missed:
        print(f"  {m}")
    print(f"CPU {time.process_time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

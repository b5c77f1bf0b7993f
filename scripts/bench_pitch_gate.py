#!/usr/bin/env python3
"""Pitch-gate benchmark: hand-held-style plate photos, the right pitch and a 5 % wrong one.

Views, each drawn from a seed (cell/sim/handheld.py):
- rendered plates: 640 x 480 or 1280 x 720, the real photos' plate (7 x 7, 10 mm pitch, 5 mm dots)
  or the paper's (22 x 16 mm pitch, 10 mm dots, as many as fit), circles 6-12 px across at the image
  centre, tilt 0-45 deg in any direction, any roll, barrel distortion k1 0 .. -0.35, blur 0.4-1.5 px,
  sensor noise, vignetting, a backlight gradient, uneven light, JPEG quality 60-95;
- the real photos in ../shared/data/circles-opencv (640 x 480; skipped, saying so, where absent)
  turned 0-35 deg more in perspective, through barrel distortion k1 0 .. -0.35, shrunk so their
  circles are 6-12 px across, blurred, lit unevenly and saved as JPEG. Their pitch is square (10 x 10
  mm configured: a uniform scale cannot be seen in one image).

Each view is calibrated once with its right pitch (the default pipeline; views whose plate is not
found whole are counted and left out), then the pitch ratio is measured with the right pitches and
with pitch_x_mm, then pitch_y_mm, 5 % too large (what `calibrate` with that config measures: the
numbering and the centres do not depend on the pitch). The gate's decision is `PitchRatio.refused`
with the default config (what cell/calibration/gates.py applies). Reference in the same run: the
earlier estimate (each circle's thresholded moments, `moment_pitch_ratio`) with its fixed 2.5 %.

A wrong pitch not refused where 5 % is not beyond the view's own threshold (pitch_ratio_refuse_sd
standard errors, at least max_pitch_ratio_error_pct) by 2 standard errors (`PitchRatio.can_show`)
is listed as "cannot show 5 %": that one view does not measure well enough; elsewhere it is a miss. Exit 1 on a right pitch refused or a miss.

    python scripts/bench_pitch_gate.py [--renders 40] [--photo-seeds 3] [--seed-base 29000] [--verbose]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import functools  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.calibration.pipeline import calibrate  # noqa: E402
from cell.calibration.roundness import PitchRatio, lattice_jacobians, measure_pitch_ratio, moment_pitch_ratio  # noqa: E402
from cell.config import CalibrationConfig, CellConfig, PlateConfig  # noqa: E402
from cell.errors import PlateNotFound  # noqa: E402
from cell.sim.handheld import View, from_photo, rendered  # noqa: E402

PHOTOS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "circles-opencv"
WRONG = 1.05
OLD_LIMIT_PCT = 2.5  # the earlier gate's fixed threshold
LIMITS = CalibrationConfig()


def wrong(plate: PlateConfig, axis: str) -> PlateConfig:
    key = f"pitch_{axis}_mm"
    return plate.model_copy(update={key: getattr(plate, key) * WRONG})


@dataclass
class Outcome:
    view: View
    diameter_px: float
    new: dict[str, PitchRatio]
    old: dict[str, PitchRatio]
    new_ms: float
    old_ms: float


def measure(view: View) -> Outcome | str:
    try:
        result = calibrate(view.gray, CellConfig(plate=view.plate))
    except PlateNotFound as e:
        return f"plate not found ({str(e)[:60]})"
    pts = result.points
    if len(pts.number) < view.plate.count:
        return f"{view.plate.count - len(pts.number)} dots missing"
    new: dict[str, PitchRatio] = {}
    old: dict[str, PitchRatio] = {}
    times = {"new": 0.0, "old": 0.0}
    for label, plate in (("right", view.plate), ("x+5%", wrong(view.plate, "x")), ("y+5%", wrong(view.plate, "y"))):
        col_row = np.rint(pts.table_mm / (view.plate.pitch_x_mm, view.plate.pitch_y_mm)).astype(int)
        for store, fn, key in ((new, measure_pitch_ratio, "new"), (old, moment_pitch_ratio, "old")):
            t0 = time.process_time()
            ratio = fn(view.gray, pts.pixel, col_row, plate)
            times[key] += time.process_time() - t0
            if ratio is None:
                return f"pitch ratio not measured ({key}, {label})"
            store[label] = ratio
    jac = lattice_jacobians(
        pts.pixel, np.rint(pts.table_mm / (view.plate.pitch_x_mm, view.plate.pitch_y_mm)).astype(int), view.plate
    )
    dets = np.abs(np.linalg.det(jac[np.isfinite(jac).all(axis=(1, 2))]))
    diameter = view.plate.diameter_mm * float(np.median(np.sqrt(dets)))
    return Outcome(view, diameter, new, old, 1e3 * times["new"] / 3, 1e3 * times["old"] / 3)


def new_refused(r: PitchRatio) -> bool:
    return r.refused(LIMITS.max_pitch_ratio_error_pct, LIMITS.pitch_ratio_refuse_sd)


def old_refused(r: PitchRatio) -> bool:
    return abs(r.factor - 1.0) > OLD_LIMIT_PCT / 100.0


def threshold(r: PitchRatio) -> float:
    return r.threshold_pct(LIMITS.max_pitch_ratio_error_pct, LIMITS.pitch_ratio_refuse_sd)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--renders", type=int, default=40, help="rendered views")
    ap.add_argument("--photo-seeds", type=int, default=3, help="views made from each real photo")
    ap.add_argument("--seed-base", type=int, default=29_000)
    ap.add_argument("--verbose", action="store_true", help="a line per view")
    args = ap.parse_args()
    cv2.setNumThreads(1)

    makers: list[Callable[[], View]] = [
        functools.partial(rendered, s) for s in range(args.seed_base, args.seed_base + args.renders)
    ]
    if PHOTOS.is_dir():
        for i in range(1, 8):
            photo = np.asarray(cv2.imread(str(PHOTOS / f"opencv_circles{i:02d}.png"), cv2.IMREAD_GRAYSCALE))
            base = args.seed_base + 1000 + 100 * i
            makers += [functools.partial(from_photo, i, photo, s) for s in range(base, base + args.photo_seeds)]
    else:
        print(f"real photos skipped: {PHOTOS} is absent (they live in ../shared/data, outside the repo)")

    t0 = time.perf_counter()
    outcomes: list[Outcome] = []
    skipped: list[str] = []
    for make in makers:
        view = make()
        got = measure(view)
        if isinstance(got, str):
            skipped.append(f"{view.name}: {got} [{view.about}]")
            continue
        outcomes.append(got)
        if args.verbose:
            nw, od = got.new, got.old
            print(
                f"{view.name:16s} d {got.diameter_px:4.1f} px  right {nw['right'].factor:.4f} +- {100 * nw['right'].log_sd:.2f} % "
                f"(old {od['right'].factor:.4f})  x+5% {nw['x+5%'].factor:.4f} (old {od['x+5%'].factor:.4f})  "
                f"y+5% {nw['y+5%'].factor:.4f} (old {od['y+5%'].factor:.4f})  threshold {threshold(nw['right']):.1f} %  "
                f"[{view.about}]"
            )
    wall = time.perf_counter() - t0

    if not outcomes:
        print(f"no view measured ({len(skipped)} left out); nothing to report")
        return 1

    def kind(o: Outcome) -> str:
        return "photo" if o.view.name.startswith("photo") else "render"

    print(
        f"\npitch gate: {len(outcomes)} views measured ({sum(kind(o) == 'render' for o in outcomes)} rendered, "
        f"{sum(kind(o) == 'photo' for o in outcomes)} from the real photos), {len(skipped)} left out (plate not found "
        f"whole); gate: refused beyond {LIMITS.pitch_ratio_refuse_sd:g} standard errors, at least "
        f"{LIMITS.max_pitch_ratio_error_pct:g} %; reference: the earlier moments with a fixed {OLD_LIMIT_PCT:g} %"
    )
    print(f"{'':34s}{'new gate':>16s}{'earlier (reference)':>22s}")
    rows = [("right pitch refused (goal 0)", "right")] + [
        (f"{label} wrong pitch refused", label) for label in ("x+5%", "y+5%")
    ]
    for title, label in rows:
        for group in ("render", "photo"):
            sel = [o for o in outcomes if kind(o) == group]
            if not sel:
                continue
            a = sum(new_refused(o.new[label]) for o in sel)
            b = sum(old_refused(o.old[label]) for o in sel)
            print(f"  {title + ' (' + group + 's)':32s}{a:>9d} / {len(sel):<6d}{b:>14d} / {len(sel):<6d}")

    cannot: list[tuple[Outcome, str, PitchRatio]] = []
    misses: list[tuple[Outcome, str, PitchRatio]] = []
    for o in outcomes:
        for label in ("x+5%", "y+5%"):
            r = o.new[label]
            if not new_refused(r):
                can = r.can_show(100 * (WRONG - 1), LIMITS.max_pitch_ratio_error_pct, LIMITS.pitch_ratio_refuse_sd)
                (misses if can else cannot).append((o, label, r))
    print(
        f"\nwrong pitch not refused where one view cannot show 5 % (5 % is not beyond its threshold by 2 standard "
        f"errors): {len(cannot)}"
    )
    for o, label, r in cannot:
        print(
            f"  {o.view.name} {label}: measured {100 * (r.factor - 1):+.1f} +- {100 * r.log_sd:.1f} %, threshold "
            f"{threshold(r):.1f} %, circles {o.diameter_px:.1f} px [{o.view.about}]"
        )
    print(f"wrong pitch not refused where the view could show it (misses): {len(misses)}")
    for o, label, r in misses:
        print(
            f"  {o.view.name} {label}: measured {100 * (r.factor - 1):+.1f} +- {100 * r.log_sd:.1f} %, threshold "
            f"{threshold(r):.1f} % [{o.view.about}]"
        )

    print("\nworst cases")
    for name, pick in (("new", lambda o: o.new), ("earlier", lambda o: o.old)):
        worst = max(outcomes, key=lambda o: abs(math.log(pick(o)["right"].factor)))
        r = pick(worst)["right"]
        print(
            f"  {name:8s} right pitch farthest from 1: {r.factor:.4f} ({100 * (r.factor - 1):+.2f} %, "
            f"{abs(math.log(r.factor)) / max(r.log_sd, 1e-12):.1f} standard errors), {worst.view.name}, circles "
            f"{worst.diameter_px:.1f} px [{worst.view.about}]"
        )
        least = min(
            ((o, label) for o in outcomes for label in ("x+5%", "y+5%")),
            key=lambda t: abs(math.log(pick(t[0])[t[1]].factor)),
        )
        r = pick(least[0])[least[1]]
        print(
            f"  {name:8s} 5 % wrong pitch read least off: {100 * (r.factor - 1):+.2f} % ({least[1]}), {least[0].view.name} "
            f"[{least[0].view.about}]"
        )
    z = np.array([abs(math.log(o.new["right"].factor)) / max(o.new["right"].log_sd, 1e-12) for o in outcomes])
    sd = np.array([100 * o.new["right"].log_sd for o in outcomes])
    print(
        f"  new, right pitch: |error| / its standard error median {np.median(z):.2f}, 95th percentile "
        f"{np.percentile(z, 95):.2f}, max {z.max():.2f} (honest: 0.67, 1.96); standard error {sd.min():.2f}-{sd.max():.2f} %"
    )
    new_ms, old_ms = [o.new_ms for o in outcomes], [o.old_ms for o in outcomes]
    print(
        f"  CPU per measurement: new {np.median(new_ms):.0f} ms median, {max(new_ms):.0f} max; earlier "
        f"{np.median(old_ms):.1f} ms median, {max(old_ms):.1f} max"
    )
    for s in skipped:
        print(f"  left out: {s}")
    print(f"({wall:.0f} s wall)")
    right_refused = sum(new_refused(o.new["right"]) for o in outcomes)
    return 1 if right_refused or misses else 0


if __name__ == "__main__":
    sys.exit(main())

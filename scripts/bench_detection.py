#!/usr/bin/env python3
"""Plate detection benchmark: ours (find_points: candidates, numbering, refinement) against
cv2.findCirclesGrid on the same image, timed in the same run, side by side.

Images: the real photos in ../shared/data/circles-opencv (640 x 480; also enlarged to 1280 x
960, 1920 x 1440 and 4000 x 3000, as a higher-resolution camera would see the same scene),
and rendered plates (the built-in 13 x 12 plate) from 640 x 480 to 4000 x 3000.

For each image both detectors run alternately --repeat times on one core
(cv2.setNumThreads(1), OPENBLAS_NUM_THREADS=1) and the medians of their CPU times are
compared (CPU time, not wall time: the machine is shared, and a waiting process would
otherwise be charged for another's work). findCirclesGrid's default blob detector
looks for blobs of 25-5000 px area; where circles are larger than that it finds no grid, so it
is also timed with the blob detector's area limits scaled to the image ("cv scaled"), which is
what a user would have to set, and the ratio is taken against the run that finds the grid.
Agreement: the largest distance between our centres and OpenCV's, in px, where both find the grid;
then the same on the shared photos made hard (noise, blur, glare, uneven light, low contrast,
scale, crops: cell/sim/degrade.py, as tests/test_real_circles.py uses them).

    python scripts/bench_detection.py [--repeat 7]

Run to run: with --runs N only the timing of the photos (native and enlarged) and of the rendered
plates is done, N times over as independent runs (each run its own medians of --repeat
alternating timings, every image once per run, so a burst of load on the machine lands in one
run of each image rather than in all runs of one); per image it prints the ratio ours /
findCirclesGrid of every run, how many runs were <= 1.0 and the worst run, then how many images
meet the target (<= 1.0 in at least 9 of 10 runs) and the worst image.

    python scripts/bench_detection.py --runs 10 [--repeat 5]
"""

from __future__ import annotations

import os

# One core for both: cv2.setNumThreads(1) below, and no BLAS worker threads for numpy (set
# before numpy loads; on small matrices they only add wake-up costs).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import functools  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.calibration.agreement import agreement  # noqa: E402
from cell.calibration.pipeline import find_points  # noqa: E402
from cell.camera_model import CameraModel  # noqa: E402
from cell.config import CellConfig, PlateConfig  # noqa: E402
from cell.errors import PlateNotFound  # noqa: E402
from cell.sim.degrade import VARIANTS, variant  # noqa: E402
from cell.sim.render import Optics, render_plate  # noqa: E402
from cell.vision.silhouette import polygon_moments  # noqa: E402

PHOTOMETRIC = ["noise", "blur", "glare", "uneven light", "low contrast", "noise+blur+glare"]

PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "data" / "circles-opencv"
PHOTO_PLATE = PlateConfig(columns=7, rows=7, pitch_x_mm=10, pitch_y_mm=10, diameter_mm=5)
PHOTO_SIZES = [(640, 480), (1280, 960), (1920, 1440), (4000, 3000)]
RENDER_SIZES = [(640, 480), (1280, 720), (1920, 1080), (4000, 3000)]


def scaled_detector(area_scale: float) -> cv2.SimpleBlobDetector:
    """findCirclesGrid's default blob detector with its area limits scaled to the image."""
    p = cv2.SimpleBlobDetector.Params()
    p.minArea *= area_scale
    p.maxArea *= area_scale
    p.minDistBetweenBlobs *= area_scale**0.5
    return cv2.SimpleBlobDetector.create(p)


def read_gray(path: Path) -> np.ndarray:
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise SystemExit(f"{path}: not a readable image")
    return gray


def run_ours(gray, config):
    try:
        return find_points(gray, config)
    except PlateNotFound:
        return None


def run_cv(gray, size, detector=None):
    kw = {"blobDetector": detector} if detector is not None else {}
    found, centres = cv2.findCirclesGrid(gray, size, flags=cv2.CALIB_CB_SYMMETRIC_GRID, **kw)
    return centres.reshape(-1, 2).astype(np.float64) if found else None


def interleaved(fns, repeat: int):
    """Run the functions alternately; (last results, median ms of each)."""
    times: list[list[float]] = [[] for _ in fns]
    out: list[object] = [None] * len(fns)
    for _ in range(repeat):
        for k, fn in enumerate(fns):
            t = time.process_time()
            out[k] = fn()
            times[k].append(1e3 * (time.process_time() - t))
    return out, [statistics.median(t) for t in times]


def bench(label: str, gray: np.ndarray, config: CellConfig, area_scale: float, repeat: int) -> float:
    size = (config.plate.columns, config.plate.rows)
    fns = [lambda: run_ours(gray, config), lambda: run_cv(gray, size)]
    if area_scale > 1.5:
        detector = scaled_detector(area_scale)
        fns.append(lambda: run_cv(gray, size, detector))
    results, ms = interleaved(fns, repeat)
    ours, cv_default = results[0], results[1]
    cv_scaled = results[2] if len(results) > 2 else None
    ref_k = 1 if cv_default is not None or cv_scaled is None else 2
    ref = results[ref_k]
    ratio = ms[0] / ms[ref_k]
    agree = "-"
    if ours is not None and ref is not None:
        a = agreement(ours.number, ours.pixel, ref, *size)
        agree = f"{a.max_px:.3f}" + ("" if a.same_numbering and a.matched == len(ref) else " (numbering differs)")
    found = lambda r: "yes" if r is not None else "no"  # noqa: E731
    ours_found = (
        "no" if ours is None else f"{len(ours.number)}" + (f" ({len(ours.missing)} missing)" if ours.missing else "")
    )
    scaled = f"{ms[2]:>8.1f} {found(cv_scaled):>4}" if len(ms) > 2 else f"{'-':>8} {'':>4}"
    print(
        f"{label:<34}{ms[0]:>8.1f} {ours_found:>14}{ms[1]:>9.1f} {found(cv_default):>4}{scaled}{ratio:>8.2f}{agree:>10}"
    )
    return ratio


def variants_table(config: CellConfig, repeat: int, seeds: int) -> list[tuple[float, str]]:
    """Time and agreement with findCirclesGrid on the shared photos made hard (cell/sim/degrade.py),
    `seeds` draws of every variant per photo; returns (time ratio, label) for each image.

    max px: largest distance between our centre and OpenCV's. For photometric variants (the
    geometry is the photo's) also how far each detector's answer moved from its own answer
    on the untouched photo: where the two disagree, the one that moved is the one misled."""
    print(
        f"\n{'photo':<18}{'variant':<18}{'seed':>5}{'ours ms':>9}{'cv ms':>8}{'ratio':>7}{'cv grid':>8}{'ours':>6}"
        f"{'max px':>8}{'ours moved':>12}{'cv moved':>10}"
    )
    worst, timed = [], []
    for path in sorted(PHOTOS.glob("opencv_circles*.png")):
        gray = read_gray(path)
        clean_cv, clean_ours = run_cv(gray, (7, 7)), run_ours(gray, config)
        for kind in VARIANTS:
            for k in range(seeds):
                seed = int(path.stem[-2:]) - 1 + 100 * k
                img = variant(kind, gray, seed=seed)
                (ours, ref), ms = interleaved([lambda: run_ours(img, config), lambda: run_cv(img, (7, 7))], repeat)
                timed.append((ms[0] / ms[1], f"{path.stem} {kind} seed {seed} ({img.shape[1]}x{img.shape[0]})"))
                row = f"{path.stem:<18}{kind:<18}{seed:>5}{ms[0]:>9.1f}{ms[1]:>8.1f}{ms[0] / ms[1]:>7.2f}"
                row += f"{'yes' if ref is not None else 'no':>8}{'no' if ours is None else len(ours.number):>6}"
                if ref is not None and ours is not None:
                    a = agreement(ours.number, ours.pixel, ref, 7, 7)
                    row += f"{a.max_px:>8.3f}"
                    worst.append(a.max_px)
                    if kind in PHOTOMETRIC and clean_cv is not None and clean_ours is not None:
                        pair = lambda pts: pts[np.linalg.norm(pts[None] - clean_cv[:, None], axis=2).argmin(axis=1)]  # noqa: E731
                        ours_moved = np.linalg.norm(pair(ours.pixel) - pair(clean_ours.pixel), axis=1).max()
                        row += f"{ours_moved:>12.3f}{np.linalg.norm(ref - clean_cv, axis=1).max():>10.3f}"
                print(row)
    print(
        f"agreement over {len(worst)} variants OpenCV found: max |ours - OpenCV| median {np.median(worst):.3f} px, "
        f"{sum(w <= 0.2 for w in worst)} of {len(worst)} within 0.2 px"
    )
    return timed


LARGE_SIZES = [(3000, 2000), (3840, 2160), (3908, 2602), (4000, 3000)]


def image_centroids(cam: CameraModel, plate: PlateConfig) -> np.ndarray:
    """Where each circle's image has its area centroid (what a centroid detector should report):
    the projected circle outline's polygon centroid, row by row."""
    ring = np.linspace(0.0, 2 * np.pi, 256, endpoint=False)
    rim = np.column_stack([np.cos(ring), np.sin(ring)]) * plate.diameter_mm / 2
    out = []
    for r in range(plate.rows):
        for c in range(plate.columns):
            _, centre = polygon_moments(cam.project(np.array([c * plate.pitch_x_mm, r * plate.pitch_y_mm]) + rim))
            out.append(centre)
    return np.array(out)


def large_rendered_table(config: CellConfig, per_size: int) -> list[float]:
    """Both detectors against the truth on rendered plates 3000-4000 px wide (random cameras from
    seeds: scale, tilt, distortion, blur, noise, an uneven backlight): where the two disagree by
    more than 0.2 px, which one is further from the circle's true image centroid."""
    print(
        f"\n{'large rendered plate':<34}{'ours-truth max':>15}{'cv-truth max':>13}{'ours-cv max':>12}"
        f"{'> 0.2 px apart':>15}{'ours further':>13}"
    )
    plate, rng, agree = config.plate, np.random.default_rng(1900), []
    for w, h in LARGE_SIZES:
        for _ in range(per_size):
            mm_per_px = 1.15 * max(plate.pitch_x_mm * plate.columns / w, plate.pitch_y_mm * plate.rows / h)
            mm_per_px *= rng.uniform(1.0, 1.3)
            cam = CameraModel.looking_down(
                w,
                h,
                mm_per_px,
                (132.0, 88.0),
                tilt_deg=rng.uniform(0, 8),
                tilt_azimuth_deg=rng.uniform(0, 360),
                roll_deg=rng.uniform(-5, 5),
                k1=rng.uniform(-0.1, 0.05),
            )
            optics = Optics(
                blur_sigma_px=rng.uniform(0.8, 2.5),
                noise_sigma=rng.uniform(1, 4),
                backlight_gradient=rng.uniform(0, 0.3),
            )
            gray = cv2.cvtColor(render_plate(cam, plate, optics, seed=int(rng.integers(1 << 20))), cv2.COLOR_BGR2GRAY)
            truth = image_centroids(cam, plate)
            ours = run_ours(gray, config)
            size = (plate.columns, plate.rows)
            ref = run_cv(gray, size)
            if ref is None:
                ref = run_cv(gray, size, scaled_detector(max(1.0, (plate.diameter_mm / mm_per_px / 40.0) ** 2)))
            label = f"13x12 {w}x{h} ({plate.diameter_mm / mm_per_px:.0f} px circles)"
            if ours is None:
                print(f"{label:<34}  ours: no plate")
                continue
            pair = lambda pts: pts[np.linalg.norm(pts[None] - truth[:, None], axis=2).argmin(axis=1)]  # noqa: E731
            off_ours = np.linalg.norm(pair(ours.pixel) - truth, axis=1)
            row = f"{label:<34}{off_ours.max():>15.3f}"
            if ref is not None:
                off_cv = np.linalg.norm(pair(ref) - truth, axis=1)
                apart = np.linalg.norm(pair(ours.pixel) - pair(ref), axis=1)
                agree.append(float(apart.max()))
                far = apart > 0.2
                row += f"{off_cv.max():>13.3f}{apart.max():>12.3f}{int(far.sum()):>15}{int((far & (off_ours > off_cv)).sum()):>13}"
            else:
                row += f"{'no grid':>13}"
            print(row)
    return agree


def timing_images() -> list[tuple[str, np.ndarray, CellConfig, float]]:
    """(label, gray image, config, blob area scale) of every image the timing table times: the
    real photos at their native 640 x 480 and enlarged (if the shared data is there), then the
    rendered plates."""
    images = []
    if PHOTOS.exists():
        config = CellConfig(plate=PHOTO_PLATE)
        for path in sorted(PHOTOS.glob("opencv_circles*.png")):
            gray0 = read_gray(path)
            for w, h in PHOTO_SIZES:
                s = w / gray0.shape[1]
                gray = gray0 if s == 1 else cv2.resize(gray0, (w, h), interpolation=cv2.INTER_CUBIC)
                images.append((f"{path.stem} {w}x{h}", gray, config, s * s))
    else:
        print(f"({PHOTOS} is absent: real photos skipped, only the rendered plates are timed)")
    rendered_config = CellConfig()
    for w, h in RENDER_SIZES:
        # The plate (264 x 176 mm) filling most of the frame, mild barrel distortion and tilt.
        plate = rendered_config.plate
        mm_per_px = 1.15 * max(plate.pitch_x_mm * plate.columns / w, plate.pitch_y_mm * plate.rows / h)
        cam = CameraModel.looking_down(
            w, h, mm_per_px, (132.0, 88.0), tilt_deg=4.0, tilt_azimuth_deg=30.0, roll_deg=2.0, k1=-0.08
        )
        gray = cv2.cvtColor(render_plate(cam, plate, seed=7), cv2.COLOR_BGR2GRAY)
        d_px = plate.diameter_mm / mm_per_px
        images.append((f"rendered 13x12 {w}x{h}", gray, rendered_config, max(1.0, (d_px / 40.0) ** 2)))
    return images


def repeated_runs(runs: int, repeat: int) -> int:
    """The timing table's images timed `runs` times over as independent runs; per image the ratio
    ours / findCirclesGrid of each run, the runs <= 1.0 and the worst."""
    need = -(-9 * runs // 10)  # at least 9 of 10 runs
    print(
        f"command: {' '.join([Path(sys.argv[0]).name, *sys.argv[1:]])}\n"
        f"ours = find_points (candidates, lattice numbering, refinement, size check): the detection only, "
        f"not the whole calibration (the pitch gate's fit and the camera solve are not detection);\n"
        f"findCirclesGrid with its default blob detector, or with the area limits scaled to the image where "
        f"the default finds no grid; CPU time, one core, median of {repeat} alternating timings per run; "
        f"{runs} runs, every image once per run; target: ratio <= 1.0 in at least {need} of {runs} runs"
    )
    items = []
    for label, gray, config, area_scale in timing_images():
        size = (config.plate.columns, config.plate.rows)
        # The reference chosen once, as bench() does: the default detector where it finds the grid.
        ref = None
        if run_cv(gray, size) is None and area_scale > 1.5:
            ref = scaled_detector(area_scale)
            if run_cv(gray, size, ref) is None:
                ref = None
        ours = run_ours(gray, config)
        fns = [functools.partial(run_ours, gray, config), functools.partial(run_cv, gray, size, ref)]
        items.append((label + (" (cv scaled)" if ref is not None else ""), fns, ours is not None))
    ratios: list[list[float]] = [[] for _ in items]
    ms_ours: list[list[float]] = [[] for _ in items]
    ms_cv: list[list[float]] = [[] for _ in items]
    load0, t0 = os.getloadavg()[0], time.monotonic()
    for run in range(runs):
        for k, (_, fns, _) in enumerate(items):
            _, ms = interleaved(fns, repeat)
            ratios[k].append(ms[0] / ms[1])
            ms_ours[k].append(ms[0])
            ms_cv[k].append(ms[1])
        print(f"  run {run + 1} of {runs} done ({time.monotonic() - t0:.0f} s)", flush=True)
    width = max(len(label) for label, _, _ in items) + 2
    print(
        f"\n{'image':<{width}}{'ratio ours / findCirclesGrid, run by run':<{6 * runs}}{'<= 1.0':>8}{'worst':>7}"
        f"{'ours ms':>9}{'cv ms':>8}"
    )
    met, worst = 0, (-1.0, "")
    for k, ((label, _, found), r) in enumerate(zip(items, ratios, strict=True)):
        ok = sum(x <= 1.0 for x in r)
        met += ok >= need
        worst = max(worst, (max(r), label))
        row = f"{label:<{width}}" + "".join(f"{x:>6.2f}" for x in r)
        row = f"{row:<{width + 6 * runs}}{f'{ok}/{runs}':>8}{max(r):>7.2f}"
        row += f"{statistics.median(ms_ours[k]):>9.1f}{statistics.median(ms_cv[k]):>8.1f}"
        print(row + ("" if found else "  (ours: no plate)"))
    print(
        f"\nimages meeting <= 1.0 in {need} of {runs} runs: {met} of {len(items)}; worst image: {worst[1]} "
        f"(worst run {worst[0]:.2f}, {sum(x <= 1.0 for x in ratios[[i[0] for i in items].index(worst[1])])}"
        f"/{runs} runs <= 1.0); all ratios {min(min(r) for r in ratios):.2f}-{worst[0]:.2f}\n"
        f"(ms: medians over the runs of each run's median CPU time; machine load average "
        f"{load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end)"
    )
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=7, help="timing repeats per image (median reported)")
    ap.add_argument("--seeds", type=int, default=3, help="draws of every hard variant of every photo")
    ap.add_argument("--large", type=int, default=2, help="rendered plates per large size (3000-4000 px wide)")
    ap.add_argument(
        "--runs",
        type=int,
        default=0,
        help="time the photos and rendered plates this many times over as independent runs "
        "(ratio per run, runs <= 1.0, worst run) instead of the one-run tables; e.g. 10",
    )
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if args.runs > 0:
        return repeated_runs(args.runs, args.repeat)
    print(
        f"{'image':<34}{'ours ms':>8} {'numbered':>14}{'cv ms':>9} {'grid':>4}{'cv scaled':>9} {'grid':>4}"
        f"{'ratio':>8}{'max px':>10}"
    )
    ratios: list[tuple[float, str]] = []
    for label, gray, config, area_scale in timing_images():
        ratios.append((bench(label, gray, config, area_scale, args.repeat), label))
    rendered_config = CellConfig()
    large = large_rendered_table(rendered_config, args.large)
    if large:
        print(f"largest distance ours - OpenCV on the large rendered plates: {min(large):.3f}-{max(large):.3f} px")
    if PHOTOS.exists():
        ratios += variants_table(CellConfig(plate=PHOTO_PLATE), args.repeat, args.seeds)
    ratios.sort(reverse=True)
    print(
        f"\ntime ratio ours / findCirclesGrid: WORST {ratios[0][0]:.2f} ({ratios[0][1]}), median "
        f"{statistics.median(r for r, _ in ratios):.2f} over {len(ratios)} images and variants (median of "
        f"{args.repeat} alternating runs each, CPU time, one core; target <= 1.0); the five slowest:"
    )
    for ratio, label in ratios[:5]:
        print(f"  {ratio:.2f}  {label}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

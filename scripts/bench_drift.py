#!/usr/bin/env python3
"""Drift-watch benchmark: is a bumped camera caught before a pick is made with it, and does
the watch stay quiet while nothing moves?

1. Bumps: the built-in simulated cell (the paper's table, its reference marks) runs with the
   camera moved by --bump-mm at a chosen pick, in several directions and at several picks.
   For each run: the pick the cell stopped before, and how many picks were made from frames
   the moved camera took (must be 0).
2. False alarms: --frames frames of the same simulated table with nothing moving, each with
   fresh sensor noise, while the light drifts slowly (exposure 0.75-1.15, the backlight's
   gradient and direction wandering); the watch measures the marks on every frame. Reported:
   frames over the limit (must be 0) and the largest drift it measured.

    python scripts/bench_drift.py [--frames 1000] [--bump-mm 0.3]
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.assembly import assemble  # noqa: E402
from cell.audit import AuditLog  # noqa: E402
from cell.calibration.drift import DriftWatch  # noqa: E402
from cell.config import CellConfig  # noqa: E402
from cell.runner import Runner  # noqa: E402
from cell.sim.parts import part_coverage  # noqa: E402
from cell.sim.render import Optics, circles_coverage, expose  # noqa: E402

BUMPS = [((1.0, 0.0), 3), ((0.0, 1.0), 6), ((-0.7071, 0.7071), 9), ((0.7071, -0.7071), 12)]


def bump_run(direction: tuple[float, float], at_pick: int, size_mm: float, log_dir: Path) -> tuple[str, int, int]:
    """(outcome, pick attempts made, picks made with the moved camera) of one simulated run."""
    config = CellConfig()
    config.sim.camera_bumped_mm = (direction[0] * size_mm, direction[1] * size_mm)
    config.sim.camera_bumped_at_pick = at_pick
    with contextlib.ExitStack() as stack:
        cell = assemble(config, True, stack)
        audit = stack.enter_context(AuditLog(log_dir / f"bump-{at_pick}.jsonl"))
        runner = Runner(
            cell.camera,
            cell.arm,
            lambda f: cell.locate(f, cell.calibration),
            cell.planner(),
            config.run,
            audit,
            drift_watch=cell.drift_watch(cell.calibration),
        )
        summary = runner.run()
    # Pick k is planned from frame k; frames from `at_pick` on are the moved camera's.
    with_moved = max(0, summary.attempts - (at_pick - 1))
    return f"{summary.outcome}: {summary.reason}", summary.attempts, with_moved


def quiet_frames(n: int, seed: int = 1) -> tuple[int, float, float, float]:
    """(frames over the limit, largest drift, 99th percentile, limit) over n frames of a still table."""
    config = CellConfig()
    with contextlib.ExitStack() as stack:
        sim = assemble(config, True, stack).sim
        if sim is None:
            raise SystemExit("the built-in config assembled no simulated cell")
        model, calibration = sim.camera.model, sim.calibration
        watch = DriftWatch(calibration, config.drift.model_copy(update={"marks_mm": sim.marks_mm}))
        opacity = circles_coverage(model, np.array(sim.marks_mm), config.drift.mark_diameter_mm / 2)
        for _, spec in sim.world.table_specs():
            got = part_coverage(model, spec)
            if got is not None:
                (x0, y0), cov = got
                sl = (slice(y0, y0 + cov.shape[0]), slice(x0, x0 + cov.shape[1]))
                np.maximum(opacity[sl], cov, out=opacity[sl])
    rng = np.random.default_rng(seed)
    drifts = []
    for i in range(n):
        t = i / max(n - 1, 1)
        exposure = 0.95 + 0.2 * math.sin(2 * math.pi * t)  # 0.75-1.15 over the run
        optics = Optics(backlight_gradient=0.15 + 0.1 * math.sin(6 * math.pi * t), backlight_angle_deg=30 + 60 * t)
        frame = expose(model, opacity, optics, rng, exposure)
        drifts.append(watch.measure(frame).drift_mm)
    d = np.array(drifts)
    return (
        int(np.count_nonzero(d > config.drift.limit_mm)),
        float(d.max()),
        float(np.percentile(d, 99)),
        config.drift.limit_mm,
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=1000, help="still frames for the false-alarm count")
    ap.add_argument("--bump-mm", type=float, default=0.3, help="how far the camera is moved")
    ap.add_argument("--log-dir", type=Path, default=Path("logs/bench-drift"), help="audit logs of the bump runs")
    args = ap.parse_args()
    logging.disable(logging.ERROR)  # the runs' fault lines: the summary below says it once each
    t0 = time.perf_counter()
    args.log_dir.mkdir(parents=True, exist_ok=True)
    print(f"camera moved {args.bump_mm} mm during the job (built-in simulated cell, 17 parts):")
    caught = True
    for direction, at_pick in BUMPS:
        outcome, attempts, with_moved = bump_run(direction, at_pick, args.bump_mm, args.log_dir)
        caught &= with_moved == 0 and outcome.startswith("fault")
        print(
            f"  moved along ({direction[0]:+.2f}, {direction[1]:+.2f}) before pick {at_pick:2d}: "
            f"stopped after {attempts} picks, {with_moved} picks made with the moved camera; {outcome[:110]}"
        )
    over, worst, p99, limit = quiet_frames(args.frames)
    print(
        f"\nstill table, {args.frames} frames of sensor noise and slow light drift: {over} false alarms "
        f"(largest drift measured {worst:.3f} mm, 99th percentile {p99:.3f} mm; limit {limit} mm)"
    )
    print(
        f"\nbump caught before any pick made with it: {'yes' if caught else 'NO'}; false alarms: {over} "
        f"(benchmark took {time.perf_counter() - t0:.0f} s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

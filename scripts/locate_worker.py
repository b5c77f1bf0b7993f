#!/usr/bin/env python3
"""The other side of `scripts/bench_parts.py --speed --against DIR`: locate from whichever `cell`
package PYTHONPATH names (the bench starts it with DIR, another checkout, e.g. main's), timed in
this process's own CPU time on one core, so that two versions run on the same frames in one run,
interleaved run by run.

Reads pickled messages on stdin: ("frame", (frame, calibration, config)) keeps a frame, ("run", None)
locates it and answers (CPU ms, [(class, table_mm, angle_deg, grasp_mm, head_mm) per part]) on stdout.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pickle  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402

from cell.vision.locate import locate  # noqa: E402


def main() -> int:
    cv2.setNumThreads(1)
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    kept = None
    while True:
        try:
            kind, payload = pickle.load(inp)
        except EOFError:
            return 0
        if kind == "frame":
            kept = payload
            continue
        if kept is None:
            raise SystemExit("locate_worker: 'run' before any 'frame': send the frame first")
        frame, cal, config = kept
        t = time.process_time()
        result = locate(frame, cal, config)
        ms = 1e3 * (time.process_time() - t)
        parts = [(o.cls, o.table_mm, o.angle_deg, o.grasp_mm, o.head_mm) for o in result.objects]
        pickle.dump((ms, parts), out)
        out.flush()


if __name__ == "__main__":
    sys.exit(main())

"""`run-cell serve`, with its Python objects counted by type every `--every-s` seconds (for bench_soak.py).

Each count is one JSON line in `--out`: the time, the process's RSS and the number of live objects of
each type the garbage collector tracks. A growth of RSS that no type's count follows is the C
allocator's (or a C library's), not a Python object's. Not for the line: counting walks every object.

    .venv/bin/python scripts/serve_counting_objects.py --out counts.jsonl [--every-s 120] -- serve --dry-run ...
"""

from __future__ import annotations

import argparse
import collections
import ctypes
import gc
import json
import os
import runpy
import sys
import threading
import time
import tracemalloc

from bench_soak import proc_figures  # RSS read as the bench reads it, in the same unit


class MallInfo2(ctypes.Structure):
    """glibc's mallinfo2(): what the C allocator holds, over all its arenas."""

    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


def malloc_figures() -> dict[str, float]:
    """MB the C allocator has in use, holds free, and has mapped for big blocks (empty off glibc)."""
    try:
        fn = ctypes.CDLL(None).mallinfo2
    except (OSError, AttributeError):
        return {}
    fn.restype = MallInfo2
    m = fn()
    return {"in_use_mb": m.uordblks / 2**20, "free_held_mb": m.fordblks / 2**20, "mmapped_mb": m.hblkhd / 2**20}


def traced_top(previous: tracemalloc.Snapshot | None, snap: tracemalloc.Snapshot) -> list[str]:
    """The source lines whose traced memory grew most since the previous snapshot."""
    if previous is None:
        return []
    return [str(d) for d in snap.compare_to(previous, "lineno")[:12]]


def count_forever(out: str, every_s: float) -> None:
    first: tracemalloc.Snapshot | None = None
    while True:
        time.sleep(every_s)
        objects = gc.get_objects()
        counts = collections.Counter(type(o).__qualname__ for o in objects)
        line = {
            "time": time.time(),
            "rss_mb": proc_figures(os.getpid())["rss_mb"],
            "objects": len(objects),
            "types": dict(counts),
            "malloc": malloc_figures(),
        }
        del objects
        if tracemalloc.is_tracing():
            snap = tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(False, tracemalloc.__file__)])
            line["traced_mb"] = tracemalloc.get_traced_memory()[0] / 2**20
            line["traced_growth_since_first"] = traced_top(first, snap)
            first = first or snap
        with open(out, "a") as f:
            f.write(json.dumps(line) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--every-s", type=float, default=120.0)
    ap.add_argument("--trace", action="store_true", help="also trace allocations (tracemalloc): slower")
    ap.add_argument("cli_args", nargs=argparse.REMAINDER, help="run-cell's arguments, after --")
    args = ap.parse_args()
    cli_args = args.cli_args[1:] if args.cli_args[:1] == ["--"] else args.cli_args
    if args.trace:
        tracemalloc.start()
    threading.Thread(target=count_forever, args=(args.out, args.every_s), daemon=True, name="count-objects").start()
    sys.argv = ["run-cell", *cli_args]
    runpy.run_module("cell.cli", run_name="__main__")


if __name__ == "__main__":
    main()

"""`run-cell serve`, with its Python objects counted by type every `--every-s` seconds (for bench_soak.py).

Each count is one JSON line in `--out`: the time, the process's RSS and the number of live objects of
each type the garbage collector tracks. A growth of RSS that no type's count follows is the C
allocator's (or a C library's), not a Python object's. Not for the line: counting walks every object.

    .venv/bin/python scripts/serve_counting_objects.py --out counts.jsonl [--every-s 120] -- serve --dry-run ...
"""

from __future__ import annotations

import argparse
import collections
import gc
import json
import os
import runpy
import sys
import threading
import time

from bench_soak import proc_figures  # RSS read as the bench reads it, in the same unit


def count_forever(out: str, every_s: float) -> None:
    while True:
        time.sleep(every_s)
        objects = gc.get_objects()
        counts = collections.Counter(type(o).__qualname__ for o in objects)
        line = {
            "time": time.time(),
            "rss_mb": proc_figures(os.getpid())["rss_mb"],
            "objects": len(objects),
            "types": dict(counts),
        }
        del objects
        with open(out, "a") as f:
            f.write(json.dumps(line) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--every-s", type=float, default=120.0)
    ap.add_argument("cli_args", nargs=argparse.REMAINDER, help="run-cell's arguments, after --")
    args = ap.parse_args()
    cli_args = args.cli_args[1:] if args.cli_args[:1] == ["--"] else args.cli_args
    threading.Thread(target=count_forever, args=(args.out, args.every_s), daemon=True, name="count-objects").start()
    sys.argv = ["run-cell", *cli_args]
    runpy.run_module("cell.cli", run_name="__main__")


if __name__ == "__main__":
    main()

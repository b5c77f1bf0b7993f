#!/usr/bin/env python3
"""The whole test suite, several times in a row, with CPU-bound processes running beside it.

Issue 15's check that the tests hold on a loaded machine: `--burners` processes spin on the CPU
for the whole run (by default two, one per core of the 2-core line PC), and the suite (`pytest -n 2`,
what `make test` runs, no retry of any test) runs `--runs` times. Prints each run's outcome, wall
time and the load average, and exits non-zero if any run failed.

    .venv/bin/python scripts/suite_under_load.py [--runs 5] [--burners 2] [-- PYTEST ARGS]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def burn(stop: Any) -> None:
    """Spin until told to stop: a CPU-bound neighbour."""
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x = (x * 1103515245 + 12345) & 0x7FFFFFFF


def junit_counts(report: Path) -> str:
    """Tests, failures, errors and skips from pytest's JUnit XML report."""
    if not report.exists():
        return "no report"
    root = ET.parse(report).getroot()
    suite = root.find("testsuite") if root.tag == "testsuites" else root
    if suite is None:
        return "an empty report"
    get = suite.attrib.get
    return f"{get('tests')} tests, {get('failures')} failed, {get('errors')} errors, {get('skipped')} skipped"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--burners", type=int, default=2, help="CPU-bound processes beside the suite")
    ap.add_argument("pytest_args", nargs="*", help="extra pytest arguments (after --)")
    args = ap.parse_args()
    stop = multiprocessing.Event()
    burners = [multiprocessing.Process(target=burn, args=(stop,), daemon=True) for _ in range(args.burners)]
    for b in burners:
        b.start()
    failed = 0
    try:
        for n in range(1, args.runs + 1):
            t0 = time.monotonic()
            with tempfile.TemporaryDirectory() as tmp:
                report = Path(tmp) / "junit.xml"
                run = subprocess.run(
                    [sys.executable, "-m", "pytest", "-n", "2", "-rfE", f"--junitxml={report}", *args.pytest_args],
                    cwd=REPO,
                    capture_output=True,
                    text=True,
                )
                counts = junit_counts(report)
            wall_s = time.monotonic() - t0
            load = " ".join(f"{v:.1f}" for v in os.getloadavg())
            outcome = "passed" if run.returncode == 0 else f"FAILED (exit {run.returncode})"
            print(f"run {n}/{args.runs}: {outcome} in {wall_s / 60:.1f} min; load {load}; {counts}", flush=True)
            if run.returncode != 0:
                failed += 1
                failures = [line for line in run.stdout.splitlines() if line.startswith(("FAILED", "ERROR"))]
                print("\n".join(failures or run.stdout.splitlines()[-40:]), flush=True)
    finally:
        stop.set()
        for b in burners:
            b.join(timeout=10)
    print(f"{args.runs - failed} of {args.runs} runs passed with {args.burners} CPU-bound processes beside them")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

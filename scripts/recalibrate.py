#!/usr/bin/env python3
"""Operator script: recalibrate the cell from a plate image (see --help); the same command
as `run-cell recalibrate`. Run it with the project's Python (.venv/bin/python), where the
package is installed.

python scripts/recalibrate.py --image PLATE.png --out CAL.json [--config FILE]
    [--model auto|quadratic|homography|polynomial|camera] [--report-dir DIR]

Signal handlers go in before the heavy imports (cell.signals is standard library only), so
a stop in the first second ends it with one line, never a traceback.
"""

import sys

from cell.signals import EXIT_STOPPED, StopRequested, handling_signals


def main() -> int:
    with handling_signals() as controls:
        try:
            from cell.commands import recalibrate
        except StopRequested as e:
            sys.stderr.write(f"recalibrate: stopped during start-up: {e.reason}; the active calibration is unchanged\n")
            return EXIT_STOPPED
        return recalibrate.main(None, controls)


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Operator script: recalibrate the cell from a plate image (see --help); the same command
as `run-cell recalibrate`. Run it with the project's Python (.venv/bin/python), where the
package is installed.

python scripts/recalibrate.py --image PLATE.png --out CAL.json [--config FILE]
    [--model auto|quadratic|homography|polynomial|camera] [--report-dir DIR]
"""

import sys

from cell.commands.recalibrate import main

if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Operator script: recalibrate the cell from a plate image (see --help).

python scripts/recalibrate.py --image PLATE.png --out CAL.json [--config FILE]
    [--model auto|quadratic|homography|polynomial|camera] [--report-dir DIR]
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.calibration.recalibrate import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())

"""argparse value types shared by the commands: what a float on the command line may be."""

from __future__ import annotations

import argparse
import math


def finite_float(text: str) -> float:
    """A float that is a real number: 'nan' and 'inf' parse as floats but pass every bound."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"not a finite number: {text!r}")
    return value


def positive_mm(text: str) -> float:
    """A length in mm above zero (a spacer's thickness)."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be above 0 mm: {text!r}")
    return value

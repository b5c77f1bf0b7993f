"""Shared test helpers: where ../shared is, and skipping, saying why, where it is absent."""
from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
PAPER = SHARED / "paper"
DATA = SHARED / "data"


def need(path: Path) -> Path:
    """Skip the test, saying why, where ../shared is absent (a user's fresh clone has none)."""
    if not path.exists():
        pytest.skip(f"{path} is absent: the paper's data and real photos live in ../shared, outside the repo")
    return path

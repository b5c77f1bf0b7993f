"""Shared test helpers: where the repo and ../shared are (skipping, saying why, where it is
absent), and reading a run's audit log."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cell.audit import read_events

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
PAPER = SHARED / "paper"
DATA = SHARED / "data"


def need(path: Path) -> Path:
    """Skip the test, saying why, where ../shared is absent (a user's fresh clone has none)."""
    if not path.exists():
        pytest.skip(f"{path} is absent: the paper's data and real photos live in ../shared, outside the repo")
    return path


def audit_of(log_dir: Path) -> list[dict]:
    """The events of the one run logged in log_dir."""
    (path,) = log_dir.glob("run-*.jsonl")
    return read_events(path)


def ctrl_c_after_first_pick(*argv: str) -> tuple[int, str]:
    """Run `python -m cell.cli ARGV`, press Ctrl-C once the first pick is reported; its exit
    code and what it printed after that."""
    proc = subprocess.Popen([sys.executable, "-m", "cell.cli", *argv], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        for line in proc.stdout:
            if line.startswith("pick  1:"):
                break
        proc.send_signal(signal.SIGINT)
        rest = proc.stdout.read()
        return proc.wait(timeout=60), rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()

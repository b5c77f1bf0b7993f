"""Fixtures shared by the test modules; the fakes themselves are in tests/doubles.py.

Markers (registered in pyproject.toml, --strict-markers): `slow` on the end-to-end runs
(`make check` leaves them out); pytest-timeout bounds every test, and the ones that open a
pty or a subprocess say their own, tighter, limit.
"""
from __future__ import annotations

import pytest

from drivers.sim.grbl_emulator import GrblEmulator
from drivers.sim.pty_port import serve_pty


@pytest.fixture
def grbl():
    """An emulated GRBL 1.1 (20x its real speed) on a fresh pseudo-terminal: (emulator, port path)."""
    emu = GrblEmulator(speed_scale=20)
    with serve_pty(emu) as path:
        yield emu, path

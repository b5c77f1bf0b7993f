"""Fixtures shared by the test modules; the fakes themselves are in tests/doubles.py.

Markers (registered in pyproject.toml, --strict-markers): `slow` on the end-to-end runs
(`make check` leaves them out); `exhaustive` on the sweeps far longer than the suite, collected only
with --exhaustive. pytest-timeout bounds every test, and the ones that open a pty or a
subprocess say their own, tighter, limit. Device and file locks go to a folder of this
test session, not the machine's.
"""

from __future__ import annotations

import os

import pytest

from cell.locks import LOCK_DIR_ENV
from cell.ownership import ALLOW_ENV
from drivers.sim.grbl_emulator import GrblEmulator
from drivers.sim.pty_port import serve_pty


def pytest_addoption(parser):
    parser.addoption(
        "--exhaustive",
        action="store_true",
        help="also run the exhaustive sweeps (every audit write, every signal in every state on both arms, "
        "every hard variant of the real plate photos through the pitch gate; far longer than the suite)",
    )


def pytest_collection_modifyitems(config, items):
    if config.getoption("--exhaustive"):
        return
    keep = [item for item in items if "exhaustive" not in item.keywords]
    if len(keep) < len(items):
        config.hook.pytest_deselected(items=[item for item in items if "exhaustive" in item.keywords])
        items[:] = keep


@pytest.fixture(scope="session", autouse=True)
def private_lock_dir(tmp_path_factory):
    before = os.environ.get(LOCK_DIR_ENV)
    os.environ[LOCK_DIR_ENV] = str(tmp_path_factory.mktemp("locks"))
    yield
    if before is None:
        os.environ.pop(LOCK_DIR_ENV, None)
    else:
        os.environ[LOCK_DIR_ENV] = before


@pytest.fixture(scope="session", autouse=True)
def root_in_a_checkout_of_another_user():
    """Run as root in a checkout another user owns (a CI's), the tests that start run-cell in it would
    be refused (cell.ownership): no service uses a checkout, so root is let work there."""
    from pathlib import Path

    if os.geteuid() == 0 and Path(__file__).resolve().parents[1].stat().st_uid != 0:
        os.environ[ALLOW_ENV] = "1"
    yield


@pytest.fixture
def grbl():
    """An emulated GRBL 1.1 (20x its real speed) on a fresh pseudo-terminal: (emulator, port path)."""
    emu = GrblEmulator(speed_scale=20)
    with serve_pty(emu) as path:
        yield emu, path

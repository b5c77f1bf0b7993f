"""`run-cell --version`: the package's version and the schema versions of the files it reads."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

from cell.calibration.store import SCHEMA, SCHEMA_VERSION
from cell.cli import DISTRIBUTION, main
from cell.history.schema import VERSION as HISTORY_VERSION

ROOT = Path(__file__).resolve().parents[1]


def test_the_distribution_is_pyproject_s() -> None:
    import tomllib

    assert tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["name"] == DISTRIBUTION


def test_version_prints_the_package_and_the_schemas(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"run-cell ({DISTRIBUTION}) {version(DISTRIBUTION)}"
    assert f"calibration file: schema {SCHEMA} version {SCHEMA_VERSION}" in lines
    assert f"history database: schema version {HISTORY_VERSION} (older stores are migrated when opened)" in lines
    assert any(line.startswith("config: no schema version;") for line in lines)


def test_the_installed_command_prints_it_and_opens_nothing(tmp_path: Path) -> None:
    """As the console script runs it (cell.launch): no start-up line, no log folder, exit 0."""
    done = subprocess.run(
        [sys.executable, "-c", "import sys; from cell.launch import main; sys.exit(main())", "--version"],
        cwd=tmp_path,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"run-cell ({DISTRIBUTION}) ") and done.stderr == ""
    assert list(tmp_path.iterdir()) == []

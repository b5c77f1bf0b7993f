"""The words `run-cell` says: the command's own name in every error, a short usage when run
bare, a description on every command and help on every option, hints naming run-cell."""

from __future__ import annotations

import argparse
import errno
import io

import pytest

from cell.cli import build_parser, main
from cell.terminal import StdoutGuard

pytestmark = pytest.mark.timeout(60)


def test_a_bare_run_cell_prints_the_common_starts_and_exits_2(capsys):
    assert main([]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    for start in ("run-cell --dry-run", "run-cell --config FILE", "run-cell serve --dry-run", "run-cell camera"):
        assert f"\n  {start} " in err
    assert len(err.splitlines()) < 15


def _parsers(parser: argparse.ArgumentParser, name: str = "run-cell"):
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from _parsers(sub, sub_name)


def test_every_command_has_a_description_and_every_option_help():
    for name, parser in _parsers(build_parser()):
        assert parser.description, f"{name} has no description"
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            assert action.help, f"{name} {action.option_strings or action.dest} has no help"


def test_the_bare_run_s_errors_say_run_cell(tmp_path, capsys):
    assert main(["--config", str(tmp_path / "missing.toml"), "--log-dir", str(tmp_path / "logs")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("run-cell: error: ") and "missing.toml" in err


def test_a_missing_calibration_s_hint_names_run_cell_recalibrate(tmp_path, capsys):
    assert main(["map", "--calibration", str(tmp_path / "none.json"), "10", "20"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("run-cell map: error: ") and "run-cell recalibrate" in err and "scripts/" not in err


@pytest.mark.parametrize(
    "gone", [BrokenPipeError(errno.EPIPE, "Broken pipe"), OSError(errno.EIO, "Input/output error")]
)
def test_the_stdout_guard_drops_output_once_the_reader_is_gone(gone):
    class Gone(io.StringIO):
        def write(self, text: str) -> int:
            raise gone

    guard = StdoutGuard(Gone())
    assert guard.write("a line\n") == len("a line\n")
    guard.flush()
    assert guard.lost is gone
    assert guard.write("more\n") == len("more\n")  # dropped, never raised


def test_the_stdout_guard_lets_other_errors_through():
    class Full(io.StringIO):
        def write(self, text: str) -> int:
            raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match="No space"):
        StdoutGuard(Full()).write("x")

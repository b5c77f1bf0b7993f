"""`run-cell`: the operator's command. Each sub-command lives in its own module.

Every failure the operator can cause or meet (bad file, bad config, device trouble) is a
CellError or a driver's DeviceError: one line on stderr saying what and where, and a
non-zero exit. Stop signals are handled from the start (cell.signals), before any command
opens a device.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from cell.commands import run
from cell.errors import REPORTED_ERRORS, describe_os_error, exit_code
from cell.memory import keep_big_blocks_mapped
from cell.oplog import quiet_terminal
from cell.ownership import refuse_root_in_anothers_folder
from cell.recordfile import tell_stderr
from cell.signals import EXIT_STOPPED, Controls, StopRequested, handling_signals
from cell.terminal import guarded_stdout

# Modules that each add sub-commands through register(subparsers).
COMMAND_MODULES = [
    "cell.commands.calibration",
    "cell.commands.recalibrate",
    "cell.commands.arm",
    "cell.commands.locate",
    "cell.commands.part",
    "cell.commands.camera",
    "cell.commands.cameras",
    "cell.commands.run",
    "cell.commands.serve",
    "cell.commands.users",
    "cell.commands.history",
    "cell.commands.report",
    "cell.commands.config",
    "cell.commands.backup",
]

log = logging.getLogger(__name__)

# The commands that write into the cell's folder (the config's relative paths: calibration, logs,
# history, certificates): refused as root in a folder of another user (cell.ownership).
WRITES_CELL_FOLDER = {None, "serve", "recalibrate", "teach"}

# What a bare `run-cell` prints (on stderr, exit 2): the usual ways to start, not every option.
SHORT_USAGE = """\
usage: run-cell [--dry-run | --config FILE] [options]   or   run-cell COMMAND [options]

Common starts:
  run-cell --dry-run              rehearse a job on the built-in simulated cell (nothing moves)
  run-cell --config FILE          run the job of the cell FILE describes (its camera, calibration, arm)
  run-cell serve --dry-run        the simulated line service: OPC UA and the operator screen
  run-cell serve --config FILE    the line service of FILE, for a whole shift
  run-cell camera --live          look through the camera: focus, exposure, the plate

`run-cell --help` lists every command and option; docs/commissioning.md sets up a new cell."""


DISTRIBUTION = "pick-cell"  # [project] name in pyproject.toml


def version_text() -> str:
    """What `run-cell --version` prints: the package, then each file format's schema and version, so an
    upgrade can be checked against what a cell holds (a calibration file of another version is refused)."""
    from importlib.metadata import PackageNotFoundError, version

    from cell.calibration.store import SCHEMA, SCHEMA_VERSION
    from cell.history.schema import VERSION as HISTORY_VERSION
    from cell.planning import SCHEMA as FRAME_SCHEMA

    try:
        package = version(DISTRIBUTION)
    except PackageNotFoundError:
        package = "unknown (not installed: running from a source tree)"
    return "\n".join(
        [
            f"run-cell ({DISTRIBUTION}) {package}",
            f"calibration file: schema {SCHEMA} version {SCHEMA_VERSION}",
            f"robot frame file: schema {FRAME_SCHEMA} (not versioned)",
            f"history database: schema version {HISTORY_VERSION} (older stores are migrated when opened)",
            "config: no schema version; checked against this version's models, unknown keys are errors "
            "(run-cell config check FILE; docs/config.md)",
        ]
    )


class VersionAction(argparse.Action):
    """`--version`: print version_text() and exit 0; computed only when asked (it imports the stores)."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)  # type: ignore[arg-type]

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: object,
        option_string: str | None = None,
    ) -> None:
        print(version_text())
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="run-cell",
        description="Vision-guided pick-and-place cell.",
        epilog=SHORT_USAGE.split("\n\n", 1)[1].rsplit("\n\n", 1)[0],  # the common starts
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug detail to stderr")
    parser.add_argument(
        "--version",
        action=VersionAction,
        help="print the package's version and the versions of the files it reads and writes, and exit",
    )
    run.add_run_arguments(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None, controls: Controls | None = None) -> int:
    """The command; `controls` are the signal handlers' (cell.launch installs them before the imports)."""
    with handling_signals(controls, install=controls is None) as controls:
        parser = build_parser()
        args = parser.parse_args(argv)
        args.controls = controls
        logging.basicConfig(
            level=logging.DEBUG if args.verbose else logging.WARNING,
            format="%(levelname)s %(name)s: %(message)s",
        )
        # The terminal keeps to warnings unless -v, even once a command logs INFO to its file.
        quiet_terminal(logging.DEBUG if args.verbose else logging.WARNING)
        if not getattr(args, "func", None):
            if not (args.dry_run or args.run_config):
                tell_stderr(SHORT_USAGE)
                return 2
            args.func, args.command = run.run_cell, None
        name = "run-cell" if args.command is None else f"run-cell {args.command}"
        keep_big_blocks_mapped()  # before any thread starts: frame-sized blocks never pile up in the heap
        with guarded_stdout() as stdout:
            code, last = _dispatch(args, name)
        if stdout.lost is not None and not last and code == 0:  # a failure's own line says what happened
            tell_stderr(
                f"{name}: note: standard output was closed early ({stdout.lost.strerror or stdout.lost}); "
                f"the rest of the output was not shown, the command ran to its end (exit {code})"
            )
        if last:  # what failed and where is always the last line
            tell_stderr(last)
        return code


def _dispatch(args: argparse.Namespace, name: str) -> tuple[int, str]:
    """Run the command: its exit code and, when it failed, the last line for stderr naming what and where."""
    try:
        if args.command in WRITES_CELL_FOLDER:
            refuse_root_in_anothers_folder(name)
        return int(args.func(args) or 0), ""
    except REPORTED_ERRORS as e:
        return exit_code(e), f"{name}: error: {e}"
    except StopRequested as e:
        return EXIT_STOPPED, f"{name}: stopped: {e.reason}"
    except KeyboardInterrupt:
        return EXIT_STOPPED, f"{name}: stopped: Ctrl-C"
    except OSError as e:
        return 3, f"{name}: error: {describe_os_error(e)}"
    except Exception as e:  # a bug: one line for the operator, the traceback in the log
        log.exception("internal error in %s", name)
        return 3, f"{name}: internal error: {type(e).__name__}: {e} (details in the log)"


if __name__ == "__main__":
    sys.exit(main())

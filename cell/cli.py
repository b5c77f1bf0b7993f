"""`run-cell`: the operator's command. Each sub-command lives in its own module.

Every failure the operator can cause or meet (bad file, bad config, device trouble) is a
CellError or a driver's DeviceError: one line on stderr saying what and where, and a
non-zero exit.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

from cell.commands import run
from cell.errors import REPORTED_ERRORS, exit_code

# Modules that each add sub-commands through register(subparsers).
COMMAND_MODULES = [
    "cell.commands.calibration",
    "cell.calibration.recalibrate",
    "cell.commands.arm",
    "cell.commands.locate",
    "cell.commands.run",
    "cell.commands.serve",
]

log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="run-cell",
        description="Vision-guided pick-and-place cell.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug detail to stderr")
    run.add_run_arguments(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        if not (args.dry_run or args.run_config):
            parser.print_help()
            return 2
        args.func, args.command = run.run_cell, "run"
    try:
        return int(args.func(args) or 0)
    except REPORTED_ERRORS as e:
        print(f"run-cell {args.command}: error: {e}", file=sys.stderr)
        return exit_code(e)
    except KeyboardInterrupt:
        print(f"run-cell {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

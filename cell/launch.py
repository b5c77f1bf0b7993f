"""`run-cell`'s first lines: signal handlers and a progress line before anything heavy is imported.

Importing the application (numpy, OpenCV, pydantic, the drivers) takes a second or more on a
busy line PC. A pause (SIGUSR1) or a stop signal in that second must neither kill the
process nor be lost, and the operator should see at once that the command started. So the
console script lands here: only the standard library and cell.signals (itself standard
library only) are imported before the handlers are in place; a stop during the imports
ends the command with exit 130 and one line; a pause is kept and honoured by the job
before its first motion.
"""

from __future__ import annotations

import os
import sys

# Sub-commands whose start-up takes seconds say so in their first line; the job itself
# (`run-cell --dry-run`, `run-cell --config FILE`) too. Other sub-commands answer quickly.
_OTHER_COMMANDS = frozenset(
    {
        "map",
        "check-calibration",
        "calibrate-demo",
        "ports",
        "jog",
        "home",
        "locate",
        "camera",
        "teach",
        "diagram",
        "hash-password",
        "user",
        "history",
        "report",
    }
)
_SLOW_STARTS = {
    "serve": "loading the cell, then OPC UA and the operator screen",
    "recalibrate": "loading the calibration tools",
}


def first_line(argv: list[str]) -> str | None:
    """The progress line a command prints before its imports, or None (help, the other commands)."""
    if any(a in ("-h", "--help") for a in argv):
        return None
    pid = os.getpid()
    words = {a for a in argv if not a.startswith("-")}
    for name, what in _SLOW_STARTS.items():
        if name in words:
            return f"run-cell {name}: starting (pid {pid}): {what}"
    if words & _OTHER_COMMANDS or not ({"--dry-run", "--config"} & set(argv)):
        return None
    where = "the configured cell" if "--config" in argv else "the built-in simulated cell"
    return f"run-cell: starting a job on {where} (pid {pid}; Ctrl-C stops safely, kill -USR1 {pid} pauses)"


def main(argv: list[str] | None = None) -> int:
    from cell.signals import EXIT_STOPPED, StopRequested, handling_signals

    args = sys.argv[1:] if argv is None else argv
    with handling_signals() as controls:
        try:
            line = first_line(args)
            if line is not None:
                _say(line)
            from cell import cli  # the heavy imports, with the handlers already in place
        except StopRequested as e:
            _tell(f"run-cell: stopped during start-up: {e.reason} (nothing was opened)")
            return EXIT_STOPPED
        return cli.main(argv, controls)


def _say(line: str) -> None:
    try:
        print(line, flush=True)
    except (OSError, ValueError):
        pass  # a closed terminal never stops the command


def _tell(line: str) -> None:
    try:
        sys.stderr.write(line + "\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass


if __name__ == "__main__":
    sys.exit(main())

"""Standard output that a closed pipe cannot turn into a failure.

`run-cell recalibrate ... | head -3`: once `head` has its lines it exits, and the next print
raises BrokenPipeError (Python ignores SIGPIPE). Work the operator asked for (replacing the
calibration) must not stop there, half done. While a command runs, sys.stdout is a guard:
the first write to a closed pipe is remembered, stdout is pointed at /dev/null (so the
interpreter's last flush cannot fail either), and everything after is dropped; the command
runs to its end and the CLI says on stderr that its output was cut short.
"""

from __future__ import annotations

import contextlib
import errno
import os
import sys
from collections.abc import Iterator
from typing import TextIO


class StdoutGuard:
    """A stand-in for sys.stdout that, once the reader is gone (a broken pipe, a hung-up
    terminal), drops all further output instead of raising; any other error is raised."""

    def __init__(self, stream: TextIO):
        self.stream = stream
        self.lost: OSError | None = None

    def write(self, text: str) -> int:
        if self.lost is None:
            try:
                return self.stream.write(text)
            except OSError as e:
                self._lose(e)
        return len(text)

    def flush(self) -> None:
        if self.lost is None:
            try:
                self.stream.flush()
            except OSError as e:
                self._lose(e)

    def _lose(self, e: OSError) -> None:
        if e.errno not in (errno.EPIPE, errno.EIO):  # the reader is gone: a closed pipe, a hung-up terminal
            raise e
        self.lost = e
        with contextlib.suppress(OSError, ValueError, AttributeError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self.stream.fileno())
            os.close(devnull)

    def __getattr__(self, name: str) -> object:
        return getattr(self.stream, name)


@contextlib.contextmanager
def guarded_stdout() -> Iterator[StdoutGuard]:
    """sys.stdout guarded for a block; `lost` on the guard says whether output was cut short."""
    guard = StdoutGuard(sys.stdout)
    sys.stdout = guard
    try:
        yield guard
    finally:
        sys.stdout = guard.stream

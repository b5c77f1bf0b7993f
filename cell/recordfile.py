"""Files the cell keeps its record in: created exclusively, written best effort.

A run's record must never be appended to another run's file, so each file is created
with O_EXCL under a name no other process can be using. And a record that cannot be
written (a full disk, a pulled USB stick) must never stop the arm being made safe: the
first failed write is reported once on stderr, later writes are dropped, and the owner
decides (via `failed`) whether that is a fault.
"""

from __future__ import annotations

import errno
import os
import sys
from datetime import UTC, datetime
from pathlib import Path


def unique_stem(folder: Path, prefix: str, suffixes: tuple[str, ...]) -> Path:
    """`folder/prefix-<utc time>-<pid>[-n]`: no file with any of `suffixes` exists under it yet."""
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    base = folder / f"{prefix}-{stamp}-{os.getpid()}"
    stem, n = base, 1
    while any(stem.with_name(stem.name + s).exists() for s in suffixes):
        n += 1
        stem = base.with_name(f"{base.name}-{n}")
    return stem


def tell_stderr(text: str) -> None:
    """Text on stderr; silent if stderr itself is gone (a closed terminal)."""
    try:
        sys.stderr.write(text + "\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass


class RecordFile:
    """An append-only text file of lines, opened exclusively (or shared, for a common log).

    `write_line` never raises: a failed write sets `failed`, is reported once through
    `on_failure`, and every later line is dropped (a half-broken file is not retried).
    """

    def __init__(self, path: str | Path, *, exclusive: bool = True, what: str = "log"):
        self.path = Path(path)
        self.what = what
        self.failed: OSError | None = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC | (os.O_EXCL if exclusive else 0)
        self._fd: int | None = os.open(self.path, flags, 0o644)

    def write_line(self, text: str) -> bool:
        """Write one line in as few writes as the OS allows; False once the file has failed."""
        if self.failed is not None or self._fd is None:
            return False
        data = (text + "\n").encode("utf-8")
        try:
            while data:
                n = self._write(data)
                if n == 0:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                data = data[n:]
        except OSError as e:
            self.failed = e
            tell_stderr(f"{self.what} {self.path}: write failed ({e.strerror or e}); its further lines are dropped")
            return False
        return True

    def _write(self, data: bytes) -> int:
        """The one system call that writes (tests inject a full disk here)."""
        if self._fd is None:
            raise OSError(errno.EBADF, f"{self.what} {self.path} is closed")
        return os.write(self._fd, data)

    def close(self) -> None:
        if self._fd is not None:
            try:
                os.close(self._fd)
            except OSError:
                pass
            self._fd = None

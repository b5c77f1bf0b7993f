"""Files written whole or not at all: a uniquely named temporary file beside the target,
synced, then renamed over it. On any failure (a full disk, a signal, a folder where a file
should be) the temporary file is removed and the error names the target in one line.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from cell.errors import OutputError, output_error


def write_atomic(path: str | Path, write: Callable[[BinaryIO], object]) -> Path:
    """Call write(f) on a temporary file, then make it `path`; OutputError if that cannot be done."""
    path = Path(path)
    tmp = _temporary_beside(path)
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise output_error(path, e) from None
        raise
    return path


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    return write_atomic(path, lambda f: f.write(data))


def write_text_atomic(path: str | Path, text: str) -> Path:
    return write_bytes_atomic(path, text.encode("utf-8"))


def copy_unique(source: str | Path, folder: str | Path, stem: str, suffix: str) -> Path:
    """Copy `source` whole into `folder` as `stem[-n]suffix`, a name no other copy has: two
    copies made in the same second (two recalibrations) never overwrite one another."""
    folder = Path(folder)
    data = Path(source).read_bytes()
    tmp = _temporary_beside(folder / f"{stem}{suffix}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        for n in range(1, 10000):
            target = folder / (f"{stem}{suffix}" if n == 1 else f"{stem}-{n}{suffix}")
            try:
                os.link(tmp, target)  # fails if the name is taken: never replaces a backup
                return target
            except FileExistsError:
                continue
        raise OutputError(f"{folder}: no free backup name for {stem}{suffix}")
    except OSError as e:
        raise output_error(folder / f"{stem}{suffix}", e) from None
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def ensure_folder(path: str | Path) -> Path:
    """Create a folder for outputs (with its parents), or OutputError naming it."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"{path}: is a file, not a folder", hint="give a folder path") from None
    except OSError as e:
        raise output_error(path, e) from None
    return path


def _temporary_beside(path: Path) -> str:
    """A new, uniquely named empty file beside `path`, with the permissions the umask gives
    (mkstemp's 0600 would make every report unreadable to the other operators)."""
    if path.is_dir():
        raise OutputError(f"{path}: is a folder, not a file", hint="give a file path")
    ensure_folder(path.parent)
    while True:
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666))
            return str(tmp)
        except FileExistsError:
            continue
        except OSError as e:
            raise output_error(path, e) from None

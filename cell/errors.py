"""Errors the operator sees: each says what went wrong and where, in one line."""

from __future__ import annotations

import errno
import os

from drivers.errors import DeviceError

DEVICE_EXIT_CODE = 2  # a device or driver-config failure exits as any other CellError does


class CellError(Exception):
    """Base of every error the CLI reports as a one-line message with a non-zero exit."""

    exit_code = 2

    def __init__(self, message: str, hint: str | None = None):
        super().__init__(message)
        self.hint = hint

    def __str__(self) -> str:
        text = super().__str__()
        return f"{text} (hint: {self.hint})" if self.hint else text


class ConfigError(CellError):
    """A config file is missing, unreadable or has a wrong value."""


class InputError(CellError):
    """An input file (image, CSV, calibration) is missing, unreadable or invalid."""


class PlateNotFound(CellError):
    """The calibration plate could not be found or numbered unambiguously."""


class CameraMoved(CellError):
    """The reference marks no longer map where they lie: the calibration no longer holds."""


class CalibrationRejected(CellError):
    """A fit was made but is not good enough to replace the active calibration."""

    exit_code = 3


# What the CLI reports as one line with a documented exit code, and the runner treats as a
# fault rather than a bug: the application's errors and the drivers' (which cannot subclass
# CellError: drivers/ never imports cell/).
REPORTED_ERRORS = (CellError, DeviceError)


def exit_code(error: CellError | DeviceError) -> int:
    """The exit code the CLI returns for a reported error."""
    return error.exit_code if isinstance(error, CellError) else DEVICE_EXIT_CODE


class OutputError(CellError):
    """A file the command writes cannot be written (a folder given, read-only, full disk)."""


def describe_os_error(e: OSError) -> str:
    """'<file>: <reason>' from an OSError, naming the file it was about when it says."""
    where = e.filename if e.filename is not None else ""
    reason = e.strerror or str(e)
    return f"{where}: {reason}" if where else reason


def output_error(path: str | os.PathLike[str], e: OSError) -> OutputError:
    """A failed write to `path` as a one-line error: exit 2 for a wrong destination, 3 for the disk failing."""
    err = OutputError(
        f"{path}: cannot write: {e.strerror or e}", hint="give a writable file path with free space on its filesystem"
    )
    if e.errno in _DISK_FAILED:
        err.exit_code = 3
    return err


_DISK_FAILED = {errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EFBIG}

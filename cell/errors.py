"""Errors the operator sees: each says what went wrong and where, in one line."""
from __future__ import annotations

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

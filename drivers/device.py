"""What every device driver shares: connect, disconnect (never raises), is_connected, and
`with device:` connecting and always disconnecting. Arm and Camera build on it."""

from __future__ import annotations

import abc
from types import TracebackType
from typing import Self


class Device(abc.ABC):
    @abc.abstractmethod
    def connect(self) -> None: ...

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Release the device (close the port); never raises."""

    @property
    @abc.abstractmethod
    def is_connected(self) -> bool: ...

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.disconnect()

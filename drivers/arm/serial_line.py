"""A text line over pyserial: open by path or URL, write, read lines against a deadline.

Knows nothing of G-code; turns every pyserial/OS failure into ConnectionLost naming the port.
"""

from __future__ import annotations

import logging
import os
import termios
import time

import serial

from drivers.arm.errors import ConnectionLost

log = logging.getLogger(__name__)

# What pyserial lets through when a device vanishes: termios.error is not an OSError.
_PORT_ERRORS = (serial.SerialException, OSError, termios.error)


def wait_for_port(port: str, timeout_s: float) -> None:
    """Wait for a re-plugged device path to reappear (URLs are tried at once)."""
    deadline = time.monotonic() + timeout_s
    while "://" not in port and not os.path.exists(port) and time.monotonic() < deadline:
        time.sleep(0.05)


class SerialLine:
    def __init__(self, port: str, baud: int):
        self.port = port
        self.baud = baud
        self._ser: serial.Serial | None = None
        self._buf = bytearray()

    @property
    def is_open(self) -> bool:
        return self._ser is not None and self._ser.is_open

    def open(self) -> None:
        """Open the port; serial_for_url so socket:// and spy:// work as well as device paths."""
        self.close()
        try:
            # exclusive: a second program opening the port is refused, never let in to reset the controller
            self._ser = serial.serial_for_url(
                self.port, baudrate=self.baud, timeout=0.01, write_timeout=1.0, exclusive=True
            )
        except (*_PORT_ERRORS, ValueError) as e:
            raise ConnectionLost(
                f"cannot open serial port: {e}",
                port=self.port,
                hint="check the port path (`run-cell ports` lists them) and that no other program holds it",
            ) from None
        self._buf.clear()

    def wait_until_present(self, timeout_s: float) -> None:
        wait_for_port(self.port, timeout_s)

    def close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except _PORT_ERRORS as e:
                log.debug("closing %s: %s", self.port, e)
            self._ser = None

    def write(self, data: bytes, what: str | None = None) -> None:
        ser = self._require(what)
        try:
            ser.write(data)
            ser.flush()
        except _PORT_ERRORS as e:
            self.close()
            raise ConnectionLost(f"connection lost while writing: {e}", port=self.port, command=what) from None

    def reset_input(self) -> None:
        self._buf.clear()
        ser = self._require(None)
        try:
            ser.reset_input_buffer()
        except _PORT_ERRORS as e:
            self.close()
            raise ConnectionLost(f"connection lost: {e}", port=self.port) from None

    def read_line(self, deadline: float, what: str | None = None) -> str | None:
        """Next line without its line ending, or None once the monotonic deadline passes."""
        ser = self._require(what)
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                raw = bytes(self._buf[:nl]).rstrip(b"\r")
                del self._buf[: nl + 1]
                return raw.decode("ascii", errors="backslashreplace")
            if time.monotonic() >= deadline:
                return None
            try:
                chunk = ser.read(max(1, ser.in_waiting))
            except _PORT_ERRORS as e:
                self.close()
                raise ConnectionLost(f"connection lost while reading: {e}", port=self.port, command=what) from None
            self._buf += chunk

    def _require(self, what: str | None) -> serial.Serial:
        if self._ser is None:
            raise ConnectionLost("serial port is not open", port=self.port, command=what)
        return self._ser

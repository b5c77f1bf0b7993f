"""Device errors: each carries the port, the command sent and the device's own reply, so the
one-line message the operator sees says what failed, where, and what to do. The application
(cell/) reports them; drivers never import it."""

from __future__ import annotations


class DeviceError(Exception):
    """Base of every driver failure (arm, camera, driver config)."""

    default_hint: str | None = None

    def __init__(
        self,
        message: str,
        *,
        port: str | None = None,
        command: str | None = None,
        reply: str | None = None,
        hint: str | None = None,
    ) -> None:
        details = []
        if port:
            details.append(f"port {port}")
        if command:
            details.append(f"command {command!r}")
        if reply:
            details.append(f"reply {reply!r}")
        super().__init__(f"{message} [{', '.join(details)}]" if details else message)
        self.port = port
        self.command = command
        self.reply = reply
        self.hint = hint or self.default_hint

    def __str__(self) -> str:
        text = super().__str__()
        return f"{text} (hint: {self.hint})" if self.hint else text


class ConfigError(DeviceError):
    """A driver config cannot build a device (a serial arm with no port). Named as the
    application's ConfigError so the audit log's fault reason reads as it always has."""

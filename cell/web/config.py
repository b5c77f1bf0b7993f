"""`[service.web]`: the operator screen's own settings. Where it listens (`service.host`,
`service.http_port`) and the password (`service.user`, `service.password_hash` or
`password_env`) are the line service's, shared with OPC UA."""

from __future__ import annotations

from pydantic import Field

from drivers.config import Strict


class WebConfig(Strict):
    """Who may watch, how long a login lasts, upload and frame limits."""

    view_without_password: bool = Field(
        False, description="with a password: let anyone who reaches the screen watch (controls still need it)"
    )
    session_h: float = Field(12.0, gt=0, le=168, description="how long a login lasts")
    max_upload_mb: float = Field(25.0, gt=0, le=200, description="largest plate image accepted by upload")
    frame_max_width_px: int = Field(
        1280, ge=160, le=8000, description="frames are scaled down to this width for the screen"
    )
    jpeg_quality: int = Field(80, ge=20, le=100)
    max_screens: int = Field(16, ge=1, le=256, description="open screens at once (each holds one event stream)")

"""`[service.web]`: where the operator screen listens and who may use it."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class WebConfig(BaseModel):
    """The screen's listener, access and frame settings."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    host: str = Field("127.0.0.1", min_length=1, description="address to listen on; loopback unless a password is set")
    port: int = Field(8080, ge=0, le=65535, description="TCP port (0: any free port, printed when ready)")
    password_scrypt: str | None = Field(
        None, description="password hash from `run-cell hash-password` (scrypt$N$r$p$salt$hash)"
    )
    password_env: str = Field(
        "CELL_WEB_PASSWORD", pattern=r"^[A-Z_][A-Z0-9_]*$", description="environment variable holding the password"
    )
    view_without_password: bool = Field(
        False, description="with a password: let anyone who reaches the screen watch (controls still need it)"
    )
    session_h: float = Field(12.0, gt=0, le=168, description="how long a login lasts")
    max_upload_mb: float = Field(25.0, gt=0, le=200, description="largest plate image accepted by upload")
    frame_max_width_px: int = Field(1280, ge=160, le=8000, description="frames are scaled down to this width for the screen")
    jpeg_quality: int = Field(80, ge=20, le=100)
    max_screens: int = Field(16, ge=1, le=256, description="open screens at once (each holds one event stream)")

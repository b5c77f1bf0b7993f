"""`[service.web]`: the operator screen's own settings. Where it listens (`service.host`,
`service.http_port`) and the password (`service.user`, `service.password_hash` or
`password_env`) are the line service's, shared with OPC UA."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, model_validator

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
    jpeg_quality: int = Field(
        80, ge=20, le=100, description="JPEG quality of the frames sent to the screens (100: best, largest)"
    )
    live_interval_s: float = Field(
        2.0,
        ge=0,
        le=60,
        description="between jobs and while paused, a live camera frame this often while a screen is open (0: none)",
    )
    max_frame_rate_hz: float = Field(
        4.0,
        ge=0,
        le=60,
        description="a running job's frames drawn and sent to the screens at most this often (0: every frame);"
        " the newest is always shown",
    )
    max_screens: int = Field(16, ge=1, le=256, description="open screens at once (each holds one event stream)")
    # HTTPS (whenever users are configured; docs/security.md)
    tls_certificate: Path | None = Field(
        None,
        description="the screen's HTTPS certificate (PEM, chain allowed); default: one made on first start, "
        "screen-cert.pem in service.certificate_dir",
    )
    tls_key: Path | None = Field(None, description="its private key (PEM); required with tls_certificate")
    hsts_max_age_s: int = Field(
        31_536_000, ge=0, le=63_072_000, description="Strict-Transport-Security max-age sent over HTTPS (0: none)"
    )
    # Limits, so no client can starve the screen or the process of descriptors
    header_timeout_s: float = Field(
        10.0, gt=0, le=300, description="a connection's TLS handshake and request headers must arrive within this"
    )
    body_timeout_s: float = Field(
        120.0, gt=0, le=3600, description="a request's body must arrive within this once its headers are in"
    )
    keepalive_timeout_s: float = Field(
        5.0, gt=0, le=300, description="an idle kept-alive connection is closed after this"
    )
    max_connections: int = Field(256, ge=8, le=10000, description="open screen connections at once, all clients")
    max_connections_per_address: int = Field(
        32,
        ge=2,
        le=10000,
        description="open screen connections from one client address (not this PC's own 127.0.0.1 / ::1)",
    )
    max_streams_per_address: int = Field(
        4,
        ge=1,
        le=256,
        description="open event streams (screens) from one client address (not this PC's own: max_screens bounds those)",
    )
    write_stall_s: float = Field(
        15.0,
        gt=0,
        le=600,
        description="a client that takes nothing we send for this long is dropped (a stream that does not read)",
    )
    send_buffer_kb: int = Field(
        256, ge=16, le=65536, description="bytes queued for one client before it counts as not reading"
    )
    decode_timeout_s: float = Field(
        10.0, gt=0, le=300, description="an uploaded image must decode within this (in a worker process, one at a time)"
    )
    report_timeout_s: float = Field(
        600.0,
        gt=0,
        le=86400,
        description="a recalibration report holds Start and Resume while it waits for its answer; unanswered "
        "this long, it is rejected by itself (recorded) and the hold released",
    )
    teach_timeout_s: float = Field(
        600.0,
        gt=0,
        le=86400,
        description="the Teach page's session (its frames and the model learnt from them) is discarded when "
        "nothing was done with it this long",
    )
    teach_max_frames: int = Field(
        5, ge=1, le=20, description="frames one teaching session holds at most (each a full camera frame in memory)"
    )

    @model_validator(mode="after")
    def _certificate_with_key(self) -> WebConfig:
        if (self.tls_certificate is None) != (self.tls_key is None):
            raise ValueError("tls_certificate and tls_key go together: give both, or neither (one is made)")
        return self

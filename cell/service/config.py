"""`[service]`: where `run-cell serve` listens, how clients prove who they are, how it paces
continuous mode and rotates its shift log. What each security setting protects:
docs/security.md."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from cell.access.network import is_loopback
from cell.service.mv_config import MachineVisionConfig
from cell.web.config import WebConfig
from drivers.config import Strict

OpcUaPolicy = Literal[
    "Basic256Sha256_SignAndEncrypt",
    "Aes128Sha256RsaOaep_SignAndEncrypt",
    "Aes256Sha256RsaPss_SignAndEncrypt",
    "Basic256Sha256_Sign",
    "Aes128Sha256RsaOaep_Sign",
    "Aes256Sha256RsaPss_Sign",
]


class LoginConfig(Strict):
    """`[service.login]`: how failed logins slow down and lock out guessing, on the screen and OPC UA alike."""

    max_failures_per_user: int = Field(
        5, ge=1, le=1000, description="failed logins for one user name before it is locked out"
    )
    max_failures_per_address: int = Field(
        20, ge=1, le=10000, description="failed logins from one client address (any user) before it is locked out"
    )
    lockout_s: float = Field(300.0, gt=0, le=86400, description="how long a lockout lasts")
    backoff_first_s: float = Field(
        1.0, ge=0, le=60, description="refuse the next try for this long after a first failure, doubling after each"
    )
    backoff_max_s: float = Field(30.0, ge=0, le=3600, description="the longest back-off between tries before lockout")
    forget_after_s: float = Field(
        900.0, gt=0, le=86400, description="failures older than this (with none since) no longer count"
    )


class OpcUaLimits(Strict):
    """`[service.opcua_limits]`: what one OPC UA client may hold, so none can starve the others."""

    max_connections: int = Field(64, ge=1, le=1000, description="open OPC UA connections at once, all clients")
    max_connections_per_address: int = Field(
        8, ge=1, le=1000, description="open OPC UA connections from one client address"
    )
    activation_timeout_s: float = Field(
        10.0, gt=0, le=600, description="a connection without an activated session after this long is closed"
    )
    session_timeout_max_s: float = Field(
        60.0, ge=5, le=3600, description="the longest idle session timeout a client may ask for"
    )
    max_subscriptions_per_session: int = Field(10, ge=1, le=1000, description="subscriptions one session may create")


class ServiceConfig(Strict):
    host: str = Field("127.0.0.1", description="address both interfaces listen on; beyond loopback needs security")
    opcua_port: int = Field(
        4840,
        ge=1,
        le=65535,
        description="TCP port the OPC UA server listens on (4840 is OPC UA's own); `serve --opcua-port` overrides it",
    )
    opcua_path: str = Field(
        "cell", pattern=r"^[A-Za-z0-9_-]{1,32}$", description="endpoint path: opc.tcp://HOST:PORT/PATH"
    )
    http_port: int = Field(8080, ge=1, le=65535, description="the operator screen's port")
    capture_interval_s: float = Field(
        1.0,
        gt=0,
        le=3600,
        description="continuous mode: a fresh frame this often while the table holds nothing to pick",
    )
    user: str | None = Field(
        None, min_length=1, max_length=64, description="the one OPC UA user (required off loopback)"
    )
    password_hash: str | None = Field(
        None, description="pbkdf2_sha256$ITERATIONS$SALT_HEX$HASH_HEX (`run-cell hash-password` makes one)"
    )
    password_env: str | None = Field(
        None, pattern=r"^[A-Z_][A-Z0-9_]*$", description="name of an environment variable holding the password instead"
    )
    certificate_dir: Path | None = Field(
        None, description="server certificate and key, made on first start; default: opcua/ beside the calibration"
    )
    users_file: Path | None = Field(
        None,
        description="one user per person with a role (viewer, operator, engineer, admin); "
        "`run-cell user add NAME --role ROLE` writes it",
    )
    trusted_clients_dir: Path | None = Field(
        None,
        description="OPC UA client certificates (.der or .pem) allowed to connect; default: trusted/ in certificate_dir",
    )
    rejected_clients_dir: Path | None = Field(
        None,
        description="where unknown OPC UA client certificates are saved for an admin to approve; "
        "default: rejected/ in certificate_dir",
    )
    opcua_security_policies: list[OpcUaPolicy] = Field(
        ["Basic256Sha256_SignAndEncrypt"],
        min_length=1,
        description="the OPC UA security policies and modes offered off loopback; any other channel is refused",
    )
    opcua_limits: OpcUaLimits = Field(OpcUaLimits(), description="[service.opcua_limits]")
    login: LoginConfig = Field(LoginConfig(), description="[service.login]: back-off and lockout of failed logins")
    web: WebConfig = Field(WebConfig(), description="[service.web]: the operator screen's own settings")
    machine_vision: MachineVisionConfig = Field(
        MachineVisionConfig(),
        description="[service.machine_vision]: the OPC 40100-1 model (identity, recipes, results)",
    )
    audit_max_bytes: int = Field(
        64 * 2**20, ge=4096, description="the shift's audit log rolls to a new file past this size (and each UTC day)"
    )

    @property
    def loopback(self) -> bool:
        return is_loopback(self.host)

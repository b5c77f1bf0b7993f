"""`[service]`: where `run-cell serve` listens, how clients prove who they are, how it paces
continuous mode and rotates its shift log."""

from __future__ import annotations

import ipaddress
import socket
from pathlib import Path

from pydantic import Field

from cell.service.mv_config import MachineVisionConfig
from cell.web.config import WebConfig
from drivers.config import Strict


class ServiceConfig(Strict):
    host: str = Field("127.0.0.1", description="address both interfaces listen on; beyond loopback needs security")
    opcua_port: int = Field(4840, ge=1, le=65535)
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


def is_loopback(host: str) -> bool:
    """True when every address the name resolves to is a loopback one (so nothing off the machine can connect)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None)
    except OSError:
        return False
    return bool(infos) and all(ipaddress.ip_address(i[4][0]).is_loopback for i in infos)

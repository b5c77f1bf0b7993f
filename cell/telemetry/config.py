"""`[telemetry.mqtt]`: the plant's MQTT broker the cell publishes to (Sparkplug B 3.0). Off unless
`url` is set. The password is never in the file: `password_env` names the environment variable
that holds it."""

from __future__ import annotations

import socket
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

from pydantic import Field, field_validator, model_validator

from drivers.config import Strict

# Sparkplug ids are UTF-8 strings without the MQTT topic's reserved characters + / #.
SPARKPLUG_ID = r"^[^+/#\s]{1,64}$"
DEFAULT_PORTS = {"mqtt": 1883, "mqtts": 8883}


def default_edge_node_id() -> str:
    """The host name, with any character a Sparkplug id may not hold replaced by '-'."""
    name = socket.gethostname() or "cell"
    return "".join("-" if c in "+/# " else c for c in name)[:64]


class MqttConfig(Strict):
    url: str | None = Field(
        None, description="mqtt://HOST[:PORT] or mqtts://HOST[:PORT] (TLS); unset: no MQTT telemetry"
    )
    user: str | None = Field(None, min_length=1, max_length=128, description="the broker user")
    password_env: str | None = Field(
        None, pattern=r"^[A-Z_][A-Z0-9_]*$", description="name of the environment variable holding the broker password"
    )
    group_id: str = Field("cells", pattern=SPARKPLUG_ID, description="Sparkplug group (a line, a hall, a plant)")
    edge_node_id: str = Field(
        default_factory=default_edge_node_id, pattern=SPARKPLUG_ID, description="Sparkplug edge node: this cell's PC"
    )
    device_id: str = Field("cell", pattern=SPARKPLUG_ID, description="Sparkplug device: the cell")
    ca_file: Path | None = Field(
        None, description="mqtts: CA certificates to check the broker by (default: the system's)"
    )
    client_cert_file: Path | None = Field(None, description="mqtts: this cell's certificate (PEM), to authenticate by")
    client_key_file: Path | None = Field(None, description="mqtts: its private key (PEM)")
    keepalive_s: int = Field(
        30, ge=5, le=3600, description="MQTT keep-alive: a lost broker is noticed within 1.5x this"
    )
    reconnect_min_s: float = Field(1.0, gt=0, le=60, description="first wait before reconnecting; doubles each try")
    reconnect_max_s: float = Field(30.0, gt=0, le=3600, description="longest wait between reconnection tries")
    queue_max: int = Field(
        2000, ge=10, le=1_000_000, description="events waiting for the publisher; beyond, the newest are dropped"
    )
    unsent_max: int = Field(
        500, ge=10, le=1_000_000, description="messages handed to the client but not yet sent; beyond, dropped"
    )
    commands: bool = Field(
        False, description="accept Start/Stop/Pause/Resume as DCMD (needs an authenticated connection)"
    )
    state_dir: Path | None = Field(
        None,
        description="the folder the Sparkplug bdSeq is kept in between runs (one small file per edge node), so "
        "each new session's NBIRTH and NDEATH carry the next bdSeq; default: `data` beside run.log_dir",
    )
    command_role: Literal["viewer", "operator", "engineer", "admin"] | None = Field(
        None,
        description="the role MQTT commands are checked against (the command table's roles); unset: every "
        "MQTT command is refused (no role may do nothing)",
    )

    @field_validator("url")
    @classmethod
    def _url(cls, url: str | None) -> str | None:
        if url is None:
            return None
        parts = urlsplit(url)
        if parts.scheme not in DEFAULT_PORTS or not parts.hostname:
            raise ValueError(f"{url!r}: give mqtt://HOST[:PORT] or mqtts://HOST[:PORT]")
        if parts.username or parts.password:
            raise ValueError(f"{url!r}: no user or password in the url (use user and password_env)")
        if parts.path not in ("", "/") or parts.query:
            raise ValueError(f"{url!r}: no path or query after HOST:PORT")
        try:
            parts.port  # noqa: B018  (raises on a port out of range)
        except ValueError as e:
            raise ValueError(f"{url!r}: {e}") from None
        return url

    @model_validator(mode="after")
    def _consistent(self) -> MqttConfig:
        if (self.user is None) != (self.password_env is None):
            raise ValueError("telemetry.mqtt: give both user and password_env, or neither")
        if (self.client_cert_file is None) != (self.client_key_file is None):
            raise ValueError("telemetry.mqtt: give both client_cert_file and client_key_file, or neither")
        if self.url is not None and not self.tls and (self.client_cert_file or self.ca_file):
            raise ValueError("telemetry.mqtt: ca_file and client certificates need an mqtts:// url")
        if self.commands and not self.authenticated:
            raise ValueError(
                "telemetry.mqtt.commands needs an authenticated connection: set user and password_env, "
                "or an mqtts:// url with client_cert_file and client_key_file"
            )
        if self.reconnect_min_s > self.reconnect_max_s:
            raise ValueError("telemetry.mqtt.reconnect_min_s must not exceed reconnect_max_s")
        return self

    @property
    def enabled(self) -> bool:
        return self.url is not None

    @property
    def tls(self) -> bool:
        return self.url is not None and self.url.startswith("mqtts://")

    @property
    def authenticated(self) -> bool:
        """The broker knows who this cell is: a user and password, or a TLS client certificate."""
        return self.user is not None or (self.tls and self.client_cert_file is not None)

    @property
    def host(self) -> str:
        return urlsplit(self.url or "").hostname or ""

    @property
    def port(self) -> int:
        parts = urlsplit(self.url or "")
        return parts.port or DEFAULT_PORTS.get(parts.scheme, 1883)


class TelemetryConfig(Strict):
    """Plant telemetry: `[telemetry.mqtt]` (Sparkplug B). Prometheus metrics need no settings: they
    are served at /metrics on the screen's port."""

    mqtt: MqttConfig = Field(
        default_factory=MqttConfig, description="[telemetry.mqtt]: Sparkplug B to the plant broker"
    )

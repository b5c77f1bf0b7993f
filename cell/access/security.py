"""Who may drive the cell from off the machine: a server listens on loopback unless configured
otherwise, and then only with encryption and users whose passwords are checked here.

Users come from the users file (`service.users_file`, cell.access.users: one per person,
each with a role) and, as before, the single `service.user` with a PBKDF2-SHA256
`password_hash` (`run-cell hash-password`) or a password in an environment variable named
by `password_env` (systemd's credentials, a secret store): that user is an admin.
What each setting protects: docs/security.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cell.access.users import ITERATIONS, Authenticator, parse_hash, verify_hash
from cell.access.users import hash_password as _hash_password
from cell.errors import ConfigError
from cell.service.config import ServiceConfig


def hash_password(password: str, iterations: int = ITERATIONS) -> str:
    return _hash_password(password, iterations)


def password_ok(cfg: ServiceConfig, user: str | None, password: str | None) -> bool:
    """Constant-time check of a client's user and password against the config's single user (any role).
    New code asks an Authenticator, which also knows the users file and the roles."""
    return Authenticator(_legacy_only(cfg)).authenticate(user, password) is not None


def _legacy_only(cfg: ServiceConfig) -> ServiceConfig:
    return cfg.model_copy(update={"users_file": None})


def credentials_configured(cfg: ServiceConfig) -> bool:
    """True when anyone can log in: a user in the users file, or the config's single user with its password."""
    if cfg.password_hash:
        parse_hash(cfg.password_hash, "service.password_hash")
    return Authenticator(cfg).configured


def certificate_dir(config: Any) -> Path:
    """Where the servers' certificates and keys live: service.certificate_dir, else opcua/ beside the calibration."""
    return config.service.certificate_dir or Path(config.calibration.active_path).parent / "opcua"


def check_exposure(cfg: ServiceConfig) -> None:
    """Refuse to listen beyond loopback without users (encryption is then always on)."""
    if cfg.loopback:
        return
    if not credentials_configured(cfg):
        missing = (
            "no user is configured (service.users_file is empty or unset, service.user is unset)"
            if not cfg.user
            else (f"the environment variable {cfg.password_env}" if cfg.password_env else "service.password_hash")
            + " is not set"
        )
        raise ConfigError(
            f"service.host {cfg.host!r} is beyond loopback and {missing}: refusing to listen unauthenticated",
            hint="add users with `run-cell user add NAME --role ROLE --config FILE` (service.users_file), "
            "or set service.user and service.password_hash (run-cell hash-password) or service.password_env, "
            "or listen on 127.0.0.1",
        )


__all__ = ["certificate_dir", "check_exposure", "credentials_configured", "hash_password", "password_ok", "verify_hash"]

"""Who may drive the cell from off the machine: a server listens on loopback unless configured
otherwise, and then only with encryption and a user whose password is checked here.

Passwords are kept as PBKDF2-SHA256 hashes (`run-cell hash-password`), or read from an
environment variable named in the config (for systemd's credentials or a secret store).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets

from cell.errors import ConfigError
from cell.service.config import ServiceConfig

_ITERATIONS = 200_000


def hash_password(password: str, iterations: int = _ITERATIONS) -> str:
    salt = secrets.token_bytes(16)
    digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return f"pbkdf2_sha256${iterations}${salt.hex()}${digest.hex()}"


def _parse_hash(stored: str) -> tuple[int, bytes, bytes]:
    try:
        scheme, iterations, salt, digest = stored.split("$")
        if scheme != "pbkdf2_sha256":
            raise ValueError(scheme)
        return int(iterations), bytes.fromhex(salt), bytes.fromhex(digest)
    except ValueError:
        raise ConfigError(
            "service.password_hash is not a pbkdf2_sha256$ITERATIONS$SALT$HASH string",
            hint="make one with `run-cell hash-password`",
        ) from None


def password_ok(cfg: ServiceConfig, user: str | None, password: str | None) -> bool:
    """Constant-time check of a client's user and password against the config."""
    if not cfg.user or user is None or password is None:
        return False
    user_ok = hmac.compare_digest(user.encode(), cfg.user.encode())
    if cfg.password_hash:
        iterations, salt, digest = _parse_hash(cfg.password_hash)
        got = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
        return user_ok and hmac.compare_digest(got, digest)
    expected = os.environ.get(cfg.password_env or "", "")
    return user_ok and bool(expected) and hmac.compare_digest(password.encode(), expected.encode())


def credentials_configured(cfg: ServiceConfig) -> bool:
    if cfg.password_hash:
        _parse_hash(cfg.password_hash)
    return bool(cfg.user) and bool(cfg.password_hash or (cfg.password_env and os.environ.get(cfg.password_env)))


def check_exposure(cfg: ServiceConfig) -> None:
    """Refuse to listen beyond loopback without a user and password (encryption is then always on)."""
    if cfg.loopback:
        return
    if not credentials_configured(cfg):
        missing = (
            "service.user"
            if not cfg.user
            else (f"the environment variable {cfg.password_env}" if cfg.password_env else "service.password_hash")
        )
        raise ConfigError(
            f"service.host {cfg.host!r} is beyond loopback and {missing} is not set: refusing to listen unauthenticated",
            hint="set service.user and service.password_hash (run-cell hash-password) or service.password_env, "
            "or listen on 127.0.0.1",
        )

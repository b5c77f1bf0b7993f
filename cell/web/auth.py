"""Who may watch and who may drive the cell from the screen.

Loopback without a password: anyone on this PC may use it (a browser page from another
site still cannot: every control needs this process's CSRF token, which only a same-origin
page can read, and the Host header must name loopback, against DNS rebinding).
With a password (required for a non-loopback bind): a login gives an HttpOnly,
SameSite=Strict session cookie and a CSRF token bound to that session.
"""
from __future__ import annotations

import base64
import hashlib
import hmac
import ipaddress
import os
import secrets
import time
from dataclasses import dataclass

from cell.errors import ConfigError
from cell.web.config import WebConfig

SESSION_COOKIE = "cell_session"
CSRF_HEADER = "x-csrf-token"
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
_SCRYPT = {"n": 2**14, "r": 8, "p": 1}
MAX_SESSIONS = 64


def hash_password(password: str, salt: bytes | None = None) -> str:
    """scrypt$N$r$p$salt$hash (base64), the form `password_scrypt` takes."""
    salt = salt or secrets.token_bytes(16)
    digest = hashlib.scrypt(password.encode(), salt=salt, dklen=32, **_SCRYPT)
    b64 = lambda b: base64.b64encode(b).decode()  # noqa: E731
    return f"scrypt${_SCRYPT['n']}${_SCRYPT['r']}${_SCRYPT['p']}${b64(salt)}${b64(digest)}"


def _parse_hash(encoded: str) -> tuple[dict, bytes, bytes]:
    try:
        scheme, n, r, p, salt, digest = encoded.split("$")
        if scheme != "scrypt":
            raise ValueError(f"scheme {scheme!r}")
        params = {"n": int(n), "r": int(r), "p": int(p)}
        return params, base64.b64decode(salt, validate=True), base64.b64decode(digest, validate=True)
    except ValueError as e:
        raise ConfigError(
            f"service.web.password_scrypt is not a scrypt hash ({e})", hint="make one with `run-cell hash-password`"
        ) from None


def verify_password(password: str, encoded: str) -> bool:
    params, salt, digest = _parse_hash(encoded)
    got = hashlib.scrypt(password.encode(), salt=salt, dklen=len(digest), maxmem=2**26, **params)
    return hmac.compare_digest(got, digest)


def is_loopback(host: str) -> bool:
    name = host.strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False  # a host name other than localhost may resolve anywhere


@dataclass
class _Session:
    csrf: str
    expires_s: float


class Access:
    """The screen's access rules: password check, sessions and CSRF tokens."""

    def __init__(self, cfg: WebConfig, environ=os.environ):
        self.loopback = is_loopback(cfg.host)
        self._hash = cfg.password_scrypt
        self._env_password = environ.get(cfg.password_env) or None
        if self._hash:
            _parse_hash(self._hash)  # a malformed hash fails at start, not at the first login
        self.login_required = bool(self._hash or self._env_password)
        if not self.loopback and not self.login_required:
            raise ConfigError(
                f"the screen would listen on {cfg.host}, beyond loopback, without a password: anyone on the "
                f"network could drive the arm",
                hint=f"set service.web.password_scrypt (`run-cell hash-password`) or the environment variable "
                f"{cfg.password_env}, or listen on 127.0.0.1",
            )
        self.view_open = cfg.view_without_password or not self.login_required
        self._session_s = cfg.session_h * 3600
        self._sessions: dict[str, _Session] = {}
        self.open_csrf = secrets.token_urlsafe(32)  # the token when no login is needed

    def check_password(self, password: str) -> bool:
        ok = False
        if self._env_password is not None:
            ok = hmac.compare_digest(password.encode(), self._env_password.encode())
        if self._hash is not None:
            ok = verify_password(password, self._hash) or ok
        return ok

    def new_session(self) -> tuple[str, str]:
        """A fresh session id (the cookie) and its CSRF token."""
        now = time.monotonic()
        self._sessions = {k: s for k, s in self._sessions.items() if s.expires_s > now}
        while len(self._sessions) >= MAX_SESSIONS:
            self._sessions.pop(next(iter(self._sessions)))
        sid, csrf = secrets.token_urlsafe(32), secrets.token_urlsafe(32)
        self._sessions[sid] = _Session(csrf, now + self._session_s)
        return sid, csrf

    def end_session(self, sid: str | None) -> None:
        self._sessions.pop(sid or "", None)

    def session(self, sid: str | None) -> _Session | None:
        s = self._sessions.get(sid or "")
        if s is None or s.expires_s <= time.monotonic():
            return None
        return s

    def csrf_for(self, sid: str | None) -> str | None:
        """The CSRF token this client must send with controls, or None when it must log in first."""
        if not self.login_required:
            return self.open_csrf
        s = self.session(sid)
        return s.csrf if s else None

    def may_view(self, sid: str | None) -> bool:
        return self.view_open or self.session(sid) is not None

    def may_control(self, sid: str | None) -> bool:
        return not self.login_required or self.session(sid) is not None

    def csrf_ok(self, sid: str | None, token: str | None) -> bool:
        want = self.csrf_for(sid)
        return bool(want and token) and hmac.compare_digest(want.encode(), token.encode())

    def host_ok(self, host_header: str) -> bool:
        """On a loopback bind, only loopback Host names (a rebound DNS name is refused)."""
        if not self.loopback:
            return True
        return _host_name(host_header).lower() in LOOPBACK_NAMES


def _host_name(host_header: str) -> str:
    """The name part of a Host header: '[::1]:8080' -> '::1', 'localhost:8080' -> 'localhost'."""
    if host_header.startswith("["):
        return host_header[1 : host_header.find("]")]
    return host_header.split(":", 1)[0]

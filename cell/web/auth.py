"""Who may watch and who may drive the cell from the screen.

Loopback without users: anyone on this PC may use it (a browser page from another
site still cannot: every control needs this process's CSRF token, which only a same-origin
page can read, and the Host header must name loopback, against DNS rebinding).
With users (required for a non-loopback bind; the line service's users, shared with OPC UA,
each with a role): the screen speaks only HTTPS, and a login gives an HttpOnly,
SameSite=Strict, Secure session cookie and a CSRF token bound to that session. Logins are
throttled per user and per client address (cell.access.throttle); the session remembers
who logged in and their role, so each command carries an Origin (`origin()`). Removing the
user, or changing their role or password, ends their sessions at the next request (each
session keeps the users file's fingerprint of its user, `Authenticator.credential`).
Every control needs a session where logins are required: there is no anonymous origin.
"""

from __future__ import annotations

import hmac
import logging
import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass

from cell.access.network import is_loopback
from cell.access.throttle import LoginThrottle
from cell.core.events import Interface, Origin, Role
from cell.errors import ConfigError
from cell.web.config import WebConfig

log = logging.getLogger(__name__)

SESSION_COOKIE = "cell_session"
CSRF_HEADER = "x-csrf-token"
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
MAX_SESSIONS = 64


@dataclass
class _Session:
    csrf: str
    expires_s: float
    user: str
    role: Role
    credential: str | None = None  # the user's fingerprint at login (Authenticator.credential); None: not followed


@dataclass(frozen=True)
class LoginResult:
    """A login's answer: the role (None: refused), or how long the throttle still refuses this user or address;
    `credential`: the user's fingerprint as the login checked it (for `new_session`)."""

    role: Role | None = None
    retry_after_s: float = 0.0
    credential: str | None = None


class Access:
    """The screen's access rules: logins (throttled), sessions with their user and role, and CSRF tokens."""

    def __init__(
        self,
        host: str,
        web: WebConfig,
        check_password: Callable[[str, str], bool] | None = None,
        *,
        authenticate: Callable[[str, str], Role | None] | None = None,
        throttle: LoginThrottle | None = None,
        credential: Callable[[str], str | None] | None = None,
    ):
        """`authenticate(user, password) -> Role | None`: the service's users (cell.access.users.Authenticator);
        or, older, `check_password(user, password) -> bool` (an admin). Neither: no login (loopback only).
        `credential(user) -> str | None` (Authenticator.credential): the user's fingerprint now; a session whose
        user's differs from the one at login (removed, new role, new password) ends at once."""
        self.loopback = is_loopback(host)
        if authenticate is None and check_password is not None:
            check = check_password
            authenticate = lambda user, password: Role.ADMIN if check(user, password) else None  # noqa: E731
        self._authenticate = authenticate
        self._credential = credential
        self.throttle = throttle
        self.login_required = authenticate is not None
        if not self.loopback and not self.login_required:
            raise ConfigError(
                f"the screen would listen on {host}, beyond loopback, without a password: anyone on the "
                f"network could drive the arm",
                hint="set service.user and service.password_hash (`run-cell hash-password`) or service.password_env, "
                "or listen on 127.0.0.1",
            )
        self.view_open = web.view_without_password or not self.login_required
        self._session_s = web.session_h * 3600
        self._sessions: dict[str, _Session] = {}
        self.open_csrf = secrets.token_urlsafe(32)  # the token when no login is needed

    def check_password(self, user: str, password: str) -> bool:
        """Unthrottled check (blocking: a password hash); new code calls login()."""
        return self._authenticate is not None and self._authenticate(user, password) is not None

    def login(self, user: str, password: str, address: str) -> LoginResult:
        """Throttle first (a refused try costs no hash; a try let through counts at once, so tries in parallel
        cannot pass it: issue 28), then the password. Blocking: call it off the event loop."""
        if self._authenticate is None:
            return LoginResult()
        if self.throttle is not None and (wait := self.throttle.begin(user, address)) > 0:
            return LoginResult(None, wait)
        try:
            credential = self._credential(user) if self._credential is not None else None  # before: a change
            role = self._authenticate(user, password)  # meanwhile ends the session at its first request
        except BaseException:
            if self.throttle is not None:
                self.throttle.abandon(user, address)
            raise
        if self.throttle is not None:
            if role is None:
                self.throttle.failed(user, address, "screen")
            else:
                self.throttle.succeeded(user, address)
        return LoginResult(role, credential=credential if role is not None else None)

    def new_session(self, user: str = "", role: Role = Role.ADMIN, credential: str | None = None) -> tuple[str, str]:
        """A fresh session id (the cookie) and its CSRF token, for `user` with `role` (`credential`: the user's
        fingerprint the login checked, LoginResult.credential; the session ends when it changes)."""
        now = time.monotonic()
        self._sessions = {k: s for k, s in self._sessions.items() if s.expires_s > now}
        while len(self._sessions) >= MAX_SESSIONS:
            self._sessions.pop(next(iter(self._sessions)))
        sid, csrf = secrets.token_urlsafe(32), secrets.token_urlsafe(32)
        self._sessions[sid] = _Session(csrf, now + self._session_s, user, role, credential)
        return sid, csrf

    def origin(self, sid: str | None, address: str = "") -> Origin | None:
        """Who sends a command from this screen: the session's user and role; without users (loopback only) the
        PC's own user, as before, may do everything. None: nobody (no session where logins are required), who
        may do nothing: there is no anonymous origin, Halt included (a viewer's session may Halt)."""
        if not self.login_required:
            return Origin(Interface.SCREEN, "", Role.ADMIN, address)
        s = self.session(sid)
        if s is None:
            return None
        return Origin(Interface.SCREEN, s.user, s.role, address)

    def end_session(self, sid: str | None) -> None:
        self._sessions.pop(sid or "", None)

    def session(self, sid: str | None) -> _Session | None:
        """The live session `sid` names, or None: none, expired, or its user removed or changed since login."""
        s = self._sessions.get(sid or "")
        if s is None or s.expires_s <= time.monotonic():
            return None
        if self._credential is not None and s.credential is not None:
            try:
                now = self._credential(s.user)
            except ConfigError as e:  # the users file cannot be read: deny rather than trust an old login
                log.error("screen: the session of %s is refused: %s", s.user, e)
                return None
            if now != s.credential:
                self._sessions.pop(sid or "", None)
                log.info(
                    "screen: the session of %s ended: the user was removed or given another role or password", s.user
                )
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
        if not want or not token:
            return False
        return hmac.compare_digest(want.encode(), token.encode())

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

"""Who may use the cell: one user per person, each with a role, for OPC UA and the screen alike.

The users file (`service.users_file`, JSON, mode 0600, written whole or not at all) holds a
PBKDF2-SHA256 hash per user; `run-cell user add|remove|passwd|list` keeps it. The old single
`service.user` with `password_hash` or `password_env` still counts, as one admin user, so an
old config starts as before.

`Authenticator.authenticate(user, password)` gives the user's Role, or None: the same answer
in about the same time whether the name is unknown or the password wrong. A check costs a
hash (about 0.14 s of CPU at 600,000 iterations): call it off an event loop, and ask the
login throttle (cell.access.throttle) first. The file is read again when it changes, so a
user added, removed or given a new password counts at the next login without a restart.

Logins made before a change end too: `credential(user)` is a fingerprint of what the user
logs in with (role and password hash; None once removed), which an interface keeps with a
session at login and compares on each request (the screen: cell.web.auth.Access). Listeners
(`add_listener`) hear the names whose fingerprint changed whenever the file is read again.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import re
import secrets
import stat
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from cell.atomicfile import write_atomic
from cell.core.events import Role
from cell.errors import ConfigError

if TYPE_CHECKING:
    from cell.service.config import ServiceConfig

log = logging.getLogger(__name__)

ITERATIONS = 600_000  # OWASP's 2023 figure for PBKDF2-HMAC-SHA256
MIN_ITERATIONS = 1_000  # below this a stored hash is refused as a mistake
MIN_PASSWORD_CHARS = 8
MAX_PASSWORD_CHARS = 1024
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}$")
FORMAT = "pick-cell users 1"
ROLE_NAMES = tuple(r.value for r in Role)


class UsersError(ConfigError):
    """The users file or a user command's input is wrong; says which file or name and why."""


def hash_password(password: str, iterations: int = ITERATIONS) -> str:
    """`pbkdf2_sha256$ITERATIONS$SALT_HEX$HASH_HEX` with a fresh 16-byte salt."""
    salt = secrets.token_bytes(16)
    digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return f"pbkdf2_sha256${iterations}${salt.hex()}${digest.hex()}"


def parse_hash(stored: str, where: str) -> tuple[int, bytes, bytes]:
    """(iterations, salt, digest) of a stored hash; UsersError naming `where` if it is not one."""
    try:
        scheme, iterations, salt, digest = stored.split("$")
        if scheme != "pbkdf2_sha256" or int(iterations) < MIN_ITERATIONS or not salt or len(digest) != 64:
            raise ValueError(scheme)
        return int(iterations), bytes.fromhex(salt), bytes.fromhex(digest)
    except ValueError:
        raise UsersError(
            f"{where} is not a pbkdf2_sha256$ITERATIONS$SALT$HASH string (at least {MIN_ITERATIONS} iterations)",
            hint="make one with `run-cell user passwd NAME` (or `run-cell hash-password` for service.password_hash)",
        ) from None


def verify_hash(stored: tuple[int, bytes, bytes], password: str) -> bool:
    iterations, salt, digest = stored
    got = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return hmac.compare_digest(got, digest)


def check_name(name: str) -> str:
    if not NAME_PATTERN.match(name):
        raise UsersError(
            f"user name {name!r} is not allowed",
            hint="1-64 characters: letters, digits and _ . @ -, starting with a letter or digit",
        )
    return name


def check_new_password(password: str) -> str:
    if len(password) < MIN_PASSWORD_CHARS:
        raise UsersError(f"the password is shorter than {MIN_PASSWORD_CHARS} characters: nothing changed")
    if len(password) > MAX_PASSWORD_CHARS:
        raise UsersError(f"the password is longer than {MAX_PASSWORD_CHARS} characters: nothing changed")
    return password


@dataclass(frozen=True)
class UserEntry:
    name: str
    role: Role
    password_hash: str
    changed_utc: str = ""

    def as_json(self) -> dict[str, str]:
        return {
            "name": self.name,
            "role": self.role.value,
            "password_hash": self.password_hash,
            "changed_utc": self.changed_utc,
        }


# ---- the users file ---------------------------------------------------------------------
def read_users(path: Path) -> dict[str, UserEntry]:
    """The users in the file; an absent file holds none. UsersError naming the file when it is wrong."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return {}
    except (OSError, UnicodeDecodeError) as e:
        raise UsersError(f"{path}: cannot read the users file: {getattr(e, 'strerror', None) or e}") from None
    try:
        data = json.loads(text)
    except ValueError as e:
        raise UsersError(f"{path}: the users file is not valid JSON: {e}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT or not isinstance(data.get("users"), list):
        raise UsersError(f"{path}: not a users file (expected {{'format': {FORMAT!r}, 'users': [...]}})")
    users: dict[str, UserEntry] = {}
    for i, item in enumerate(data["users"]):
        entry = _entry(item, f"{path}: users[{i}]")
        if entry.name in users:
            raise UsersError(f"{path}: user {entry.name!r} is listed twice")
        users[entry.name] = entry
    return users


def _entry(item: object, where: str) -> UserEntry:
    if not isinstance(item, dict) or set(item) - {"name", "role", "password_hash", "changed_utc"}:
        raise UsersError(f"{where}: expected an object with name, role, password_hash (and changed_utc)")
    name, role, stored = item.get("name"), item.get("role"), item.get("password_hash")
    if not isinstance(name, str) or not isinstance(stored, str):
        raise UsersError(f"{where}: name and password_hash must be strings")
    check_name(name)
    if role not in ROLE_NAMES:
        raise UsersError(f"{where} ({name}): role {role!r} is not one of {', '.join(ROLE_NAMES)}")
    parse_hash(stored, f"{where} ({name}): password_hash")
    return UserEntry(name, Role(role), stored, str(item.get("changed_utc", "")))


def write_users(path: Path, users: Iterable[UserEntry], owner: tuple[int, int] | None = None) -> None:
    """The whole file, atomically, readable by its owner only (0600); `owner` (uid, gid): given to that
    user before it takes the file's name (root only)."""
    body = {"format": FORMAT, "users": [u.as_json() for u in sorted(users, key=lambda u: u.name)]}
    data = (json.dumps(body, indent=2) + "\n").encode()

    def write(f: BinaryIO) -> None:
        os.fchmod(f.fileno(), 0o600)
        if owner is not None:
            os.fchown(f.fileno(), *owner)
        f.write(data)

    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, write)


def now_utc() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


# ---- authentication -----------------------------------------------------------------------
@dataclass(frozen=True)
class _Known:
    role: Role
    stored: tuple[int, bytes, bytes] | None  # None: the legacy user's password is in an environment variable
    fingerprint: str = ""


def fingerprint(role: Role, stored: str) -> str:
    """What a user logs in with, as a short digest: it differs after a new role or a new password."""
    return hashlib.sha256(f"{role.value}\0{stored}".encode()).hexdigest()[:32]


class Authenticator:
    """`authenticate(user, password) -> Role | None` for every interface; thread-safe."""

    def __init__(self, cfg: ServiceConfig) -> None:
        """`cfg`: the ServiceConfig (users_file, and the legacy user, password_hash, password_env)."""
        self.users_file: Path | None = cfg.users_file
        self._legacy_name: str | None = cfg.user
        self._legacy_hash = parse_hash(cfg.password_hash, "service.password_hash") if cfg.password_hash else None
        self._legacy_env: str | None = cfg.password_env
        self._lock = threading.Lock()
        self._stamp: tuple[int, int, int] | None = None
        self._file_users: dict[str, UserEntry] = {}
        self._decoy = (ITERATIONS, secrets.token_bytes(16), secrets.token_bytes(32))  # matches no password
        self._listeners: list[Callable[[frozenset[str]], None]] = []
        self._reload(first=True)

    # ---- what is configured --------------------------------------------------------------
    @property
    def configured(self) -> bool:
        """True when anyone at all can log in (then both interfaces require a login)."""
        self._reload()
        return bool(self._file_users) or self._legacy_usable()

    def names(self) -> dict[str, Role]:
        self._reload()
        out = {name: e.role for name, e in self._file_users.items()}
        if self._legacy_usable():
            out[self._legacy_name or ""] = Role.ADMIN
        return out

    def _legacy_usable(self) -> bool:
        if not self._legacy_name:
            return False
        return self._legacy_hash is not None or bool(self._legacy_env and os.environ.get(self._legacy_env))

    # ---- checking a password -------------------------------------------------------------
    def authenticate(self, user: str | None, password: str | None) -> Role | None:
        """The user's role if the password is theirs, else None. Costs one hash whatever the outcome."""
        if not isinstance(user, str) or not isinstance(password, str) or len(password) > MAX_PASSWORD_CHARS:
            verify_hash(self._decoy, "")
            return None
        known = self._lookup(user)
        if known is None:
            verify_hash(self._decoy, password)  # the same work as a wrong password: a name's existence does not show
            return None
        if known.stored is None:
            expected = os.environ.get(self._legacy_env or "", "")
            ok = bool(expected) and hmac.compare_digest(password.encode(), expected.encode())
            verify_hash(self._decoy, password)
        else:
            ok = verify_hash(known.stored, password)
        return known.role if ok else None

    def credential(self, user: str) -> str | None:
        """`user`'s fingerprint now (role and password hash; None: they cannot log in any more). Keep it with a
        session at login and compare it on each request: a difference means the user was removed or given
        another role or password since, and the session must end (issue 28). Costs a stat of the users file."""
        known = self._lookup(user)
        return None if known is None else known.fingerprint

    def add_listener(self, callback: Callable[[frozenset[str]], None]) -> None:
        """`callback(names)` whenever the users file is read again and these users were removed or got another
        role or password (called on the thread that noticed, outside the lock; an error in it is logged)."""
        self._listeners.append(callback)

    def _lookup(self, user: str) -> _Known | None:
        self._reload()
        entry = self._file_users.get(user)
        if entry is not None:
            stored = parse_hash(entry.password_hash, f"{self.users_file}: {user}")
            return _Known(entry.role, stored, fingerprint(entry.role, entry.password_hash))
        if self._legacy_name and hmac.compare_digest(user.encode(), self._legacy_name.encode()):
            if self._legacy_hash is not None:
                return _Known(Role.ADMIN, self._legacy_hash, fingerprint(Role.ADMIN, "legacy hash"))
            if self._legacy_env and os.environ.get(self._legacy_env):
                return _Known(Role.ADMIN, None, fingerprint(Role.ADMIN, "legacy environment"))
        return None

    # ---- following the file ----------------------------------------------------------------
    def _reload(self, first: bool = False) -> None:
        """Read the users file again if it changed; a broken file keeps the last good users (logged)."""
        path = self.users_file
        if path is None:
            return
        try:
            st: os.stat_result | None = path.stat()
        except FileNotFoundError:
            st = None
        except OSError as e:
            raise UsersError(f"{path}: cannot read the users file: {e.strerror or e}") from None
        stamp = None if st is None else (st.st_mtime_ns, st.st_size, st.st_ino)
        with self._lock:
            if stamp == self._stamp and not first:
                return
            try:
                users = self._read_checked(path) if st is not None else {}
            except UsersError as e:
                if first:
                    raise
                log.error("users file changed but cannot be used, keeping the previous users: %s", e)
                self._stamp = stamp
                return
            if st is not None and st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
                log.warning(
                    "%s is readable by others (mode %o): its password hashes could be guessed offline; chmod 600 it",
                    path,
                    stat.S_IMODE(st.st_mode),
                )
            if not first and users.keys() != self._file_users.keys():
                log.info("users file %s now lists %d users", path, len(users))
            changed = frozenset(
                name
                for name, old in self._file_users.items()
                if (new := users.get(name)) is None or (new.role, new.password_hash) != (old.role, old.password_hash)
            )
            self._file_users, self._stamp = users, stamp
        if changed:
            log.info("users removed or changed (their logins end): %s", ", ".join(sorted(changed)))
            for listener in list(self._listeners):
                try:
                    listener(changed)
                except Exception:  # one interface's failure must not stop the others hearing it
                    log.exception("a listener to users' changes failed")

    def _read_checked(self, path: Path) -> dict[str, UserEntry]:
        users = read_users(path)
        if self._legacy_name and self._legacy_name in users:
            raise UsersError(
                f"user {self._legacy_name!r} is both service.user and in {path}",
                hint="remove service.user (and password_hash/password_env) from the config, or the user from the file",
            )
        return users

"""`run-cell user add|remove|passwd|list`: the users file (`service.users_file`) of the config.

A password is read from stdin when stdin is not a terminal (one line; for scripts and
provisioning), else asked twice without echo. Every change rewrites the whole file
atomically (mode 0600) under its lock; nothing is half-written. A running service reads
the file again at the next login.

The file is readable by its owner alone, and a rewrite belongs to whoever runs the command:
so a change is refused when the file (or, for a new file, its folder) belongs to another
user, the service's, unless `--owner USER` gives the new file to that user (root only).
"""

from __future__ import annotations

import argparse
import getpass
import os
import pwd
import sys
from pathlib import Path

from cell.access.users import (
    ROLE_NAMES,
    UserEntry,
    UsersError,
    check_name,
    check_new_password,
    hash_password,
    now_utc,
    read_users,
    write_users,
)
from cell.config import load_config
from cell.core.events import Role
from cell.errors import ConfigError
from cell.locks import holding
from cell.ownership import user_name

LOCK_WAIT_S = 5.0


def register(sub) -> None:
    p = sub.add_parser(
        "user",
        help="add, remove, re-password or list the users of service.users_file",
        description="Keep the users of the config's service.users_file: one per person, each with a role "
        "(viewer, operator, engineer, admin; docs/security.md). A running service reads the file again at the "
        "next login.",
    )
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    add = verbs.add_parser(
        "add",
        help="add a user with a role; the password from stdin or asked twice",
        description="Add a user with a role. The password is one line on stdin when stdin is not a terminal, "
        "else asked twice without echo; at least 8 characters.",
    )
    add.add_argument("name", help="the user name: letters, digits and _ . @ -")
    add.add_argument("--role", required=True, choices=ROLE_NAMES, help="what the user may do (docs/security.md)")
    remove = verbs.add_parser(
        "remove", help="remove a user (their next login fails)", description="Remove a user: their next login fails."
    )
    remove.add_argument("name", help="the user to remove")
    passwd = verbs.add_parser(
        "passwd",
        help="give a user a new password; --role also changes the role",
        description="Give a user a new password (read as for add); --role also changes their role.",
    )
    passwd.add_argument("name", help="the user")
    passwd.add_argument("--role", choices=ROLE_NAMES, help="also change the role")
    verbs.add_parser(
        "list",
        help="the users and their roles (no hashes)",
        description="List the users, their roles and when changed.",
    )
    for v in (add, remove, passwd, verbs.choices["list"]):
        v.add_argument("--config", dest="run_config", type=Path, default=argparse.SUPPRESS, help="cell config (TOML)")
        v.set_defaults(func=cmd_user)
    for v in (add, remove, passwd):
        v.add_argument(
            "--owner",
            metavar="USER",
            help="give the rewritten file to USER (the service's user, e.g. cell; needs root): the file is "
            "readable by its owner alone",
        )


def users_path(args: argparse.Namespace) -> tuple[Path, str | None]:
    """The config's users file, and its legacy single user's name (which the file may not reuse)."""
    if getattr(args, "run_config", None) is None:
        raise ConfigError("run-cell user needs --config FILE: the users file is that config's service.users_file")
    service = load_config(args.run_config).service
    if service.users_file is None:
        raise ConfigError(
            f"{args.run_config}: service.users_file is not set",
            hint='add users_file = "users.json" (in the cell\'s folder, docs/commissioning.md; any path) under [service]',
        )
    return service.users_file, service.user


def read_password(prompt: str = "password") -> str:
    """One line from stdin when it is not a terminal; else asked twice, not echoed."""
    if not sys.stdin.isatty():
        line = sys.stdin.readline()
        if not line:
            raise UsersError("no password on stdin (give it as one line): nothing changed")
        return check_new_password(line.rstrip("\r\n"))
    first = getpass.getpass(f"{prompt}: ")
    if first != getpass.getpass(f"{prompt} again: "):
        raise UsersError("the two passwords differ: nothing changed")
    return check_new_password(first)


def file_owner(path: Path, owner: str | None) -> tuple[int, int] | None:
    """Who the rewritten file must belong to (uid, gid; None: whoever runs this). Refused when that is
    another user than this process's and no --owner says so: the service could no longer read it."""
    me = os.geteuid()
    if owner is not None:
        try:
            account = pwd.getpwnam(owner)
        except KeyError:
            raise UsersError(
                f"--owner {owner}: no such user on this computer", hint="give the service's user, e.g. cell"
            ) from None
        if me not in (0, account.pw_uid):
            raise UsersError(
                f"--owner {owner}: only root can give a file to another user (this runs as {user_name(me)})",
                hint=f"run it as root, or as {owner} without --owner",
            )
        return account.pw_uid, account.pw_gid
    existing = path if path.exists() else next((p for p in path.absolute().parents if p.exists()), None)
    if existing is None or existing.stat().st_uid == me:
        return None
    holder = user_name(existing.stat().st_uid)
    what = f"{path} belongs to {holder}" if existing == path else f"{path}'s folder {existing} belongs to {holder}"
    raise UsersError(
        f"{what} and this runs as {user_name(me)}: the file written now would be {user_name(me)}'s, readable by "
        f"its owner alone (mode 0600), and a service running as {holder} could not read it; nothing changed",
        hint=f"run it as {holder} (sudo -u {holder} run-cell user ...), or add --owner {holder}",
    )


def cmd_user(args: argparse.Namespace) -> int:
    path, legacy = users_path(args)
    if args.verb == "list":
        return _list(path, legacy)
    name = check_name(args.name)
    owner = file_owner(path, args.owner)
    with holding(path, "users file", wait_s=LOCK_WAIT_S):
        users = read_users(path)
        if args.verb == "add":
            if name in users or name == legacy:
                where = "the config's service.user" if name == legacy else str(path)
                raise UsersError(f"user {name!r} already exists in {where}", hint=f"run-cell user passwd {name}")
            users[name] = UserEntry(name, Role(args.role), hash_password(read_password()), now_utc())
            done = f"added {name} ({args.role}) to {path}"
        elif name not in users:
            hint = "it is service.user in the config: change it there" if name == legacy else "run-cell user list"
            raise UsersError(f"no user {name!r} in {path}", hint=hint)
        elif args.verb == "remove":
            del users[name]
            done = f"removed {name} from {path}"
        else:
            role = Role(args.role) if args.role else users[name].role
            users[name] = UserEntry(name, role, hash_password(read_password(f"new password for {name}")), now_utc())
            done = f"new password for {name} ({role.value}) in {path}"
        write_users(path, users.values(), owner)
    print(done if owner is None else f"{done}, owned by {args.owner}")
    return 0


def _list(path: Path, legacy: str | None) -> int:
    users = read_users(path)
    rows = [(u.name, u.role.value, u.changed_utc or "-") for u in users.values()]
    if legacy:
        rows.append((legacy, Role.ADMIN.value, "service.user in the config"))
    if not rows:
        print(f"no users in {path}: add one with `run-cell user add NAME --role ROLE --config FILE`")
        return 0
    width = max(len(r[0]) for r in rows)
    for name, role, changed in sorted(rows):
        print(f"{name:<{width}}  {role:<8}  {changed}")
    return 0

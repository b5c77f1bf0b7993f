"""Users and roles: the users file, the `run-cell user` commands, and who authenticates as what."""

from __future__ import annotations

import io
import json
import os
import pwd
import stat

import pytest

from cell.access.users import Authenticator, UserEntry, UsersError, hash_password, read_users, write_users
from cell.cli import main
from cell.commands import users as users_cli
from cell.core.events import Role
from cell.ownership import ALLOW_ENV, refuse_root_in_anothers_folder
from cell.service.config import ServiceConfig

pytestmark = pytest.mark.timeout(60)

FAST = 1000  # iterations for test hashes (the default, 600,000, costs 0.14 s of CPU per check)


@pytest.fixture
def config(tmp_path, monkeypatch):
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[service]\nusers_file = "users.json"\n')
    monkeypatch.chdir(tmp_path)  # users_file is relative, as the configs' other paths are: to the working folder
    return cfg


def run_user(*argv: str, stdin: str = "") -> int:
    """`run-cell user ...` through run-cell's own entry point, stdin not a terminal."""
    old = users_cli.sys.stdin
    users_cli.sys.stdin = io.StringIO(stdin)
    try:
        return main(list(argv))
    finally:
        users_cli.sys.stdin = old


def test_add_list_passwd_remove(config, tmp_path, capsys):
    assert run_user("user", "add", "anna", "--role", "operator", "--config", str(config), stdin="anna-pass-1\n") == 0
    assert run_user("user", "add", "ben", "--role", "engineer", "--config", str(config), stdin="ben-pass-12\n") == 0
    path = tmp_path / "users.json"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert "anna-pass-1" not in path.read_text()
    auth = Authenticator(ServiceConfig(users_file=path))
    assert auth.authenticate("anna", "anna-pass-1") is Role.OPERATOR
    assert auth.authenticate("ben", "ben-pass-12") is Role.ENGINEER
    assert auth.authenticate("anna", "ben-pass-12") is None

    assert run_user("user", "passwd", "anna", "--role", "admin", "--config", str(config), stdin="new-anna-pw\n") == 0
    assert auth.authenticate("anna", "anna-pass-1") is None  # the file is read again: no restart needed
    assert auth.authenticate("anna", "new-anna-pw") is Role.ADMIN

    capsys.readouterr()
    assert run_user("user", "list", "--config", str(config)) == 0
    listing = capsys.readouterr().out
    assert "anna" in listing and "admin" in listing and "ben" in listing and "pbkdf2" not in listing

    assert run_user("user", "remove", "ben", "--config", str(config)) == 0
    assert auth.authenticate("ben", "ben-pass-12") is None
    assert set(read_users(path)) == {"anna"}


@pytest.mark.parametrize(
    "argv, stdin, message",
    [
        (("add", "anna", "--role", "operator"), "short\n", "shorter than 8 characters"),
        (("add", "anna", "--role", "operator"), "", "no password on stdin"),
        (("add", "bad name", "--role", "operator"), "long-enough-pw\n", "user name 'bad name' is not allowed"),
        (("remove", "nobody"), "", "no user 'nobody'"),
        (("passwd", "nobody"), "long-enough-pw\n", "no user 'nobody'"),
    ],
)
def test_bad_input_is_one_line_and_changes_nothing(config, tmp_path, capsys, argv, stdin, message):
    before = None
    if argv[0] != "add" or argv[1] != "anna":
        assert run_user("user", "add", "keep", "--role", "viewer", "--config", str(config), stdin="keep-pass-1\n") == 0
        before = (tmp_path / "users.json").read_bytes()
    capsys.readouterr()
    assert run_user("user", *argv, "--config", str(config), stdin=stdin) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and err.count("\n") == 0 and "Traceback" not in err
    if before is None:
        assert not (tmp_path / "users.json").exists()
    else:
        assert (tmp_path / "users.json").read_bytes() == before


def test_add_twice_and_missing_config_setting(config, tmp_path, capsys):
    assert run_user("user", "add", "anna", "--role", "viewer", "--config", str(config), stdin="anna-pass-1\n") == 0
    assert run_user("user", "add", "anna", "--role", "admin", "--config", str(config), stdin="other-pass-1\n") == 2
    assert "already exists" in capsys.readouterr().err
    bare = tmp_path / "bare.toml"
    bare.write_text("[service]\n")
    assert run_user("user", "list", "--config", str(bare)) == 2
    assert "service.users_file is not set" in capsys.readouterr().err
    assert run_user("user", "list") == 2
    assert "needs --config FILE" in capsys.readouterr().err


def test_the_terminal_asks_twice(config, tmp_path, monkeypatch, capsys):
    answers = iter(["typed-pass-1", "typed-pass-2"])
    monkeypatch.setattr(users_cli.getpass, "getpass", lambda prompt: next(answers))

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    monkeypatch.setattr(users_cli.sys, "stdin", Tty())
    assert main(["user", "add", "anna", "--role", "viewer", "--config", str(config)]) == 2
    assert "the two passwords differ" in capsys.readouterr().err
    assert not (tmp_path / "users.json").exists()


def test_the_old_single_user_is_an_admin(tmp_path, monkeypatch):
    auth = Authenticator(ServiceConfig(user="plc", password_hash=hash_password("plc-secret", FAST)))
    assert auth.configured and auth.authenticate("plc", "plc-secret") is Role.ADMIN
    assert auth.authenticate("plc", "wrong-pass") is None and auth.authenticate("PLC", "plc-secret") is None
    env = Authenticator(ServiceConfig(user="plc", password_env="CELL_TEST_PW"))
    assert not env.configured and env.authenticate("plc", "") is None  # unset: nobody gets in
    monkeypatch.setenv("CELL_TEST_PW", "from-the-env")
    assert env.configured and env.authenticate("plc", "from-the-env") is Role.ADMIN


def test_old_user_and_file_together(tmp_path):
    path = tmp_path / "users.json"
    write_users(path, [UserEntry("op", Role.OPERATOR, hash_password("op-pass-123", FAST))])
    both = Authenticator(ServiceConfig(user="plc", password_hash=hash_password("plc-secret", FAST), users_file=path))
    assert both.names() == {"op": Role.OPERATOR, "plc": Role.ADMIN}
    assert both.authenticate("op", "op-pass-123") is Role.OPERATOR
    assert both.authenticate("plc", "plc-secret") is Role.ADMIN
    with pytest.raises(UsersError, match="both service.user and in"):
        Authenticator(ServiceConfig(user="op", password_hash=hash_password("x" * 8, FAST), users_file=path))


def test_a_broken_file_is_refused_at_start_and_kept_at_runtime(tmp_path, caplog):
    path = tmp_path / "users.json"
    path.write_text('{"format": "pick-cell users 1", "users": [{"name": "a", "role": "boss", "password_hash": "x"}]}')
    with pytest.raises(UsersError, match=r"users\[0\] \(a\): role 'boss' is not one of"):
        Authenticator(ServiceConfig(users_file=path))
    write_users(path, [UserEntry("op", Role.OPERATOR, hash_password("op-pass-123", FAST))])
    auth = Authenticator(ServiceConfig(users_file=path))
    path.write_text("{ not json")
    assert auth.authenticate("op", "op-pass-123") is Role.OPERATOR  # the last good users stay
    assert "cannot be used, keeping the previous users" in caplog.text


def test_a_missing_file_means_no_users(tmp_path):
    auth = Authenticator(ServiceConfig(users_file=tmp_path / "none.json"))
    assert not auth.configured and auth.authenticate("anyone", "anything") is None


def test_file_is_json_with_the_roles(tmp_path):
    path = tmp_path / "users.json"
    write_users(path, [UserEntry(n, r, hash_password("pass-word-1", FAST)) for n, r in zip("abcd", Role, strict=True)])
    data = json.loads(path.read_text())
    assert [u["role"] for u in data["users"]] == ["viewer", "operator", "engineer", "admin"]
    auth = Authenticator(ServiceConfig(users_file=path))
    assert [auth.authenticate(n, "pass-word-1") for n in "abcd"] == list(Role)


def test_removing_a_user_or_changing_their_role_or_password_ends_their_screen_sessions_at_once(config, tmp_path):
    """issue 28: a login made before the change kept its access until a restart."""
    import threading

    from starlette.testclient import TestClient

    from cell.access.throttle import LoginThrottle
    from cell.config import CellConfig
    from cell.service.config import LoginConfig
    from cell.web.app import build_app
    from cell.web.auth import Access
    from cell.web.config import WebConfig
    from tests.fake_service import FakeLineService

    path = tmp_path / "users.json"
    people = {"otto": ("otto-pass-1", Role.OPERATOR), "vera": ("vera-pass-1", Role.OPERATOR)}
    people["erik"] = ("erik-pass-1", Role.ENGINEER)
    write_users(path, [UserEntry(n, r, hash_password(p, FAST)) for n, (p, r) in people.items()])
    users = Authenticator(ServiceConfig(users_file=path))
    changed: list[frozenset[str]] = []
    users.add_listener(changed.append)  # what an OPC UA server would follow
    web = WebConfig()
    access = Access(
        "127.0.0.1",
        web,
        authenticate=users.authenticate,
        throttle=LoginThrottle(LoginConfig(backoff_first_s=0)),
        credential=users.credential,
    )
    service = FakeLineService()
    try:
        app = build_app(service, CellConfig(), web, access)
        clients = {name: TestClient(app, base_url="http://127.0.0.1:8080") for name in people}
        for name, client in clients.items():
            reply = client.post("/api/login", json={"user": name, "password": people[name][0]})
            client.headers["x-csrf-token"] = reply.json()["csrf"]
            assert client.get("/api/state").status_code == 200
        with clients["erik"]:  # the screen's lifespan: its event streams
            ended = threading.Event()

            def watch() -> None:
                with clients["erik"].stream("GET", "/api/events") as stream:
                    for _ in stream.iter_lines():
                        pass
                ended.set()

            watcher = threading.Thread(target=watch, daemon=True)
            watcher.start()

            assert run_user("user", "remove", "otto", "--config", str(config)) == 0
            assert clients["otto"].get("/api/state").status_code == 401
            assert clients["otto"].post("/api/command/Halt").status_code == 401
            assert clients["vera"].get("/api/state").status_code == 200 and not ended.is_set()

            entries = read_users(path)  # vera's role only: the same password hash
            write_users(
                path,
                [
                    *(e for n, e in entries.items() if n != "vera"),
                    UserEntry("vera", Role.VIEWER, entries["vera"].password_hash),
                ],
            )
            assert clients["vera"].post("/api/command/StartSingleJob").status_code == 401
            assert clients["erik"].get("/api/state").status_code == 200

            assert run_user("user", "passwd", "erik", "--config", str(config), stdin="erik-new-pw-2\n") == 0
            assert clients["erik"].get("/api/state").status_code == 401
            assert ended.wait(30), "erik's open event stream went on after his password changed"
            again = clients["erik"].post("/api/login", json={"user": "erik", "password": "erik-new-pw-2"})
            assert again.status_code == 200
        assert changed == [frozenset({"otto"}), frozenset({"vera"}), frozenset({"erik"})]
        assert service.commands == []
    finally:
        service.close()


root_only = pytest.mark.skipif(os.geteuid() != 0, reason="giving a file to another user needs root")


@root_only
def test_a_file_of_the_services_user_is_not_taken_from_it(config, tmp_path, capsys, monkeypatch):
    """The cell's folder belongs to the service's user: root writing the users file there would make it
    root's, mode 0600, which that service cannot read. Refused with the fix; --owner gives it to that user."""
    monkeypatch.delenv(ALLOW_ENV, raising=False)
    nobody = pwd.getpwnam("nobody")
    os.chown(tmp_path, nobody.pw_uid, nobody.pw_gid)
    capsys.readouterr()
    assert run_user("user", "add", "anna", "--role", "operator", "--config", str(config), stdin="anna-pass-1\n") == 2
    err = capsys.readouterr().err
    assert f"folder {tmp_path} belongs to nobody" in err and "--owner nobody" in err and "sudo -u nobody" in err, err
    assert not (tmp_path / "users.json").exists()
    argv = ("--config", str(config), "--owner", "nobody")
    assert run_user("user", "add", "anna", "--role", "operator", *argv, stdin="anna-pass-1\n") == 0
    path = tmp_path / "users.json"
    assert (path.stat().st_uid, path.stat().st_gid, stat.S_IMODE(path.stat().st_mode)) == (
        nobody.pw_uid,
        nobody.pw_gid,
        0o600,
    )
    assert "owned by nobody" in capsys.readouterr().out
    # the file now is nobody's: a change without --owner is refused and leaves it as it was
    before = path.read_bytes()
    assert run_user("user", "passwd", "anna", "--config", str(config), stdin="anna-pass-2\n") == 2
    assert "users.json belongs to nobody" in capsys.readouterr().err and path.read_bytes() == before
    assert run_user("user", "remove", "anna", *argv) == 0 and path.stat().st_uid == nobody.pw_uid
    assert run_user("user", "list", "--config", str(config)) == 0  # reading needs nothing of the kind


def test_owner_must_be_a_user_here(config, capsys):
    assert (
        run_user("user", "add", "anna", "--role", "viewer", "--config", str(config), "--owner", "no-such-user-x") == 2
    )
    assert "--owner no-such-user-x: no such user" in capsys.readouterr().err


@root_only
@pytest.mark.parametrize("argv", [["--dry-run"], ["serve", "--dry-run"], ["recalibrate", "--config", "cell.toml"]])
def test_root_in_the_services_folder_is_refused_before_writing(tmp_path, monkeypatch, capsys, argv):
    """Calibration, logs, history and keys made by root in the service user's folder could not be
    replaced or read by the service: refused with the fix, nothing written."""
    monkeypatch.delenv(ALLOW_ENV, raising=False)
    os.chown(tmp_path, pwd.getpwnam("nobody").pw_uid, pwd.getpwnam("nobody").pw_gid)
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"runs as root in {tmp_path}, which belongs to nobody" in err and "sudo -u nobody run-cell" in err, err
    assert list(tmp_path.iterdir()) == []


@root_only
def test_root_may_work_in_a_developers_checkout_when_told(tmp_path, monkeypatch):
    os.chown(tmp_path, pwd.getpwnam("nobody").pw_uid, pwd.getpwnam("nobody").pw_gid)
    monkeypatch.delenv(ALLOW_ENV, raising=False)
    with pytest.raises(Exception, match="belongs to nobody") as refused:
        refuse_root_in_anothers_folder("run-cell serve", tmp_path)
    assert f"{ALLOW_ENV}=1" in refused.value.hint
    monkeypatch.setenv(ALLOW_ENV, "1")
    refuse_root_in_anothers_folder("run-cell serve", tmp_path)  # no refusal

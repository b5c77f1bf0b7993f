"""The screen's logins and who sends a command (cell.web.auth.Access), the rate-limited log,
and the open-file check at start (issue 21)."""

from __future__ import annotations

import logging
import resource
import threading
import time

import pytest

from cell.access.throttle import Lockout, LoginThrottle
from cell.access.users import Authenticator, UserEntry, hash_password, write_users
from cell.core.events import Interface, Role
from cell.logratelimit import LogRateLimiter
from cell.oplog import log_to_file, stop_logging_to
from cell.service.config import LoginConfig, ServiceConfig
from cell.service.fdlimit import check_open_files, needed_descriptors
from cell.web.auth import Access
from cell.web.config import WebConfig

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def users(tmp_path):
    path = tmp_path / "users.json"
    write_users(
        path,
        [
            UserEntry("vera", Role.VIEWER, hash_password("vera-pass-1", 1000)),
            UserEntry("otto", Role.OPERATOR, hash_password("otto-pass-1", 1000)),
        ],
    )
    return Authenticator(ServiceConfig(users_file=path))


def test_a_login_gives_a_session_with_the_users_role(users):
    access = Access("10.0.0.5", WebConfig(), authenticate=users.authenticate, throttle=LoginThrottle(LoginConfig()))
    result = access.login("otto", "otto-pass-1", "10.0.0.9")
    assert result.role is Role.OPERATOR and result.retry_after_s == 0
    sid, csrf = access.new_session("otto", result.role)
    origin = access.origin(sid, "10.0.0.9")
    assert (origin.interface, origin.user, origin.role, origin.address) == (
        Interface.SCREEN,
        "otto",
        Role.OPERATOR,
        "10.0.0.9",
    )
    assert access.csrf_ok(sid, csrf) and access.may_control(sid)
    assert access.origin(None, "10.0.0.9") is None  # no session: nobody, who may do nothing (issue 28)


def test_guessing_on_the_screen_backs_off_then_locks_out(users):
    fired: list[Lockout] = []
    cfg = LoginConfig(max_failures_per_user=3, backoff_first_s=0, backoff_max_s=0, lockout_s=600)
    access = Access("10.0.0.5", WebConfig(), authenticate=users.authenticate, throttle=LoginThrottle(cfg, fired.append))
    for i in range(3):
        assert access.login("otto", f"guess-{i}", "10.0.0.66").role is None
    locked = access.login("otto", "otto-pass-1", "10.0.0.66")  # right, but locked out: no hash computed
    assert locked.role is None and locked.retry_after_s == pytest.approx(600, abs=5)
    assert fired == [Lockout("user", "otto", 3, 600, "screen")]
    assert access.login("vera", "vera-pass-1", "10.0.0.7").role is Role.VIEWER  # others still get in


def test_without_users_only_loopback_and_the_local_user_may_do_all():
    from cell.errors import ConfigError

    access = Access("127.0.0.1", WebConfig())
    assert not access.login_required and access.origin(None).role is Role.ADMIN
    with pytest.raises(ConfigError, match="beyond loopback"):
        Access("0.0.0.0", WebConfig())


def test_the_old_password_check_still_works_as_an_admin():
    access = Access("127.0.0.1", WebConfig(), lambda user, password: (user, password) == ("plc", "secret-1"))
    assert access.login("plc", "secret-1", "127.0.0.1").role is Role.ADMIN
    assert access.check_password("plc", "secret-1") and not access.check_password("plc", "nope")


def test_the_same_failure_is_logged_a_few_times_a_minute(tmp_path):
    clock = [0.0]
    limiter = LogRateLimiter(burst=3, window_s=60, clock=lambda: clock[0])
    record = logging.LogRecord(
        "asyncio", logging.ERROR, __file__, 1, "socket.accept() out of system resource", (), None
    )
    assert [limiter.check(record)[0] for _ in range(10)] == [True] * 3 + [False] * 7
    clock[0] = 61
    assert limiter.check(record) == (True, 7)  # the next window says how many were left out
    info = logging.LogRecord("x", logging.INFO, __file__, 1, "routine", (), None)
    assert all(limiter.check(info)[0] for _ in range(100))  # only warnings and errors are limited

    path = log_to_file(tmp_path / "serve.log")
    try:
        for _ in range(1000):
            logging.getLogger("asyncio").error("socket.accept() out of system resource")
    finally:
        stop_logging_to(path)
    lines = path.read_text().splitlines()
    assert 1 <= len(lines) <= 10 and "Too many" not in path.read_text()


def test_a_low_open_file_limit_is_raised_or_reported(monkeypatch, caplog):
    service = ServiceConfig()
    needed = needed_descriptors(service)
    limits = {"now": (512, 4096)}
    assert 512 < needed <= 1024  # the defaults fit systemd's 1024; 512 does not

    monkeypatch.setattr(resource, "getrlimit", lambda which: limits["now"])
    monkeypatch.setattr(resource, "setrlimit", lambda which, value: limits.update(now=value))
    assert check_open_files(service) is None and limits["now"] == (4096, 4096)  # raised to the hard limit

    limits["now"] = (256, 256)
    warning = check_open_files(service)
    assert warning and f"below the {needed} descriptors" in warning and "LimitNOFILE" in warning
    assert "LimitNOFILE" in caplog.text


@pytest.mark.parametrize(
    ("cfg", "checked"),
    [
        (LoginConfig(), 1),  # with back-off: one check at a time per address, as one after another
        (LoginConfig(max_failures_per_address=3, backoff_first_s=0, backoff_max_s=0), 3),  # at most the limit
    ],
)
def test_guesses_sent_together_from_one_address_get_no_further_than_one_after_another(users, cfg, checked):
    """issue 28: the throttle was asked, then the password hashed, then the failure counted; eight guesses sent
    at once were all asked before any failure was counted, so all eight were checked."""
    hashed: list[str] = []
    release = threading.Event()

    def slow_check(user: str, password: str) -> Role | None:
        hashed.append(user)
        release.wait(30)  # every guess is in flight together
        return users.authenticate(user, password)

    access = Access("10.0.0.5", WebConfig(), authenticate=slow_check, throttle=LoginThrottle(cfg))
    results: dict[int, object] = {}
    threads = [
        threading.Thread(target=lambda i=i: results.update({i: access.login(f"name{i}", "guess", "10.0.0.66")}))
        for i in range(8)
    ]
    for thread in threads:
        thread.start()
    deadline = time.monotonic() + 30
    while len(hashed) + len(results) < 8:  # each guess either checked (waiting) or already refused
        assert time.monotonic() < deadline, (hashed, results)
        time.sleep(0.01)
    release.set()
    for thread in threads:
        thread.join(30)
    assert len(hashed) == checked, hashed
    refused = [r for r in results.values() if r.retry_after_s > 0]  # type: ignore[attr-defined]
    assert len(refused) == 8 - checked

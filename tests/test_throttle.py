"""Login throttling: back-off, lockout with its alarm, forgetting, bounded memory. A fake clock: no sleeping."""

from __future__ import annotations

import pytest

from cell.access.throttle import Lockout, LoginThrottle
from cell.service.config import LoginConfig

pytestmark = pytest.mark.timeout(30)


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def make(**kw) -> tuple[LoginThrottle, Clock, list[Lockout]]:
    clock, fired = Clock(), []
    cfg = LoginConfig(**{"max_failures_per_user": 4, "max_failures_per_address": 6, "lockout_s": 60, **kw})
    return LoginThrottle(cfg, fired.append, clock=clock), clock, fired


def test_back_off_doubles_then_locks_out_with_one_alarm():
    t, clock, fired = make(backoff_first_s=1, backoff_max_s=3)
    assert t.refuse_for("anna", "10.0.0.9") == 0
    assert t.failed("anna", "10.0.0.9", "screen") == 1
    assert t.refuse_for("anna", "10.0.0.9") == 1 and t.refuse_for("anna", "10.0.0.7") == 1  # the name waits anywhere
    assert t.refuse_for("ben", "10.0.0.9") == 1  # and the address for any name
    assert t.refuse_for("ben", "10.0.0.7") == 0
    clock.now += 1
    assert t.failed("anna", "10.0.0.9") == 2
    clock.now += 2
    assert t.failed("anna", "10.0.0.9") == 3  # capped at backoff_max_s
    clock.now += 3
    assert not fired
    assert t.failed("anna", "10.0.0.9", "opcua") == 60  # the fourth: locked out
    assert fired == [Lockout("user", "anna", 4, 60, "opcua")]
    clock.now += 59
    assert t.refuse_for("anna", "10.0.0.1") == pytest.approx(1)
    assert [lk.key for lk in t.locked()] == ["anna"]
    clock.now += 1
    assert t.refuse_for("anna", "10.0.0.1") == 0  # the lockout has run out
    t.failed("anna", "10.0.0.1")
    assert len(fired) == 1 and t.refuse_for("anna", "10.0.0.1") == 1  # counting starts over


def test_many_names_from_one_address_lock_the_address():
    t, clock, fired = make(backoff_first_s=0, backoff_max_s=0)
    for i in range(6):
        t.failed(f"guess{i}", "10.0.0.66")
    assert [(f.kind, f.key) for f in fired] == [("address", "10.0.0.66")]
    assert t.refuse_for("anyone", "10.0.0.66") == 60 and t.refuse_for("anyone", "10.0.0.5") == 0


def test_success_clears_the_name_not_the_address():
    t, clock, fired = make(backoff_first_s=0, backoff_max_s=0)
    for _ in range(3):
        t.failed("anna", "10.0.0.9")
    t.succeeded("anna", "10.0.0.9")
    t.failed("anna", "10.0.0.9")
    assert not any(f.kind == "user" for f in fired)  # 1 failure counted for anna, not 4
    for _ in range(2):
        t.failed("anna", "10.0.0.9")
    assert [(f.kind, f.key) for f in fired] == [("address", "10.0.0.9")]  # 3 + 3 from the address


def test_old_failures_are_forgotten():
    t, clock, fired = make(backoff_first_s=0, backoff_max_s=0, forget_after_s=100)
    for _ in range(3):
        t.failed("anna", "10.0.0.9")
    clock.now += 101
    t.failed("anna", "10.0.0.9")
    assert not fired


def test_memory_is_bounded_and_lockouts_are_kept():
    clock, fired = Clock(), []
    t = LoginThrottle(LoginConfig(max_failures_per_user=2, lockout_s=60), fired.append, clock=clock, max_entries=50)
    t.failed("victim", "10.0.0.1")
    t.failed("victim", "10.0.0.1")  # locked out
    for i in range(500):  # one failure each: throttled, not locked
        t.failed(f"name{i}", f"10.1.{i // 250}.{i % 250}")
    assert len(t._records) <= 50
    assert t.refuse_for("victim", "10.9.9.9") > 0  # its lockout survived the flood of names
    assert [(f.kind, f.key) for f in fired] == [("user", "victim")]


def test_a_failing_alarm_callback_does_not_break_the_login_path():
    def broken(lockout: Lockout) -> None:
        raise RuntimeError("alarm sink down")

    t = LoginThrottle(LoginConfig(max_failures_per_user=1), broken, clock=Clock())
    assert t.failed("anna", "10.0.0.9") > 0


def test_a_try_let_through_counts_at_once_so_tries_in_parallel_get_no_further():
    """issue 28: the check and the count were apart, so tries sent together were all let through to the hash."""
    t, clock, fired = make(backoff_first_s=1, backoff_max_s=8)
    assert t.begin("anna", "10.0.0.9") == 0  # let through: in flight until settled
    assert t.begin("anna", "10.0.0.7") > 0  # the same name elsewhere waits as after a failure
    assert t.begin("ben", "10.0.0.9") > 0  # and any name from that address
    assert t.begin("ben", "10.0.0.7") == 0
    t.failed("anna", "10.0.0.9")
    t.succeeded("ben", "10.0.0.7")
    assert t.begin("anna", "10.0.0.9") == 1  # the back-off of one failure: the in-flight try was settled
    clock.now += 1
    assert t.begin("carl", "10.0.0.7") == 0  # ben's good login settled his address too
    t.abandon("carl", "10.0.0.7")  # a check that could not be made (the users file unreadable) counts nothing
    assert t.begin("dora", "10.0.0.7") == 0  # and never settled:
    assert t.begin("erin", "10.0.0.7") > 0
    clock.now += 61  # a try never settled stops counting
    assert t.begin("erin", "10.0.0.7") == 0


def test_without_back_off_the_checks_in_flight_count_towards_the_lockout():
    t, clock, fired = make(backoff_first_s=0, backoff_max_s=0)  # 6 failures lock an address
    assert [t.begin(f"guess{i}", "10.0.0.66") for i in range(8)] == [0.0] * 6 + [0.5] * 2
    for i in range(6):
        t.failed(f"guess{i}", "10.0.0.66")
    assert [(f.kind, f.key) for f in fired] == [("address", "10.0.0.66")]
    assert t.begin("anyone", "10.0.0.66") == 60

"""Login throttling, per user name and per client address, for the screen and OPC UA alike.

After a failed login the same user name, and the same address, must wait before the next
try: `backoff_first_s`, doubling with each failure up to `backoff_max_s`. After
`max_failures_per_user` (or `_per_address`) failures the name (or address) is locked out
for `lockout_s`, and `on_lockout` is called once, so the service can raise an alarm.
Failures older than `forget_after_s` with none since are forgotten; a successful login
clears its user name's failures (not its address's: one valid account must not reset the
count of an address guessing others).

Nothing here sleeps: `begin(user, address)` says how many seconds the caller must still
refuse (0: it may check the password), so an event loop is never held and a refused try
costs no password hash. A try `begin` lets through counts, under the same lock, as in
flight until `failed` or `succeeded` settles it: tries sent in parallel cannot get past the
throttle (issue 28: eight at once were all checked). While a user name or an address has a
check in flight, its next try waits as after a failure (with back-off configured), and the
checks in flight count towards the lockout limits. A try never settled (its caller gave
up) stops counting after IN_FLIGHT_MAX_S. `refuse_for` only asks, counting nothing.
Thread-safe; memory is bounded (`max_entries` keys, the oldest unlocked forgotten first).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cell.service.config import LoginConfig

log = logging.getLogger(__name__)

IN_FLIGHT_MAX_S = 60.0  # a try let through by begin() and never settled stops counting after this


@dataclass(frozen=True)
class Lockout:
    """A user name or a client address locked out after too many failed logins."""

    kind: str  # "user" | "address"
    key: str  # the user name or the address
    failures: int
    lockout_s: float
    interface: str = ""  # where the failure that locked it came from (screen, opcua)

    def describe(self) -> str:
        return (
            f"{self.kind} {self.key!r} locked out for {self.lockout_s:g} s after {self.failures} failed logins"
            f"{f' ({self.interface})' if self.interface else ''}"
        )


@dataclass
class _Record:
    failures: int = 0
    last_failure_s: float = 0.0
    blocked_until_s: float = 0.0
    locked: bool = False
    in_flight: list[float] = field(default_factory=list)  # when each unsettled try began (monotonic s)


class LoginThrottle:
    def __init__(
        self,
        cfg: LoginConfig,
        on_lockout: Callable[[Lockout], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        max_entries: int = 10_000,
    ) -> None:
        """`cfg`: a LoginConfig (cell.service.config)."""
        self.cfg = cfg
        self.on_lockout = on_lockout
        self._clock = clock
        self._max_entries = max_entries
        self._records: OrderedDict[tuple[str, str], _Record] = OrderedDict()
        self._lock = threading.Lock()

    def refuse_for(self, user: str, address: str) -> float:
        """Seconds the caller must still refuse a login of `user` from `address` (0: go ahead and check it)."""
        now = self._clock()
        with self._lock:
            waits = [self._wait(key, now) for key in self._keys(user, address)]
        return max(waits)

    def begin(self, user: str, address: str) -> float:
        """Before a password check: seconds to refuse it (> 0), or 0, and then the try is counted as in flight
        (towards the limits, and holding back the next try of this user or address) until `failed` or
        `succeeded` settles it. Checked and counted under one lock: parallel tries get no further than one
        after another would."""
        now = self._clock()
        with self._lock:
            keys = self._keys(user, address)
            wait = max(self._wait(key, now) for key in keys)
            if wait > 0:
                return wait
            for key in keys:
                record = self._fresh(key, now)
                record.in_flight = [t for t in record.in_flight if now - t < IN_FLIGHT_MAX_S]
                if record.in_flight and (
                    self.cfg.backoff_first_s > 0 or record.failures + len(record.in_flight) >= self._limit(key[0])
                ):
                    # the check in flight may fail: wait as its failure would make us (at least a moment)
                    failures = record.failures + len(record.in_flight)
                    return float(max(0.5, min(self.cfg.backoff_max_s, self.cfg.backoff_first_s * 2 ** (failures - 1))))
            for key in keys:
                self._records[key].in_flight.append(now)
                self._records.move_to_end(key)
            self._trim()
        return 0.0

    def failed(self, user: str, address: str, interface: str = "") -> float:
        """Record a failed login; returns how long the next try (of this user or address) is refused."""
        now = self._clock()
        fired: list[Lockout] = []
        with self._lock:
            for key in self._keys(user, address):
                record = self._fresh(key, now)
                if record.in_flight:
                    record.in_flight.pop(0)
                record.failures += 1
                record.last_failure_s = now
                limit = self._limit(key[0])
                if record.failures >= limit:
                    record.blocked_until_s = now + self.cfg.lockout_s
                    if not record.locked:
                        record.locked = True
                        fired.append(Lockout(key[0], key[1], record.failures, self.cfg.lockout_s, interface))
                else:
                    backoff = self.cfg.backoff_first_s * 2 ** (record.failures - 1)
                    record.blocked_until_s = now + min(self.cfg.backoff_max_s, backoff)
                self._records.move_to_end(key)
            self._trim()
            wait = max(self._wait(key, now) for key in self._keys(user, address))
        for lockout in fired:
            log.warning("login throttle: %s", lockout.describe())
            if self.on_lockout is not None:
                try:
                    self.on_lockout(lockout)
                except Exception:  # the alarm must not turn a refused login into an error
                    log.exception("login throttle: the lockout callback failed")
        return wait

    def succeeded(self, user: str, address: str) -> None:
        """A good login clears the user name's failures (the address's age out) and settles its try in flight."""
        with self._lock:
            self._records.pop(("user", user), None)
            record = self._records.get(("address", address))
            if record is not None and record.in_flight:
                record.in_flight.pop(0)

    def abandon(self, user: str, address: str) -> None:
        """Settle a try let through by `begin` whose check could not be made (an error, not a wrong password)."""
        with self._lock:
            for key in self._keys(user, address):
                record = self._records.get(key)
                if record is not None and record.in_flight:
                    record.in_flight.pop(0)

    def locked(self) -> list[Lockout]:
        """The lockouts in force now (for a status page or an alarm's text)."""
        now = self._clock()
        with self._lock:
            return [
                Lockout(kind, key, r.failures, round(r.blocked_until_s - now, 1))
                for (kind, key), r in self._records.items()
                if r.locked and r.blocked_until_s > now
            ]

    # ---- inside the lock ---------------------------------------------------------------
    @staticmethod
    def _keys(user: str, address: str) -> tuple[tuple[str, str], tuple[str, str]]:
        return ("user", user), ("address", address)

    def _limit(self, kind: str) -> int:
        limit: int = self.cfg.max_failures_per_user if kind == "user" else self.cfg.max_failures_per_address
        return limit

    def _fresh(self, key: tuple[str, str], now: float) -> _Record:
        """The key's record, started over when its lockout has run out or its failures are old."""
        record = self._records.get(key)
        if record is None:
            record = self._records[key] = _Record()
        elif (record.locked and record.blocked_until_s <= now) or now - record.last_failure_s > self.cfg.forget_after_s:
            record.failures, record.locked, record.blocked_until_s = 0, False, 0.0
        return record

    def _wait(self, key: tuple[str, str], now: float) -> float:
        record = self._records.get(key)
        return max(0.0, record.blocked_until_s - now) if record is not None else 0.0

    def _trim(self) -> None:
        """Forget the oldest keys past `max_entries`, keeping lockouts in force while it can."""
        excess = len(self._records) - self._max_entries
        if excess <= 0:
            return
        now = self._clock()
        for key in [k for k, r in self._records.items() if not (r.locked and r.blocked_until_s > now)][:excess]:
            del self._records[key]
        while len(self._records) > self._max_entries:
            self._records.popitem(last=False)

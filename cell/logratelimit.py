"""Rate-limited logging: the same failure logged a thousand times a second (a flood of refused
connections, "Too many open files" on every accept) becomes a few lines and a count.

`Tally` is for code that refuses things by the thousand (connections, logins): it counts
them per reason and client address and logs one line per reason at most once a minute.

`LogRateLimiter.check(record)` lets through the first `burst` records of one kind (logger,
level, message template, exception type) per `window_s`; the rest are counted, and the next
record of that kind let through after the window carries how many were left out. The log
handler (cell.oplog.RecordHandler) writes that count as a line of its own.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass


class Tally:
    """Counts of what was refused or cut, logged as one warning per reason at most every `every_s`."""

    MAX_KEYS = 1000  # (reason, address) pairs kept between two lines; more addresses count as "others"

    def __init__(self, what: str, every_s: float = 60.0, logger: str = "cell.limits") -> None:
        self.what, self.every_s = what, every_s
        self.log = logging.getLogger(logger)
        self.total: Counter[str] = Counter()  # since start, for tests and status
        self._pending: Counter[tuple[str, str]] = Counter()
        self._last_log_s: dict[str, float] = {}

    def note(self, reason: str, address: str) -> None:
        self.total[reason] += 1
        key = (reason, address) if len(self._pending) < self.MAX_KEYS else (reason, "others")
        self._pending[key] += 1
        now = time.monotonic()
        if now - self._last_log_s.get(reason, -1e9) >= self.every_s:
            self._flush(reason, now)

    def _flush(self, reason: str, now: float) -> None:
        items = [(a, n) for (r, a), n in self._pending.items() if r == reason]
        for a, _ in items:
            del self._pending[(reason, a)]
        count = sum(n for _, n in items)
        top = ", ".join(f"{a} x{n}" for a, n in sorted(items, key=lambda i: -i[1])[:5])
        self.log.warning("%s: %s (%d times: %s)", self.what, reason, count, top)
        self._last_log_s[reason] = now


@dataclass
class _Window:
    start_s: float
    passed: int = 0
    dropped: int = 0


class LogRateLimiter:
    def __init__(
        self,
        burst: int = 10,
        window_s: float = 60.0,
        max_kinds: int = 1000,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.burst, self.window_s, self.max_kinds = burst, window_s, max_kinds
        self._clock = clock
        self._windows: OrderedDict[tuple, _Window] = OrderedDict()
        self._lock = threading.Lock()

    @staticmethod
    def kind(record: logging.LogRecord) -> tuple:
        exc = record.exc_info[0].__name__ if record.exc_info and record.exc_info[0] else ""
        return record.name, record.levelno, str(record.msg), exc

    def check(self, record: logging.LogRecord) -> tuple[bool, int]:
        """(log it?, how many of its kind were left out before it). Records below WARNING are never limited."""
        if record.levelno < logging.WARNING:
            return True, 0
        key, now = self.kind(record), self._clock()
        with self._lock:
            window = self._windows.get(key)
            dropped_before = 0
            if window is None or now - window.start_s >= self.window_s:
                dropped_before = window.dropped if window else 0
                window = self._windows[key] = _Window(now)
                self._windows.move_to_end(key)
                while len(self._windows) > self.max_kinds:
                    self._windows.popitem(last=False)
            if window.passed >= self.burst:
                window.dropped += 1
                return False, 0
            window.passed += 1
            return True, dropped_before

    def summary(self, record: logging.LogRecord, dropped: int) -> str:
        return f"log rate limit: {dropped} more like the next line were left out in {self.window_s:g} s"

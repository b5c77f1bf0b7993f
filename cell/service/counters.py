"""The shift's counters, kept up event by event from the audit stream; the same counts as
cell.summary.counts_from_log, so reading the shift's log back after a restart gives them again."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from cell.core.records import Counters


class ShiftCounts:
    def __init__(self) -> None:
        self.picked: dict[str, int] = {}
        self.misses = self.retries = self.failed = self.unreachable = self.unknown_left = self.attempts = 0

    def apply(self, e: dict[str, Any]) -> bool:
        """Count one audit event; True when a counter changed."""
        kind = e.get("kind")
        if kind == "target":
            self.attempts += 1
            self.retries += e["attempt"] > 1
            return bool(e["attempt"] > 1)
        if kind == "verify":
            if e["result"] == "picked":
                self.picked[e["cls"]] = self.picked.get(e["cls"], 0) + 1
            self.misses += e["result"] == "missed"
            return e["result"] in ("picked", "missed")
        if kind in ("failed", "unreachable"):
            setattr(self, kind, getattr(self, kind) + 1)
            return True
        if kind == "frame":
            left = sum(1 for d in e["detections"] if not d["pick"])
            changed, self.unknown_left = left != self.unknown_left, left
            return changed
        return False

    @classmethod
    def from_events(cls, events: Iterable[dict[str, Any]]) -> ShiftCounts:
        counts = cls()
        for e in events:
            counts.apply(e)
        return counts

    @classmethod
    def from_counters(cls, c: Counters) -> ShiftCounts:
        """Counts restored from a store (attempts are not kept there: only the shown counters)."""
        counts = cls()
        counts.picked = {k: v for k, v in c.picked if v}
        counts.misses, counts.retries, counts.failed = c.misses, c.retries, c.failed
        counts.unreachable, counts.unknown_left = c.unreachable, c.unknown_left
        return counts

    def counters(self) -> Counters:
        return Counters(
            tuple(sorted((k, v) for k, v in self.picked.items() if v)),
            self.misses,
            self.retries,
            self.failed,
            self.unreachable,
            self.unknown_left,
        )

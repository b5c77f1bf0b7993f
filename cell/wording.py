"""Counts in words the operator reads: "1 nut", "2 nuts", "1 miss", "0 misses"."""

from __future__ import annotations


def plural(n: int, word: str, many: str | None = None) -> str:
    """`n` and the noun agreeing with it; `many` for a plural that is not word + 's'."""
    return f"{n} {word if n == 1 else (many or word + 's')}"

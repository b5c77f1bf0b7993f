"""Freed memory given back to the system after rare bulk work.

glibc keeps what a thread frees in that thread's arena, for its next allocations. A thread
that works rarely but in bulk (the history store's image saver: a 1080p frame and its
annotation as PNG, some 20 MB of buffers) would hold that memory for the rest of the process's
life. `release_free_memory()` returns the free pages of every arena to the system
(malloc_trim(0): 1-2 ms); elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    try:
        trim: Callable[[int], int] = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return None
    return trim


def release_free_memory() -> bool:
    """Give every arena's free pages back to the system; False where that cannot be done."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True

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
import os
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


M_MMAP_THRESHOLD = -3  # mallopt's parameter numbers (glibc's malloc.h)
MMAP_THRESHOLD_BYTES = 1 << 20  # blocks of 1 MB or more (a frame, a band of it) are mapped, and unmapped when freed
_ENV = "MALLOC_MMAP_THRESHOLD_"  # glibc's own setting: an operator's value wins over ours


def keep_big_blocks_mapped() -> bool:
    """Serve every allocation of 1 MB or more from its own mapping, returned to the system when freed.

    glibc starts with that threshold at 128 KB but raises it to the size of each mapped block freed
    (up to 32 MB): after the first frames, frame-sized arrays come from the heap, and a heap whose
    top holds one live block keeps every hole below it. Over a long shift that is RSS climbing in
    steps no Python object explains. A fixed threshold turns that adjustment off. Call it before
    the threads start; a no-op off glibc or where MALLOC_MMAP_THRESHOLD_ is set in the environment.
    """
    if os.environ.get(_ENV):
        return False
    try:
        mallopt: Callable[[int, int], int] = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))

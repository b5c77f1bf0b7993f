"""cell.memory: freed memory given back to the system (glibc's malloc_trim), callable from any thread."""

from __future__ import annotations

import platform
import threading

import pytest

from cell.memory import release_free_memory


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="malloc_trim is glibc's: elsewhere it does nothing")
def test_free_memory_is_released_from_any_thread() -> None:
    results: list[bool] = []
    worker = threading.Thread(target=lambda: results.append(release_free_memory()))
    worker.start()
    worker.join(10)
    assert results == [True] and release_free_memory()


PROBE = """
import ctypes, sys
from cell.memory import keep_big_blocks_mapped
class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
tuned = keep_big_blocks_mapped() if sys.argv[1] == "tuned" else False
big = libc.malloc(8 << 20)  # a frame-sized block, mapped (over glibc's first threshold), then freed:
libc.free(big)              # glibc's dynamic threshold rises to its size
before = libc.mallinfo2().hblkhd
block = libc.malloc(2 << 20)  # the next frame-sized block: its own mapping, or from the heap
print(tuned, libc.mallinfo2().hblkhd - before >= 2 << 20)
libc.free(block)
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt and mallinfo2 are glibc's")
def test_frame_sized_blocks_stay_mapped_after_a_bigger_one_was_freed() -> None:
    """Without a fixed threshold glibc serves the second block from the heap (its holes pile up over a
    long shift); with it, from a mapping given back when freed. The operator's own setting wins."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "MALLOC_MMAP_THRESHOLD_"}

    def probe(mode: str, **extra: str) -> str:
        run = subprocess.run(
            [sys.executable, "-c", PROBE, mode], env={**env, **extra}, capture_output=True, text=True, timeout=60
        )
        assert run.returncode == 0, run.stderr
        return run.stdout.strip()

    assert probe("default") == "False False"  # glibc's dynamic threshold: the 2 MB block came from the heap
    assert probe("tuned") == "True True"
    assert probe("tuned", MALLOC_MMAP_THRESHOLD_="33554432") == "False False"  # the environment's 32 MB wins

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

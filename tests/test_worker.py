"""The one worker-and-queue (cell.core.worker.QueueWorker) the event bus's subscribers, the history's
image saver and its writer run on: the offerer never waits, what cannot be queued is counted, a
handler that raises is counted and the thread goes on, close drains then drops past its timeout.

A handler held on an Event stands for a slow or stuck consumer, so no test depends on the machine's
speed: every wait is on a condition, and a short timeout is only given where the outcome cannot
depend on it (the handler is held until the test lets it go)."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable

import pytest

from cell.core.worker import BoundedQueue, QueueWorker

pytestmark = pytest.mark.timeout(60)


def wait_until(cond: Callable[[], bool], timeout_s: float = 30.0) -> bool:
    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


class Held:
    """A handler that records what it gets and holds on each item until `gate` is set."""

    def __init__(self) -> None:
        self.gate, self.entered, self.seen = threading.Event(), threading.Event(), []

    def __call__(self, item: int) -> None:
        self.entered.set()
        self.gate.wait()
        self.seen.append(item)


def test_a_full_queue_drops_the_newest_and_counts_never_blocks_the_offerer(caplog):
    held = Held()
    worker: QueueWorker[int, int] = QueueWorker("slow", held, BoundedQueue(4))
    assert worker.offer(0)
    assert held.entered.wait(30)  # taken: the handler holds it
    assert wait_until(lambda: worker.stats().queued == 0)
    with caplog.at_level(logging.WARNING, logger="cell.core.worker"):
        accepted = [worker.offer(i) for i in range(1, 100)]  # returns although the handler is held
    assert accepted == [True] * 4 + [False] * 95
    s = worker.stats()
    assert (s.queued, s.dropped, s.handled, s.failed) == (4, 95, 0, 0)
    drops = [r for r in caplog.records if "queue full" in r.getMessage()]
    assert len(drops) == 1 and "worker slow" in drops[0].getMessage()  # rate-limited: one line, not 95
    held.gate.set()
    assert worker.wait_idle(30)
    assert held.seen == [0, 1, 2, 3, 4] and worker.stats().handled == 5  # in order, the oldest kept
    assert worker.close(30)


def test_a_raising_handler_is_counted_and_the_thread_goes_on(caplog):
    seen: list[int] = []

    def handler(item: int) -> None:
        if item % 2:
            raise RuntimeError(f"a bug on {item}")
        seen.append(item)

    worker: QueueWorker[int, int] = QueueWorker(
        "buggy", handler, BoundedQueue(64), describe=lambda item: f"item {item}"
    )
    with caplog.at_level(logging.WARNING, logger="cell.core.worker"):
        for i in range(10):
            worker.offer(i)
        assert worker.wait_idle(30)
    s = worker.stats()
    assert (s.handled, s.failed, s.dropped) == (5, 5, 0) and seen == [0, 2, 4, 6, 8]
    failures = [r for r in caplog.records if "raised" in r.getMessage()]
    assert len(failures) == 1 and "item 1" in failures[0].getMessage() and failures[0].exc_info  # once, traceback
    assert worker.is_alive()
    worker.offer(10)  # still working
    assert worker.wait_idle(30) and seen[-1] == 10 and worker.stats().handled == 6
    assert worker.close(30) and not worker.is_alive()


def test_wait_idle_counts_the_item_in_hand():
    held = Held()
    worker: QueueWorker[int, int] = QueueWorker("held", held, BoundedQueue(8))
    assert worker.wait_idle(30)  # nothing offered: idle
    worker.offer(1)
    assert held.entered.wait(30) and wait_until(lambda: worker.stats().queued == 0)
    assert not worker.wait_idle(0.05)  # nothing queued, but the one taken is not handled (held)
    held.gate.set()
    assert worker.wait_idle(30) and held.seen == [1]
    worker.close(30)


def test_close_handles_what_is_queued_then_ends_the_thread_and_takes_nothing_more():
    held = Held()
    worker: QueueWorker[int, int] = QueueWorker("draining", held, BoundedQueue(16))
    for i in range(10):
        worker.offer(i)
    closer = threading.Thread(target=lambda: results.append(worker.close(30)))
    results: list[bool] = []
    closer.start()
    assert wait_until(lambda: worker.closing)
    assert not worker.offer(99)  # closing: nothing new (not counted as dropped)
    held.gate.set()
    closer.join(30)
    assert results == [True] and not worker.is_alive()
    assert held.seen == list(range(10)) and worker.stats().dropped == 0


def test_close_past_its_timeout_drops_what_is_left_and_the_thread_ends_after_the_item_in_hand(caplog):
    held = Held()
    worker: QueueWorker[int, int] = QueueWorker("stuck", held, BoundedQueue(16))
    for i in range(4):
        worker.offer(i)
    assert held.entered.wait(30)
    with caplog.at_level(logging.WARNING, logger="cell.core.worker"):
        assert worker.close(0.05) is False  # the handler is held: the thread cannot have ended
    s = worker.stats()
    assert (s.queued, s.dropped) == (0, 3)
    assert any("still busy" in r.getMessage() and "3 queued items dropped" in r.getMessage() for r in caplog.records)
    held.gate.set()
    assert wait_until(lambda: not worker.is_alive())
    assert held.seen == [0] and worker.stats().handled == 1  # the dropped ones never reach the handler


def test_close_from_the_handler_itself_does_not_wait_on_its_own_thread():
    box: list[QueueWorker[int, int]] = []
    ended: list[bool] = []
    worker: QueueWorker[int, int] = QueueWorker("self", lambda item: ended.append(box[0].close(30)), BoundedQueue(4))
    box.append(worker)
    worker.offer(1)
    assert wait_until(lambda: not worker.is_alive())
    assert ended == [False]  # it could not have ended while still in its handler


def test_a_batching_worker_takes_what_came_meanwhile_and_close_ends_the_wait():
    seen: list[int] = []
    threads: set[int] = set()

    def handler(item: int) -> None:
        seen.append(item)
        threads.add(threading.get_ident())

    worker: QueueWorker[int, int] = QueueWorker("batch", handler, BoundedQueue(64), batch_s=3600.0)
    for i in range(20):
        worker.offer(i)
    assert worker.stats().queued == 20 and not seen  # gathering for an hour: nothing handled
    assert worker.close(30)  # ends the batch's wait; everything queued is handled, in order
    assert seen == list(range(20)) and len(threads) == 1


class Batches:
    """A queue hook that hands the handler everything waiting at once (as the history's writer's does)."""

    def __init__(self) -> None:
        self.items: deque[int] = deque()

    def put(self, item: int) -> bool:
        self.items.append(item)
        return True

    def take(self) -> list[int]:
        batch = list(self.items)
        self.items.clear()
        return batch

    def __len__(self) -> int:
        return len(self.items)

    def clear(self) -> int:
        n = len(self.items)
        self.items.clear()
        return n


def test_a_queue_hook_decides_what_the_handler_gets_and_on_drained_follows_each_burst():
    held = Held()
    batches: list[list[int]] = []
    drained = threading.Semaphore(0)

    def handler(batch: list[int]) -> None:
        held(batch[0])
        batches.append(batch)

    worker: QueueWorker[int, list[int]] = QueueWorker("rows", handler, Batches(), on_drained=drained.release)
    worker.offer(0)
    assert held.entered.wait(30)
    for i in range(1, 6):
        worker.offer(i)  # wait while the first batch is held
    held.gate.set()
    assert worker.wait_idle(30)
    assert batches == [[0], [1, 2, 3, 4, 5]]
    assert drained.acquire(timeout=30)  # called on the worker's thread once its queue ran empty
    assert worker.close(30)

"""One worker behind one bounded queue: what the event bus's subscribers, the history's image saver
and the history's writer share.

- `offer` never blocks: the item is queued, or dropped and counted when the queue is full (the
  queue's own rule says what full means), or ignored once the worker is closing.
- The worker's thread takes items one at a time and hands each to the handler; a handler that
  raises is counted and logged, and the thread goes on with the next item.
- Drops and failures are logged at most once a minute per worker (a stuck or broken consumer must
  not flood the log), with the counts so far.
- `wait_idle(timeout_s)`: True once everything offered so far has been handled.
- `close(timeout_s)`: no new items; what is queued is handled until the timeout, then what is left
  is dropped (counted) and the thread ends after the item in hand; True if it had ended in time.

What differs between the users are hooks: the queue (`WorkQueue`: a plain bounded deque by default;
the bus's coalesces frames, the writer's takes a transaction's worth of rows at once), `batch_s`
(wake at most once a batch_s and take what came meanwhile, for consumers that need nothing at once)
and `on_drained` (called on the worker's thread each time the queue runs empty, e.g. to give
buffers back to the system).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

log = logging.getLogger(__name__)

LOG_EVERY_S = 60.0  # a worker's drops, and its handler's failures, are logged at most this often

ItemT = TypeVar("ItemT")  # what is offered
WorkT = TypeVar("WorkT")  # what the handler gets (the same as what is offered, unless the queue batches)
ItemC = TypeVar("ItemC", contravariant=True)
WorkC = TypeVar("WorkC", covariant=True)


class WorkQueue(Protocol[ItemC, WorkC]):
    """A worker's queue. Every method is called with the worker's lock held, so none may block."""

    def put(self, item: ItemC) -> bool:
        """Queue the item; False if the queue is full and the item is dropped."""
        ...

    def take(self) -> WorkC:
        """The next piece of work; only called while `len(self) > 0`."""
        ...

    def __len__(self) -> int:
        """Items waiting (what `stats().queued` shows, and what the thread waits for)."""
        ...

    def clear(self) -> int:
        """Drop everything waiting; returns how many items were dropped."""
        ...


class BoundedQueue(Generic[ItemT]):
    """First in, first out, at most `maxsize` items; when full the newest (the one offered) is dropped."""

    def __init__(self, maxsize: int):
        self.maxsize = maxsize
        self._items: deque[ItemT] = deque()

    def put(self, item: ItemT) -> bool:
        if len(self._items) >= self.maxsize:
            return False
        self._items.append(item)
        return True

    def take(self) -> ItemT:
        return self._items.popleft()

    def __len__(self) -> int:
        return len(self._items)

    def clear(self) -> int:
        n = len(self._items)
        self._items.clear()
        return n


@dataclass(frozen=True)
class WorkerStats:
    name: str
    handled: int  # items the handler returned from
    dropped: int  # items never handled: the queue was full, or left at close
    failed: int  # items the handler raised on
    queued: int  # items waiting (not the one in hand)


class QueueWorker(Generic[ItemT, WorkT]):
    """A thread handling what is offered to it, in order, behind a bounded queue (see the module's text).

    `label` begins its log lines (e.g. "subscriber screen"); `describe` names an item the handler
    raised on (e.g. "a frame event")."""

    def __init__(
        self,
        name: str,
        handler: Callable[[WorkT], object],
        queue: WorkQueue[ItemT, WorkT],
        *,
        label: str = "",
        thread_name: str = "",
        batch_s: float = 0.0,
        on_drained: Callable[[], object] | None = None,
        describe: Callable[[WorkT], str] | None = None,
    ):
        self.name, self.handler, self.queue = name, handler, queue
        self.label = label or f"worker {name}"
        self.batch_s = batch_s  # > 0: wake at most once a batch_s, taking every item queued meanwhile
        self.on_drained = on_drained
        self.describe = describe
        self.handled = self.dropped = self.failed = 0
        self._cond = threading.Condition()
        self._busy = False  # the thread holds items it took and has not finished with
        self._closing = False
        self._closed = threading.Event()  # set by close: ends a batch's wait (and a handler's, see closing_wait)
        self._last_log = {"dropped": -LOG_EVERY_S, "failed": -LOG_EVERY_S}
        self._thread = threading.Thread(target=self._run, name=thread_name or name, daemon=True)
        self._thread.start()

    # ---- the offerer's side (never blocks) ------------------------------------------------
    def offer(self, item: ItemT) -> bool:
        """Queue an item for the thread; False if it was dropped (queue full) or the worker is closing."""
        with self._cond:
            if self._closing:
                return False
            if not self.queue.put(item):
                self.dropped += 1
                self._note("dropped", "queue full: dropping; %d dropped so far", self.dropped)
                return False
            self._cond.notify()
            return True

    # ---- the thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                while not len(self.queue) and not self._closing:
                    self._cond.wait()
                if not len(self.queue):
                    return
                self._busy = True
            if self.batch_s > 0:
                self._closed.wait(self.batch_s)  # let the batch gather (an offer's notify wakes nobody meanwhile)
            while True:
                with self._cond:
                    if not len(self.queue):
                        self._busy = False
                        self._cond.notify_all()
                        break
                    work = self.queue.take()
                self._handle(work)
            if self.on_drained is not None:
                try:
                    self.on_drained()
                except Exception:
                    log.exception("%s: after its queue ran empty", self.label)

    def _handle(self, work: WorkT) -> None:
        try:
            self.handler(work)
            self.handled += 1
        except Exception:
            self.failed += 1
            what = self.describe(work) if self.describe is not None else "an item"
            self._note("failed", "handler raised on %s (%d so far)", what, self.failed, exc=True)

    def _note(self, what: str, message: str, *args: object, exc: bool = False) -> None:
        now = time.monotonic()
        if now - self._last_log[what] >= LOG_EVERY_S:
            self._last_log[what] = now
            log.warning("%s: " + message, self.label, *args, exc_info=exc)

    def closing_wait(self, timeout_s: float) -> bool:
        """For a handler that waits before trying again: True (at once) when the worker is closing."""
        return self._closed.wait(timeout_s)

    @property
    def closing(self) -> bool:
        return self._closed.is_set()

    # ---- control ----------------------------------------------------------------------------------
    def wait_idle(self, timeout_s: float) -> bool:
        """True once every item offered so far has been handled (or dropped)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while len(self.queue) or self._busy:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def close(self, timeout_s: float = 5.0) -> bool:
        """Take nothing new, handle what is queued (up to the timeout), end the thread; True if it ended.
        Past the timeout what is still queued is dropped (counted) and the thread ends once the
        handler returns from the item in hand."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._closed.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout_s)
        if self._thread.is_alive():
            with self._cond:
                left = self.queue.clear()
                self.dropped += left
                self._cond.notify_all()
            log.warning("%s: still busy %.1f s after close; %d queued items dropped", self.label, timeout_s, left)
            return False
        return True

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def stats(self) -> WorkerStats:
        with self._cond:
            return WorkerStats(self.name, self.handled, self.dropped, self.failed, len(self.queue))

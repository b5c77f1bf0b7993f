"""One stream of typed events (cell.core.events), with two kinds of listener.

- Records (`add_record`): called on the emitting thread, in order, before `emit` returns.
  Only the audit log is one: safety needs the record written before the next motion, so it
  stays synchronous and cheap (one JSON line). A record that fails raises into the emitter
  (the job faults safely) unless `best_effort` is set (while making safe and ending).
- Subscribers (`subscribe`): each on its own thread behind its own bounded queue (a
  cell.core.worker.QueueWorker, the worker the history store's threads use too). `emit`
  only appends (never blocks, never raises for them); a subscriber that is slow loses the
  newest events once its queue is full, one that raises is logged; both are counted
  (`stats()`), and neither ever delays or faults a pick. Frames (FrameLocated) coalesce:
  a subscriber that has not taken the last frame yet gets the newer one in its place.
  A subscriber that needs no event at once (a screen, /metrics) names a `batch_s`: its thread
  wakes at most once a batch_s and takes what came meanwhile in one go, in order. Every wake
  of a subscriber's thread takes Python's interpreter lock from the control thread for a
  moment; a runner step emits several events, so waking for each would cost picks.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol

from cell.core.events import Event, FrameLocated, PickOrderChosen
from cell.core.worker import QueueWorker

log = logging.getLogger(__name__)

Handler = Callable[[Event], object]  # its return value is not used
_GONE = Event()  # what a dropped slot holds: the frame it held is let go at once


@dataclass(frozen=True)
class SubscriberStats:
    name: str
    delivered: int
    dropped: int  # queue full: events this subscriber never saw
    failed: int  # events its handler raised on
    queued: int


class _Box:
    """A queue slot. A frame's slot is dropped for a newer frame until it is taken, with the slots
    of the events queued after it that exist only for it (`followers`: its pick order), unless an
    event after it that must be delivered refers to it (`pinned`)."""

    __slots__ = ("event", "taken", "dead", "pinned", "followers")

    def __init__(self, event: Event):
        self.event, self.taken, self.dead, self.pinned = event, False, False, False
        self.followers: list[_Box] = []


# Events that only describe a frame (the screen's pick order): dropped with the frame they refer to.
_FRAME_ONLY: frozenset[type[Event]] = frozenset({PickOrderChosen})


def _frame_of(event: Event) -> int | None:
    """The frame number an event (not a frame itself) refers to: its `frame`, or its frame's (`ref`)."""
    n = getattr(event, "frame", None)
    if isinstance(n, int) and not isinstance(n, bool):
        return n
    ref = getattr(event, "ref", None)
    return ref.frame_no if ref is not None else None


class FrameQueue:
    """A subscriber's queue (cell.core.worker.WorkQueue): at most `maxsize` events, the newest dropped
    when full; frames (the `coalesce` kinds) coalesce, see the module's text."""

    def __init__(self, maxsize: int, coalesce: frozenset[type[Event]]):
        self.maxsize, self.coalesce = maxsize, coalesce
        self._queue: deque[_Box] = deque()
        self._latest: dict[type[Event], _Box] = {}
        self._dead = 0  # slots in the queue whose frame a newer one replaced (skipped, not counted as queued)

    def put(self, event: Event) -> bool:
        kind = type(event)
        if kind in self.coalesce:
            stale = self._latest.get(kind)
            if stale is not None and not stale.taken and not stale.dead:
                if self._queue and self._queue[-1] is stale:
                    stale.event = event  # nothing came after the older frame: the newer one takes its place
                    return True
                if not stale.pinned:  # never delivered ahead of what came after the older frame:
                    self._drop(stale)  # the older one goes (with its pick order), the newer one at the end
        frame = None if kind in self.coalesce or not self._latest else _frame_of(event)
        if len(self._queue) - self._dead >= self.maxsize:
            return False
        box = _Box(event)
        if kind in self.coalesce:
            self._latest[kind] = box
        elif frame is not None:
            for latest in self._latest.values():
                if not latest.taken and not latest.dead and getattr(latest.event, "frame", None) == frame:
                    if kind in _FRAME_ONLY:
                        latest.followers.append(box)
                    else:
                        latest.pinned = True  # delivered after the frame it refers to, so the frame stays
        self._queue.append(box)
        return True

    def _drop(self, box: _Box) -> None:
        """A frame's slot and its followers' are skipped (their events let go now)."""
        for b in (box, *box.followers):
            if not b.dead and not b.taken:
                b.dead, b.event = True, _GONE
                self._dead += 1
        box.followers = []

    def take(self) -> Event:
        while True:
            box = self._queue.popleft()
            box.taken = True
            if not box.dead:
                return box.event
            self._dead -= 1

    def __len__(self) -> int:
        return len(self._queue) - self._dead

    def clear(self) -> int:
        n = len(self)
        self._queue.clear()
        self._dead = 0
        return n


class Subscription:
    """One subscriber: its queue and its thread (a cell.core.worker.QueueWorker), its counters."""

    def __init__(
        self,
        name: str,
        handler: Handler,
        kinds: frozenset[type[Event]] | None,
        maxsize: int,
        coalesce: frozenset[type[Event]],
        frames: bool | Callable[[Event], bool] = False,
        batch_s: float = 0.0,
    ):
        self.name, self.handler, self.kinds, self.maxsize, self.coalesce = name, handler, kinds, maxsize, coalesce
        self.batch_s = batch_s  # > 0: wake at most once a batch_s, taking every event queued meanwhile
        self.frames = frames  # False: events reach it without their frame (`ref`), so its queue holds no images
        self._worker: QueueWorker[Event, Event] = QueueWorker(
            name,
            handler,
            FrameQueue(maxsize, coalesce),
            label=f"subscriber {name}",
            thread_name=f"events-{name}",
            batch_s=batch_s,
            describe=lambda event: f"a {event.kind} event",
        )

    # ---- the emitter's side (never blocks) ---------------------------------------------
    def offer(self, event: Event) -> None:
        if self.kinds is not None and type(event) not in self.kinds:
            return
        if getattr(event, "ref", None) is not None and not (
            self.frames(event) if callable(self.frames) else self.frames
        ):
            event = dataclasses.replace(event, ref=None)  # type: ignore[call-arg]
        self._worker.offer(event)

    # ---- counters and control -------------------------------------------------------------
    @property
    def delivered(self) -> int:
        return self._worker.handled

    @property
    def dropped(self) -> int:
        return self._worker.dropped

    @property
    def failed(self) -> int:
        return self._worker.failed

    def wait_idle(self, timeout_s: float) -> bool:
        """True once every event offered so far has been handled (for tests and orderly shutdown)."""
        return self._worker.wait_idle(timeout_s)

    def close(self, timeout_s: float = 5.0) -> bool:
        """Stop taking events, deliver what is queued (up to the timeout), end the thread; True if it ended."""
        return self._worker.close(timeout_s)

    def stats(self) -> SubscriberStats:
        s = self._worker.stats()
        return SubscriberStats(self.name, s.handled, s.dropped, s.failed, s.queued)


class Record(Protocol):
    """A synchronous record's write: raises when it cannot write, unless best effort (its owner's
    switch, or this one call's)."""

    def __call__(self, event: Event, best_effort: bool = False) -> object: ...


class RecordOwner(Protocol):
    """What keeps a synchronous record (the audit log): its writes raise unless best effort."""

    best_effort: bool


class EventBus:
    """The one stream: `emit` from the runner or the service; records and subscribers listen."""

    def __init__(self) -> None:
        self._records: list[Record] = []
        self._subs: tuple[Subscription, ...] = ()
        self._lock = threading.Lock()
        self._best_effort = False
        self._record_objs: list[RecordOwner] = []

    # ---- listeners -----------------------------------------------------------------------
    def add_record(self, record: Record, owner: RecordOwner | None = None) -> None:
        """A synchronous record (the audit log): `owner.best_effort` follows the bus's."""
        self._records.append(record)
        if owner is not None:
            self._record_objs.append(owner)
            owner.best_effort = self._best_effort

    def subscribe(
        self,
        name: str,
        handler: Handler,
        *,
        kinds: Iterable[type[Event]] | None = None,
        maxsize: int = 1024,
        coalesce: Iterable[type[Event]] = (FrameLocated,),
        frames: bool | Callable[[Event], bool] = False,
        batch_s: float = 0.0,
    ) -> Subscription:
        """`frames`: the subscriber uses the images events carry (the screen), or those of the events
        it names (the history store: failures only); the others get the events without them, so a
        queue that backs up holds no frame it does not need. `batch_s`: see the module's text."""
        kind_set = None if kinds is None else frozenset(kinds)
        sub = Subscription(name, handler, kind_set, maxsize, frozenset(coalesce), frames, batch_s)
        with self._lock:
            self._subs = (*self._subs, sub)
        return sub

    def unsubscribe(self, sub: Subscription, timeout_s: float = 5.0) -> None:
        with self._lock:
            self._subs = tuple(s for s in self._subs if s is not sub)
        sub.close(timeout_s)

    # ---- emitting --------------------------------------------------------------------------
    @property
    def best_effort(self) -> bool:
        return self._best_effort

    @best_effort.setter
    def best_effort(self, on: bool) -> None:
        self._best_effort = on
        for owner in self._record_objs:
            owner.best_effort = on

    def emit(self, event: Event, *, best_effort: bool = False, unrecorded_too: bool = True) -> None:
        """Records first (may raise: the record could not be kept), then every subscriber's queue.
        `best_effort`: this one event is written if it can be, never raised (a record owner that
        knows it, e.g. the service's shift log, then does not try a new file for it). With
        `unrecorded_too` False an event whose record failed reaches no subscriber (a job start
        refused for its record: nothing started, so nobody hears of it)."""
        recorded = False
        try:
            for record in self._records:
                if best_effort:
                    record(event, best_effort=True)
                else:
                    record(event)
            recorded = True
        finally:
            if recorded or unrecorded_too:
                for sub in self._subs:
                    sub.offer(event)

    # ---- state -----------------------------------------------------------------------------
    def stats(self) -> tuple[SubscriberStats, ...]:
        return tuple(s.stats() for s in self._subs)

    def wait_idle(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        return all(s.wait_idle(max(deadline - time.monotonic(), 0.0)) for s in self._subs)

    def close(self, timeout_s: float = 5.0) -> None:
        """End every subscriber, each delivering what it has queued within the time left."""
        with self._lock:
            subs, self._subs = self._subs, ()
        deadline = time.monotonic() + timeout_s
        for s in subs:
            s.close(max(deadline - time.monotonic(), 0.1))

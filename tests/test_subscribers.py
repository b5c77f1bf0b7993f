"""Subscribers of the event stream never hold up or fault a pick.

A subscriber that never returns and one that raises on every event are attached to a
dry-run service for a whole job: the job must end as without them (every part picked, no
fault), their losses counted where OPC UA and the screen show them. Blocking the subscriber
outright (rather than making it slow) makes the test independent of the machine's speed:
if the control thread waited on a subscriber even once, the job could not end.
How fast picks go with slow subscribers beside them is measured by
scripts/bench_subscribers.py, not asserted here.
"""

from __future__ import annotations

import socket
import threading

import pytest

from cell.core.commands import Command, VisionState
from cell.core.eventbus import EventBus
from cell.core.events import PickVerified, SnapshotChanged, StateChanged
from tests.ports import free_port
from tests.test_service import picked, running, small_config, wait_for

pytestmark = pytest.mark.timeout(180)


def test_a_stuck_and_a_raising_subscriber_never_hold_up_or_fault_a_job(tmp_path):
    no_feeder = small_config(tmp_path).sim.feeder.model_copy(update={"parts_per_minute": 0})
    release = threading.Event()
    with running(small_config(tmp_path, feeder=no_feeder)) as service:
        stuck = service.subscribe("stuck", lambda e: release.wait(), maxsize=8)

        def broken(event):
            raise RuntimeError("a subscriber with a bug")

        raising = service.subscribe("raising", broken)
        service.command(Command.START_SINGLE)
        wait_for(lambda: service.snapshot().vision_state == VisionState.READY, timeout_s=150, what="the job's end")
        snap = service.snapshot()
        assert picked(service) == 17 and snap.alarm is None and snap.counters.failed == 0
        assert raising.wait_idle(30)
        stats = {s.name: s for s in service.snapshot().subscribers}
        assert stats["stuck"].dropped > 0 and stats["stuck"].queued <= 8
        assert stats["raising"].delivered == 0 and stats["raising"].failed > 100
        assert stats["ledger"].dropped == stats["ledger"].failed == 0
        release.set()
        assert stuck.wait_idle(30)


def test_the_bus_never_blocks_the_emitter_and_counts_what_it_drops():
    bus = EventBus()
    gate = threading.Event()
    sub = bus.subscribe("slow", lambda e: gate.wait(), maxsize=4)
    bus.emit(SnapshotChanged(what="first"))
    assert wait_until(lambda: sub.stats().queued == 0)  # taken: the handler is stuck on it
    for i in range(99):
        bus.emit(SnapshotChanged(what=str(i)))  # returns at once although the subscriber is stuck
    s = sub.stats()
    assert s.queued == 4 and s.dropped == 95  # one taken by the stuck handler, four queued
    gate.set()
    assert sub.wait_idle(10) and sub.stats().delivered == 5
    bus.close()


def test_a_batching_subscriber_takes_what_came_meanwhile_in_one_wake_in_order():
    """batch_s: the thread waits that long after the first event and then takes everything queued
    meanwhile; nothing is lost or reordered, and closing does not wait out the batch."""
    bus = EventBus()
    seen: list[str] = []
    threads: set[int] = set()
    waking = threading.Event()

    def handler(e):
        seen.append(e.what)
        threads.add(threading.get_ident())
        waking.set()

    sub = bus.subscribe("screen", handler, batch_s=3600.0)  # one batch for the whole test
    for i in range(50):
        bus.emit(SnapshotChanged(what=str(i)))
    assert not waking.wait(0.2) and sub.stats().queued == 50  # gathering: nothing handled yet
    assert not sub.wait_idle(0.1)  # what is queued is not handled yet
    bus.close(timeout_s=30)  # ends the batch's wait: everything queued is delivered, in order
    assert seen == [str(i) for i in range(50)] and len(threads) == 1
    assert sub.stats().delivered == 50 and sub.stats().dropped == 0


def test_frames_coalesce_a_slow_subscriber_sees_the_newest(tmp_path):
    from cell.core.events import FrameLocated

    bus = EventBus()
    gate, seen = threading.Event(), []
    sub = bus.subscribe("screen", lambda e: (gate.wait(), seen.append(e)))
    bus.emit(StateChanged(source="idle", target="home", reason="x"))  # taken: the handler waits on the gate
    assert wait_until(lambda: sub.stats().queued == 0)
    for n in range(1, 6):
        bus.emit(FrameLocated(frame=n, locate_ms=1.0, warnings=(), detections=()))
    bus.emit(StateChanged(source="home", target="capture", reason="y"))
    gate.set()
    assert sub.wait_idle(10)
    assert [getattr(e, "frame", e.kind) for e in seen] == ["state", 5, "state"]  # frames 1-4 replaced by 5
    assert sub.stats().dropped == 0
    bus.close()


def test_a_coalesced_frame_never_goes_ahead_of_the_events_about_the_older_one(tmp_path):
    """A slow subscriber has frame 1 and its pick order queued when frame 2 comes: frame 2 is not
    delivered in frame 1's place, ahead of frame 1's pick order (the screen would number frame 2
    with frame 1's order); frame 1 goes with its order, frame 2 comes after what came between.
    A frame an event to deliver refers to (its verdict, carrying it) is kept; every event comes
    after the frame it refers to."""
    import numpy as np

    from cell.core.events import FrameLocated, FrameRef, PickOrderChosen

    def located(n: int, ref=None) -> FrameLocated:
        return FrameLocated(frame=n, locate_ms=1.0, warnings=(), detections=(), ref=ref)

    def verdict(n: int, ref) -> PickVerified:
        return PickVerified(
            pick_id=f"j/{n}", track=n, cls="nut", attempt=1, result="picked", pixel=(0.0, 0.0),
            table_mm=(0.0, 0.0), robot_mm=(0.0, 0.0, 0.0), jaw_angle_deg=None, still_at_mm=(), ref=ref,
        )  # fmt: skip

    bus = EventBus()
    gate, seen = threading.Event(), []
    sub = bus.subscribe("screen", lambda e: (gate.wait(), seen.append(e)), frames=True)
    bus.emit(StateChanged(source="idle", target="home", reason="x"))  # taken: the handler waits on the gate
    assert wait_until(lambda: sub.stats().queued == 0)
    refs = {n: FrameRef(n, np.zeros((4, 4, 3), np.uint8), None, 0.0) for n in range(1, 5)}
    bus.emit(located(1, refs[1]))
    bus.emit(PickOrderChosen(frame=1, order=(3, 1, 2)))
    bus.emit(StateChanged(source="plan", target="pick", reason="part 3"))
    bus.emit(located(2, refs[2]))  # frame 1 was never taken: it goes, with its order
    bus.emit(PickOrderChosen(frame=2, order=(1, 2)))
    bus.emit(verdict(2, refs[2]))  # refers to frame 2: frame 2 stays for it
    bus.emit(located(3, refs[3]))
    bus.emit(PickOrderChosen(frame=3, order=(2,)))
    bus.emit(located(4, refs[4]))  # frame 3 had nothing to deliver after it but its order: both go
    queued = sub.stats().queued
    gate.set()
    assert sub.wait_idle(10)
    got = [(e.kind, getattr(e, "frame", None) or getattr(getattr(e, "ref", None), "frame_no", None)) for e in seen]
    assert got == [
        ("state", None),
        ("state", None),
        ("frame", 2),
        ("plan", 2),
        ("verify", 2),
        ("frame", 4),
    ]
    delivered: set[int] = set()
    for kind, n in got:  # the rule itself: nothing before the frame it refers to
        if kind == "frame":
            delivered.add(n)
        elif n is not None:
            assert n in delivered, f"{kind} of frame {n} delivered before its frame"
    assert queued == 5 and sub.stats().dropped == 0  # the frames let go are neither queued nor dropped
    bus.close()


def wait_until(cond, timeout_s: float = 10.0) -> bool:
    import time

    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


@pytest.mark.slow
def test_thirty_screens_that_never_read_do_not_hold_up_the_job(tmp_path):
    """Thirty browsers open the event stream and never read it; the job runs to its end."""
    from cell.web.server import screen_server

    cfg = small_config(tmp_path, feeder=small_config(tmp_path).sim.feeder.model_copy(update={"parts_per_minute": 0}))
    cfg.service.http_port = free_port()
    cfg.service.web.max_screens = 32
    with running(cfg) as service:
        server = screen_server(service, cfg)
        server.start()
        streams = []
        try:
            for _ in range(30):
                s = socket.create_connection(("127.0.0.1", server.port), timeout=10)
                s.sendall(b"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
                s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # and never read: the buffers fill
                streams.append(s)
            picks = []
            sub = service.subscribe("picks", picks.append, kinds=(PickVerified,))
            service.command(Command.START_SINGLE)
            wait_for(lambda: service.snapshot().vision_state == VisionState.READY, timeout_s=150, what="the job's end")
            assert sub.wait_idle(30) and len(picks) == picked(service) == 17
        finally:
            for s in streams:
                s.close()
            server.stop()


def test_only_subscribers_that_ask_for_frames_get_them():
    import numpy as np

    from cell.core.events import FrameRef, PickVerified

    bus = EventBus()
    plain, framed = [], []
    a = bus.subscribe("opcua", plain.append)
    b = bus.subscribe("history", framed.append, frames=True)
    ref = FrameRef(1, np.zeros((4, 4, 3), np.uint8), None, 0.0)
    fields = {"pick_id": "j/1", "track": 1, "cls": "nut", "attempt": 1, "result": "missed", "pixel": (1.0, 2.0)}
    bus.emit(
        PickVerified(
            **fields, table_mm=(1.0, 2.0), robot_mm=(1.0, 2.0, 3.0), jaw_angle_deg=None, still_at_mm=(), ref=ref
        )
    )
    assert a.wait_idle(10) and b.wait_idle(10)
    assert plain[0].ref is None and framed[0].ref is ref  # a queue that backs up holds no images
    assert plain[0].pick_id == framed[0].pick_id == "j/1"
    bus.close()

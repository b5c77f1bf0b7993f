"""Subscribers that take frames hold few of them however far they lag: while /metrics's
subscriber is stuck, a shift's worth of frames (every verdict and failure carries one) leaves
at most the frame it is on and the newest located one alive, not one per queued event."""

from __future__ import annotations

import gc
import threading
import time
import weakref
from collections.abc import Iterator

import numpy as np
import pytest

from cell.core.events import Event, FrameLocated, FrameRef, PartFailed, PickVerified
from cell.web.metrics import CellMetrics
from tests.fake_service import FakeLineService

pytestmark = pytest.mark.timeout(60)


def shift(n_frames: int, alive: list[weakref.ref[np.ndarray]]) -> Iterator[Event]:
    """Each frame located, then judged (a verdict) or given up on (a failure), carrying it."""
    for i in range(n_frames):
        image = np.zeros((108, 192, 3), np.uint8)
        alive.append(weakref.ref(image))
        ref = FrameRef(i, image, None, time.monotonic())
        yield FrameLocated(frame=i, locate_ms=1.0, warnings=(), detections=(), ref=ref)
        if i % 5:
            yield PickVerified(
                pick_id=f"j/{i}", track=i, cls="nut", attempt=1, result="picked", pixel=(0.0, 0.0),
                table_mm=(0.0, 0.0), robot_mm=(0.0, 0.0, 0.0), jaw_angle_deg=None, still_at_mm=(), ref=ref,
            )  # fmt: skip
        else:
            yield PartFailed(track=i, cls="bolt", attempts=3, ref=ref)


def test_a_stuck_metrics_subscriber_keeps_at_most_two_frames() -> None:
    service = FakeLineService()  # at rest: it emits nothing of its own
    metrics = CellMetrics(service)
    inside, release = threading.Event(), threading.Event()
    counted = metrics.handle

    def stuck(event: Event) -> None:
        inside.set()
        release.wait(30)
        counted(event)

    metrics.handle = stuck  # type: ignore[method-assign]  # the subscriber's handler, slowed down
    metrics.start()
    alive: list[weakref.ref[np.ndarray]] = []
    try:
        events = shift(300, alive)
        service.bus.emit(next(events))
        assert inside.wait(10), "the subscriber took the first event and is stuck in it"
        for event in events:
            service.bus.emit(event)
        del events
        gc.collect()
        held = sum(r() is not None for r in alive)
        assert service.bus.stats()[0].queued > 100, "the events themselves are queued"
        assert held <= 2, f"{held} frames kept alive by the stuck subscriber's queue"
    finally:
        release.set()
        metrics.close()
        service.close()

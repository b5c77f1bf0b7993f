"""Fan-out of the cell's events to every open screen, off the control thread.

Two subscriptions on the service's event bus, each on its own thread: state changes only
wake the web server's loop with a fresh snapshot; located frames are held until PLAN has
numbered their parts (so the order drawn is the runner's own), then annotated and encoded
as a JPEG once, and handed to the loop. Each screen keeps only the newest state and frame:
a slow screen skips frames, it never holds up the cell or the other screens, and a frame
the subscriber has not drawn yet is replaced by the next (the bus coalesces frames).
"""

from __future__ import annotations

import asyncio
import base64
import logging
import threading
import time
from dataclasses import dataclass, field

import cv2

from cell.events import Event, FrameLocated, FrameRef, PickOrderChosen, RunEnded, SnapshotChanged, StateChanged
from cell.service.api import FrameView, LineServiceAPI, Snapshot
from cell.vision.annotate import annotate

log = logging.getLogger(__name__)
_HELD_THROUGH = frozenset({"verify", "plan"})  # after LOCATE a frame waits through these for its pick order


@dataclass(frozen=True)
class EncodedFrame:
    seq: int
    capture_wall_ms: float  # wall-clock time of the capture, for the page's capture -> shown latency
    jpeg: bytes
    encode_ms: float
    encoded_wall_ms: float  # when the JPEG was ready: capture -> encoded is the service's share of the latency

    def event_json(self) -> dict:
        return {
            "seq": self.seq,
            "capture_wall_ms": round(self.capture_wall_ms, 1),
            "encode_ms": round(self.encode_ms, 2),
            "encoded_wall_ms": round(self.encoded_wall_ms, 1),
            "jpeg_b64": base64.b64encode(self.jpeg).decode(),
        }


def encode_frame(frame: FrameView, max_width_px: int, quality: int) -> EncodedFrame:
    t0 = time.monotonic()
    wall_ms = 1e3 * (time.time() - (t0 - frame.capture_monotonic_s))
    image = frame.image_bgr
    h, w = image.shape[:2]
    if w > max_width_px:
        # linear: INTER_AREA costs 5x more at a non-integer ratio (1920 -> 1280), for no visible gain here
        image = cv2.resize(image, (max_width_px, round(h * max_width_px / w)), interpolation=cv2.INTER_LINEAR)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError(f"frame {frame.seq}: JPEG encoding failed ({w} x {h})")
    return EncodedFrame(frame.seq, wall_ms, buf.tobytes(), 1e3 * (time.monotonic() - t0), 1e3 * time.time())


@dataclass(eq=False)
class Screen:
    """One open event stream: the newest state and frame not yet sent."""

    wake: asyncio.Event = field(default_factory=asyncio.Event)
    snapshot: Snapshot | None = None
    frame: EncodedFrame | None = None
    closed: bool = False


class Hub:
    def __init__(self, service: LineServiceAPI, max_width_px: int, jpeg_quality: int, max_screens: int):
        self.service = service
        self.max_width_px, self.jpeg_quality, self.max_screens = max_width_px, jpeg_quality, max_screens
        self.screens: set[Screen] = set()
        self.latest: EncodedFrame | None = None
        self.latest_view: FrameView | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._held: FrameRef | None = None  # located, waiting for PLAN to number its parts
        self._seq = 0
        self._subs: list = []
        self._lock = threading.Lock()

    # ---- life ----------------------------------------------------------------------
    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._subs = [
            self.service.subscribe("screen-state", self._on_state, kinds=(SnapshotChanged, StateChanged), maxsize=256),
            self.service.subscribe(
                "screen-frames",
                self._on_frame_event,
                kinds=(FrameLocated, PickOrderChosen, StateChanged, RunEnded),
                maxsize=256,
                frames=True,
            ),
        ]

    def close(self) -> None:
        """Unsubscribe and end every open stream (safe to call twice)."""
        with self._lock:
            subs, self._subs = self._subs, []
        for sub in subs:
            self.service.unsubscribe(sub)
        if self._loop is not None and not self._loop.is_closed():
            try:
                self._loop.call_soon_threadsafe(self._close_screens)
            except RuntimeError:
                pass  # the loop already stopped: no stream is left to end

    def _close_screens(self) -> None:
        for s in self.screens:
            s.closed = True
            s.wake.set()

    # ---- the subscribers' threads --------------------------------------------------
    def _on_state(self, event: Event) -> None:
        self._to_loop(self._publish_state, self.service.snapshot())

    def _on_frame_event(self, event: Event) -> None:
        """Hold a located frame until its pick order (or until the runner moves on without one)."""
        if isinstance(event, FrameLocated):
            self._flush(None)  # never more than one frame waiting
            self._held = event.ref
        elif isinstance(event, PickOrderChosen):
            if self._held is not None and self._held.frame_no == event.frame:
                self._flush(event.order)
        elif isinstance(event, StateChanged):
            if event.target not in _HELD_THROUGH:
                self._flush(None)
        elif isinstance(event, RunEnded):
            self._flush(None)

    def _flush(self, order: tuple[int, ...] | None) -> None:
        ref, self._held = self._held, None
        if ref is None:
            return
        self._seq += 1
        try:
            image = annotate(ref.image, ref.result, order or ())
            view = FrameView(self._seq, ref.captured_monotonic_s, image, tuple(order or ()))
            encoded = encode_frame(view, self.max_width_px, self.jpeg_quality)
        except (ValueError, cv2.error) as e:
            log.warning("screen: frame not shown: %s", e)
            return
        self.latest_view = view
        self._to_loop(self._publish_frame, encoded)

    def _to_loop(self, fn, *args) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(fn, *args)
            except RuntimeError:
                pass  # the server is shutting down

    # ---- the server's loop ---------------------------------------------------------
    def _publish_state(self, snapshot: Snapshot) -> None:
        for s in self.screens:
            s.snapshot = snapshot
            s.wake.set()

    def publish_now(self) -> None:
        """Push the current state to every screen (from the loop: the screen's own news, e.g. a report opened)."""
        self._publish_state(self.service.snapshot())

    def _publish_frame(self, frame: EncodedFrame) -> None:
        self.latest = frame
        for s in self.screens:
            s.frame = frame
            s.wake.set()

    def open_screen(self) -> Screen | None:
        """A new stream primed with the current state and frame, or None when too many are open."""
        if len(self.screens) >= self.max_screens:
            return None
        screen = Screen(snapshot=self.service.snapshot(), frame=self.latest)
        screen.wake.set()
        self.screens.add(screen)
        return screen

    def close_screen(self, screen: Screen) -> None:
        self.screens.discard(screen)

"""Fan-out of the service's events to every open screen.

The service calls our listener from its own thread, which must never wait on a browser:
the listener only keeps the newest frame and wakes an encoder thread; the JPEG is made once
and handed to the web server's event loop, where each screen keeps only the newest state and
frame (a slow screen skips frames, it never holds up the cell or the other screens).
"""

from __future__ import annotations

import asyncio
import base64
import logging
import threading
import time
from dataclasses import dataclass, field

import cv2

from cell.service.api import FrameView, LineServiceAPI, ServiceEvent, Snapshot

log = logging.getLogger(__name__)


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
        self._loop: asyncio.AbstractEventLoop | None = None
        self._pending: FrameView | None = None
        self._pending_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._unsubscribe = None

    # ---- life ----------------------------------------------------------------------
    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._thread = threading.Thread(target=self._encode_loop, name="screen-jpeg", daemon=True)
        self._thread.start()
        self._unsubscribe = self.service.subscribe(self._on_event)
        first = self.service.latest_frame()
        if first is not None:
            self._hand_over(first)

    def close(self) -> None:
        """Unsubscribe, stop the encoder and end every open stream (safe to call twice)."""
        if self._unsubscribe:
            self._unsubscribe()
            self._unsubscribe = None
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        if self._loop is not None and not self._loop.is_closed():
            try:
                self._loop.call_soon_threadsafe(self._close_screens)
            except RuntimeError:
                pass  # the loop already stopped: no stream is left to end

    def _close_screens(self) -> None:
        for s in self.screens:
            s.closed = True
            s.wake.set()

    # ---- the service's thread ------------------------------------------------------
    def _on_event(self, event: ServiceEvent) -> None:
        if event.frame is not None:
            self._hand_over(event.frame)
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._publish_state, event.snapshot)
            except RuntimeError:
                pass  # the server is shutting down

    def _hand_over(self, frame: FrameView) -> None:
        with self._pending_lock:
            self._pending = frame
        self._wake.set()

    # ---- the encoder thread --------------------------------------------------------
    def _encode_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait()
            self._wake.clear()
            with self._pending_lock:
                frame, self._pending = self._pending, None
            if frame is None or self._stop.is_set():
                continue
            try:
                encoded = encode_frame(frame, self.max_width_px, self.jpeg_quality)
            except (ValueError, cv2.error) as e:
                log.warning("screen: frame not shown: %s", e)
                continue
            try:
                self._loop.call_soon_threadsafe(self._publish_frame, encoded)
            except RuntimeError:
                return  # the server's loop is gone

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

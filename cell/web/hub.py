"""Fan-out of the cell's events to every open screen, off the control thread.

Two subscriptions on the service's event bus, each on its own thread: state changes only
wake the web server's loop with a fresh snapshot; located frames are held until PLAN has
numbered their parts (so the order drawn is the runner's own), then annotated and encoded
as a JPEG once, and handed to the loop. Each screen keeps only the newest state and frame:
a slow screen skips frames, it never holds up the cell or the other screens, and a frame
the subscriber has not drawn yet is replaced by the next (the bus coalesces frames).

Frames are drawn on demand: only when a screen has sent the last one it was given and waits for
the next (`want_frame`). A screen whose reader is slow or gone (its stream stuck in a send)
asks for nothing, so screens that cannot take frames cost the cell no drawing at all.

Between jobs (and while paused) a third thread asks the service for a live camera frame every
`live_interval_s` while a screen is open (`preview_frame`: the service takes it under its device
lock, only at rest), encoded the same way and marked live; a job's annotated frames take over as
soon as it runs (the service then gives none).
"""

from __future__ import annotations

import asyncio
import base64
import itertools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import cv2

from cell.core.api import LineServiceAPI
from cell.core.eventbus import Subscription
from cell.core.events import (
    Event,
    FrameLocated,
    FrameRef,
    Interface,
    Origin,
    PickOrderChosen,
    Role,
    RunEnded,
    SnapshotChanged,
    StateChanged,
)
from cell.core.records import FrameView, Snapshot
from cell.errors import REPORTED_ERRORS
from cell.vision.annotate import annotate
from cell.web.camera_check import CameraCheck

log = logging.getLogger(__name__)
_HELD_THROUGH = frozenset({"verify", "plan"})  # after LOCATE a frame waits through these for its pick order
LIVE_ORIGIN = Origin(Interface.SCREEN, "live view", Role.VIEWER)
_LIVE_ERROR_LOG_S = 60.0  # a camera that keeps failing is logged once a minute, not every frame
STATE_INTERVAL_S = 0.1  # the screens' state at most ten times a second: the runner changes step far more often
STATE_REFRESH_S = 1.0  # and at least once a second (the heartbeat), changed or not
FRAME_BATCH_S = 0.05  # the frame events' thread wakes at most 20 times a second (a runner step emits several)


@dataclass(frozen=True)
class EncodedFrame:
    seq: int
    capture_wall_ms: float  # wall-clock time of the capture, for the page's capture -> shown latency
    jpeg: bytes
    encode_ms: float
    encoded_wall_ms: float  # when the JPEG was ready: capture -> encoded is the service's share of the latency
    live: bool = False  # a raw camera frame between jobs, not a job's annotated frame
    check: dict[str, Any] | None = None  # the camera check's readings of a live frame, when it is on

    def event_json(self) -> dict[str, Any]:
        return {
            **({"check": self.check} if self.check is not None else {}),
            "seq": self.seq,
            "live": self.live,
            "captured_utc": datetime.fromtimestamp(self.capture_wall_ms / 1e3, UTC).isoformat(timespec="milliseconds"),
            "capture_wall_ms": round(self.capture_wall_ms, 1),
            "encode_ms": round(self.encode_ms, 2),
            "encoded_wall_ms": round(self.encoded_wall_ms, 1),
            "jpeg_b64": base64.b64encode(self.jpeg).decode(),
        }


def encode_frame(
    frame: FrameView, max_width_px: int, quality: int, live: bool = False, check: dict[str, Any] | None = None
) -> EncodedFrame:
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
    return EncodedFrame(
        frame.seq, wall_ms, buf.tobytes(), 1e3 * (time.monotonic() - t0), 1e3 * time.time(), live, check
    )


@dataclass(eq=False)
class Screen:
    """One open event stream: the newest state and frame not yet sent."""

    wake: asyncio.Event = field(default_factory=asyncio.Event)
    snapshot: Snapshot | None = None
    frame: EncodedFrame | None = None
    closed: bool = False
    sending: bool = False  # the stream is handing an event to its socket (stuck there while the reader is slow)


class Hub:
    def __init__(
        self,
        service: LineServiceAPI,
        max_width_px: int,
        jpeg_quality: int,
        max_screens: int,
        live_interval_s: float = 0.0,
        check: CameraCheck | None = None,
        max_frame_rate_hz: float = 0.0,
    ):
        self.service = service
        self.max_width_px, self.jpeg_quality, self.max_screens = max_width_px, jpeg_quality, max_screens
        self.live_interval_s = live_interval_s  # 0: no live view
        self.check = check  # the camera check, assessing live frames while it is on
        self.screens: set[Screen] = set()
        self.latest: EncodedFrame | None = None
        self.latest_view: FrameView | None = None
        self.latest_snapshot: Snapshot | None = None  # the last state sent (set on the loop)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._held: FrameRef | None = None  # located, waiting for PLAN to number its parts
        self._seq = itertools.count(1)  # frames of both kinds, in the order they were taken
        self._subs: list[Subscription] = []
        self._lock = threading.Lock()
        self._live_wake = threading.Event()  # a screen opened: take a live frame now
        self._live_stop = threading.Event()
        self._live_thread: threading.Thread | None = None
        self._live_error_logged_s = -1e9
        # A job's frames go through a mailbox (the newest waits, older ones are dropped) to one encoder
        # thread: nothing is drawn or encoded while no screen is open, and at most max_frame_rate_hz
        # frames a second are (0: as fast as they come), so the screens never take the cell's CPU.
        self.min_frame_interval_s = 1.0 / max_frame_rate_hz if max_frame_rate_hz > 0 else 0.0
        self._mailbox: tuple[FrameRef, tuple[int, ...] | None] | None = None
        self._mail = threading.Condition()
        self._encoder_stop = False
        self._encoder: threading.Thread | None = None
        self._state_dirty = False  # a state change not yet sent (guarded by _mail)
        self._frame_wanted = False  # a screen sent its last frame and waits for the next (guarded by _mail)
        self.snapshots_taken = 0  # states taken for the screens (for tests)
        self.frames_drawn = 0  # job and live frames annotated/encoded for the screens (for tests)
        self._stater: threading.Thread | None = None

    # ---- life ----------------------------------------------------------------------
    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._subs = [
            self.service.subscribe(
                "screen-state",
                self._on_state,
                kinds=(SnapshotChanged, StateChanged),
                maxsize=256,
                batch_s=STATE_INTERVAL_S,  # the state goes out at most that often anyway
            ),
            self.service.subscribe(
                "screen-frames",
                self._on_frame_event,
                kinds=(FrameLocated, PickOrderChosen, StateChanged, RunEnded),
                maxsize=256,
                frames=True,
                batch_s=FRAME_BATCH_S,
            ),
        ]
        self._encoder = threading.Thread(target=self._encode_loop, name="screen-encoder", daemon=True)
        self._encoder.start()
        self._stater = threading.Thread(target=self._state_loop, name="screen-state", daemon=True)
        self._stater.start()
        if self.live_interval_s > 0:
            self._live_thread = threading.Thread(target=self._live_loop, name="screen-live", daemon=True)
            self._live_thread.start()

    def close(self) -> None:
        """Unsubscribe and end every open stream (safe to call twice)."""
        with self._lock:
            subs, self._subs = self._subs, []
        for sub in subs:
            self.service.unsubscribe(sub)
        self._live_stop.set()
        self._live_wake.set()
        with self._mail:
            self._encoder_stop = True
            self._mail.notify_all()
        for thread in (self._live_thread, self._encoder, self._stater):
            if thread is not None:
                thread.join(timeout=10)
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
    def _on_state(self, event: Event | None) -> None:
        if not self.screens:
            return  # nobody to tell: a screen that opens gets a fresh snapshot of its own
        with self._mail:
            self._state_dirty = True
            self._mail.notify_all()

    def _state_loop(self) -> None:
        """Send the state after a change, at most one a STATE_INTERVAL_S (the changes in between are
        one snapshot), and once a STATE_REFRESH_S anyway. Every snapshot the screens get is taken
        here, one after another, off the server's loop and off the control thread: they arrive in
        the order they were taken, so a screen never goes back to an older state."""
        while True:
            with self._mail:
                while not self._encoder_stop:
                    if self._state_dirty and self._any_idle():
                        break
                    if not self._mail.wait(STATE_REFRESH_S) and self._any_idle():
                        break  # the heartbeat (a screen free to take it now, not before the wait)
                if self._encoder_stop:
                    return
                self._state_dirty = False
            self._to_loop(self._publish_state, self.service.snapshot())
            self.snapshots_taken += 1
            if self._live_stop.wait(STATE_INTERVAL_S):
                return

    def _any_idle(self) -> bool:
        """Whether a screen could take a new state now: one is open and not still sending what it got.
        A screen whose reader is slow or gone sits in a send: while every open one does, no snapshot
        is taken (the state stays marked as changed and goes out once one is free)."""
        return any(not s.sending for s in list(self.screens))

    def screen_idle(self) -> None:
        """A stream finished sending and waits for news: the state thread may have some for it."""
        with self._mail:
            if self._state_dirty:
                self._mail.notify_all()

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
        with self._mail:
            self._mailbox = (ref, order)  # a frame not yet taken is replaced: the screens show the newest
            self._mail.notify_all()

    def _encode_loop(self) -> None:
        """Annotate and encode the newest job frame while a screen is open, at most one a
        min_frame_interval_s (the frames that arrive meanwhile replace each other)."""
        last_s = -1e9
        while True:
            with self._mail:
                while not self._encoder_stop and (self._mailbox is None or not self._frame_wanted or not self.screens):
                    self._mail.wait()
                if self._encoder_stop:
                    return
            rest_s = last_s + self.min_frame_interval_s - time.monotonic()
            if rest_s > 0 and self._live_stop.wait(rest_s):
                return  # closing
            with self._mail:
                taken, self._mailbox = self._mailbox, None
                self._frame_wanted = taken is None and self._frame_wanted
            if taken is not None:
                last_s = time.monotonic()
                self._encode_job_frame(*taken)

    def _encode_job_frame(self, ref: FrameRef, order: tuple[int, ...] | None) -> None:
        try:
            image = annotate(ref.image, ref.result, order or ())
            view = FrameView(next(self._seq), ref.captured_monotonic_s, image, tuple(order or ()))
            encoded = encode_frame(view, self.max_width_px, self.jpeg_quality)
        except (ValueError, cv2.error) as e:
            log.warning("screen: frame not shown: %s", e)
            return
        self.latest_view = view
        self.frames_drawn += 1
        self._to_loop(self._publish_frame, encoded)

    def _live_loop(self) -> None:
        """While a screen is open: a live frame now and then every live_interval_s (none while a job runs)."""
        while not self._live_stop.is_set():
            self._live_wake.wait(self.live_interval_s)
            self._live_wake.clear()
            if self._live_stop.is_set():
                return
            if self.screens and self._frame_wanted:
                self._take_live()

    def _take_live(self) -> None:
        try:
            live = self.service.preview_frame(LIVE_ORIGIN)
            if live is None:
                return  # a job runs: its own frames are shown
            check = self.check.read(live.image_bgr) if self.check is not None else None
            view = FrameView(next(self._seq), live.captured_monotonic_s, live.image_bgr)
            encoded = encode_frame(view, self.max_width_px, self.jpeg_quality, live=True, check=check)
        except (*REPORTED_ERRORS, ValueError, cv2.error) as e:
            now = time.monotonic()
            if now - self._live_error_logged_s >= _LIVE_ERROR_LOG_S:
                self._live_error_logged_s = now
                log.warning("screen: no live frame: %s", e)
            return
        with self._mail:
            self._frame_wanted = False
        self.frames_drawn += 1
        self._to_loop(self._publish_frame, encoded)

    def want_frame(self) -> None:
        """A screen sent the frame it was given (or just opened) and can take the next: draw one."""
        with self._mail:
            self._frame_wanted = True
            self._mail.notify_all()

    def live_now(self) -> None:
        """Take a live frame now rather than at the next interval (e.g. the camera check was switched on)."""
        self._live_wake.set()

    def _to_loop(self, fn: Callable[..., object], *args: object) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(fn, *args)
            except RuntimeError:
                pass  # the server is shutting down

    # ---- the server's loop ---------------------------------------------------------
    def _publish_state(self, snapshot: Snapshot) -> None:
        self.latest_snapshot = snapshot
        for s in self.screens:
            s.snapshot = snapshot
            s.wake.set()

    def publish_now(self) -> None:
        """Push the current state to every screen soon (the screen's own news, e.g. a report opened)."""
        self._on_state(None)

    def _publish_frame(self, frame: EncodedFrame) -> None:
        latest = self.latest
        if latest is not None and frame.live and frame.capture_wall_ms < latest.capture_wall_ms:
            return  # a live frame taken just before a job started, encoded after its first frame
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
        if self.latest is None:
            self._live_wake.set()  # the first screen: a picture now, not after a whole interval
        self.want_frame()  # a job frame kept while no screen was open is drawn now
        return screen

    def close_screen(self, screen: Screen) -> None:
        self.screens.discard(screen)

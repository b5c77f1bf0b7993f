"""`/metrics` for Prometheus (prometheus_client's text exposition), on the screen's port.

Each screen server has its own CollectorRegistry (nothing global: two services in one process,
as in the tests, never share a number). Two sources:
- events, counted as they happen by a bus subscriber (its own thread): picks by class and
  outcome, misses, faults, the pick cycle time and the frame latency (capture to located) as
  histograms. Counters since the service started, as Prometheus expects (rate() handles restarts).
- the service's snapshot, read at each scrape: the state, the shift's counters, the pick rate,
  active alarms, the calibration's cross-validated RMS, and every bus subscriber's delivered,
  dropped and failed events.

Access is the screen's: open on a loopback screen without users; otherwise a logged-in session
or HTTP basic authentication with a user of the service (any role may read; failed tries are
throttled like the screen's logins).
"""

from __future__ import annotations

import base64
import binascii
import math
import time
from collections.abc import Iterator
from datetime import UTC, datetime

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric, StateSetMetricFamily
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from starlette.requests import Request
from starlette.responses import JSONResponse, Response

from cell.core.api import LineServiceAPI
from cell.core.commands import VisionState
from cell.core.eventbus import Subscription
from cell.core.events import AlarmRaised, Event, FrameLocated, PartFailed, PickVerified
from cell.core.values import counter_values
from cell.web.auth import SESSION_COOKIE, Access

CYCLE_BUCKETS_S = (0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 8.0, 13.0, 20.0, 30.0, 60.0)
LATENCY_BUCKETS_S = (0.01, 0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 2.0)


def _is_located(event: Event) -> bool:
    return isinstance(event, FrameLocated)


class CellMetrics:
    """The registry /metrics serves, fed by one bus subscriber and the snapshot at scrape time."""

    def __init__(self, service: LineServiceAPI):
        self.service = service
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.picks = Counter(
            "cell_picks", "Finished pick attempts by part class and outcome (picked, missed, failed, rehearsed)",
            ["cls", "outcome"], registry=r,
        )  # fmt: skip
        self.misses = Counter("cell_misses", "Picks that left the part on the table", registry=r)
        self.faults = Counter("cell_faults", "Fault alarms raised (each needs a Reset)", registry=r)
        self.cycle = Histogram(
            "cell_pick_cycle_seconds", "From choosing a target to its verdict", buckets=CYCLE_BUCKETS_S, registry=r
        )
        self.latency = Histogram(
            "cell_frame_latency_seconds",
            "From a frame's capture to its parts located (frames this subscriber took; newer frames replace "
            "untaken ones)",
            buckets=LATENCY_BUCKETS_S,
            registry=r,
        )
        r.register(_SnapshotCollector(service))
        self._sub: Subscription | None = None

    def start(self) -> None:
        """Count events from now on (the screen's lifespan: with the server)."""
        if self._sub is None:
            # frames: the latency needs a located frame's capture time (its `ref`). Only FrameLocated's:
            # those coalesce, so the queue holds one at most; a verdict's or a failure's frame would be
            # kept for every queued event while this thread lags (6 MB each at 1080p)
            self._sub = self.service.subscribe(
                "metrics",
                self.handle,
                kinds=(PickVerified, PartFailed, AlarmRaised, FrameLocated),
                maxsize=10_000,
                frames=_is_located,
                batch_s=0.25,  # a scrape is seconds apart: no need to wake for every event
            )

    def handle(self, event: Event) -> None:
        if isinstance(event, PickVerified):
            self.picks.labels(event.cls, event.result).inc()
            if event.result == "missed":
                self.misses.inc()
            if event.cycle_ms > 0:
                self.cycle.observe(event.cycle_ms / 1000.0)
        elif isinstance(event, PartFailed):
            self.picks.labels(event.cls, "failed").inc()
        elif isinstance(event, AlarmRaised) and event.severity == "fault":
            self.faults.inc()
        elif isinstance(event, FrameLocated) and event.ref is not None:
            self.latency.observe(frame_latency_s(event))

    def text(self) -> bytes:
        return generate_latest(self.registry)

    def close(self) -> None:
        sub, self._sub = self._sub, None
        if sub is not None:
            self.service.unsubscribe(sub)


def frame_latency_s(event: FrameLocated) -> float:
    """Capture to located: the frame's age now (monotonic) less the time the event has waited since it
    was made right after locate (wall clock, over a few milliseconds)."""
    assert event.ref is not None
    age_s = time.monotonic() - event.ref.captured_monotonic_s
    waited_s = (datetime.now(UTC) - event.time_utc).total_seconds()
    return max(age_s - max(waited_s, 0.0), 0.0)


class _SnapshotCollector:
    """What the service's snapshot says, read at each scrape."""

    def __init__(self, service: LineServiceAPI):
        self.service = service

    def collect(self) -> Iterator[Metric]:  # prometheus_client's collector protocol
        s = self.service.snapshot()
        yield StateSetMetricFamily(
            "cell_state", "OPC 40100-1 state of the cell", value={v.value: v is s.vision_state for v in VisionState}
        )
        shift = GaugeMetricFamily("cell_shift_parts", "This shift's counters", labels=["counter"])
        for name, value in counter_values(s, self.service.parts).items():
            if name != "picked":  # the total is the sum of the classes' series
                shift.add_metric([name], value)
        yield shift
        yield GaugeMetricFamily(
            "cell_parts_per_minute", "Pick rate over the last 20 picks; 0 between jobs", value=s.parts_per_min
        )
        alarms = GaugeMetricFamily("cell_alarms_active", "Active alarms by severity", labels=["severity"])
        alarms.add_metric(["fault"], 1 if s.alarm is not None else 0)
        alarms.add_metric(["warning"], len(s.warnings))
        yield alarms
        cv = s.calibration.cv_rms_mm if s.calibration is not None else math.nan
        yield GaugeMetricFamily(
            "cell_calibration_cv_rms_mm", "Cross-validated RMS error of the calibration in use", value=cv
        )
        for what, help_text in (
            ("delivered", "Events each bus subscriber handled"),
            ("dropped", "Events each bus subscriber lost because its queue was full"),
            ("failed", "Events each bus subscriber's handler raised on"),
        ):
            family = CounterMetricFamily(f"cell_subscriber_events_{what}", help_text, labels=["subscriber"])
            for sub in s.subscribers:
                family.add_metric([sub.name], getattr(sub, what))
            yield family


def metrics_refused(request: Request, access: Access) -> Response | None:
    """The screen's rule: whoever may view may read; without a session, HTTP basic auth with a service user."""
    if access.may_view(request.cookies.get(SESSION_COOKIE)):
        return None
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    if scheme.lower() == "basic":
        try:
            user, _, password = base64.b64decode(token, validate=True).decode().partition(":")
        except (binascii.Error, UnicodeDecodeError):
            user = password = ""
        address = request.client.host if request.client else ""
        if user and access.login(user, password, address).role is not None:  # throttled, as the screen's login
            return None
    return JSONResponse(
        {"error": "log in, or send the service's user and password (HTTP basic auth)"},
        status_code=401,
        headers={"www-authenticate": 'Basic realm="cell metrics"'},
    )


def metrics_response(metrics: CellMetrics) -> Response:
    return Response(metrics.text(), media_type=CONTENT_TYPE_LATEST)

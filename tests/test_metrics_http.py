"""/metrics on the screen's port (Starlette's TestClient on the fake line service): the text parsed
with prometheus_client's own parser, counts from events, the snapshot's gauges, and the screen's
access rule (open on a loopback screen without a password; else a session or basic auth)."""

from __future__ import annotations

import base64
import time
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from cell.core.events import AlarmRaised, FrameLocated, FrameRef, PartFailed, PickVerified
from cell.web.config import WebConfig
from tests.fake_service import FakeLineService
from tests.test_web_http import config, make_client, operator_pw7  # noqa: F401  (the config fixture)

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def service():
    s = FakeLineService()
    yield s
    s.close()


def samples(text: str) -> dict[tuple[str, tuple], float]:
    """Every sample as {(name, sorted labels): value}, parsed as Prometheus would."""
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def verdict(result: str, cls: str = "bolt", cycle_ms: float = 0.0) -> PickVerified:
    return PickVerified(
        pick_id="j/1", track=1, cls=cls, attempt=1, result=result, pixel=(0.0, 0.0), table_mm=(0.0, 0.0),
        robot_mm=(0.0, 0.0, 0.0), jaw_angle_deg=None, still_at_mm=(), cycle_ms=cycle_ms,
    )  # fmt: skip


def test_metrics_count_events_and_show_the_snapshot(service, config):  # noqa: F811
    with make_client(service, config) as client:
        wait_subscribed(service)
        for event in (
            verdict("picked", "bolt", 1800.0),
            verdict("picked", "nut", 2400.0),
            verdict("missed", "nut", 2600.0),
            PartFailed(track=1, cls="nut", attempts=3),
            AlarmRaised(alarm_id="A1", severity="fault", reason="arm stalled", hint="Reset"),
            AlarmRaised(alarm_id="A2", severity="warning", reason="history slow", hint="-"),
            located(captured_s_ago=0.080, located_s_ago=0.030),
        ):
            service.bus.emit(event)
        assert service.bus.wait_idle(10)
        reply = client.get("/metrics")
        assert reply.status_code == 200 and reply.headers["content-type"].startswith("text/plain; version=")
        got = samples(reply.text)
    picks = {k[1]: v for k, v in got.items() if k[0] == "cell_picks_total"}
    assert picks == {
        (("cls", "bolt"), ("outcome", "picked")): 1,
        (("cls", "nut"), ("outcome", "picked")): 1,
        (("cls", "nut"), ("outcome", "missed")): 1,
        (("cls", "nut"), ("outcome", "failed")): 1,
    }
    assert got[("cell_misses_total", ())] == 1 and got[("cell_faults_total", ())] == 1
    assert got[("cell_pick_cycle_seconds_count", ())] == 3
    assert got[("cell_pick_cycle_seconds_sum", ())] == pytest.approx(6.8)
    assert got[("cell_pick_cycle_seconds_bucket", (("le", "2.0"),))] == 1
    assert got[("cell_pick_cycle_seconds_bucket", (("le", "3.0"),))] == 3
    assert got[("cell_frame_latency_seconds_count", ())] == 1
    # capture to located: 50 ms, whatever the subscriber's queue added
    assert got[("cell_frame_latency_seconds_sum", ())] == pytest.approx(0.050, abs=0.004)
    assert got[("cell_state", (("cell_state", "Ready"),))] == 1
    assert got[("cell_state", (("cell_state", "Error"),))] == 0
    assert got[("cell_calibration_cv_rms_mm", ())] == pytest.approx(0.0101)
    assert got[("cell_shift_parts", (("counter", "picked_bolts"),))] == service.snapshot().counters.picked_of("bolt")
    assert got[("cell_subscriber_events_dropped_total", (("subscriber", "metrics"),))] == 0
    assert got[("cell_subscriber_events_delivered_total", (("subscriber", "metrics"),))] >= 7


def wait_subscribed(service) -> None:
    end = time.monotonic() + 10
    while "metrics" not in {s.name for s in service.bus.stats()}:
        assert time.monotonic() < end, "the metrics subscriber never subscribed"
        time.sleep(0.02)


def located(captured_s_ago: float, located_s_ago: float) -> FrameLocated:
    """A frame captured `captured_s_ago`, its parts located `located_s_ago` (the event's time)."""
    ref = FrameRef(1, np.zeros((4, 4, 3), np.uint8), None, time.monotonic() - captured_s_ago)
    return FrameLocated(
        frame=1,
        locate_ms=1.0,
        warnings=(),
        detections=(),
        ref=ref,
        time_utc=datetime.now(UTC) - timedelta(seconds=located_s_ago),
    )


def basic(user: str, password: str) -> dict[str, str]:
    return {"authorization": "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode()}


def test_metrics_follow_the_screen_s_access_rule(service, config):  # noqa: F811
    with make_client(service, config) as client:  # loopback, no password: open like the screen
        assert client.get("/metrics").status_code == 200
    with make_client(service, config, host="0.0.0.0", check=operator_pw7) as client:
        refused = client.get("/metrics")
        assert refused.status_code == 401 and refused.headers["www-authenticate"].startswith("Basic")
        assert "cell_picks" not in refused.text
        assert client.get("/metrics", headers=basic("operator", "wrong")).status_code == 401
        assert client.get("/metrics", headers={"authorization": "Basic !!!"}).status_code == 401
        ok = client.get("/metrics", headers=basic("operator", "pw-7"))
        assert ok.status_code == 200 and "cell_state" in ok.text
        assert client.post("/api/login", json={"user": "operator", "password": "pw-7"}).status_code == 200
        assert client.get("/metrics").status_code == 200  # a logged-in session reads it too
    web = WebConfig(view_without_password=True)
    with make_client(service, config, host="0.0.0.0", check=operator_pw7, web=web) as client:
        assert client.get("/metrics").status_code == 200  # viewing is open: so are the numbers


def test_two_screens_never_share_a_number(config):  # noqa: F811
    a, b = FakeLineService(), FakeLineService()
    try:
        with make_client(a, config) as ca, make_client(b, config) as cb:
            wait_subscribed(a)
            wait_subscribed(b)
            a.bus.emit(verdict("picked"))
            assert a.bus.wait_idle(10)
            picked = '{cls="bolt",outcome="picked"}'
            assert f"cell_picks_total{picked} 1.0" in ca.get("/metrics").text
            assert "cell_picks_total{" not in cb.get("/metrics").text
    finally:
        a.close()
        b.close()

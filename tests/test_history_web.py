"""The History page's routes over HTTP (TestClient on the fake line service, a real store):
filters and paging, the alarm list, images by row id, and nothing from a request reaching a path."""

from __future__ import annotations

import pytest
from starlette.testclient import TestClient

from cell.core.records import Alarm
from cell.web.app import build_app
from cell.web.auth import Access
from cell.web.config import WebConfig
from tests.fake_service import FakeLineService
from tests.history_helpers import JOB, T0, history_config
from tests.test_history import fill

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def setup(tmp_path):
    cfg = history_config(tmp_path)
    cfg.calibration.active_path = tmp_path / "calibration" / "active.json"
    fill(cfg).close()
    service = FakeLineService()
    app = build_app(service, cfg, WebConfig(), Access("127.0.0.1", WebConfig()))
    with TestClient(app, base_url="http://127.0.0.1:8080") as client:
        yield client, service, cfg
    service.close()


def test_the_page_and_its_script_are_served(setup):
    client, _, _ = setup
    page = client.get("/history")
    assert page.status_code == 200 and 'src="/static/history.js"' in page.text
    assert "default-src 'self'" in page.headers["content-security-policy"]
    assert client.get("/static/history.js").status_code == 200
    assert 'href="/history"' in client.get("/").text


def test_picks_filtered_and_paged(setup):
    client, _, _ = setup
    r = client.get("/api/history/picks", params={"shift": "2026-12-01/early", "limit": 2, "offset": 0}).json()
    assert r["total"] == 5 and [p["id"] for p in r["picks"]] == [f"{JOB}/1", f"{JOB}/2"]
    r = client.get("/api/history/picks", params={"shift": "2026-12-01/early", "limit": 2, "offset": 4}).json()
    assert [p["id"] for p in r["picks"]] == [f"{JOB}/6"]
    r = client.get("/api/history/picks", params={"outcome": "missed", "class": "nut", "job": JOB}).json()
    assert [p["id"] for p in r["picks"]] == [f"{JOB}/3"] and r["picks"][0]["image_id"]
    since = (T0.replace(second=3)).isoformat()
    assert client.get("/api/history/picks", params={"since": since}).json()["total"] == 3
    assert client.get("/api/history/picks", params={"shift": "2026-12-01/late"}).json()["total"] == 0


@pytest.mark.parametrize(
    "params, message",
    [
        ({"shift": "2026-12-01/lunch"}, "no shift 'lunch'"),
        ({"since": "yesterday"}, "since: an ISO 8601 time"),
        ({"outcome": "stolen"}, "outcome: one of"),
        ({"limit": "100000"}, "limit: a whole number 1-200"),
        ({"job": "../../etc/passwd"}, "job: letters, digits"),
    ],
)
def test_bad_filters_are_refused_saying_what(setup, params, message):
    client, _, _ = setup
    r = client.get("/api/history/picks", params=params)
    assert r.status_code == 400 and message in r.json()["error"]


def test_alarms_active_first_then_history_with_who_reset_each(setup):
    client, service, _ = setup
    service.alarm = Alarm("camera moved 0.3 mm", "recalibrate", T0, "A7", "fault", "job")
    r = client.get("/api/history/alarms").json()
    assert [a["reason"] for a in r["active"]] == ["camera moved 0.3 mm"]
    (old,) = r["history"]
    assert old["reason"] == "arm stalled" and (old["cleared_user"], old["cleared_interface"]) == ("anna", "screen")


def test_images_come_by_row_id_only(setup):
    client, _, cfg = setup
    pick = client.get("/api/history/picks", params={"outcome": "failed"}).json()["picks"][0]
    for which in ("frame.png", "annotated.png"):
        r = client.get(f"/api/history/image/{pick['image_id']}/{which}")
        assert r.status_code == 200 and r.headers["content-type"] == "image/png" and r.content[:4] == b"\x89PNG"
    (cfg.history.data_dir / "secret.png").write_bytes(b"\x89PNG secret")
    for path in (
        "/api/history/image/..%2F..%2Fsecret/frame.png",
        "/api/history/image/0123456789abcdef0123/frame.png",  # well formed, no such row
        f"/api/history/image/{pick['image_id']}/..%2F..%2Fsecret.png",
        "/api/history/image/secret/frame.png",
    ):
        r = client.get(path)
        assert r.status_code == 404 and b"secret" not in r.content


def test_history_needs_the_view_right(tmp_path):
    cfg = history_config(tmp_path)
    fill(cfg).close()
    service = FakeLineService()
    web = WebConfig()
    access = Access("0.0.0.0", web, lambda user, password: password == "pw-12345678")
    with TestClient(build_app(service, cfg, web, access), base_url="http://127.0.0.1:8080") as client:
        for path in ("/api/history/picks", "/api/history/alarms", "/api/history/image/0123456789abcdef0123/frame.png"):
            assert client.get(path).status_code == 401
    service.close()


def test_a_store_that_cannot_be_read_is_a_clear_503(tmp_path):
    cfg = history_config(tmp_path)  # nothing written: no database file
    service = FakeLineService()
    app = build_app(service, cfg, WebConfig(), Access("127.0.0.1", WebConfig()))
    with TestClient(app, base_url="http://127.0.0.1:8080") as client:
        r = client.get("/api/history/picks")
        assert r.status_code == 503 and "does not exist" in r.json()["error"]
    service.close()

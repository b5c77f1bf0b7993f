"""The screen's server in its thread (uvicorn on a real socket) on the fake line service:
server-sent events reach two screens, frames arrive as JPEG, stopping leaves nothing behind."""

from __future__ import annotations

import base64
import json
import socket
import threading
import time

import httpx
import pytest

from cell.config import CellConfig
from cell.errors import ConfigError
from cell.web.config import WebConfig
from cell.web.server import WebServer
from tests.fake_service import FakeLineService
from tests.serve_process import free_port

pytestmark = pytest.mark.timeout(60)  # real sockets and threads: never hang the suite


@pytest.fixture
def service():
    s = FakeLineService(interval_s=0.05)
    yield s
    s.close()


@pytest.fixture
def server(service):
    srv = WebServer(service, CellConfig(), WebConfig(), "127.0.0.1", 0)
    srv.start()
    yield srv
    srv.stop()


def read_events(url: str, want: set[str], timeout_s: float = 10.0) -> dict[str, list[dict]]:
    """Events from the stream until each kind in `want` has come at least once."""
    got: dict[str, list[dict]] = {}
    deadline = time.monotonic() + timeout_s
    with httpx.stream("GET", url + "api/events", timeout=timeout_s) as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        kind = None
        for line in r.iter_lines():
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: "):
                got.setdefault(kind, []).append(json.loads(line[6:]))
                if want <= got.keys():
                    return got
            assert time.monotonic() < deadline, f"only {sorted(got)} within {timeout_s} s"
    return got


def test_two_screens_see_the_same_state_and_frames(server, service):
    token = httpx.get(server.url + "api/session").json()["csrf"]
    r = httpx.post(server.url + "api/command/StartContinuous", headers={"x-csrf-token": token})
    assert r.status_code == 200
    results = [None, None]

    def watch(i):
        results[i] = read_events(server.url, {"state", "frame"})

    threads = [threading.Thread(target=watch, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=15)
    for got in results:
        assert got["state"][0]["vision_state"] == "ContinuousExecution"
        frame = got["frame"][0]
        assert base64.b64decode(frame["jpeg_b64"])[:2] == b"\xff\xd8"
        assert abs(frame["capture_wall_ms"] - 1e3 * time.time()) < 10_000


def test_stop_ends_streams_and_threads_and_unsubscribes(service):
    before = {t.name for t in threading.enumerate()}
    srv = WebServer(service, CellConfig(), WebConfig(), "127.0.0.1", 0)
    srv.start()
    assert service.listeners == 3  # the screen: its state, its frames and /metrics, each a subscriber of its own
    stream_ended = threading.Event()

    def hold_stream():
        with httpx.stream("GET", srv.url + "api/events", timeout=10) as r:
            for _ in r.iter_lines():
                pass
        stream_ended.set()

    t = threading.Thread(target=hold_stream)
    t.start()
    deadline = time.monotonic() + 30
    while not srv.app.screen.hub.screens:  # the stream is open on the server
        assert time.monotonic() < deadline, "the event stream never opened"
        time.sleep(0.02)
    srv.stop()  # ends the open stream rather than waiting for it
    t.join(timeout=30)
    assert stream_ended.is_set() and service.listeners == 0
    assert {t.name for t in threading.enumerate()} - before == set()
    with pytest.raises(httpx.ConnectError):
        httpx.get(srv.url, timeout=2)


def test_port_in_use_is_a_clear_error(service):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ConfigError, match=f"cannot listen on 127.0.0.1:{port}"):
            WebServer(service, CellConfig(), WebConfig(), "127.0.0.1", port)


def test_non_loopback_without_password_refused_before_binding(service):
    with pytest.raises(ConfigError, match="without a password"):
        WebServer(service, CellConfig(), WebConfig(), "0.0.0.0", 0)


@pytest.mark.parametrize("where", ["hash", "env"])
def test_screen_uses_the_services_user_and_password(service, monkeypatch, tmp_path, where):
    import ssl

    from cell.service.security import hash_password
    from cell.web.server import screen_server

    config = CellConfig()
    config.service.http_port = free_port()
    config.service.certificate_dir = tmp_path  # with users the screen is HTTPS only (issue 21): its certificate
    config.service.login.backoff_first_s = 0  # the wrong password below would hold the right one back 1 s
    config.service.user = "operator"
    if where == "hash":
        config.service.password_hash = hash_password("line-4", iterations=1000)
    else:
        config.service.password_env = "CELL_TEST_SCREEN_PW"
        monkeypatch.setenv("CELL_TEST_SCREEN_PW", "line-4")
    srv = screen_server(service, config)
    srv.start()
    try:
        assert srv.url.startswith("https://")
        trust = ssl.create_default_context(cafile=str(tmp_path / "screen-cert.pem"))
        with httpx.Client(base_url=srv.url, timeout=10, verify=trust) as c:
            assert c.get("api/state").status_code == 401
            assert c.post("api/login", json={"user": "operator", "password": "line-5"}).status_code == 401
            token = c.post("api/login", json={"user": "operator", "password": "line-4"}).json()["csrf"]
            assert c.get("api/state").status_code == 200
            assert c.post("api/command/StartSingleJob", headers={"x-csrf-token": token}).status_code == 200
    finally:
        srv.stop()


def test_screen_beyond_loopback_without_credentials_is_refused(service):
    from cell.web.server import screen_server

    config = CellConfig()
    config.service.host = "0.0.0.0"
    with pytest.raises(ConfigError, match="beyond loopback"):
        screen_server(service, config)

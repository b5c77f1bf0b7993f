"""The screen's server in its thread (uvicorn on a real socket) on the fake line service:
server-sent events reach two screens, frames arrive as JPEG, stopping leaves nothing behind."""

from __future__ import annotations

import base64
import json
import socket
import threading
import time
from datetime import datetime

import httpx
import pytest

from cell.config import CellConfig
from cell.errors import ConfigError
from cell.web.config import WebConfig
from cell.web.server import WebServer
from tests.fake_service import FakeLineService
from tests.ports import free_port

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


def frames_until(url: str, done, timeout_s: float = 15.0) -> list[dict]:
    """The stream's frames, in order, until `done(frames)` holds."""
    frames: list[dict] = []
    deadline = time.monotonic() + timeout_s
    with httpx.stream("GET", url + "api/events", timeout=timeout_s) as r:
        kind = None
        for line in r.iter_lines():
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: ") and kind == "frame":
                frames.append(json.loads(line[6:]))
                if done(frames):
                    return frames
            assert time.monotonic() < deadline, f"{len(frames)} frames within {timeout_s} s: not done"
    return frames


def test_live_frames_between_jobs_and_the_jobs_own_frames_while_it_runs(service):
    srv = WebServer(service, CellConfig(), WebConfig(live_interval_s=0.1), "127.0.0.1", 0)
    srv.start()
    try:
        idle = frames_until(srv.url, lambda f: len(f) >= 2)  # Ready: a live frame at once, then one per interval
        assert all(f["live"] for f in idle) and idle[1]["seq"] > idle[0]["seq"]
        assert datetime.fromisoformat(idle[1]["captured_utc"]) >= datetime.fromisoformat(idle[0]["captured_utc"])
        assert base64.b64decode(idle[0]["jpeg_b64"])[:2] == b"\xff\xd8"
        token = httpx.get(srv.url + "api/session").json()["csrf"]
        httpx.post(srv.url + "api/command/StartContinuous", headers={"x-csrf-token": token})
        running = frames_until(srv.url, lambda f: sum(not x["live"] for x in f) >= 5)
        first_job = next(i for i, f in enumerate(running) if not f["live"])
        assert not any(f["live"] for f in running[first_job:])  # while it runs, only the job's frames
        httpx.post(srv.url + "api/command/Pause", headers={"x-csrf-token": token})
        frames_until(srv.url, lambda f: f[-1]["live"])  # paused at rest: the live view again
        assert service.previews >= 3
    finally:
        srv.stop()


def test_the_camera_check_reads_live_frames_while_it_is_on(service):
    srv = WebServer(service, CellConfig(), WebConfig(live_interval_s=0.1), "127.0.0.1", 0)
    srv.start()
    try:
        token = httpx.get(srv.url + "api/session").json()["csrf"]
        assert httpx.post(srv.url + "api/camera-check", json={"on": True}).status_code == 403  # no CSRF token
        r = httpx.post(srv.url + "api/camera-check", json={"on": True}, headers={"x-csrf-token": token})
        assert r.json() == {"ok": True, "on": True} and httpx.get(srv.url + "api/state").json()["camera_check"]
        checked = frames_until(srv.url, lambda f: len(f) >= 3 and "check" in f[-1])[-1]["check"]
        assert checked["focus"] > 0 and checked["focus_best"] >= checked["focus"]
        assert abs(sum(checked["exposure"]["histogram"]) - 1.0) < 1e-3
        assert checked["plate"] is None and checked["advice"][0].startswith("plate: not in view")  # a table, no plate
        httpx.post(srv.url + "api/camera-check", json={"on": False}, headers={"x-csrf-token": token})
        assert not httpx.get(srv.url + "api/state").json()["camera_check"]
        assert "check" not in frames_until(srv.url, lambda f: len(f) >= 2)[-1]
    finally:
        srv.stop()


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


def test_stop_ends_a_stream_whose_reader_takes_nothing_without_a_traceback(service, caplog):
    """A browser that stopped reading leaves its stream stuck in a send: stopping the server resets
    that connection and the stream ends cleanly, with no error logged (uvicorn would wait out its
    grace period, cancel the stream and log a traceback for it)."""
    from cell.core.commands import Command

    srv = WebServer(service, CellConfig(), WebConfig(send_buffer_kb=16), "127.0.0.1", 0)
    srv.start()
    reader = socket.create_connection(("127.0.0.1", srv.port), timeout=10)
    try:
        reader.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        reader.sendall(b"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")  # and never read
        service.command(Command.START_CONTINUOUS)  # frames for the screen, far more than it takes
        connections = srv.serving.server.server_state.connections
        deadline = time.monotonic() + 30
        while not any(c.flow.write_paused for c in list(connections)):
            assert time.monotonic() < deadline, "the stream never filled its send buffer"
            time.sleep(0.02)
        with caplog.at_level("WARNING"):
            srv.stop()
        assert not srv.app.screen.hub.screens, "the stuck stream did not end"
        logged = [f"{r.name}: {r.getMessage()}" for r in caplog.records if r.levelname in ("WARNING", "ERROR")]
        assert logged == [], logged
    finally:
        reader.close()
        srv.stop()


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

    from cell.access.security import hash_password
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


def test_frames_are_drawn_only_while_a_screen_can_take_one(service):
    """A screen whose stream is stuck in a send (a slow or gone reader) asks for no frame: after the
    one it was given nothing more is drawn, however many the cell locates; once it has sent that
    frame (`want_frame`, as the stream does), the next is drawn."""
    import asyncio

    from cell.core.commands import Command
    from cell.core.events import FrameLocated
    from cell.web.hub import Hub

    loop = asyncio.new_event_loop()
    runner = threading.Thread(target=loop.run_forever, daemon=True)
    runner.start()
    hub = Hub(service, 960, 80, 4, max_frame_rate_hz=0.0)  # every frame a screen can take, none withheld by rate
    located = []
    sub = service.subscribe("located", located.append, kinds=(FrameLocated,))
    try:
        hub.start(loop)

        async def open_one():
            return hub.open_screen()

        screen = asyncio.run_coroutine_threadsafe(open_one(), loop).result(10)
        assert screen is not None
        service.command(Command.START_CONTINUOUS)
        deadline = time.monotonic() + 30
        while len(located) < 12 or hub.frames_drawn < 1:
            assert time.monotonic() < deadline, f"{len(located)} frames located, {hub.frames_drawn} drawn in 30 s"
            time.sleep(0.02)
        assert hub.frames_drawn == 1, f"{hub.frames_drawn} frames drawn for a screen that took one"
        hub.want_frame()  # the stream handed its frame to the socket and waits for the next
        while hub.frames_drawn < 2:
            assert time.monotonic() < deadline, "no frame drawn once the screen asked for one"
            time.sleep(0.02)
        assert sub.wait_idle(10)

        # the same for the state: a screen stuck in a send gets no new snapshot taken for it
        screen.sending = True
        taken = hub.snapshots_taken
        while len(located) < 40:  # the job goes on changing state many times
            assert time.monotonic() < deadline + 30, "the job stopped locating frames"
            time.sleep(0.02)
        # one snapshot may have been on its way when the screen got stuck; none after it
        assert hub.snapshots_taken - taken <= 1, "snapshots taken for a screen that cannot take them"
        screen.sending = False
        hub.screen_idle()  # the stream sent what it had and waits again
        while hub.snapshots_taken == taken:
            assert time.monotonic() < deadline + 60, "no snapshot taken once the screen could take one"
            time.sleep(0.02)
    finally:
        hub.close()
        loop.call_soon_threadsafe(loop.stop)
        runner.join(10)
        loop.close()

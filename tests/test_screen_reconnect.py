"""The real page (cell/web/static) in headless Chromium comes back by itself after its event stream
is refused (503: every screen slot taken) or dropped by the server (issue 21: it used to say
"connection lost, retrying" and stay dead until reloaded).

The page is served by a small app through the screen's transport, whose /api/events refuses or
ends streams on cue; the rest of the screen is not needed for this."""

from __future__ import annotations

import asyncio
import json
from importlib import resources

import pytest
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response, StreamingResponse
from starlette.routing import Route

from cell.web.transport import ServerThread, TransportLimits
from tests.browser import launch, why_no_browser

pytestmark = [
    pytest.mark.skipif(why_no_browser() is not None, reason=str(why_no_browser())),
    pytest.mark.slow,
    pytest.mark.timeout(120),
]

STATE = {
    "display": {"key": "ready", "label": "Ready"},
    "vision_state": "Ready",
    "cell_state": "IDLE",
    "paused": False,
    "waiting_for_parts": False,
    "counters": {},
    "parts_per_min": 0.0,
    "last_picks": [],
    "alarm": None,
    "calibration": None,
    "heartbeat": 0,
    "allowed": [],
    "recalibration_allowed": False,
    "recalibration_open": False,
}


class Cue:
    """What /api/events does next: refuse the next `refuse` requests; `drop()` ends the open streams."""

    def __init__(self) -> None:
        self.refuse = 0
        self.generation = 0
        self.requests = 0
        self.refused = 0

    def drop(self) -> None:
        self.generation += 1


def page_app(cue: Cue) -> Starlette:
    static = resources.files("cell.web") / "static"
    files = {"/": ("index.html", "text/html"), "/static/screen.js": ("screen.js", "text/javascript")}
    files["/static/screen.css"] = ("screen.css", "text/css")

    async def page(request: Request) -> Response:
        name, kind = files[request.url.path]
        return Response((static / name).read_bytes(), media_type=kind)

    async def session(request: Request) -> JSONResponse:
        return JSONResponse({"login_required": False, "logged_in": False, "can_view": True, "can_control": False})

    async def events(request: Request) -> Response:
        cue.requests += 1
        if cue.refuse > 0:
            cue.refuse -= 1
            cue.refused += 1
            return JSONResponse({"error": "16 screens are already open"}, status_code=503)

        generation = cue.generation

        async def stream():
            beat = 0
            while cue.generation == generation:  # the server ends the stream when told to
                yield f"event: state\ndata: {json.dumps({**STATE, 'heartbeat': beat})}\n\n"
                beat += 1
                await asyncio.sleep(0.2)

        return StreamingResponse(stream(), media_type="text/event-stream")

    routes = [Route(path, page) for path in files]
    return Starlette(routes=routes + [Route("/api/session", session), Route("/api/events", events)])


@pytest.fixture
def served():
    cue = Cue()
    server = ServerThread(page_app(cue), "127.0.0.1", 0, TransportLimits())
    server.start()
    yield server.url, cue
    server.stop()


def test_the_page_reconnects_after_503_and_after_the_server_drops_it(served):
    from playwright.sync_api import sync_playwright

    url, cue = served
    cue.refuse = 2  # every screen slot taken at first
    with sync_playwright() as p:
        browser = launch(p)
        try:
            page = browser.new_page()
            page.goto(url)
            page.wait_for_function("window.screenStats.states > 0", timeout=30_000)
            assert cue.refused == 2 and page.evaluate("window.screenStats.retries") >= 2
            assert page.text_content("#link") == "live"

            before = cue.requests
            cue.refuse = 1
            cue.drop()  # the server ends the stream, then refuses the next try
            seen = page.evaluate("window.screenStats.states")
            page.wait_for_function(f"window.screenStats.states > {seen} + 5", timeout=60_000)
            assert cue.requests >= before + 2  # dropped, refused, and connected again: no reload
            assert page.text_content("#link") == "live"
        finally:
            browser.close()

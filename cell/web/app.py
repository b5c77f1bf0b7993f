"""The operator screen's routes (Starlette). Every request is checked by `Access`; controls
are POSTs that go to the service's command table and nowhere else."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import threading
from collections.abc import AsyncIterator, Callable
from importlib import resources
from typing import Any

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import JSONResponse, Response, StreamingResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from cell.asyncwait import wait_event
from cell.config import CellConfig
from cell.core.api import LineServiceAPI
from cell.core.commands import Command, CommandRefused, RecipeRequest, Refusal
from cell.core.events import Origin
from cell.core.records import Snapshot
from cell.errors import REPORTED_ERRORS, CalibrationRejected
from cell.recipes import RecipeBook, RecipeError
from cell.web.auth import CSRF_HEADER, SESSION_COOKIE, Access
from cell.web.camera_check import CameraCheck
from cell.web.config import WebConfig
from cell.web.history import HistoryRoutes
from cell.web.hub import EncodedFrame, Hub, Screen
from cell.web.metrics import CellMetrics, metrics_refused, metrics_response
from cell.web.recalibration import Busy, NotInstalled, RecalibrationDesk, Report
from cell.web.shield import set_on_disconnect
from cell.web.teaching import TeachRoutes
from cell.web.views import COMMANDS, snapshot_json
from cell.web.words import calibration_words

log = logging.getLogger(__name__)

STATIC = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/static/screen.css": ("screen.css", "text/css; charset=utf-8"),
    "/static/screen.js": ("screen.js", "text/javascript; charset=utf-8"),
    "/static/no-frame.svg": ("no-frame.svg", "image/svg+xml"),
}
SECURITY_HEADERS = [
    (
        b"content-security-policy",
        b"default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
        b"connect-src 'self'; frame-ancestors 'none'; form-action 'self'; base-uri 'none'",
    ),
    (b"x-frame-options", b"DENY"),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
    (b"cache-control", b"no-store"),
]
REFUSAL_STATUS = {  # a refused command's HTTP status
    Refusal.INVALID_STATE: 409,
    Refusal.ACCESS_DENIED: 403,
    Refusal.SHUTTING_DOWN: 503,
    Refusal.BAD_ARGUMENT: 422,
    Refusal.NOT_RECORDED: 503,
}
KEEPALIVE_S = 3.0  # a stream that heard nothing sends the last state again (the hub sends one a second)
PICTURES = {"plate.jpg": "image/jpeg", "deviation.png": "image/png"}


def _error(status: int, message: str, **extra: object) -> JSONResponse:
    return JSONResponse({"error": message, **extra}, status_code=status)


def _refused(status: int, message: str, **extra: Any) -> JSONResponse:
    """A refused recalibration: the technical message (`error`) and, for the page, operator words
    (`say`, `do`) with that message as their `details`."""
    return _error(status, message, **calibration_words(message).as_json(), **extra)


def _recipe_list(book: RecipeBook | None) -> list[dict[str, Any]]:
    """The recipe files as the page lists them (an invalid one with its error, never chosen)."""
    listed = []
    for info in book.list() if book is not None else []:
        description, error = "", info.error
        if not error:
            try:
                description = book.load(info.recipe_id).description  # type: ignore[union-attr]
            except RecipeError as e:
                error = str(e)
        listed.append(
            {"id": info.recipe_id, "description": description, "products": list(info.products), "error": error}
        )
    return listed


class Guard:
    """Pure-ASGI middleware: Host check (DNS rebinding) and the security headers on every reply."""

    def __init__(self, app: ASGIApp, screen: ScreenApp):
        self.app, self.screen, self.access = app, screen, screen.access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        host = dict(scope["headers"]).get(b"host", b"").decode("latin-1")
        if not self.access.host_ok(host):
            reply = _error(421, f"Host {host!r} is not this screen's loopback address")
            return await reply(scope, receive, self._secure(send))
        return await self.app(scope, receive, self._secure(send))

    @staticmethod
    def _secure(send: Send) -> Send:
        async def wrapped(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": list(message.get("headers", [])) + SECURITY_HEADERS}
            await send(message)

        return wrapped


class ScreenApp:
    """Routes bound to one service, one access policy and one recalibration desk."""

    def __init__(self, service: LineServiceAPI, config: CellConfig, web: WebConfig, access: Access):
        self.service, self.web, self.access = service, web, access
        self.check = CameraCheck(config)
        self.hub = Hub(
            service,
            web.frame_max_width_px,
            web.jpeg_quality,
            web.max_screens,
            web.live_interval_s,
            self.check,
            web.max_frame_rate_hz,
        )
        self.desk = RecalibrationDesk(service, config, web.report_timeout_s)
        self.metrics = CellMetrics(service)  # /metrics (Prometheus); its own registry
        pkg = resources.files("cell.web") / "static"
        self.static = {route: ((pkg / name).read_bytes(), kind) for route, (name, kind) in STATIC.items()}
        self.max_upload = int(web.max_upload_mb * 1024 * 1024)
        # Every open stream sends the same text: each state and frame is serialised once, not once per
        # screen (30 screens would otherwise cost 30 JSON encodings per state change; on the loop only).
        self._sent_state: tuple[tuple[object, ...], str] | None = None
        self._sent_frame: tuple[EncodedFrame, str] | None = None
        self.history = HistoryRoutes(self._view_refused, service, config)  # the History page and alarm list
        self.teach = TeachRoutes(service, config, web, self._view_refused, self._controller, self._read_body)

    # ---- checks ----------------------------------------------------------------------
    @staticmethod
    def _sid(request: Request) -> str | None:
        return request.cookies.get(SESSION_COOKIE)

    def _view_refused(self, request: Request) -> Response | None:
        if not self.access.may_view(self._sid(request)):
            return _error(401, "log in to watch the cell")
        return None

    def _controller(self, request: Request) -> Origin | Response:
        """Who sends this control (the logged-in user with their role; without logins, anyone on this PC, with
        every right: Access.origin), or the refusal when the request may not control at all (`_control_refused`).
        Nobody without a session may do anything, Halt included (issue 28)."""
        if refused := self._control_refused(request):
            return refused
        address = request.client.host if request.client else ""
        origin = self.access.origin(self._sid(request), address)
        if origin is None:
            return _error(401, "log in to control the cell")
        return origin

    def _refusal(self, command: Command, origin: Origin, **kw: Any) -> Response | None:
        """The command table's refusal of an interface's own step (service.authorize), as the screen answers it."""
        try:
            self.service.authorize(command, origin, **kw)
        except CommandRefused as e:
            return _error(REFUSAL_STATUS[e.reason], str(e), refusal=e.reason.value)
        return None

    def web_user(self, request: Request) -> str:
        return "operator" if self.access.login_required and self.access.session(self._sid(request)) else ""

    def _control_refused(self, request: Request) -> Response | None:
        """Same origin, logged in where a password is set, and this session's CSRF token."""
        origin = request.headers.get("origin")
        if origin is not None and origin != f"{request.url.scheme}://{request.headers.get('host', '')}":
            return _error(403, f"cross-origin request from {origin!r} refused")
        if request.headers.get("sec-fetch-site", "same-origin") not in ("same-origin", "none"):
            return _error(403, "cross-site request refused")
        sid = self._sid(request)
        if not self.access.may_control(sid):
            return _error(401, "log in to control the cell")
        if not self.access.csrf_ok(sid, request.headers.get(CSRF_HEADER)):
            return _error(403, "missing or wrong CSRF token: reload the page")
        return None

    # ---- pages and session -----------------------------------------------------------
    async def static_file(self, request: Request) -> Response:
        body, kind = self.static[request.url.path]
        return Response(body, media_type=kind)

    async def session(self, request: Request) -> Response:
        sid = self._sid(request)
        can_control = self.access.may_control(sid)
        return JSONResponse(
            {
                "login_required": self.access.login_required,
                "logged_in": self.access.session(sid) is not None,
                "can_view": self.access.may_view(sid),
                "can_control": can_control,
                "csrf": self.access.csrf_for(sid) if can_control else None,
            }
        )

    async def login(self, request: Request) -> Response:
        origin = request.headers.get("origin")
        if origin is not None and origin != f"{request.url.scheme}://{request.headers.get('host', '')}":
            return _error(403, f"cross-origin login from {origin!r} refused")
        if not self.access.login_required:
            return _error(400, "this screen has no password")
        body = await self._read_body(request, 4096)
        if isinstance(body, Response):
            return body
        try:
            sent = json.loads(body)
            user, password = sent["user"], sent["password"]
            if not (isinstance(user, str) and isinstance(password, str)):
                raise TypeError("user and password must be strings")
        except (ValueError, KeyError, TypeError):
            return _error(400, 'send JSON {"user": "...", "password": "..."}')
        address = request.client.host if request.client else "?"
        result = await run_in_threadpool(self.access.login, user, password, address)  # throttled (issue 21)
        if result.retry_after_s > 0:
            wait = max(1, round(result.retry_after_s))
            return JSONResponse(
                {"error": f"too many failed logins: try again in {wait} s"}, 429, {"retry-after": str(wait)}
            )
        if result.role is None:
            log.warning("screen: failed login from %s", address)
            return _error(401, "wrong user or password")
        sid, csrf = self.access.new_session(user, result.role, result.credential)  # ends if the user changes
        log.info("screen: login of %s (%s) from %s", user, result.role.value, address)
        reply = JSONResponse({"csrf": csrf})
        reply.set_cookie(
            SESSION_COOKIE, sid, max_age=int(self.web.session_h * 3600), httponly=True, samesite="strict", path="/"
        )
        return reply

    async def logout(self, request: Request) -> Response:
        if refused := self._control_refused(request):
            return refused
        self.access.end_session(self._sid(request))
        reply = JSONResponse({"ok": True})
        reply.delete_cookie(SESSION_COOKIE, path="/")
        return reply

    # ---- state and frames ------------------------------------------------------------
    def _state(self, snapshot: Snapshot | None = None) -> dict[str, Any]:
        snapshot = snapshot or self.service.snapshot()
        state = snapshot_json(
            snapshot, self.desk.open is not None, self.desk.has_pictures(snapshot.calibration), self.service.parts
        )
        state["camera_check"] = self.check.on and self.web.live_interval_s > 0
        return state

    async def state(self, request: Request) -> Response:
        return self._view_refused(request) or JSONResponse(self._state())

    def _state_event(self, snapshot: Snapshot | None) -> str:
        """The `state` event for `snapshot` (None: the last one the hub sent, again), serialised once
        for every stream that sends it."""
        if snapshot is None:
            snapshot = self.hub.latest_snapshot or self.service.snapshot()
        key = (snapshot, self.desk.open, self.desk.active_pictures, self.check.on)
        cached = self._sent_state
        if cached is None or any(a is not b for a, b in zip(cached[0], key, strict=True)):
            cached = self._sent_state = (key, _sse("state", self._state(snapshot)))
        return cached[1]

    def _frame_event(self, frame: EncodedFrame) -> str:
        """The `frame` event, base64 and JSON made once per frame for every stream."""
        if self._sent_frame is None or self._sent_frame[0] is not frame:
            self._sent_frame = (frame, _sse("frame", frame.event_json()))
        return self._sent_frame[1]

    async def frame_jpeg(self, request: Request) -> Response:
        if refused := self._view_refused(request):
            return refused
        latest = self.hub.latest
        if latest is None:
            return _error(404, "no frame captured yet")
        return Response(latest.jpeg, media_type="image/jpeg", headers={"x-frame-seq": str(latest.seq)})

    async def events(self, request: Request) -> Response:
        """Server-sent events: `state` on every change (and each second), `frame` per new JPEG."""
        if refused := self._view_refused(request):
            return refused
        screen = self.hub.open_screen()
        if screen is None:
            return _error(503, f"{self.web.max_screens} screens are already open (service.web.max_screens)")
        return StreamingResponse(
            self._stream(screen, self._sid(request)),
            media_type="text/event-stream",
            headers={"x-accel-buffering": "no"},
        )

    async def _stream(self, screen: Screen, sid: str | None) -> AsyncIterator[str]:
        try:
            sent_seq = -1
            while not screen.closed:
                await wait_event(screen.wake, KEEPALIVE_S)
                screen.wake.clear()
                if screen.closed or not self.access.may_view(sid):  # logged out, or the user removed or changed
                    break
                snapshot, screen.snapshot = screen.snapshot, None
                screen.sending = True  # each yield returns once its event is handed to the socket
                yield self._state_event(snapshot)
                frame, screen.frame = screen.frame, None
                if frame is not None and frame.seq != sent_seq:
                    sent_seq = frame.seq
                    yield self._frame_event(frame)
                screen.sending = False
                if frame is not None:
                    self.hub.want_frame()  # a stream stuck in a send (a slow reader) asks for none
                self.hub.screen_idle()
        finally:
            self.hub.close_screen(screen)

    # ---- controls --------------------------------------------------------------------
    async def command(self, request: Request) -> Response:
        origin = self._controller(request)
        if isinstance(origin, Response):
            return origin
        command = COMMANDS.get(request.path_params["name"])
        if command is None:
            return _error(404, "unknown command", known=sorted(COMMANDS))
        try:
            self.service.command(command, origin)
        except CommandRefused as e:
            return _error(REFUSAL_STATUS[e.reason], str(e), refusal=e.reason.value)
        log.info("screen: %s accepted", command.value)
        return JSONResponse({"ok": True, "command": command.value})

    async def recal_capture(self, request: Request) -> Response:
        """CapturePlate: the service checks the role and the state before the camera is touched."""
        origin = self._controller(request)
        if isinstance(origin, Response):
            return origin
        return await self._recal(self.desk.from_camera, origin)

    async def recal_upload(self, request: Request) -> Response:
        """Checked as CapturePlate (role, then the cell at rest) before the body is read: refused, nothing is
        decoded, fitted or held (issue 28)."""
        origin = self._controller(request)
        if isinstance(origin, Response):
            return origin
        try:
            self.desk.authorize_upload(origin)
        except CommandRefused as e:
            return _refused(REFUSAL_STATUS[e.reason], str(e), refusal=e.reason.value)
        body = await self._read_body(request, self.max_upload, _refused)
        if isinstance(body, Response):
            return body
        gone = threading.Event()  # the decode stops when the client goes (issue 21)
        watcher = asyncio.create_task(set_on_disconnect(request.receive, gone))
        try:
            return await self._recal(self.desk.from_upload, body, origin, gone)
        finally:
            watcher.cancel()

    async def _recal(self, make: Callable[..., Report], *args: object) -> Response:
        try:
            report = await run_in_threadpool(make, *args)
        except CommandRefused as e:
            return _refused(REFUSAL_STATUS[e.reason], str(e), refusal=e.reason.value)
        except Busy as e:
            return _refused(409, str(e))
        except REPORTED_ERRORS as e:  # no plate, bad image, or the camera failed
            return _refused(422, f"{e}; the active calibration is unchanged")
        self.hub.publish_now()  # every screen: Start and Resume wait for the answer
        summary = report.summary_json()
        if report.gate_failure:
            summary["gate_words"] = calibration_words(report.gate_failure).as_json()
        return JSONResponse(summary)

    async def recal_picture(self, request: Request) -> Response:
        if refused := self._view_refused(request):
            return refused
        kind = request.path_params["kind"]
        if kind not in PICTURES:
            return _error(404, "no such picture", known=sorted(PICTURES))
        try:
            report = self.desk.report(request.path_params["report_id"])
        except Busy as e:
            return _error(404, str(e))
        return Response(report.plate_jpeg if kind == "plate.jpg" else report.deviation_png, media_type=PICTURES[kind])

    async def recal_answer(self, request: Request) -> Response:
        """Accept (InstallCalibration: role and state checked before the file is written) or reject (its role)."""
        origin = self._controller(request)
        if isinstance(origin, Response):
            return origin
        report_id, answer = request.path_params["report_id"], request.path_params["answer"]
        if answer not in ("accept", "reject"):
            return _error(404, "answer accept or reject")
        try:
            if answer == "reject":
                await run_in_threadpool(self.desk.reject, report_id, origin)
                self.hub.publish_now()
                return JSONResponse({"ok": True, "accepted": False})
            info = await run_in_threadpool(self.desk.accept, report_id, origin)
        except Busy as e:
            return _refused(409, str(e))
        except CalibrationRejected as e:
            return _refused(422, str(e))
        except CommandRefused as e:  # nothing written
            return _refused(REFUSAL_STATUS[e.reason], str(e), refusal=e.reason.value)
        except NotInstalled as e:
            return _refused(REFUSAL_STATUS[e.refusal.reason], str(e), refusal=e.refusal.reason.value)
        except (*REPORTED_ERRORS, OSError) as e:
            return _refused(500, f"accepting failed: {e}")
        self.hub.publish_now()
        return JSONResponse({"ok": True, "accepted": True, "model": info.model})

    async def calibration_picture(self, request: Request) -> Response:
        """The active calibration's numbered plate and deviation plot, when it was made on this screen."""
        if refused := self._view_refused(request):
            return refused
        kind = request.path_params["kind"]
        if kind not in PICTURES:
            return _error(404, "no such picture", known=sorted(PICTURES))
        if not self.desk.has_pictures(self.service.snapshot().calibration):
            return _error(404, "no report pictures for the calibration in use (not made on this screen since start)")
        return Response(self.desk.active_pictures[kind], media_type=PICTURES[kind])

    async def camera_check(self, request: Request) -> Response:
        """Switch the camera check on the live view on or off (`{"on": true}`): commissioning the camera, CapturePlate's
        role (engineer) in the command table, checked first (issue 28)."""
        origin = self._controller(request)
        if isinstance(origin, Response):
            return origin
        if refused := self._refusal(Command.CAPTURE_PLATE, origin, state=False):
            return refused
        body = await self._read_body(request, 256)
        if isinstance(body, Response):
            return body
        try:
            on = json.loads(body)["on"]
            if not isinstance(on, bool):
                raise TypeError("on must be true or false")
        except (ValueError, KeyError, TypeError):
            return _error(400, 'send JSON {"on": true} or {"on": false}')
        if on and self.web.live_interval_s <= 0:
            return _error(409, "the live view is off (service.web.live_interval_s = 0): no frames to check")
        self.check.switch(on)
        if on:
            self.hub.live_now()
        self.hub.publish_now()
        log.info("screen: camera check %s", "on" if on else "off")
        return JSONResponse({"ok": True, "on": on})

    # ---- recipes ---------------------------------------------------------------------
    async def recipes(self, request: Request) -> Response:
        """The recipe files and the prepared one (read-only)."""
        if refused := self._view_refused(request):
            return refused
        listed = await run_in_threadpool(_recipe_list, getattr(self.service, "recipes", None))
        return JSONResponse({"active": self.service.snapshot().recipe, "recipes": listed})

    async def recipe(self, request: Request) -> Response:
        """Prepare a recipe (`{"recipe_id": "..."}`) or go back to the cell's own config (`""`), through the
        command table (PrepareRecipe / UnprepareRecipe: Ready only, the engineer's role)."""
        origin = self._controller(request)
        if isinstance(origin, Response):
            return origin
        body = await self._read_body(request, 4096)
        if isinstance(body, Response):
            return body
        try:
            recipe_id = json.loads(body)["recipe_id"]
            if not isinstance(recipe_id, str):
                raise TypeError("recipe_id must be a string")
        except (ValueError, KeyError, TypeError):
            return _error(400, 'send JSON {"recipe_id": "..."} ("" for none)')
        command = Command.PREPARE_RECIPE if recipe_id else Command.UNPREPARE_RECIPE
        try:
            await run_in_threadpool(
                self.service.command, command, origin, RecipeRequest(recipe_id) if recipe_id else None
            )
        except CommandRefused as e:
            return _error(REFUSAL_STATUS[e.reason], str(e), refusal=e.reason.value)
        log.info("screen: %s %s accepted", command.value, recipe_id)
        return JSONResponse({"ok": True, "command": command.value, "recipe": recipe_id})

    async def metrics_page(self, request: Request) -> Response:
        """Prometheus text exposition; the screen's access rule (basic auth checked off the event loop)."""
        if refused := await run_in_threadpool(metrics_refused, request, self.access):
            return refused
        return await run_in_threadpool(metrics_response, self.metrics)

    @staticmethod
    async def _read_body(
        request: Request, limit: int, refuse: Callable[..., JSONResponse] = _error
    ) -> bytes | Response:
        """The body up to `limit` bytes; longer (declared or sent) is refused without reading it all."""
        declared = request.headers.get("content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > limit):
            return refuse(413, f"upload too large: at most {limit // 1024} KiB")
        chunks, size = [], 0
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                return refuse(413, f"upload too large: at most {limit // 1024} KiB")
            chunks.append(chunk)
        return b"".join(chunks)

    def routes(self) -> list[Route]:
        return [
            *(Route(path, self.static_file) for path in STATIC),
            Route("/api/session", self.session),
            Route("/api/login", self.login, methods=["POST"]),
            Route("/api/logout", self.logout, methods=["POST"]),
            Route("/api/state", self.state),
            Route("/api/events", self.events),
            Route("/api/frame.jpg", self.frame_jpeg),
            Route("/api/command/{name}", self.command, methods=["POST"]),
            Route("/api/recipes", self.recipes),
            Route("/api/camera-check", self.camera_check, methods=["POST"]),
            Route("/api/recipe", self.recipe, methods=["POST"]),
            Route("/api/recalibration/capture", self.recal_capture, methods=["POST"]),
            Route("/api/recalibration/upload", self.recal_upload, methods=["POST"]),
            Route("/api/recalibration/{report_id}/{kind:str}", self.recal_picture),
            Route("/api/recalibration/{report_id}/{answer}", self.recal_answer, methods=["POST"]),
            Route("/api/calibration/{kind}", self.calibration_picture),
            *self.history.routes(),
            *self.teach.routes(),
            Route("/metrics", self.metrics_page),
        ]


def _sse(event: str, data: dict[str, Any]) -> str:
    return f"event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


def build_app(service: LineServiceAPI, config: CellConfig, web: WebConfig, access: Access) -> Guard:
    """The screen as an ASGI app: Starlette routes behind the Host check and security headers."""
    screen = ScreenApp(service, config, web, access)

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        screen.hub.start(asyncio.get_running_loop())
        screen.metrics.start()
        try:
            yield
        finally:
            screen.metrics.close()
            screen.hub.close()
            screen.desk.close()  # an open report's hold and timeout end with the screen
            screen.teach.desk.close()  # and a teaching session with its timeout

    app = Starlette(routes=screen.routes(), lifespan=lifespan)
    return Guard(app, screen)

"""The screen's History page and alarm list: read-only JSON routes over the history store, behind
the same view check as the rest of the screen.

No request parameter ever becomes a path or SQL text: filters are bound parameters, and an
image is asked for by its row's id (20 hex digits); the file comes from the row, and only
from inside the store's images folder.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from datetime import UTC, datetime
from importlib import resources
from typing import TYPE_CHECKING, Any, TypeVar

from starlette.concurrency import run_in_threadpool
from starlette.datastructures import QueryParams
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from cell.config import CellConfig
from cell.core.api import LineServiceAPI
from cell.core.parts import NAME_PATTERN
from cell.errors import REPORTED_ERRORS

if TYPE_CHECKING:  # imported where used: the screen without a store never loads them
    from cell.history.query import HistoryReader, PickFilter

T = TypeVar("T")

log = logging.getLogger(__name__)

STATIC = {
    "/history": ("history.html", "text/html; charset=utf-8"),
    "/static/history.js": ("history.js", "text/javascript; charset=utf-8"),
    "/static/history.css": ("history.css", "text/css; charset=utf-8"),
}
_IMAGE_ID = re.compile(r"^[0-9a-f]{20}$")
_JOB_ID = re.compile(r"^[0-9A-Za-z_.:-]{1,64}$")
PAGE_MAX = 200
OUTCOMES = ("picked", "missed", "failed", "rehearsed", "placed")


def _error(status: int, message: str) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status)


class HistoryRoutes:
    """Routes bound to the screen (its view check, the service's snapshot) and the cell's config."""

    def __init__(self, view_refused: Callable[[Request], Response | None], service: LineServiceAPI, config: CellConfig):
        """`view_refused(request)`: the screen's view check (a response when refused, else None)."""
        self.view_refused, self.service, self.config = view_refused, service, config
        pkg = resources.files("cell.web") / "static"
        self.static = {route: ((pkg / name).read_bytes(), kind) for route, (name, kind) in STATIC.items()}

    def routes(self) -> list[Route]:
        return [
            *(Route(path, self.static_file) for path in STATIC),
            Route("/api/history/picks", self.picks),
            Route("/api/history/alarms", self.alarms),
            Route("/api/history/image/{image_id}/{which}", self.image),
        ]

    async def static_file(self, request: Request) -> Response:
        body, kind = self.static[request.url.path]
        return Response(body, media_type=kind)

    def _reader(self) -> HistoryReader:
        from cell.history.query import open_reader

        return open_reader(self.config)

    async def _query(self, work: Callable[[HistoryReader], T]) -> T | Response:
        """Run `work(reader)` off the loop; a store that cannot be read is a 503 saying why."""

        def run() -> T:
            reader = self._reader()
            try:
                return work(reader)
            finally:
                reader.close()

        try:
            return await run_in_threadpool(run)
        except REPORTED_ERRORS as e:
            return _error(503, f"history: {e}")
        except Exception as e:  # a database error: said, never a stack trace to the page
            log.warning("history page: %s", e)
            return _error(503, f"history cannot be read: {type(e).__name__}")

    # ---- picks ----------------------------------------------------------------------------------
    async def picks(self, request: Request) -> Response:
        if refused := self.view_refused(request):
            return refused
        try:
            f, limit, offset, shift = self._filter(request.query_params)
        except ValueError as e:
            return _error(400, str(e))

        def work(reader: HistoryReader) -> dict[str, Any]:
            return {
                "shift": shift,
                "since": f.since.isoformat() if f.since else None,
                "until": f.until.isoformat() if f.until else None,
                "total": reader.count_picks(f),
                "offset": offset,
                "limit": limit,
                "picks": reader.list_picks(f, limit=limit, offset=offset),
            }

        result = await self._query(work)
        return result if isinstance(result, Response) else JSONResponse(result)

    def _filter(self, q: QueryParams) -> tuple[PickFilter, int, int, str]:
        from cell.history.query import PickFilter
        from cell.shifts import ShiftCalendar

        calendar = ShiftCalendar(self.config.shifts)
        since = _time(q.get("since"), "since")
        until = _time(q.get("until"), "until")
        shift_id = q.get("shift", "")
        if shift_id:
            shift = calendar.by_id(shift_id)
            since = max(since or shift.start_utc, shift.start_utc)
            until = min(until or shift.end_utc, shift.end_utc)
        job = q.get("job") or None
        if job is not None and not _JOB_ID.match(job):
            raise ValueError("job: letters, digits and -_.: only")
        cls = q.get("class") or None
        if cls is not None and not NAME_PATTERN.match(cls):
            raise ValueError("class: a part class's name (bolt, nut, a taught type's name)")
        outcome = q.get("outcome") or None
        if outcome is not None and outcome not in OUTCOMES:
            raise ValueError(f"outcome: one of {', '.join(OUTCOMES)}")
        limit = _int(q.get("limit"), 50, 1, PAGE_MAX, "limit")
        offset = _int(q.get("offset"), 0, 0, 10**9, "offset")
        return PickFilter(since, until, job, cls, outcome), limit, offset, shift_id

    # ---- alarms -----------------------------------------------------------------------------------
    async def alarms(self, request: Request) -> Response:
        """The active alarms (the fault, then warnings), then the history, newest first, with who reset each."""
        if refused := self.view_refused(request):
            return refused
        try:
            limit = _int(request.query_params.get("limit"), 50, 1, PAGE_MAX, "limit")
            offset = _int(request.query_params.get("offset"), 0, 0, 10**9, "offset")
        except ValueError as e:
            return _error(400, str(e))
        snap = self.service.snapshot()
        active = [a for a in (snap.alarm, *snap.warnings) if a is not None]
        result = await self._query(lambda reader: reader.alarms(limit, offset))
        if isinstance(result, Response):
            return result
        return JSONResponse(
            {
                "active": [
                    {
                        "alarm_id": a.alarm_id,
                        "severity": a.severity,
                        "reason": a.reason,
                        "hint": a.hint,
                        "source": a.source,
                        "raised_utc": a.time_utc.isoformat(timespec="seconds"),
                    }
                    for a in active
                ],
                "history": result,
                "offset": offset,
                "limit": limit,
            }
        )

    # ---- images -----------------------------------------------------------------------------------
    async def image(self, request: Request) -> Response:
        if refused := self.view_refused(request):
            return refused
        image_id, which = request.path_params["image_id"], request.path_params["which"]
        if not _IMAGE_ID.match(image_id) or which not in ("frame.png", "annotated.png"):
            return _error(404, "no such image")
        files = await self._query(lambda reader: reader.image_files(image_id))
        if isinstance(files, Response):
            return files
        if files is None:
            return _error(404, "no such image (never saved, or deleted by retention)")
        path = files[0] if which == "frame.png" else files[1]
        try:
            body = await run_in_threadpool(path.read_bytes)
        except OSError:
            return _error(404, "the image file is gone (deleted by retention)")
        return Response(body, media_type="image/png")


def _time(text: str | None, what: str) -> datetime | None:
    if not text:
        return None
    try:
        t = datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(f"{what}: an ISO 8601 time, e.g. 2026-12-01T14:32:00Z") from None
    return (t if t.tzinfo else t.replace(tzinfo=UTC)).astimezone(UTC)


def _int(text: str | None, default: int, low: int, high: int, what: str) -> int:
    if text is None or text == "":
        return default
    if not text.isdigit() or not low <= int(text) <= high:
        raise ValueError(f"{what}: a whole number {low}-{high}")
    return int(text)

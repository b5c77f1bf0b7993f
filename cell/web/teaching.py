"""The screen's Teach page: a part type taught from frames of the cell's camera, as `run-cell part teach`
teaches it from files (cell.vision.teaching: the same examples, the same model, the same refusals).

The engineer captures one or more frames of example parts (CapturePartImage: the engineer's role, the cell
idle, refused in words otherwise), names the type and gives its height; the server learns the model and
shows each frame with every example's outline and the jaws where they would close, the consistency and
the symmetry found, or the refusal in words. Confirm adds the type to a recipe file (AddPartType through
the command table: the model file and `[types.NAME]` written whole or not at all, recorded); Cancel
discards. The session is the engineer's who captured its first frame: another engineer's capture, teach,
confirm or cancel on it is refused in words naming whose it is (403, recorded); an admin may cancel it.
One session at a time, at most `service.web.teach_max_frames` frames, discarded when nothing
was done with it for `service.web.teach_timeout_s`: a client cannot make the screen hold more. Nothing
from a request names a file: the type's name and the recipe id are checked against their patterns, the
session and its pictures live in memory under a random id.
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import resources
from typing import Any

import cv2
import numpy as np
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from cell.config import CellConfig
from cell.core.api import LineServiceAPI
from cell.core.commands import Command, CommandRefused, PartTypeRequest, Refusal
from cell.core.events import Origin, Role
from cell.core.records import PartImage
from cell.errors import REPORTED_ERRORS, CellError
from cell.recipes import RecipeError, bins_of, check_recipe_id, read_recipe_if_any
from cell.vision.shapes import Example, ShapeModel, TeachRefused
from cell.vision.teaching import (
    check_height_mm,
    check_type_name,
    draw_examples,
    example_fit,
    examples_in,
    teach_examples,
)
from cell.web.config import WebConfig

log = logging.getLogger(__name__)

STATIC = {
    "/teach": ("teach.html", "text/html; charset=utf-8"),
    "/static/teach.js": ("teach.js", "text/javascript; charset=utf-8"),
    "/static/teach.css": ("teach.css", "text/css; charset=utf-8"),
}
REFUSAL_STATUS = {
    Refusal.INVALID_STATE: 409,
    Refusal.ACCESS_DENIED: 403,
    Refusal.SHUTTING_DOWN: 503,
    Refusal.BAD_ARGUMENT: 422,
    Refusal.NOT_RECORDED: 503,
}
CANCEL = "CancelPartType"  # a session discarded, in the record (AddPartType's role)


class NoSession(Exception):
    """No teaching session, or not the one asked for (confirmed, cancelled, expired or replaced)."""


class Full(Exception):
    """The session holds its most frames already, or another learn is being computed."""


@dataclass
class Learnt:
    """What the frames taught: the model and its words, or the refusal; a picture per frame."""

    name: str
    height_mm: float
    model: ShapeModel | None
    lines: list[str]
    refusal: str
    hint: str
    examples: list[dict[str, Any]]
    pictures: list[bytes]


@dataclass
class Session:
    """One teaching session: its frames (each with the calibration it was taken with) and what they taught."""

    id: str
    owner: str  # the user who captured its first frame: only they capture into it, teach from it, confirm it
    started_utc: datetime = field(default_factory=lambda: datetime.now(UTC))
    frames: list[PartImage] = field(default_factory=list)
    learnt: Learnt | None = None

    def whose(self) -> str:
        return f"the teaching session is {self.owner or 'anonymous'}'s (started {self.started_utc:%H:%M:%S} UTC)"


def _jpeg(image: np.ndarray, max_width_px: int, quality: int) -> bytes:
    h, w = image.shape[:2]
    if w > max_width_px:
        image = cv2.resize(image, (max_width_px, round(h * max_width_px / w)), interpolation=cv2.INTER_AREA)
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise CellError("the teaching picture could not be encoded")
    return bytes(data.tobytes())


class TeachDesk:
    """The one teaching session; every change under one lock, its timeout restarted by each step."""

    def __init__(self, service: LineServiceAPI, config: CellConfig, web: WebConfig):
        self.service, self.config, self.web = service, config, web
        self._lock = threading.RLock()
        self._learning = threading.Lock()  # one model computed at a time: a client cannot queue up CPU work
        self.session: Session | None = None
        self._timer: threading.Timer | None = None

    # -- the session and its timeout
    def _touch(self, session: Session | None) -> None:
        """`session` becomes the open one (None: none), its timeout started again."""
        with self._lock:
            self.session = session
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
            if session is not None:
                self._timer = threading.Timer(self.web.teach_timeout_s, self._expire, (session.id,))
                self._timer.name, self._timer.daemon = "teach-timeout", True
                self._timer.start()

    def _expire(self, session_id: str) -> None:
        with self._lock:
            if self.session is not None and self.session.id == session_id:
                self.session = None
                self._timer = None
                log.info("teaching session %s discarded: nothing done with it for %g s", session_id, self._timeout)

    @property
    def _timeout(self) -> float:
        return self.web.teach_timeout_s

    def open(self, session_id: str) -> Session:
        s = self.session
        if s is None or not secrets.compare_digest(s.id.encode(), session_id.encode()):
            raise NoSession(
                "no such teaching session (confirmed, cancelled, replaced, or discarded after "
                f"{self._timeout:g} s without a step): capture again"
            )
        return s

    def close(self) -> None:
        self._touch(None)

    def _own(self, s: Session, origin: Origin, command: Command, action: str, admin_may: bool = False) -> None:
        """The step is `origin`'s to take on `s`: the session's own engineer (or, with `admin_may`, an admin).
        Otherwise the role is checked first (its refusal recorded as ever), then this refusal, in words
        naming whose session it is, recorded (AccessDenied); nothing is done."""
        if origin.user == s.owner or (admin_may and origin.role is Role.ADMIN):
            return
        self.service.authorize(command, origin, state=False)
        who = s.owner or "anonymous"
        also = "; an admin may cancel it" if action == CANCEL else ""
        self.service.refuse(
            command,
            origin,
            action,
            f"{s.whose()}: only {who} may capture into it, teach from it, confirm or cancel it{also} "
            f"(hint: ask {who} to confirm or cancel it, or wait until it is discarded after "
            f"{self._timeout:g} s without a step)",
            {"session": s.id, "owner": s.owner},
        )

    # -- the steps
    def capture(self, origin: Origin) -> Session:
        """A frame from the cell's camera added to the session (a new one if none is open): CapturePartImage's
        role and state checked by the service first, and the session's room before the camera is touched."""
        capture = Command.CAPTURE_PART_IMAGE
        with self._lock:
            s = self.session
            if s is not None:
                self._own(s, origin, capture, capture.value)
            if s is not None and len(s.frames) >= self.web.teach_max_frames:
                raise Full(
                    f"the session holds {len(s.frames)} frames, the most it takes (service.web.teach_max_frames): "
                    "teach from these, or cancel and start again"
                )
        frame = self.service.capture_part_image(origin)  # CommandRefused: recorded, nothing held
        with self._lock:
            s = self.session
            if s is None:
                s = Session(secrets.token_urlsafe(16), origin.user)
            self._own(s, origin, capture, capture.value)  # another engineer's session began meanwhile
            if len(s.frames) >= self.web.teach_max_frames:  # another capture filled it meanwhile
                raise Full(f"the session holds {len(s.frames)} frames, the most it takes: teach from these")
            s.frames.append(frame)
            s.learnt = None
            self._touch(s)
            return s

    def learn(self, session_id: str, name: str, height_mm: float, origin: Origin) -> Learnt:
        """The model from every frame of the session, with the same code as `run-cell part teach`, and a picture
        per frame; a refusal (TeachRefused, no part seen) is kept with its pictures, and its words returned."""
        self.service.authorize(Command.ADD_PART_TYPE, origin, state=False)  # the role; refused: recorded
        check_type_name(name)
        check_height_mm(height_mm)
        with self._lock:
            s = self.open(session_id)
            self._own(s, origin, Command.ADD_PART_TYPE, Command.ADD_PART_TYPE.value)
            frames = list(s.frames)
        if not self._learning.acquire(blocking=False):
            raise Full("a model is being learnt from these frames already: wait for it")
        try:
            return self._learn(session_id, frames, name, height_mm)
        finally:
            self._learning.release()

    def _learn(self, session_id: str, frames: list[PartImage], name: str, height_mm: float) -> Learnt:
        parts = self.config.parts
        per_frame: list[list[Example]] = []
        refusal, hint, model, lines = "", "", None, []
        try:
            for k, f in enumerate(frames, start=1):
                per_frame.append(examples_in(f.image_bgr, f.calibration, parts, height_mm, f"frame {k}"))
            report = teach_examples(name, [e for frame in per_frame for e in frame], height_mm, parts)
            model, lines = report.model, report.lines
        except (TeachRefused, *REPORTED_ERRORS) as e:
            refusal, hint = e.args[0] if e.args else str(e), getattr(e, "hint", "") or ""
        examples = []
        for k, found in enumerate(per_frame, start=1):
            for i, ex in enumerate(found, start=1):
                row: dict[str, Any] = {"frame": k, "part": i, "area_mm2": round(ex.footprint.area_mm2, 1)}
                if ex.touches_border:
                    row["leaves_image"] = True
                if model is not None:
                    _, angle, misfit, score = example_fit(model, ex)
                    row.update(angle_deg=round(angle, 1), misfit_mm2=round(misfit, 2), score=round(score, 4))
                examples.append(row)
        pictures = []
        for k, f in enumerate(frames):
            found = per_frame[k] if k < len(per_frame) else []
            drawn = draw_examples(f.image_bgr, f.calibration, found, model, parts, crop=True)
            pictures.append(_jpeg(drawn, self.web.frame_max_width_px, self.web.jpeg_quality))
        learnt = Learnt(name, height_mm, model, lines, refusal, hint, examples, pictures)
        with self._lock:
            s = self.open(session_id)
            if len(s.frames) == len(frames):  # no capture came meanwhile: what was learnt is the session's
                s.learnt = learnt
            self._touch(s)
        log.info("teaching %s from %d frame(s): %s", name, len(frames), refusal or "learnt")
        return learnt

    def confirm(
        self,
        session_id: str,
        recipe_id: str,
        origin: Origin,
        bin_robot_mm: tuple[float, float, float] | None = None,
        bin_of: str = "",
    ) -> tuple[str, str, tuple[str, ...]]:
        """AddPartType through the command table (role, the cell idle, recorded; the files written whole or not at
        all; the bin checked there); then the session is closed. Returns (recipe id, type name, what it said)."""
        self.service.authorize(Command.ADD_PART_TYPE, origin, state=False)  # the role first; refused: recorded
        with self._lock:
            s = self.open(session_id)
            self._own(s, origin, Command.ADD_PART_TYPE, Command.ADD_PART_TYPE.value)
            learnt = s.learnt
        if learnt is None or learnt.model is None:
            raise NoSession("nothing learnt to confirm: give the name and height, and teach from the frames first")
        check_recipe_id(recipe_id)
        request = PartTypeRequest(recipe_id, learnt.name, learnt.model.to_json(), bin_robot_mm, bin_of)
        result = self.service.command(Command.ADD_PART_TYPE, origin, request)  # CommandRefused: nothing written
        with self._lock:
            if self.session is s:
                self._touch(None)
        log.info("part type %s added to recipe %s by %s", learnt.name, recipe_id, origin.describe())
        return recipe_id, learnt.name, result.said

    def bins(self, recipe_id: str) -> dict[str, tuple[float, float, float]]:
        """The classes of a recipe that have a bin (bolt and nut: the recipe's, else the config's), each with it:
        what a new type may share. A recipe not there yet: bolt's and nut's. RecipeError when it cannot be read."""
        check_recipe_id(recipe_id)
        try:
            path = self.service.recipes.info(recipe_id).path
        except RecipeError:  # not there yet: confirming creates it
            return bins_of(None, self.config.planning)
        return bins_of(read_recipe_if_any(path), self.config.planning)

    def cancel(self, session_id: str, origin: Origin) -> None:
        """The session discarded: AddPartType's role first (a refusal changes nothing), then whose it is (its
        engineer's, or an admin's), then recorded."""
        self.service.authorize(Command.ADD_PART_TYPE, origin, state=False)
        with self._lock:
            s = self.open(session_id)
            self._own(s, origin, Command.ADD_PART_TYPE, CANCEL, admin_may=True)
            self.service.authorize(
                Command.ADD_PART_TYPE,
                origin,
                CANCEL,
                state=False,
                arguments={"session": session_id, "owner": s.owner},
            )
            self._touch(None)


def session_json(s: Session | None, active_recipe: str) -> dict[str, Any]:
    """The session as the page shows it (what was learnt too), or none."""
    if s is None:
        return {"session": None, "active_recipe": active_recipe}
    out: dict[str, Any] = {
        "session": s.id,
        "owner": s.owner,
        "started": s.started_utc.isoformat(timespec="seconds"),
        "active_recipe": active_recipe,
        "frames": len(s.frames),
        "taken": [f.time_utc.astimezone(UTC).isoformat(timespec="seconds") for f in s.frames],
        "learnt": None,
    }
    if s.learnt is not None:
        out["learnt"] = learnt_json(s.id, s.learnt)
    return out


def learnt_json(session_id: str, learnt: Learnt) -> dict[str, Any]:
    out: dict[str, Any] = {
        "name": learnt.name,
        "height_mm": learnt.height_mm,
        "ok": learnt.model is not None,
        "refusal": learnt.refusal,
        "hint": learnt.hint,
        "lines": learnt.lines,
        "examples": learnt.examples,
        "pictures": [f"/api/teach/{session_id}/frame/{k}.jpg" for k in range(1, len(learnt.pictures) + 1)],
    }
    m = learnt.model
    if m is not None:
        out.update(
            examples_count=m.examples,
            consistency={k: round(v, 4) for k, v in m.consistency.items()},
            tolerance_mm2=round(m.tolerance_mm2, 3),
            symmetry=m.symmetry,
            symmetry_words="round (no angle)"
            if m.symmetry == 0
            else "none"
            if m.symmetry == 1
            else f"{m.symmetry}-fold (the same every {360 // m.symmetry} deg)",
            mirror_distinct=m.mirror_distinct,
            grip={
                "angle_deg": round(m.grip.angle_deg, 1),
                "width_mm": round(m.grip.width_mm, 2),
                "opening_mm": round(m.grip.opening_mm, 2),
            },
            area_mm2=round(m.area_mm2, 1),
            holes=len(m.holes_mm),
        )
    return out


def _error(status: int, message: str, todo: str = "", **extra: Any) -> JSONResponse:
    """A refusal: the message (`error`) and the page's words: `say` what happened, `do` what to do."""
    say = message[:1].upper() + message[1:]
    return JSONResponse({"error": message, "say": say, "do": todo, **extra}, status_code=status)


def _refused(e: CommandRefused) -> JSONResponse:
    return _error(REFUSAL_STATUS[e.reason], str(e), refusal=e.reason.value)


Check = Callable[[Request], Response | None]


class TeachRoutes:
    """The Teach page and its JSON routes, behind the screen's checks (`view_refused`, `controller`: who sends a
    control, or the refusal; `read_body`: a body within a limit)."""

    def __init__(
        self,
        service: LineServiceAPI,
        config: CellConfig,
        web: WebConfig,
        view_refused: Check,
        controller: Callable[[Request], Origin | Response],
        read_body: Callable[[Request, int], Awaitable[bytes | Response]],
    ):
        self.service = service
        self.desk = TeachDesk(service, config, web)
        self.view_refused, self.controller, self.read_body = view_refused, controller, read_body
        pkg = resources.files("cell.web") / "static"
        self.static = {route: ((pkg / name).read_bytes(), kind) for route, (name, kind) in STATIC.items()}

    def routes(self) -> list[Route]:
        return [
            *(Route(path, self.static_file) for path in STATIC),
            Route("/api/teach", self.state),
            Route("/api/teach/capture", self.capture, methods=["POST"]),
            Route("/api/teach/bins", self.bins),
            Route("/api/teach/{session_id}/frame/{n:int}.jpg", self.picture),
            Route("/api/teach/{session_id}/{step}", self.step, methods=["POST"]),
        ]

    async def static_file(self, request: Request) -> Response:
        body, kind = self.static[request.url.path]
        return Response(body, media_type=kind)

    def _active_recipe(self) -> str:
        return self.service.snapshot().recipe

    async def state(self, request: Request) -> Response:
        if refused := self.view_refused(request):
            return refused
        return JSONResponse(session_json(self.desk.session, self._active_recipe()))

    async def capture(self, request: Request) -> Response:
        origin = self.controller(request)
        if isinstance(origin, Response):
            return origin
        try:
            s = await run_in_threadpool(self.desk.capture, origin)
        except CommandRefused as e:
            return _refused(e)
        except Full as e:
            return _error(409, str(e))
        except REPORTED_ERRORS as e:  # the camera failed
            return _error(503, f"no frame from the camera: {e}", getattr(e, "hint", "") or "")
        return JSONResponse(session_json(s, self._active_recipe()))

    async def bins(self, request: Request) -> Response:
        """The bins a new type of recipe `recipe_id` may share: {"bins": [{"class", "bin_robot_mm"}]}."""
        if refused := self.view_refused(request):
            return refused
        recipe_id = request.query_params.get("recipe_id", "")
        try:
            found = await run_in_threadpool(self.desk.bins, recipe_id)
        except REPORTED_ERRORS as e:
            return _error(422, e.args[0] if e.args else str(e), getattr(e, "hint", "") or "")
        rows = [{"class": cls, "bin_robot_mm": list(where)} for cls, where in found.items()]
        return JSONResponse({"recipe_id": recipe_id, "bins": rows})

    async def picture(self, request: Request) -> Response:
        if refused := self.view_refused(request):
            return refused
        try:
            s = self.desk.open(request.path_params["session_id"])
        except NoSession as e:
            return _error(404, str(e))
        learnt, n = s.learnt, request.path_params["n"]
        if learnt is None or not 1 <= n <= len(learnt.pictures):
            return _error(404, "no such picture: teach from the frames first")
        return Response(learnt.pictures[n - 1], media_type="image/jpeg")

    async def step(self, request: Request) -> Response:
        """learn ({"name", "height_mm"}), confirm ({"recipe_id"}) or cancel."""
        origin = self.controller(request)
        if isinstance(origin, Response):
            return origin
        session_id, step = request.path_params["session_id"], request.path_params["step"]
        if step not in ("learn", "confirm", "cancel"):
            return _error(404, "the steps are learn, confirm and cancel")
        body = await self.read_body(request, 4096)
        if isinstance(body, Response):
            return body
        try:
            sent = json.loads(body) if body else {}
            if not isinstance(sent, dict):
                raise TypeError("send a JSON object")
        except (ValueError, TypeError):
            return _error(400, "send a JSON object")
        try:
            if step == "cancel":
                await run_in_threadpool(self.desk.cancel, session_id, origin)
                return JSONResponse({"ok": True, "cancelled": True})
            if step == "learn":
                name, height = sent.get("name"), sent.get("height_mm")
                if not isinstance(name, str) or isinstance(height, bool) or not isinstance(height, int | float):
                    return _error(400, 'send JSON {"name": "...", "height_mm": 3.0}')
                learnt = await run_in_threadpool(self.desk.learn, session_id, name, float(height), origin)
                reply = learnt_json(session_id, learnt)
                if learnt.model is None:
                    return _error(422, learnt.refusal, learnt.hint, **reply)
                return JSONResponse(reply)
            recipe_id, where, of = sent.get("recipe_id"), sent.get("bin_robot_mm"), sent.get("bin_of") or ""
            if (
                not isinstance(recipe_id, str)
                or not isinstance(of, str)
                or not (where is None or _three_numbers(where))
            ):
                return _error(
                    400,
                    'send JSON {"recipe_id": "...", "bin_robot_mm": [x, y, z] or null, "bin_of": "..." or ""}',
                )
            bin_mm = None if where is None else (float(where[0]), float(where[1]), float(where[2]))
            recipe, name, said = await run_in_threadpool(self.desk.confirm, session_id, recipe_id, origin, bin_mm, of)
        except CommandRefused as e:
            return _refused(e)
        except (NoSession, Full) as e:
            return _error(409, str(e))
        except REPORTED_ERRORS as e:  # a name, height or recipe id not allowed
            return _error(422, e.args[0] if e.args else str(e), getattr(e, "hint", "") or "")
        return JSONResponse({"ok": True, "recipe_id": recipe, "name": name, "said": list(said)})


def _three_numbers(value: object) -> bool:
    return (
        isinstance(value, list)
        and len(value) == 3
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    )

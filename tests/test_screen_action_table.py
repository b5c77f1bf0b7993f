"""Every state-changing route of the operator screen, walked as a logged-in viewer (issue 28).

The real line service in-process (the simulated cell at 960 x 540), the screen's Starlette app
with users (a viewer, an engineer), and one table of actions: every POST/PUT/PATCH/DELETE route
of the app must have an entry here (a new route without one fails the walk), and each call as
the viewer, with the CSRF header the screen requires, must be refused with 403 and change
nothing: the calibration file's hash, the hold, the open report, the recipe, the recipes on
disk, the camera check and the state all as they were; every refusal recorded in the audit log.
Halt is the one exception, by rule: any logged-in viewer may Halt (docs/security.md).
The walk is made twice: with no recalibration report open, and with the engineer's open.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import pytest
from starlette.routing import Route
from starlette.testclient import TestClient

from cell.access.throttle import LoginThrottle
from cell.access.users import Authenticator, UserEntry, hash_password, write_users
from cell.commands.serve import open_service
from cell.config import CellConfig
from cell.core.commands import VisionState
from cell.core.events import Role
from cell.service.config import LoginConfig
from cell.web.app import build_app
from cell.web.auth import Access
from cell.web.config import WebConfig
from cell.web.views import COMMANDS
from tests.mv_harness import RECIPE_BOLTS

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

BASE = "http://127.0.0.1:8080"
CHANGING = {"POST", "PUT", "PATCH", "DELETE"}
USERS = {"vera": ("vera-pass-1", Role.VIEWER), "erik": ("erik-pass-1", Role.ENGINEER)}


@dataclass(frozen=True)
class Call:
    path: str
    body: bytes = b""
    content_type: str = ""


def calls(route: str, report_id: str, png: bytes) -> list[Call]:
    """The viewer's calls for one route of the table (every command of the command route, both answers)."""
    recipe = json.dumps({"recipe_id": "bolts-only"}).encode()
    table: dict[str, list[Call]] = {
        "/api/command/{name}": [Call(f"/api/command/{name}") for name in sorted(COMMANDS) if name != "Halt"],
        "/api/camera-check": [Call("/api/camera-check", b'{"on": true}', "application/json")],
        "/api/recipe": [
            Call("/api/recipe", recipe, "application/json"),
            Call("/api/recipe", b'{"recipe_id": ""}', "application/json"),
        ],
        "/api/recalibration/capture": [Call("/api/recalibration/capture")],
        "/api/recalibration/upload": [Call("/api/recalibration/upload", png, "image/png")],
        "/api/recalibration/{report_id}/{answer}": [
            Call(f"/api/recalibration/{report_id}/accept"),
            Call(f"/api/recalibration/{report_id}/reject"),
        ],
        "/api/teach/capture": [Call("/api/teach/capture", b"{}", "application/json")],
        "/api/teach/{session_id}/{step}": [
            Call(f"/api/teach/{report_id}/learn", b'{"name": "bracket", "height_mm": 3.0}', "application/json"),
            Call(f"/api/teach/{report_id}/confirm", b'{"recipe_id": "bolts-only"}', "application/json"),
            Call(f"/api/teach/{report_id}/cancel", b"{}", "application/json"),
        ],
    }
    return table[route]


REFUSED_ROUTES = {
    "/api/command/{name}",
    "/api/camera-check",
    "/api/recipe",
    "/api/recalibration/capture",
    "/api/recalibration/upload",
    "/api/recalibration/{report_id}/{answer}",
    "/api/teach/capture",
    "/api/teach/{session_id}/{step}",
}
EXEMPT = {  # state-changing routes a viewer may use, and why
    "/api/login": "starts a session: nothing of the cell changes",
    "/api/logout": "ends the caller's own session: nothing of the cell changes",
}
# and one call of the command route: Halt, which any logged-in viewer may send (walked at the end)


def small_config(tmp_path: Path) -> CellConfig:
    cfg = CellConfig()
    cfg.camera.width_px, cfg.camera.height_px = 960, 540
    cfg.sim.reference_marks_mm = []
    cfg.run.log_dir = tmp_path / "logs"
    cfg.service.capture_interval_s = 0.2
    cfg.calibration.active_path = tmp_path / "calibration" / "active.json"
    cfg.calibration.backup_dir = tmp_path / "calibration" / "backups"
    cfg.service.machine_vision.recipes_dir = tmp_path / "recipes"
    return cfg


@contextlib.contextmanager
def served(
    tmp_path: Path,
    web: WebConfig | None = None,
    cfg: CellConfig | None = None,
    users_by_name: dict[str, tuple[str, Role]] = USERS,
) -> Iterator[tuple[Any, Any, CellConfig, Authenticator]]:
    """The line service in-process with `users_by_name` (name: (password, role)) and its screen's app."""
    cfg = cfg or small_config(tmp_path)
    write_users(
        tmp_path / "users.json", [UserEntry(n, r, hash_password(p, 1000)) for n, (p, r) in users_by_name.items()]
    )
    cfg.service.users_file = tmp_path / "users.json"
    users = Authenticator(cfg.service)
    web = web or WebConfig()
    with contextlib.ExitStack() as stack:
        service = open_service(cfg, True, stack)
        service.start()
        access = Access(
            "127.0.0.1",
            web,
            authenticate=users.authenticate,
            throttle=LoginThrottle(LoginConfig()),
            credential=users.credential,
        )
        app = build_app(service, cfg, web, access)
        yield service, app, cfg, users


def logged_in(app: Any, user: str) -> TestClient:
    client = TestClient(app, base_url=BASE)
    reply = client.post("/api/login", json={"user": user, "password": USERS[user][0]})
    assert reply.status_code == 200, reply.text
    client.headers["x-csrf-token"] = reply.json()["csrf"]
    return client


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def audit(cfg: CellConfig) -> list[dict[str, Any]]:
    lines: list[dict[str, Any]] = []
    for path in sorted(cfg.run.log_dir.glob("cell-*.jsonl")):
        lines += [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return lines


def refusals_of(cfg: CellConfig, user: str) -> list[dict[str, Any]]:
    return [e for e in audit(cfg) if e.get("kind") == "command" and not e["accepted"] and e["origin"]["user"] == user]


def state_changing_routes(app: Any) -> set[str]:
    """Every route of the screen's Starlette app that a POST, PUT, PATCH or DELETE reaches."""
    found = set()
    for route in app.app.routes:
        assert isinstance(route, Route), f"{route!r}: the walk knows Starlette Routes only; add this kind"
        if (route.methods or set()) & CHANGING:
            found.add(route.path)
    return found


def what_a_viewer_must_not_change(service: Any, app: Any, cfg: CellConfig) -> dict[str, object]:
    s = service.snapshot()
    return {
        "calibration file sha256": digest(cfg.calibration.active_path),
        "calibration in use": s.calibration,
        "hold": s.hold,
        "open report": app.screen.desk.open,
        "state": (s.vision_state, s.paused, s.job_id),
        "recipe": s.recipe,
        "recipe files": sorted(p.name for p in cfg.service.machine_vision.recipes_dir.glob("*")),
        "camera check": app.screen.check.on,
        "teaching session": app.screen.teach.desk.session,
    }


def walk(service: Any, app: Any, cfg: CellConfig, viewer: TestClient, report_id: str, png: bytes) -> None:
    for route in sorted(REFUSED_ROUTES):
        for call in calls(route, report_id, png):
            before = what_a_viewer_must_not_change(service, app, cfg)
            refused_before = len(refusals_of(cfg, "vera"))
            headers = {"content-type": call.content_type} if call.content_type else {}
            reply = viewer.post(call.path, content=call.body, headers=headers)
            assert reply.status_code == 403, f"{call.path}: {reply.status_code} {reply.text}"
            assert "role" in reply.json()["error"], reply.json()
            assert what_a_viewer_must_not_change(service, app, cfg) == before, call.path
            assert len(refusals_of(cfg, "vera")) == refused_before + 1, f"{call.path}: the refusal is not recorded"


def test_a_viewer_is_refused_every_state_changing_route_and_changes_nothing(tmp_path):
    with served(tmp_path) as (service, app, cfg, _users):
        assert state_changing_routes(app) == REFUSED_ROUTES | set(EXEMPT), (
            "a state-changing route without an entry in this table (or an entry without a route): "
            "add it, with the role it needs"
        )
        (tmp_path / "recipes").mkdir()
        (tmp_path / "recipes" / "bolts-only.toml").write_text(RECIPE_BOLTS)
        ok, png = cv2.imencode(".png", service.capture_plate_image())  # the cell's own plate: an upload that fits
        assert ok
        with logged_in(app, "erik") as engineer, logged_in(app, "vera") as viewer:
            first = engineer.post("/api/recalibration/capture")  # an active calibration file to keep unchanged
            assert first.status_code == 200, first.text
            accepted = engineer.post(f"/api/recalibration/{first.json()['id']}/accept")
            assert accepted.status_code == 200 and cfg.calibration.active_path.is_file(), accepted.text
            assert service.snapshot().hold == ""

            walk(service, app, cfg, viewer, "no-report-open", png.tobytes())  # nothing open: no hold may appear

            report = engineer.post("/api/recalibration/capture")
            assert report.status_code == 200 and service.snapshot().hold, report.text
            walk(service, app, cfg, viewer, report.json()["id"], png.tobytes())  # the engineer's stays as it is
            assert app.screen.desk.open is not None and app.screen.desk.open.id == report.json()["id"]

            halt = viewer.post("/api/command/Halt")  # the one thing a viewer may do: stop the cell
            assert halt.status_code == 200, halt.text
            deadline = time.monotonic() + 30
            while service.snapshot().vision_state is not VisionState.HALTED:
                assert time.monotonic() < deadline, "Halt from a viewer's session did not halt the cell"
                time.sleep(0.05)
            assert engineer.post(f"/api/recalibration/{report.json()['id']}/reject").json()["accepted"] is False
        recorded = [(e["command"], e["origin"]["user"]) for e in audit(cfg) if e.get("kind") == "command"]
        assert ("Halt", "vera") in recorded and ("RejectCalibration", "erik") in recorded


def test_without_a_session_nobody_may_do_anything_not_even_halt(tmp_path):
    """view_without_password lets anyone watch; controls, Halt included, need a session (issue 28: the old
    'anyone who may watch may Halt' was dead code)."""
    cfg = small_config(tmp_path)
    write_users(tmp_path / "users.json", [UserEntry("vera", Role.VIEWER, hash_password("vera-pass-1", 1000))])
    cfg.service.users_file = tmp_path / "users.json"
    users = Authenticator(cfg.service)
    web = WebConfig(view_without_password=True)
    from tests.fake_service import FakeLineService

    service = FakeLineService()
    try:
        app = build_app(service, cfg, web, Access("127.0.0.1", web, authenticate=users.authenticate))
        with TestClient(app, base_url=BASE) as anonymous:
            assert anonymous.get("/api/state").status_code == 200  # may watch
            session = anonymous.get("/api/session").json()
            assert session["can_view"] and not session["can_control"] and session["csrf"] is None
            assert anonymous.post("/api/command/Halt").status_code == 401
        assert service.commands == [] and service.snapshot().vision_state is VisionState.READY
    finally:
        service.close()


def test_a_viewers_accept_writes_nothing_and_the_engineers_still_may(tmp_path):
    """Before issue 28 the file was replaced first and the role checked after: the viewer got a 403 and the next
    restart loaded their calibration."""
    with served(tmp_path) as (service, app, cfg, _users):
        with logged_in(app, "erik") as engineer, logged_in(app, "vera") as viewer:
            first = engineer.post("/api/recalibration/capture").json()
            assert engineer.post(f"/api/recalibration/{first['id']}/accept").status_code == 200
            before = digest(cfg.calibration.active_path)
            report = engineer.post("/api/recalibration/capture").json()
            refused = viewer.post(f"/api/recalibration/{report['id']}/accept")
            assert refused.status_code == 403, refused.text
            assert digest(cfg.calibration.active_path) == before  # nothing written
            assert refused.json()["refusal"] == "access_denied"
            assert "InstallCalibration needs the engineer role; vera is viewer" in refused.json()["error"]
            assert refused.json()["say"].startswith("Recalibrating needs the engineer role")
            assert not list(cfg.calibration.backup_dir.glob("*"))  # nor the active file backed up
            assert service.snapshot().hold and app.screen.desk.open.id == report["id"]  # still waiting
            assert engineer.post(f"/api/recalibration/{report['id']}/accept").status_code == 200
            assert len(list(cfg.calibration.backup_dir.glob("*"))) == 1  # written: the previous one kept
            assert service.snapshot().hold == ""
        refused_lines = [e for e in refusals_of(cfg, "vera") if e["command"] == "InstallCalibration"]
        assert len(refused_lines) == 1 and refused_lines[0]["refusal"] == "access_denied"


def test_an_unanswered_report_is_rejected_by_itself_and_the_hold_released(tmp_path):
    # long enough that the held Start below is asked well within it, even on a loaded machine
    with served(tmp_path, WebConfig(report_timeout_s=5.0)) as (service, app, cfg, _users):
        with logged_in(app, "erik") as engineer:
            report = engineer.post("/api/recalibration/capture")
            assert report.status_code == 200, report.text
            assert engineer.post("/api/command/StartSingleJob").status_code == 409  # held while it waits
            deadline = time.monotonic() + 60
            while service.snapshot().hold:
                assert time.monotonic() < deadline, "the report still holds Start after its timeout"
                time.sleep(0.05)
            assert app.screen.desk.open is None and engineer.get("/api/state").json()["recalibration_open"] is False
            gone = engineer.post(f"/api/recalibration/{report.json()['id']}/accept")
            assert gone.status_code == 409 and "no such recalibration report" in gone.json()["error"]
            assert engineer.post("/api/command/StartSingleJob").status_code == 200  # no longer held
        rejected = [e for e in audit(cfg) if e.get("kind") == "command" and e["command"] == "RejectCalibration"]
        assert len(rejected) == 1 and rejected[0]["accepted"], rejected
        assert rejected[0]["origin"]["user"] == "recalibration report timeout"
        assert rejected[0]["arguments"] == {
            "report": report.json()["id"],
            "reason": "no answer within 5 s (service.web.report_timeout_s)",
        }

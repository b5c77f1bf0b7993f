"""The screen's Teach page (issue 30): frames of example parts from the cell's camera, the model learnt
with the same code as `run-cell part teach`, its outlines and jaws on the picture, Confirm through the
command table (AddPartType) into a recipe file, Cancel; roles, CSRF, refusals in words, bounded sessions.

The real line service in-process over the simulated cell at 960 x 540 whose table holds L brackets alone
(sim.teach_family), the screen's Starlette app with users (a viewer, an operator, an engineer)."""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from starlette.testclient import TestClient

from cell.config import CellConfig
from cell.core.commands import Command, RecipeRequest, VisionState
from cell.core.events import Role
from cell.recipes import load_recipe_file
from cell.sim.cell import teach_family
from cell.vision.locate import locate
from cell.web.config import WebConfig
from tests.test_screen_action_table import served as screen_served

pytestmark = [pytest.mark.timeout(120)]

BASE = "http://127.0.0.1:8080"
USERS = {
    "vera": ("vera-pass-1", Role.VIEWER),
    "otto": ("otto-pass-1", Role.OPERATOR),
    "erik": ("erik-pass-1", Role.ENGINEER),
    "eve": ("eve-pass-1", Role.ENGINEER),
    "ada": ("ada-pass-1", Role.ADMIN),
}
FAMILY = "l-bracket"
HEIGHT_MM = teach_family(FAMILY, 0).height_mm
NO_BIN_HINT = " (give types.NAME.bin_robot_mm, or teach again with --bin-robot-mm X Y Z or --bin-of TYPE)"


def teach_config(tmp_path: Path) -> CellConfig:
    cfg = CellConfig()
    cfg.camera.width_px, cfg.camera.height_px = 960, 540
    cfg.sim.reference_marks_mm = []
    cfg.sim.teach_family = FAMILY
    cfg.sim.taught_parts_per_type = 3
    cfg.run.log_dir = tmp_path / "logs"
    cfg.service.capture_interval_s = 0.2
    cfg.calibration.active_path = tmp_path / "calibration" / "active.json"
    cfg.calibration.backup_dir = tmp_path / "calibration" / "backups"
    cfg.service.machine_vision.recipes_dir = tmp_path / "recipes"
    return cfg


@contextlib.contextmanager
def served(tmp_path: Path, web: WebConfig | None = None, **parts: Any) -> Iterator[tuple[Any, Any, CellConfig]]:
    cfg = teach_config(tmp_path)
    for key, value in parts.items():
        setattr(cfg.parts, key, value)
    with screen_served(tmp_path, web, cfg, USERS) as (service, app, cfg, _users):
        yield service, app, cfg


def logged_in(app: Any, user: str) -> TestClient:
    client = TestClient(app, base_url=BASE)
    reply = client.post("/api/login", json={"user": user, "password": USERS[user][0]})
    assert reply.status_code == 200, reply.text
    client.headers["x-csrf-token"] = reply.json()["csrf"]
    return client


def audit(cfg: CellConfig) -> list[dict[str, Any]]:
    lines: list[dict[str, Any]] = []
    for path in sorted(cfg.run.log_dir.glob("cell-*.jsonl")):
        lines += [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [e for e in lines if e.get("kind") == "command"]


def wait_for(condition, what: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def learn(client: TestClient, session: str, name: str = "bracket", height_mm: float = HEIGHT_MM):
    return client.post(f"/api/teach/{session}/learn", json={"name": name, "height_mm": height_mm})


def test_capture_learn_confirm_writes_the_recipe_and_locate_finds_the_type(tmp_path):
    with served(tmp_path) as (service, app, cfg):
        with logged_in(app, "erik") as engineer:
            first = engineer.post("/api/teach/capture", json={})
            assert first.status_code == 200, first.text
            session = first.json()["session"]
            second = engineer.post("/api/teach/capture", json={})
            assert second.json()["session"] == session and second.json()["frames"] == 2

            learnt = learn(engineer, session)
            assert learnt.status_code == 200, learnt.text
            body = learnt.json()
            assert body["ok"] and body["examples_count"] == 6  # three brackets on each frame
            assert body["symmetry"] == 1 and body["symmetry_words"] == "none" and body["mirror_distinct"]
            assert body["consistency"]["worst_misfit_mm2"] <= body["tolerance_mm2"]
            assert body["lines"][0].startswith("bracket: 6 example(s)")  # the CLI's own words
            assert all(e["score"] > 0.9 for e in body["examples"]) and len(body["examples"]) == 6

            picture = engineer.get(body["pictures"][0])
            assert picture.status_code == 200 and picture.headers["content-type"] == "image/jpeg"
            drawn = cv2.imdecode(np.frombuffer(picture.content, np.uint8), cv2.IMREAD_COLOR)
            # the jaws (blue, BGR 255 80 0) and the outlines (purple, BGR 170 60 150) are drawn on the frame
            blue = np.all(np.abs(drawn.astype(int) - (255, 80, 0)) < 40, axis=2).sum()
            purple = np.all(np.abs(drawn.astype(int) - (170, 60, 150)) < 40, axis=2).sum()
            assert blue > 100 and purple > 100, (blue, purple)

            state = engineer.get("/api/teach").json()
            assert state["session"] == session and state["learnt"]["ok"] and state["frames"] == 2

            bins = engineer.get("/api/teach/bins", params={"recipe_id": "brackets"})  # a new recipe: bolt's, nut's
            assert bins.status_code == 200 and [b["class"] for b in bins.json()["bins"]] == ["bolt", "nut"]
            for where, says in (
                ({"bin_robot_mm": [900, 0, 60]}, "bin_robot_mm (900, 0, 60) mm: robot x = 900.0 mm is outside"),
                ({"bin_of": "washer"}, "the recipe has no type 'washer'"),
            ):
                bad = engineer.post(f"/api/teach/{session}/confirm", json={"recipe_id": "brackets", **where})
                assert bad.status_code == 422 and says in bad.json()["error"], bad.text
            assert (
                engineer.post(
                    f"/api/teach/{session}/confirm", json={"recipe_id": "brackets", "bin_robot_mm": [1, "x", 3]}
                ).status_code
                == 400
            )
            assert not (cfg.service.machine_vision.recipes_dir / "brackets.toml").exists()  # nothing written
            confirmed = engineer.post(
                f"/api/teach/{session}/confirm", json={"recipe_id": "brackets", "bin_robot_mm": [200, 160.5, 60]}
            )
            assert confirmed.status_code == 200, confirmed.text
            assert confirmed.json()["said"] == [
                "bracket: into the bin at robot (200, 160.5, 60) mm; the robot is told class_no 3"
            ]
            assert engineer.get("/api/teach").json()["session"] is None  # the session ends with its answer
            bins = engineer.get("/api/teach/bins", params={"recipe_id": "brackets"}).json()["bins"]
            assert {"class": "bracket", "bin_robot_mm": [200.0, 160.5, 60.0]} in bins

        recipe, shapes = load_recipe_file(cfg.service.machine_vision.recipes_dir / "brackets.toml")
        assert list(recipe.types) == ["bracket"] and recipe.types["bracket"].height_mm == pytest.approx(
            HEIGHT_MM, abs=1e-3
        )
        assert recipe.types["bracket"].bin_robot_mm == (200.0, 160.5, 60.0) and recipe.classes == {"bracket"}
        frame = service.capture_part_image()
        found = locate(frame.image_bgr, frame.calibration, cfg, shapes)
        assert [p.cls for p in found.objects] == ["bracket"] * 3, [p.reason for p in found.objects]

        accepted = [(e["command"], e["origin"]["user"]) for e in audit(cfg) if e["accepted"]]
        assert accepted.count(("CapturePartImage", "erik")) == 2 and ("AddPartType", "erik") in accepted
        added = next(e for e in audit(cfg) if e["command"] == "AddPartType" and e["accepted"])
        assert added["arguments"]["recipe_id"] == "brackets" and added["arguments"]["name"] == "bracket"
        assert added["arguments"]["bin_robot_mm"] == [200.0, 160.5, 60.0]
        refused = [e["message"] for e in audit(cfg) if e["command"] == "AddPartType" and not e["accepted"]]
        assert len(refused) == 2 and "outside the workspace" in refused[0]  # the bad bins, recorded as refused


def test_a_type_confirmed_without_a_bin_or_with_another_types_bin_is_told_in_words(tmp_path, caplog):
    """Teach now, place later: confirmed without a bin, the page is told the type stays on the table; confirmed
    again with the nut's bin (a class chosen from the list), it goes there. A prepared recipe with a type
    without a bin says so in the service's log."""
    with served(tmp_path) as (service, app, cfg):
        with logged_in(app, "erik") as engineer:
            session = engineer.post("/api/teach/capture", json={}).json()["session"]
            assert learn(engineer, session).status_code == 200
            confirmed = engineer.post(
                f"/api/teach/{session}/confirm", json={"recipe_id": "later", "bin_robot_mm": None}
            )
            assert confirmed.status_code == 200, confirmed.text
            assert confirmed.json()["said"] == [
                "bracket: no bin: found and counted, left on the table; the robot is told class_no 3"
            ]
            book = cfg.service.machine_vision.recipes_dir
            assert load_recipe_file(book / "later.toml")[0].unbinned() == ["bracket"]
            with caplog.at_level(logging.WARNING, logger="cell.service.service"):
                service.command(Command.PREPARE_RECIPE, request=RecipeRequest("later"))
            said = "recipe later: bracket has no bin: found and counted but left on the table"
            assert [r.getMessage() for r in caplog.records].count(said + NO_BIN_HINT) == 1, caplog.text
            session = engineer.post("/api/teach/capture", json={}).json()["session"]
            assert learn(engineer, session).status_code == 200
            nut = next(b for b in engineer.get("/api/teach/bins?recipe_id=later").json()["bins"] if b["class"] == "nut")
            again = engineer.post(f"/api/teach/{session}/confirm", json={"recipe_id": "later", "bin_of": "nut"})
            assert again.status_code == 200, again.text
            assert again.json()["said"][0].startswith(f"bracket: into the bin at robot ({nut['bin_robot_mm'][0]:g}")
            recipe = load_recipe_file(book / "later.toml")[0]
            assert list(recipe.types["bracket"].bin_robot_mm) == nut["bin_robot_mm"] and not recipe.unbinned()
            assert "# the bin of nut" in (book / "later.toml").read_text()


def test_viewers_and_operators_are_refused_and_csrf_is_required(tmp_path):
    with served(tmp_path) as (service, app, cfg):
        with logged_in(app, "erik") as engineer, logged_in(app, "vera") as viewer, logged_in(app, "otto") as operator:
            for client, role in ((viewer, "viewer"), (operator, "operator")):
                refused = client.post("/api/teach/capture", json={})
                assert refused.status_code == 403, refused.text
                assert (
                    f"CapturePartImage needs the engineer role; {client is viewer and 'vera' or 'otto'} is {role}"
                    in (refused.json()["error"])
                )
            assert app.screen.teach.desk.session is None  # nothing captured, nothing held
            session = engineer.post("/api/teach/capture", json={}).json()["session"]
            assert learn(engineer, session).status_code == 200
            for client in (viewer, operator):
                for step, body in (
                    ("learn", {"name": "x", "height_mm": 3}),
                    ("confirm", {"recipe_id": "r"}),
                    ("cancel", {}),
                ):
                    reply = client.post(f"/api/teach/{session}/{step}", json=body)
                    assert reply.status_code == 403 and "AddPartType needs the engineer role" in reply.json()["error"]
            no_token = TestClient(app, base_url=BASE, cookies=engineer.cookies)
            assert no_token.post("/api/teach/capture", json={}).status_code == 403
            assert no_token.post(f"/api/teach/{session}/confirm", json={"recipe_id": "r"}).status_code == 403
            cross = engineer.post(
                f"/api/teach/{session}/confirm", json={"recipe_id": "r"}, headers={"origin": "http://evil.example"}
            )
            assert cross.status_code == 403
            assert not (cfg.service.machine_vision.recipes_dir / "r.toml").exists()
            assert app.screen.teach.desk.session.id == session  # still the engineer's
        refusals = [(e["command"], e["origin"]["user"]) for e in audit(cfg) if not e["accepted"]]
        assert ("CapturePartImage", "vera") in refusals and ("AddPartType", "otto") in refusals


def test_the_session_is_its_engineers_another_is_refused_in_words_and_an_admin_may_cancel_it(tmp_path):
    with served(tmp_path) as (service, app, cfg):
        with logged_in(app, "erik") as erik, logged_in(app, "eve") as eve, logged_in(app, "ada") as admin:
            session = erik.post("/api/teach/capture", json={}).json()["session"]
            assert learn(erik, session).status_code == 200
            state = eve.get("/api/teach").json()
            assert state["session"] == session and state["owner"] == "erik"
            whose = "the teaching session is erik's (started "
            for step, body in (
                ("capture", {}),
                (f"{session}/learn", {"name": "bracket", "height_mm": 3}),
                (f"{session}/confirm", {"recipe_id": "r"}),
                (f"{session}/cancel", {}),
            ):
                refused = eve.post(f"/api/teach/{step}", json=body)
                assert refused.status_code == 403, (step, refused.text)
                said = refused.json()["error"]
                assert whose in said and "only erik may capture into it, teach from it, confirm or cancel it" in said
                assert ("an admin may cancel it" in said) == step.endswith("cancel"), said
            assert admin.post(f"/api/teach/{session}/confirm", json={"recipe_id": "r"}).status_code == 403
            held = app.screen.teach.desk.session
            assert held.id == session and len(held.frames) == 1 and held.learnt.name == "bracket"  # as erik left it
            assert not (cfg.service.machine_vision.recipes_dir / "r.toml").exists()
            cancelled = admin.post(f"/api/teach/{session}/cancel", json={})
            assert cancelled.status_code == 200 and app.screen.teach.desk.session is None
        lines = audit(cfg)
        eves = [(e["command"], e["refusal"]) for e in lines if e["origin"]["user"] == "eve"]
        assert eves == [
            ("CapturePartImage", "access_denied"),
            ("AddPartType", "access_denied"),
            ("AddPartType", "access_denied"),
            ("CancelPartType", "access_denied"),
        ]
        assert all(
            whose in e["message"] and e["arguments"]["owner"] == "erik" for e in lines if e["origin"]["user"] == "eve"
        )
        (ada_cancel,) = [e for e in lines if e["origin"]["user"] == "ada" and e["accepted"]]
        assert ada_cancel["command"] == "CancelPartType" and ada_cancel["arguments"]["owner"] == "erik"


def test_refusals_in_words_names_and_recipe_ids_never_paths(tmp_path):
    with served(tmp_path) as (service, app, cfg):
        with logged_in(app, "erik") as engineer:
            session = engineer.post("/api/teach/capture", json={}).json()["session"]
            for name in ("../../etc/passwd", "Bracket", "bolt", "unknown", "a" * 40, ""):
                bad = learn(engineer, session, name)
                assert bad.status_code == 422 and "part type name" in bad.json()["error"], (name, bad.text)
            bad = learn(engineer, session, height_mm=0)
            assert bad.status_code == 422 and "more than 0 and at most 200 mm" in bad.json()["error"]
            assert learn(engineer, session).status_code == 200
            for recipe_id in ("../escape", "/tmp/x", "a/b", ""):
                bad = engineer.post(f"/api/teach/{session}/confirm", json={"recipe_id": recipe_id})
                assert bad.status_code == 422 and "recipe id" in bad.json()["error"], (recipe_id, bad.text)
            assert not list(tmp_path.glob("**/*.toml")) and not (tmp_path.parent / "escape.toml").exists()

            # a broken recipe is not made worse: refused before anything is written
            book = cfg.service.machine_vision.recipes_dir
            book.mkdir(parents=True, exist_ok=True)
            (book / "broken.toml").write_text("this is = not [ a recipe")
            broken = engineer.post(f"/api/teach/{session}/confirm", json={"recipe_id": "broken"})
            assert broken.status_code == 422 and "not valid TOML" in broken.json()["error"]
            assert not (book / "models").exists()

            # a job running: no frame is taken, in words
            assert engineer.post("/api/command/StartContinuous").status_code == 200
            wait_for(lambda: service.snapshot().vision_state is VisionState.CONTINUOUS_EXECUTION, "no job started")
            busy = engineer.post("/api/teach/capture", json={})
            assert busy.status_code == 409
            assert busy.json()["say"].startswith("CapturePartImage is not allowed in ContinuousExecution")
            late = engineer.post(f"/api/teach/{session}/confirm", json={"recipe_id": "brackets"})
            assert (
                late.status_code == 409 and "AddPartType is not allowed in ContinuousExecution" in late.json()["error"]
            )
            assert engineer.post("/api/command/Abort").status_code == 200
            wait_for(lambda: service.snapshot().vision_state is VisionState.READY, "the job did not end")

            cancelled = engineer.post(f"/api/teach/{session}/cancel", json={})
            assert cancelled.status_code == 200 and app.screen.teach.desk.session is None
            gone = learn(engineer, session)
            assert gone.status_code == 409 and "no such teaching session" in gone.json()["error"]
        assert any(e["command"] == "CancelPartType" and e["accepted"] for e in audit(cfg))


def test_examples_that_cannot_be_gripped_are_refused_in_words_with_the_outlines_drawn(tmp_path):
    with served(tmp_path, jaw_max_opening_mm=6.0) as (service, app, cfg):
        with logged_in(app, "erik") as engineer:
            session = engineer.post("/api/teach/capture", json={}).json()["session"]
            refused = learn(engineer, session)
            assert refused.status_code == 422, refused.text
            body = refused.json()
            assert body["say"].startswith("Cannot teach 'bracket': it cannot be gripped: its narrowest width")
            assert "jaw_max_opening_mm" in body["do"] and body["ok"] is False
            assert engineer.get(body["pictures"][0]).status_code == 200  # the outlines, without jaws
            assert engineer.post(f"/api/teach/{session}/confirm", json={"recipe_id": "r"}).status_code == 409
            assert not cfg.service.machine_vision.recipes_dir.exists()


def test_sessions_are_bounded_and_expire(tmp_path):
    with served(tmp_path, WebConfig(teach_max_frames=2, teach_timeout_s=1.0)) as (service, app, cfg):
        with logged_in(app, "erik") as engineer:
            session = engineer.post("/api/teach/capture", json={}).json()["session"]
            assert engineer.post("/api/teach/capture", json={}).status_code == 200
            full = engineer.post("/api/teach/capture", json={})
            assert full.status_code == 409 and "the most it takes" in full.json()["error"]
            assert len(app.screen.teach.desk.session.frames) == 2
            assert (
                sum(e["command"] == "CapturePartImage" for e in audit(cfg)) == 2
            )  # the third never reached the camera
            wait_for(lambda: app.screen.teach.desk.session is None, "the session was not discarded after its timeout")
            gone = engineer.post(f"/api/teach/{session}/cancel", json={})
            assert gone.status_code == 409 and "no such teaching session" in gone.json()["error"]
            assert engineer.get(f"/api/teach/{session}/frame/1.jpg").status_code == 404

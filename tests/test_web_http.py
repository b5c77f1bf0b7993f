"""The operator screen over HTTP (Starlette's TestClient) on the fake line service: status
codes, refused requests, auth, CSRF, uploads and recalibration."""

from __future__ import annotations

import re
import struct
import zlib
from importlib import resources

import cv2
import numpy as np
import pytest
from starlette.testclient import TestClient

from cell.access.network import is_loopback
from cell.config import CellConfig
from cell.core.commands import Command, VisionState
from cell.errors import ConfigError
from cell.web.app import build_app
from cell.web.auth import Access
from cell.web.config import WebConfig
from tests.fake_service import FakeLineService, plate_image

LOCAL = "http://127.0.0.1:8080"


@pytest.fixture
def service():
    s = FakeLineService()
    yield s
    s.close()


@pytest.fixture
def config(tmp_path):
    c = CellConfig()
    c.calibration.active_path = tmp_path / "calibration" / "active.json"
    c.calibration.backup_dir = tmp_path / "calibration" / "backups"
    return c


def make_client(service, config, host="127.0.0.1", web=None, check=None, base_url=LOCAL):
    web = web or WebConfig()
    return TestClient(build_app(service, config, web, Access(host, web, check)), base_url=base_url)


def operator_pw7(user: str, password: str) -> bool:
    return user == "operator" and password == "pw-7"


@pytest.fixture
def client(service, config):
    with make_client(service, config) as c:
        c.headers["x-csrf-token"] = c.get("/api/session").json()["csrf"]
        yield c


def png_bytes(image) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    assert ok
    return buf.tobytes()


# ---- the page ----------------------------------------------------------------------
def test_page_and_assets_served_with_security_headers(client):
    page = client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert page.headers["x-frame-options"] == "DENY"
    assert "frame-ancestors 'none'" in page.headers["content-security-policy"]
    for asset in ("/static/screen.js", "/static/screen.css"):
        assert client.get(asset).status_code == 200
    for label in ("Start", "Start continuous", "Pause", "Resume", "Stop", "Halt", "Reset"):
        assert f">{label}</button>" in page.text


def test_static_files_load_nothing_from_outside():
    static = resources.files("cell.web") / "static"
    for name in ("index.html", "screen.css", "screen.js"):
        text = (static / name).read_text()
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}/", text, re.I), f"{name} references another host"


def test_no_path_from_the_request_reaches_the_disk(client):
    for path in (
        "/static/../app.py",
        "/static/%2e%2e/app.py",
        "/static/index.html",
        "/etc/passwd",
        "/api/calibration/..%2fx",
    ):
        assert client.get(path).status_code == 404


# ---- commands ----------------------------------------------------------------------
def test_command_goes_through_the_service_and_its_table(client, service):
    assert client.post("/api/command/StartContinuous").json() == {"ok": True, "command": "StartContinuous"}
    assert service.commands == [Command.START_CONTINUOUS]
    refused = client.post("/api/command/Reset")  # not allowed while running
    assert refused.status_code == 409 and "Reset is not allowed in ContinuousExecution" in refused.json()["error"]
    assert service.state is VisionState.CONTINUOUS_EXECUTION
    assert client.post("/api/command/Stop").status_code == 200
    assert service.state is VisionState.READY


def test_command_refused_without_or_with_a_wrong_csrf_token(client, service):
    assert client.post("/api/command/StartSingleJob", headers={"x-csrf-token": ""}).status_code == 403
    assert client.post("/api/command/StartSingleJob", headers={"x-csrf-token": "guess"}).status_code == 403
    assert service.commands == []


def test_command_refused_from_another_origin_even_with_the_token(client, service):
    r = client.post("/api/command/Halt", headers={"origin": "http://evil.example"})
    assert r.status_code == 403 and "cross-origin" in r.json()["error"]
    assert client.post("/api/command/Halt", headers={"sec-fetch-site": "cross-site"}).status_code == 403
    assert client.post("/api/command/Halt", headers={"origin": LOCAL}).status_code == 200
    assert service.commands == [Command.HALT]


def test_command_must_be_a_post_and_a_known_name(client, service):
    assert client.get("/api/command/StartSingleJob").status_code == 405
    r = client.post("/api/command/rm%20-rf")
    assert r.status_code == 404 and "StartContinuous" in r.json()["known"]
    assert service.commands == []


def test_a_rebound_host_name_is_refused_on_loopback(client):
    r = client.get("/api/state", headers={"host": "attacker.example:8080"})
    assert r.status_code == 421
    assert client.get("/api/state", headers={"host": "localhost:8080"}).status_code == 200
    assert client.get("/api/state", headers={"host": "[::1]:8080"}).status_code == 200


def test_state_json_has_what_the_screen_shows(client, service):
    service.fault("arm not answering on /dev/ttyUSB0", "check the cable, then Reset")
    s = client.get("/api/state").json()
    assert s["display"] == {"key": "fault", "label": "Fault", "next": s["alarm"]["say"] + " " + s["alarm"]["do"]}
    assert s["alarm"]["reason"].startswith("arm not answering") and s["alarm"]["hint"].endswith("Reset")
    assert s["alarm"]["do"] == "Check the cable, then Reset."  # a hint in plain words is shown as it is
    assert s["allowed"] == ["Reset"]
    assert s["calibration"]["model"] == "polynomial"


# ---- recipes -----------------------------------------------------------------------
BOLTS_ONLY = (
    'description = "bolts only"\n\n[pick.bolt]\npick_above_table_mm = 3.5\nbin_robot_mm = [-200.0, 60.0, 60.0]\n'
)


@pytest.fixture
def recipe_client(tmp_path, config):
    folder = tmp_path / "recipes"
    folder.mkdir()
    (folder / "bolts-only.toml").write_text(BOLTS_ONLY)
    (folder / "broken.toml").write_text("pick = 3\n")
    service = FakeLineService(recipes_dir=folder)
    with make_client(service, config) as c:
        c.headers["x-csrf-token"] = c.get("/api/session").json()["csrf"]
        yield c, service
    service.close()


def test_recipes_are_listed_and_switched_through_the_command_table(recipe_client):
    client, service = recipe_client
    listed = client.get("/api/recipes").json()
    assert listed["active"] == ""
    by_id = {r["id"]: r for r in listed["recipes"]}
    assert by_id["bolts-only"]["description"] == "bolts only" and by_id["bolts-only"]["error"] == ""
    assert "pick" in by_id["broken"]["error"]  # listed, with why it cannot be used
    r = client.post("/api/recipe", json={"recipe_id": "bolts-only"})
    assert r.json() == {"ok": True, "command": "PrepareRecipe", "recipe": "bolts-only"}
    assert client.get("/api/state").json()["recipe"] == "bolts-only"
    assert client.get("/api/recipes").json()["active"] == "bolts-only"
    r = client.post("/api/recipe", json={"recipe_id": "broken"})
    assert r.status_code == 422 and r.json()["refusal"] == "bad_argument"
    r = client.post("/api/recipe", json={"recipe_id": "nothing-here"})
    assert r.status_code == 422 and "not found" in r.json()["error"]
    assert client.post("/api/recipe", json={"recipe_id": ""}).json()["command"] == "UnprepareRecipe"
    assert client.get("/api/state").json()["recipe"] == ""
    assert service.commands == [Command.PREPARE_RECIPE, Command.UNPREPARE_RECIPE]


def test_a_recipe_changes_only_in_ready_and_only_with_the_token(recipe_client):
    client, service = recipe_client
    assert client.post("/api/recipe", json={"recipe_id": "bolts-only"}, headers={"x-csrf-token": ""}).status_code == 403
    assert client.post("/api/recipe", content=b"bolts-only").status_code == 400
    client.post("/api/command/StartContinuous")
    assert client.get("/api/state").json()["recipe_allowed"] is False
    r = client.post("/api/recipe", json={"recipe_id": "bolts-only"})
    assert r.status_code == 409 and "PrepareRecipe is not allowed in ContinuousExecution" in r.json()["error"]
    assert service.recipe == "" and service.commands == [Command.START_CONTINUOUS]


# ---- password ----------------------------------------------------------------------
def test_loopback_detection():
    assert all(is_loopback(h) for h in ("127.0.0.1", "localhost", "::1", "[::1]", "127.0.0.2"))
    assert not any(is_loopback(h) for h in ("0.0.0.0", "192.168.1.20", "cellpc.local", "::"))


def test_non_loopback_bind_without_password_refuses_to_start():
    with pytest.raises(ConfigError, match="beyond loopback, without a password"):
        Access("0.0.0.0", WebConfig())


def test_non_loopback_needs_the_password_for_view_and_controls(service, config):
    with make_client(service, config, "0.0.0.0", check=operator_pw7, base_url="http://192.0.2.10:8080") as c:
        assert c.get("/").status_code == 200  # the login page itself
        assert c.get("/api/session").json()["can_view"] is False
        assert c.get("/api/state").status_code == 401
        assert c.get("/api/events").status_code == 401
        assert c.post("/api/command/StartSingleJob").status_code == 401
        wrong = c.post("/api/login", json={"user": "operator", "password": "pw-8"})
        assert wrong.status_code == 401 and "cell_session" not in c.cookies
        assert c.post("/api/login", json={"password": "pw-7"}).status_code == 400
        ok = c.post("/api/login", json={"user": "operator", "password": "pw-7"})
        assert ok.status_code == 200 and "cell_session" in c.cookies
        assert "httponly" in ok.headers["set-cookie"].lower() and "samesite=strict" in ok.headers["set-cookie"].lower()
        assert c.get("/api/state").status_code == 200
        assert c.post("/api/command/StartSingleJob").status_code == 403  # logged in, still needs the CSRF token
        r = c.post("/api/command/StartSingleJob", headers={"x-csrf-token": ok.json()["csrf"]})
        assert r.status_code == 200 and service.commands == [Command.START_SINGLE]
        c.post("/api/logout", headers={"x-csrf-token": ok.json()["csrf"]})
        assert c.post("/api/command/Stop", headers={"x-csrf-token": ok.json()["csrf"]}).status_code == 401


def test_view_may_be_left_open_while_controls_keep_the_password(service, config):
    web = WebConfig(view_without_password=True)
    with make_client(service, config, "0.0.0.0", web, operator_pw7, base_url="http://192.0.2.10:8080") as c:
        assert c.get("/api/state").status_code == 200
        session = c.get("/api/session").json()
        assert session["can_view"] and not session["can_control"] and session["csrf"] is None
        assert c.post("/api/command/StartContinuous").status_code == 401
        assert c.post("/api/recalibration/upload", content=b"x").status_code == 401
    assert service.commands == []


def test_login_from_another_origin_is_refused(service, config):
    with make_client(service, config, check=operator_pw7) as c:
        r = c.post(
            "/api/login", json={"user": "operator", "password": "pw-7"}, headers={"origin": "http://evil.example"}
        )
        assert r.status_code == 403 and "cell_session" not in c.cookies


# ---- recalibration -----------------------------------------------------------------
def test_recalibration_refused_while_running(client, service, config):
    client.post("/api/command/StartContinuous")
    r = client.post("/api/recalibration/capture")
    assert r.status_code == 409 and "the cell is moving (pause or stop it first)" in r.json()["error"]  # the table's
    assert r.json()["say"] == "The cell is running."
    assert not config.calibration.active_path.exists()


@pytest.mark.slow  # fits a rendered plate
def test_recalibrate_from_camera_accept_installs_through_the_gate(client, service, config):
    client.post("/api/command/StartContinuous")
    client.post("/api/command/Pause")
    report = client.post("/api/recalibration/capture").json()
    assert report["passes"] and report["points"] == 156 and report["cv_rms_mm"] < 0.05
    assert client.get(f"/api/recalibration/{report['id']}/plate.jpg").headers["content-type"] == "image/jpeg"
    assert client.get(f"/api/recalibration/{report['id']}/deviation.png").content[:4] == b"\x89PNG"
    assert client.post("/api/command/Resume").status_code == 409  # stays paused while the report is open
    assert client.post(f"/api/recalibration/{report['id']}/accept").json()["accepted"] is True
    assert config.calibration.active_path.is_file() and len(service.installed) == 1
    assert service.calibration.source_image.startswith("camera frame")
    state = client.get("/api/state").json()
    assert state["calibration"]["pictures"] is True and state["recalibration_open"] is False
    assert client.get("/api/calibration/deviation.png").status_code == 200
    # a second accept of the same report, or a guessed id, changes nothing
    assert client.post(f"/api/recalibration/{report['id']}/accept").status_code == 409
    assert client.post("/api/recalibration/deadbeef/accept").status_code == 409
    assert client.post("/api/command/Resume").status_code == 200


@pytest.mark.slow  # fits a rendered plate
def test_recalibration_reject_leaves_everything(client, service, config):
    report = client.post("/api/recalibration/upload", content=png_bytes(plate_image())).json()
    assert report["passes"] and report["source"].startswith("uploaded image sha256")
    assert client.post(f"/api/recalibration/{report['id']}/reject").json()["accepted"] is False
    assert not config.calibration.active_path.exists() and service.installed == []
    assert client.get(f"/api/recalibration/{report['id']}/plate.jpg").status_code == 404


@pytest.mark.slow  # fits a rendered plate
def test_a_fit_over_the_limits_is_refused_by_the_same_gate(client, service, config):
    config.calibration.max_cv_rms_mm = 0.0001
    config.calibration.active_path.parent.mkdir(parents=True)
    config.calibration.active_path.write_text("previous")
    report = client.post("/api/recalibration/upload", content=png_bytes(plate_image())).json()
    assert report["passes"] is False and "max_cv_rms_mm" in report["gate_failure"]
    r = client.post(f"/api/recalibration/{report['id']}/accept")
    assert r.status_code == 422 and "left unchanged" in r.json()["error"]
    assert config.calibration.active_path.read_text() == "previous" and service.installed == []


def _png_header(width: int, height: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))


@pytest.mark.parametrize(
    "body, status, message",
    [
        (b"", 422, "empty file"),
        (b"#!/bin/sh\nrm -rf /\n", 422, "not a PNG or JPEG"),
        (_png_header(1920, 1080) + b"garbage", 422, "cannot decode"),
        (_png_header(60000, 60000), 422, "60000 x 60000 px but the camera is configured for 1920 x 1080"),
        (b"\xff\xd8\xff\xe0" + b"\x00" * 40, 422, "not a PNG or JPEG"),
    ],
    ids=["empty", "shell-text", "truncated-png", "gigapixel-header", "broken-jpeg"],
)
def test_malformed_upload_refused_with_the_calibration_untouched(client, service, config, body, status, message):
    config.calibration.active_path.parent.mkdir(parents=True)
    config.calibration.active_path.write_text("previous")
    r = client.post("/api/recalibration/upload", content=body, headers={"content-type": "application/octet-stream"})
    assert r.status_code == status and message in r.json()["error"]
    assert "active calibration is unchanged" in r.json()["error"]
    assert config.calibration.active_path.read_text() == "previous" and service.installed == []


def test_upload_of_the_wrong_size_and_without_a_plate(client, config):
    small = client.post("/api/recalibration/upload", content=png_bytes(np.zeros((480, 640, 3), np.uint8)))
    assert small.status_code == 422 and "640 x 480 px" in small.json()["error"]
    blank = client.post("/api/recalibration/upload", content=png_bytes(np.full((1080, 1920, 3), 255, np.uint8)))
    assert blank.status_code == 422 and "no plate in view" in blank.json()["error"]
    assert not config.calibration.active_path.exists()


def test_a_refused_recalibration_says_what_to_do_with_the_technical_text_as_details(client, config):
    blank = client.post("/api/recalibration/upload", content=png_bytes(np.full((1080, 1920, 3), 255, np.uint8)))
    body = blank.json()
    assert blank.status_code == 422 and body["say"] == "No plate in view."
    assert body["do"].startswith("Put the calibration plate") and body["details"] == body["error"]
    small = client.post("/api/recalibration/upload", content=png_bytes(np.zeros((480, 640, 3), np.uint8))).json()
    assert small["say"] == "The picture is 640 x 480 pixels; this cell's camera takes 1920 x 1080."
    client.post("/api/command/StartContinuous")
    running = client.post("/api/recalibration/capture").json()
    assert running["say"] == "The cell is running." and running["do"] == "Press Pause or Stop first, then Recalibrate."


def test_oversized_upload_refused_before_it_is_read(service, config):
    with make_client(service, config, web=WebConfig(max_upload_mb=1)) as c:
        token = c.get("/api/session").json()["csrf"]
        r = c.post(
            "/api/recalibration/upload",
            content=b"\x89PNG" + b"\x00" * (1024 * 1024 + 1),
            headers={"x-csrf-token": token},
        )
        assert r.status_code == 413 and "at most 1024 KiB" in r.json()["error"]
        assert r.json()["say"] == "The file is too large (at most 1 MB)."
    assert not config.calibration.active_path.exists()


def test_upload_header_sizes_for_png_and_jpeg():
    from cell.web.recalibration import decode_upload, image_size_from_header

    image = np.zeros((1080, 1920, 3), np.uint8)
    for ext in (".png", ".jpg"):
        ok, buf = cv2.imencode(ext, image)
        assert image_size_from_header(buf.tobytes()) == (1920, 1080)
        assert decode_upload(buf.tobytes(), CellConfig()).shape == (1080, 1920, 3)
    ok, progressive = cv2.imencode(".jpg", image[:480, :640], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    assert image_size_from_header(progressive.tobytes()) == (640, 480)
    assert image_size_from_header(b"GIF89a....") is None

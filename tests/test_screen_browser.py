"""The operator screen's layout and words in a real browser (headless system Chromium through
Playwright) at 1920 x 1080, 1280 x 720 and a 10" panel's 1024 x 600: the essentials without
scrolling (element boxes measured against the window), the still before the first job and the
live view between jobs, the next action in each state, ISO 8601 dates, the status line clear
of the picks table, the recalibration dialog (pictures full size, Reject closes, refusals in
operator words), recipes; and, against `run-cell serve --dry-run` with its simulated camera
bumped after calibration, the drift alarm from the real drift watch through to Recalibrate and
Reset.

Skips, saying why, without Playwright or a Chromium."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from cell.config import CellConfig
from cell.web.config import WebConfig
from cell.web.server import WebServer
from tests.browser import launch, why_no_browser
from tests.fake_service import FakeLineService
from tests.serve_process import ServeProcess

pytestmark = [
    pytest.mark.skipif(why_no_browser() is not None, reason=str(why_no_browser())),
    pytest.mark.slow,  # a browser; one module runs `run-cell serve` in a subprocess
    pytest.mark.timeout(240),
]

SIZES = [(1920, 1080), (1280, 720), (1024, 600)]
TIMEOUT_S = 15.0
ZONE = "Asia/Kolkata"  # +05:30 all year: the page's own zone, not the machine's, and a half hour to format
ISO_LOCAL = r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}\+05:30$"
DRIFT = (
    "CameraMoved: camera moved 0.81 mm since calibration (reference marks seen shifted by -0.80, +0.00 mm, "
    "limit drift.limit_mm 0.25 mm); check or recalibrate",
    "run-cell check-calibration with the plate in its fixture, or run-cell recalibrate",
)
RECIPE = 'description = "bolts only"\n\n[pick.bolt]\npick_above_table_mm = 3.5\nbin_robot_mm = [-200.0, 60.0, 60.0]\n'


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = launch(p)
        yield b
        b.close()


def fake_screen(tmp_path, live_interval_s: float = 0.3, camera=(1920, 1080)):
    service = FakeLineService(interval_s=0.1, recipes_dir=tmp_path / "recipes", plate_size=camera)
    config = CellConfig()
    config.camera.width_px, config.camera.height_px = camera
    config.calibration.active_path = tmp_path / "active.json"
    config.calibration.backup_dir = tmp_path / "backups"
    server = WebServer(service, config, WebConfig(live_interval_s=live_interval_s), "127.0.0.1", 0)
    server.start()
    return service, server


@pytest.fixture
def fake_cell(tmp_path):
    service, server = fake_screen(tmp_path)
    yield service, server.url
    server.stop()
    service.close()


class Page:
    """One screen at one window size, in the page's own time zone, recording console errors."""

    def __init__(self, browser, url: str, size=(1600, 1000)):
        self.context = browser.new_context(viewport={"width": size[0], "height": size[1]}, timezone_id=ZONE)
        self.page = self.context.new_page()
        self.page.set_default_timeout(TIMEOUT_S * 1000)
        self.errors: list[str] = []
        self.page.on("console", lambda m: m.type == "error" and self.errors.append(m.text))
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.goto(url)
        self.wait("window.screenStats && screenStats.states > 0")

    def wait(self, expression: str, timeout_s: float = TIMEOUT_S) -> None:
        """Until the JS expression is true, polled from here (the page's CSP forbids wait_for_function's eval)."""
        deadline = time.monotonic() + timeout_s
        while not self.page.evaluate(expression):
            assert time.monotonic() < deadline, f"not true within {timeout_s} s: {expression}"
            time.sleep(0.05)

    def js(self, expression: str):
        return self.page.evaluate(expression)

    def text(self, selector: str) -> str:
        return self.page.inner_text(selector)

    def press(self, name: str) -> None:
        self.page.get_by_role("button", name=name, exact=True).click()

    def key(self, key: str) -> None:
        self.wait(f"screenStats.lastState && screenStats.lastState.display.key === {json.dumps(key)}")

    def box(self, selector: str) -> dict:
        return self.js(
            f"(() => {{ const r = document.querySelector({json.dumps(selector)}).getBoundingClientRect();"
            " return {x: r.left, y: r.top, right: r.right, bottom: r.bottom, w: r.width, h: r.height}; })()"
        )

    def close(self) -> None:
        self.context.close()


def inside(box: dict, w: int, h: int) -> bool:
    return (
        box["w"] > 0 and box["h"] > 0 and box["x"] >= 0 and box["y"] >= 0 and box["right"] <= w and box["bottom"] <= h
    )


def overlap(a: dict, b: dict) -> bool:
    return a["x"] < b["right"] and b["x"] < a["right"] and a["y"] < b["bottom"] and b["y"] < a["bottom"]


ESSENTIALS = ["#state-label", "#state-next", "#frame", "#controls", "#counts", "#picks", "#picks tbody tr"]
COMMANDS = ["Start", "Start continuous", "Pause", "Resume", "Stop", "Halt", "Reset"]


@pytest.mark.parametrize("size", SIZES, ids=[f"{w}x{h}" for w, h in SIZES])
def test_the_essentials_fit_the_window_without_scrolling(browser, fake_cell, size):
    service, url = fake_cell
    w, h = size
    screen = Page(browser, url, size)
    screen.press("Start continuous")
    screen.wait("document.querySelectorAll('#picks-body tr').length >= 3")
    for selector in ESSENTIALS:
        assert inside(screen.box(selector), w, h), (
            f"{selector} not wholly in the {w} x {h} window: {screen.box(selector)}"
        )
    for name in COMMANDS:
        assert inside(screen.box(f"button[data-command='{_command(name)}']"), w, h), name
    assert screen.js("document.scrollingElement.scrollHeight <= window.innerHeight + 1"), "the page itself scrolls"
    assert screen.js("document.scrollingElement.scrollWidth <= window.innerWidth + 1"), "the page scrolls sideways"
    frame = screen.box("#frame")
    assert frame["h"] >= 0.4 * h and frame["w"] >= 0.5 * w  # the frame keeps most of the window
    # "Start continuous" on one line: its text is one line box, and the button holds it all
    lines = screen.js(
        "(() => { const b = document.querySelector('[data-command=StartContinuous]'); const r = document.createRange();"
        " r.selectNodeContents(b); return [r.getClientRects().length, b.scrollWidth <= b.clientWidth]; })()"
    )
    assert lines == [1, True]
    # every column of the picks table in view: the last one (Outcome) too
    assert inside(screen.box("#picks thead th:last-child"), w, h)
    assert screen.box("#picks thead th:last-child")["right"] <= screen.box("#picks")["right"]
    assert screen.errors == []
    screen.close()


def _command(name: str) -> str:
    return {"Start": "StartSingleJob", "Start continuous": "StartContinuous"}.get(name, name)


@pytest.mark.parametrize("size", SIZES, ids=[f"{w}x{h}" for w, h in SIZES])
def test_the_status_line_never_covers_the_picks_table(browser, fake_cell, size):
    service, url = fake_cell
    screen = Page(browser, url, size)
    screen.press("Start continuous")
    screen.wait("document.querySelectorAll('#picks-body tr').length >= 3")
    screen.press("Pause")
    screen.wait("document.getElementById('message').textContent === 'Pause: accepted'")
    message = screen.box("#message")
    assert inside(message, *size)
    for selector in ("#picks", "#picks table", "#frame", "#controls", "#counts", "#banner"):
        assert not overlap(message, screen.box(selector)), f"the status line covers {selector}"
    picks = screen.box("#picks")
    screen.js("showMessage('Start continuous refused: ' + 'a long reason why, '.repeat(20), true)")  # the longest kind
    assert screen.box("#message") == message and screen.box("#picks") == picks  # one line, nothing moved
    assert screen.errors == []
    screen.close()


def test_dates_are_iso_8601_in_the_pages_local_time_with_its_zone(browser, fake_cell):
    service, url = fake_cell
    screen = Page(browser, url)
    screen.press("Start continuous")
    screen.wait("document.querySelectorAll('#picks-body tr').length >= 1 && screenStats.frames > 0")
    service.fault(*DRIFT)
    screen.key("fault")
    screen.wait("document.getElementById('frame-time').textContent !== ''")
    dates = [
        screen.text("#picks-body tr:first-child td:first-child"),
        screen.text("#alarm-time"),
        screen.text("#cal-time"),
        screen.text("#frame-time"),
    ]
    for date in dates:
        assert re.match(ISO_LOCAL, date), date
    screen.close()


def test_a_still_before_the_first_job_then_the_live_view_with_its_time_advancing(browser, fake_cell):
    service, url = fake_cell
    screen = Page(browser, url)
    screen.wait("document.getElementById('frame').complete")
    assert screen.js("document.getElementById('frame').naturalWidth") > 0  # never a broken image
    screen.wait("screenStats.lastLive && screenStats.liveFrames >= 1")
    assert screen.text("#frame-kind") == "● live camera"
    first = screen.text("#frame-time")
    screen.wait(f"document.getElementById('frame-time').textContent > {json.dumps(first)}")  # a newer frame
    assert screen.js("document.getElementById('frame').naturalWidth") == 960  # the camera's picture
    screen.press("Start continuous")
    screen.wait("!screenStats.lastLive && document.getElementById('frame-kind').textContent === 'job frame'")
    assert screen.errors == []
    screen.close()


def test_without_a_live_view_the_still_is_a_picture_saying_so(browser, tmp_path):
    service, server = fake_screen(tmp_path, live_interval_s=0)
    try:
        screen = Page(browser, server.url, (1024, 600))
        screen.wait("document.getElementById('frame').complete")
        assert screen.js("document.getElementById('frame').naturalWidth") > 0
        assert screen.js("document.getElementById('frame').src").endswith("/static/no-frame.svg")
        assert screen.errors == []
        screen.close()
    finally:
        server.stop()
        service.close()


def test_each_state_says_what_to_do_next_and_the_rate_is_a_dash_when_not_running(browser, fake_cell):
    service, url = fake_cell
    screen = Page(browser, url, (1024, 600))
    screen.key("stopped")
    assert screen.text("#state-next") == "Press Start to clear the table once, or Start continuous to keep picking."
    assert screen.text("#parts-per-min") == "-"
    screen.press("Start continuous")
    screen.key("running")
    assert screen.text("#state-next").startswith("Picking parts as they arrive")
    screen.wait("document.getElementById('parts-per-min').textContent !== '-'")
    screen.press("Pause")
    screen.key("paused")
    assert screen.text("#state-next").startswith("Press Resume to go on, or Stop")
    assert screen.text("#parts-per-min") == "-"
    screen.press("Halt")
    screen.page.click("#confirm-yes")
    screen.key("halted")
    assert screen.text("#state-next") == "Nothing runs until you press Reset."
    screen.press("Reset")
    screen.key("stopped")
    service.fault(*DRIFT)
    screen.key("fault")
    said = "The camera has moved since calibration (by 0.81 mm). Check it is fixed, then use Recalibrate, then press Reset."
    assert screen.text("#state-next") == said
    assert "run-cell" not in screen.text("#banner") + screen.text("#alarm")
    assert not screen.page.is_visible("#alarm-technical")  # the technical text waits behind "details"
    screen.page.click("#alarm-details summary")
    assert "drift.limit_mm" in screen.text("#alarm-technical") and "run-cell check-calibration" in screen.text(
        "#alarm-technical"
    )
    assert screen.page.is_enabled("#alarm-recal")  # the alarm's own advice, one press away and in view
    assert inside(screen.box("#alarm-recal"), 1024, 600)
    screen.page.click("#alarm-recal")
    assert screen.js("document.getElementById('recal').open")
    assert screen.errors == []
    screen.close()


@pytest.fixture
def small_camera_cell(tmp_path):
    """The fake cell with a 960 x 540 camera: a plate fitted in a quarter of the time."""
    service, server = fake_screen(tmp_path, camera=(960, 540))
    yield service, server.url
    server.stop()
    service.close()


def test_recalibration_pictures_open_full_size_reject_closes_and_refusals_say_what_to_do(
    browser, small_camera_cell, tmp_path
):
    service, url = small_camera_cell
    screen = Page(browser, url, (1280, 720))
    screen.page.click("#recal-open")
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((540, 960, 3), 255, np.uint8))
    screen.page.set_input_files("#recal-file", str(blank))
    screen.wait("document.getElementById('recal-status').textContent.startsWith('Refused')", 60)
    assert screen.text("#recal-status") == "Refused: No plate in view."
    assert screen.text("#recal-do").startswith("Put the calibration plate")
    screen.page.click("#recal-details summary")
    assert "no plate in view" in screen.text("#recal-technical")
    screen.page.click("#recal-capture")
    screen.wait("!document.getElementById('recal-report').hidden", 90)
    screen.wait("document.getElementById('rep-plate').naturalWidth > 0")
    screen.page.click("#rep-plate")
    screen.wait("document.getElementById('picture').open && document.getElementById('picture-img').complete")
    full = screen.js(
        "(() => { const i = document.getElementById('picture-img'); return [i.naturalWidth, i.width]; })()"
    )
    assert full[0] == 960 and full[1] == full[0]  # at its own size (the dialog scrolls where it is larger)
    screen.page.keyboard.press("Escape")
    screen.wait("!document.getElementById('picture').open")
    assert screen.js("document.getElementById('recal').open")  # Esc closed the picture only
    screen.wait("document.querySelector('[data-command=StartContinuous]').disabled")  # held while the report is open
    screen.page.click("#recal-reject")
    screen.wait("!document.getElementById('recal').open")  # Reject closes the dialog
    screen.wait("!document.querySelector('[data-command=StartContinuous]').disabled")
    assert service.installed == [] and screen.text("#message").startswith("Rejected")
    assert screen.errors == [
        "Failed to load resource: the server responded with a status of 422 (Unprocessable Entity)"
    ]
    screen.close()


def test_the_active_recipe_is_shown_and_switched_in_ready_only(browser, fake_cell, tmp_path):
    service, url = fake_cell
    (tmp_path / "recipes").mkdir()
    (tmp_path / "recipes" / "bolts-only.toml").write_text(RECIPE)
    screen = Page(browser, url, (1024, 600))
    screen.wait("document.querySelectorAll('#recipe-select option').length === 2")
    assert screen.text("#recipe-active") == "none" and inside(screen.box("#recipe"), 1024, 600)
    screen.page.select_option("#recipe-select", "bolts-only")
    screen.page.click("#recipe-use")
    screen.wait("document.getElementById('recipe-active').textContent === 'bolts-only'")
    assert service.recipe == "bolts-only"
    screen.press("Start continuous")
    screen.key("running")
    assert screen.page.is_disabled("#recipe-select") and screen.page.is_disabled("#recipe-use")
    assert screen.errors == []
    screen.close()


def test_the_camera_check_shows_focus_exposure_plate_and_advice_in_place_of_the_picks(browser, fake_cell):
    service, url = fake_cell
    screen = Page(browser, url, (1024, 600))
    screen.page.click("#check-toggle")
    screen.wait("!document.getElementById('check').hidden && document.getElementById('picks').hidden")
    screen.wait("!document.getElementById('check-readings').hidden", 30)
    assert re.match(r"^\d+\.\d, best \d+\.\d \(\d+ %\)$", screen.text("#check-focus"))
    assert screen.text("#check-exposure").startswith("mean ")
    assert screen.js("document.querySelectorAll('#check-histogram i').length") == 16
    assert screen.text("#check-plate").startswith("not found") and screen.text("#check-advice").startswith("plate:")
    assert inside(screen.box("#check"), 1024, 600)
    screen.page.click("#check-toggle")
    screen.wait("document.getElementById('check').hidden && !document.getElementById('picks').hidden")
    assert screen.errors == []
    screen.close()


# ---- the real service: the drift watch's alarm, followed from the screen --------------------
@pytest.fixture(scope="module")
def bumped_serve(tmp_path_factory):
    """`run-cell serve --dry-run` whose simulated camera moved 0.8 mm after the plate was calibrated."""
    workdir: Path = tmp_path_factory.mktemp("bumped")
    (workdir / "bumped.toml").write_text("[sim]\ncamera_bumped_mm = [0.8, 0.0]\ncamera_bumped_at_pick = 0\n")
    proc = ServeProcess(workdir, "--config", str(workdir / "bumped.toml"))
    yield proc
    assert proc.stop() == 0, "\n".join(proc.lines[-20:])


def test_the_drift_alarm_from_the_real_watch_is_followed_by_recalibrate_and_reset(browser, bumped_serve):
    screen = Page(browser, bumped_serve.url, (1280, 720))
    screen.wait("screenStats.lastLive && screenStats.liveFrames >= 1")  # the live view while Ready
    first = screen.text("#frame-time")
    screen.wait(f"document.getElementById('frame-time').textContent > {json.dumps(first)}")
    screen.press("Start")
    screen.key("fault")  # the first frame of the job: the marks have moved
    assert screen.text("#state-next").startswith("The camera has moved since calibration (by 0.8")
    assert screen.text("#state-next").endswith("Check it is fixed, then use Recalibrate, then press Reset.")
    screen.page.click("#alarm-recal")
    screen.page.click("#recal-capture")
    screen.wait("!document.getElementById('recal-report').hidden", 120)
    assert screen.text("#rep-gate") == "passes"
    screen.page.click("#recal-accept")
    screen.wait("document.getElementById('recal-status').textContent.startsWith('Accepted')", 60)
    screen.page.click("#recal-close")
    screen.press("Reset")
    screen.key("stopped")
    screen.press("Start")  # the new calibration sees the marks where they are: the job runs
    screen.wait(
        "Number(document.getElementById('count-picked_bolts')?.textContent ?? 0) + "
        "Number(document.getElementById('count-picked_nuts')?.textContent ?? 0) >= 1",
        120,
    )
    assert screen.js("screenStats.lastState.display.key") != "fault"
    screen.press("Stop")
    screen.page.click("#confirm-yes")
    screen.key("stopped")
    assert screen.errors == []
    screen.close()

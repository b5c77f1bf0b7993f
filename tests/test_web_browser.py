"""The operator screen in a real browser (headless system Chromium through Playwright),
against `run-cell serve --dry-run` in a subprocess; the fault alarm against the fake service,
which can fault on cue.

Skips, saying why, without Playwright or a Chromium; a screenshot of each run is kept in
test-artifacts/."""

from __future__ import annotations

import json
import time
from pathlib import Path

import httpx
import pytest

from cell.config import CellConfig
from cell.web.config import WebConfig
from cell.web.server import WebServer
from tests.browser import launch, why_no_browser
from tests.fake_service import FakeLineService
from tests.serve_process import ServeProcess

pytestmark = [
    pytest.mark.skipif(why_no_browser() is not None, reason=str(why_no_browser())),
    pytest.mark.slow,  # a browser and `run-cell serve` in a subprocess
    pytest.mark.timeout(180),
]

ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts"
TIMEOUT_MS = 10_000


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = launch(p)
        yield b
        b.close()


@pytest.fixture(scope="module")
def serve(tmp_path_factory):
    """`run-cell serve --dry-run` in a subprocess (in a folder of its own: logs, calibration)."""
    workdir = tmp_path_factory.mktemp("serve")
    proc = ServeProcess(workdir)
    yield proc
    assert proc.stop() == 0, "\n".join(proc.lines[-20:])


@pytest.fixture
def live(serve):
    """The served screen's address, with the cell back in Ready after the test."""
    yield serve.url
    token = httpx.get(serve.url + "api/session").json()["csrf"]
    deadline = time.monotonic() + 30
    while (state := httpx.get(serve.url + "api/state").json())["vision_state"] != "Ready":
        for command in ("Resume", "Stop", "Reset"):
            if command in state["allowed"]:
                httpx.post(serve.url + f"api/command/{command}", headers={"x-csrf-token": token})
        assert time.monotonic() < deadline, f"the cell did not come back to Ready: {state['display']}"
        time.sleep(0.2)


@pytest.fixture
def fake_cell(tmp_path):
    """The fake line service with the real screen server in a thread (for what a dry run cannot do on cue)."""
    service = FakeLineService(interval_s=0.1)
    config = CellConfig()
    config.calibration.active_path = tmp_path / "active.json"
    config.calibration.backup_dir = tmp_path / "backups"
    server = WebServer(service, config, WebConfig(), "127.0.0.1", 0)
    server.start()
    yield service, server.url
    server.stop()
    service.close()


class Screen:
    """A page on the screen that records every console error and failed request."""

    def __init__(self, browser, url: str):
        self.page = browser.new_page(viewport={"width": 1600, "height": 1000})
        self.page.set_default_timeout(TIMEOUT_MS)
        self.errors: list[str] = []
        self.page.on("console", lambda m: m.type == "error" and self.errors.append(m.text))
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.on("requestfailed", lambda r: self.errors.append(f"{r.url}: {r.failure}"))
        self.page.goto(url)
        self.wait("window.screenStats && window.screenStats.states > 0")

    def label(self) -> str:
        return self.page.inner_text("#state-label")

    def wait(self, expression: str, timeout_s: float = TIMEOUT_MS / 1000) -> None:
        """Until the JS expression is true, polled from here (wait_for_function would eval in the page,
        which its Content-Security-Policy forbids)."""
        deadline = time.monotonic() + timeout_s
        while not self.page.evaluate(expression):
            assert time.monotonic() < deadline, f"not true within {timeout_s} s: {expression}"
            time.sleep(0.05)

    def wait_label(self, text: str, timeout_s: float = TIMEOUT_MS / 1000) -> None:
        self.wait(f"document.getElementById('state-label').textContent.startsWith({json.dumps(text)})", timeout_s)

    def wait_picked_over(self, n: int, timeout_s: float = TIMEOUT_MS / 1000) -> None:
        self.wait(
            f"Number(document.getElementById('count-picked_bolts')?.textContent ?? 0) + "
            f"Number(document.getElementById('count-picked_nuts')?.textContent ?? 0) > {n}",
            timeout_s,
        )

    def button(self, name: str):
        return self.page.get_by_role("button", name=name, exact=True)

    def picked(self) -> int:
        return int(self.page.inner_text("#count-picked_bolts")) + int(self.page.inner_text("#count-picked_nuts"))

    def stats(self) -> dict:
        return self.page.evaluate("({frames: screenStats.frames, seq: screenStats.lastSeq})")


RUNNING_OR_WAITING = "/^(Running|Waiting for parts)/.test(document.getElementById('state-label').textContent)"


def test_page_loads_without_console_errors_and_shows_the_state(browser, live):
    screen = Screen(browser, live)
    screen.wait_label("Stopped: ready to start")
    assert screen.button("Start continuous").is_enabled() and screen.button("Start").is_enabled()
    assert screen.button("Pause").is_disabled() and screen.button("Reset").is_disabled()
    assert "state-stopped" in screen.page.get_attribute("#banner", "class")
    assert screen.page.inner_text("#cal-model") != ""
    assert screen.errors == []


def test_start_continuous_pause_resume_stop(browser, live):
    screen = Screen(browser, live)
    before = screen.picked()
    screen.button("Start continuous").click()
    screen.wait(RUNNING_OR_WAITING)
    screen.wait_picked_over(before + 1, timeout_s=60)  # counts rise
    first = screen.stats()
    screen.wait(f"screenStats.lastSeq > {first['seq'] + 2}")  # the frame changes
    assert screen.page.locator("#picks-body tr").count() > 0
    ARTIFACTS.mkdir(exist_ok=True)
    screen.page.screenshot(path=str(ARTIFACTS / "screen-running.png"))

    screen.button("Pause").click()
    screen.wait_label("Paused")
    assert "state-paused" in screen.page.get_attribute("#banner", "class")
    assert screen.button("Resume").is_enabled() and screen.button("Pause").is_disabled()
    screen.page.wait_for_timeout(1000)  # the pick in hand, if any, is finished first
    held = screen.picked()
    screen.page.wait_for_timeout(1000)
    assert screen.picked() == held  # nothing picked while paused

    screen.button("Resume").click()
    screen.wait(RUNNING_OR_WAITING)
    screen.button("Stop").click()  # asks first
    assert screen.page.is_visible("#confirm")
    screen.page.click("#confirm-yes")
    screen.wait_label("Stopped: ready to start", timeout_s=30)
    assert screen.button("Start continuous").is_enabled()
    assert screen.errors == []


def test_stop_and_halt_ask_and_cancel_changes_nothing(browser, live):
    screen = Screen(browser, live)
    screen.button("Start continuous").click()
    screen.wait(RUNNING_OR_WAITING)
    for name in ("Stop", "Halt"):
        screen.button(name).click()
        assert screen.page.is_visible("#confirm")
        screen.page.click("#confirm-no")
    screen.page.wait_for_timeout(300)
    assert screen.page.evaluate(RUNNING_OR_WAITING)
    screen.button("Halt").click()
    screen.page.click("#confirm-yes")
    screen.wait_label("Halted", timeout_s=30)
    assert "state-halted" in screen.page.get_attribute("#banner", "class")
    assert screen.button("Reset").is_enabled() and screen.button("Start").is_disabled()
    screen.button("Reset").click()
    screen.wait_label("Stopped")
    assert screen.errors == []


def test_two_screens_see_the_same_state(browser, live):
    a, b = Screen(browser, live), Screen(browser, live)
    a.button("Start continuous").click()
    b.wait(RUNNING_OR_WAITING)
    b.button("Pause").click()
    a.wait_label("Paused")
    assert a.button("Resume").is_enabled() and b.button("Resume").is_enabled()
    assert a.errors == [] and b.errors == []


def test_recalibrate_from_the_camera_and_accept(browser, live, serve):
    screen = Screen(browser, live)
    screen.page.click("#recal-open")
    screen.page.click("#recal-capture")
    screen.page.wait_for_selector("#recal-report:not([hidden])", timeout=60_000)
    assert screen.page.inner_text("#rep-gate") == "passes"
    screen.wait("document.getElementById('rep-dev').naturalWidth > 0")
    screen.wait("document.querySelector('[data-command=StartContinuous]').disabled")  # the cell stays put meanwhile
    screen.page.click("#recal-accept")
    screen.wait("document.getElementById('recal-status').textContent.startsWith('Accepted')", timeout_s=30)
    assert (serve.workdir / "calibration" / "active.json").is_file()
    screen.page.click("#recal-close")
    screen.wait("document.getElementById('cal-plate').naturalWidth > 0")
    assert screen.page.inner_text("#cal-source").startswith("camera frame")
    assert screen.errors == []


def test_fault_shows_the_alarm_with_reason_and_hint_and_reset_clears_it(browser, fake_cell):
    service, url = fake_cell
    screen = Screen(browser, url)
    service.fault("arm: no answer on /dev/ttyUSB0 within 5 s", "check the arm's cable and power, then Reset")
    screen.wait_label("Fault")
    assert screen.page.is_visible("#alarm")
    assert "no answer on /dev/ttyUSB0" in screen.page.inner_text("#alarm-reason")
    assert "then Reset" in screen.page.inner_text("#alarm-hint")
    assert "state-fault" in screen.page.get_attribute("#banner", "class")
    screen.button("Reset").click()
    screen.wait_label("Stopped")
    assert screen.page.is_hidden("#alarm")
    assert screen.errors == []

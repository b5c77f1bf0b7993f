"""The History page and the alarm list in a real browser (headless system Chromium through
Playwright) against `run-cell serve --dry-run` with a wrong offset: misses with their images, a
safety stop (a fault with its image), a Reset from the screen. Screenshots of the page and of a
failure image opened full size are kept in test-artifacts/ (and, with CELL_DOCS_SCREENSHOTS=1,
in docs/)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import httpx
import pytest

from tests.browser import launch, why_no_browser
from tests.serve_process import ServeProcess

pytestmark = [
    pytest.mark.skipif(why_no_browser() is not None, reason=str(why_no_browser())),
    pytest.mark.slow,  # a browser and `run-cell serve` in a subprocess
    pytest.mark.timeout(180),
]

REPO = Path(__file__).resolve().parents[1]
ARTIFACTS = REPO / "test-artifacts"
TIMEOUT_MS = 15_000


def _wait_js(page, expression: str, timeout_s: float = TIMEOUT_MS / 1000) -> None:
    """Until the JS expression is true, polled from here (wait_for_function would eval in the page,
    which its Content-Security-Policy forbids)."""
    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expression):
        assert time.monotonic() < deadline, f"not true within {timeout_s} s: {expression}"
        time.sleep(0.05)


def _wait_state(url: str, want: str, timeout_s: float = 90.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while (state := httpx.get(url + "api/state").json())["vision_state"] != want:
        assert time.monotonic() < deadline, f"not {want}: {state['display']}"
        time.sleep(0.2)
    return state


def test_history_page_filters_pages_opens_images_and_lists_alarms(tmp_path):
    from playwright.sync_api import sync_playwright

    (tmp_path / "cell.toml").write_text(
        "[camera]\nwidth_px = 960\nheight_px = 540\n[sim]\nreference_marks_mm = []\n"
        "[planning]\noffset_x_mm = -129.0\n[run]\nmax_attempts_total = 8\n[history]\nmin_free_mb = 1\n"
        "[calibration]\nmax_height_cost_mm = 5.0\n"  # 960 x 540's plate-only height doubt: not this test's alarm
    )
    serve = ServeProcess(tmp_path, "--config", str(tmp_path / "cell.toml"))
    try:
        url = serve.url
        token = httpx.get(url + "api/session").json()["csrf"]
        httpx.post(url + "api/command/StartSingleJob", headers={"x-csrf-token": token})
        _wait_state(url, "Error")  # the safety stop after 8 attempts, most of them misses
        httpx.post(url + "api/command/Reset", headers={"x-csrf-token": token})
        _wait_state(url, "Ready")
        with sync_playwright() as p:
            browser = launch(p)
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            errors = []
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.goto(url)
            page.click("#history-link")
            _wait_js(page, "window.historyStats && window.historyStats.picksLoads > 0")
            _wait_js(page, "window.historyStats.alarmsLoads > 0")
            rows = page.locator("#history-body tr")
            assert rows.count() == 8
            assert page.locator("#picks-status").inner_text() == "8 picks"
            assert "missed" in page.locator("#history-body").inner_text()
            alarm = page.locator("#alarms-history-body tr").first.inner_text()
            assert "safety stop" in alarm and "anonymous via screen" in alarm
            assert page.locator("#alarms-none").is_visible()  # nothing active after the Reset
            page.screenshot(path=str(ARTIFACTS / "history.png"), full_page=True)
            page.select_option("#f-outcome", "picked")
            page.click("#f-apply")
            _wait_js(page, "window.historyStats.lastPicks.picks.every(p => p.outcome === 'picked')")
            page.select_option("#f-outcome", "missed")
            page.click("#f-apply")
            _wait_js(
                page,
                "window.historyStats.lastPicks.picks.length > 0 && "
                "window.historyStats.lastPicks.picks.every(p => p.outcome === 'missed')",
            )
            page.locator("#history-body button.image-open").first.click()
            _wait_js(page, "window.historyStats.imagesShown > 0")
            size = page.evaluate(
                "[$('image-full').naturalWidth, $('image-full').naturalHeight]".replace("$", "document.getElementById")
            )
            assert size == [960, 540]  # full size
            page.screenshot(path=str(ARTIFACTS / "history-image.png"))
            page.click("#image-close")
            page.locator("#alarms-history-body button.image-open").first.click()
            _wait_js(page, "window.historyStats.imagesShown > 1")
            assert not errors, errors
            if os.environ.get("CELL_DOCS_SCREENSHOTS"):
                page.click("#image-close")
                page.select_option("#f-outcome", "")
                page.click("#f-apply")
                _wait_js(page, "window.historyStats.lastPicks.picks.length === 8")
                page.screenshot(path=str(REPO / "docs" / "history.png"), full_page=True)
            browser.close()
    finally:
        assert serve.stop() == 0, "\n".join(serve.lines[-20:])

#!/usr/bin/env python3
"""Frame push latency of the operator screen, capture -> shown in the page, in headless Chromium.

Starts `run-cell serve --dry-run` (or, with --fake, the tests' fake service with the real
screen server), opens the screen, presses `Start continuous`, and reads what the page
measured for each frame: Date.now() once the JPEG is decoded in the <img>, minus the
frame's capture time (same machine, same clock). Prints count, median, p95 and max.
With --screenshot PATH it also saves the screen while running (docs/screen.png).

    .venv/bin/python scripts/bench_screen_latency.py [--frames 100] [--fake] [--screenshot docs/screen.png]

Needs the test extras (playwright) and the system Chromium (Debian package `chromium`).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.browser import launch, why_no_browser  # noqa: E402


def start_fake():
    from cell.config import CellConfig
    from cell.web.config import WebConfig
    from cell.web.server import WebServer
    from tests.fake_service import FakeLineService

    service = FakeLineService(frame_size=(1920, 1080), interval_s=0.1)
    server = WebServer(service, CellConfig(), WebConfig(), "127.0.0.1", 0)
    server.start()

    def stop():
        server.stop()
        service.close()

    return server.url, stop


def start_serve(workdir: Path):
    from tests.serve_process import ServeProcess

    proc = ServeProcess(workdir)
    return proc.url, proc.stop


def poll(page, expression: str, timeout_s: float):
    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expression):
        if time.monotonic() > deadline:
            raise SystemExit(f"bench_screen_latency: not true within {timeout_s} s: {expression}")
        time.sleep(0.05)


def measure(url: str, frames: int, screenshot: Path | None, timeout_s: float) -> list[list[float]]:
    """Per frame: capture -> shown in the page, and capture -> JPEG ready in the service (ms)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = launch(p)
        page = browser.new_page(viewport={"width": 1600, "height": 1000})
        page.goto(url)
        poll(page, "window.screenStats && screenStats.states > 0", 20)
        page.get_by_role("button", name="Start continuous", exact=True).click()
        if screenshot is not None:  # early, while the table is still full of parts being picked
            poll(
                page,
                "screenStats.lastState.display.key === 'running' && screenStats.lastState.last_picks.length >= 2",
                timeout_s,
            )
            screenshot.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(screenshot))
            print(f"wrote {screenshot}")
            page.evaluate("screenStats.frames = 0; screenStats.latenciesMs = []; screenStats.serviceMs = []")
        poll(page, f"screenStats.frames >= {frames}", timeout_s)
        latencies = page.evaluate("[screenStats.latenciesMs.slice(), screenStats.serviceMs.slice()]")
        page.get_by_role("button", name="Stop", exact=True).click()
        page.click("#confirm-yes")
        poll(page, "document.getElementById('state-label').textContent.startsWith('Stopped')", 30)
        browser.close()
    return latencies


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100, help="frames to measure (default 100)")
    ap.add_argument("--fake", action="store_true", help="the tests' fake service instead of run-cell serve --dry-run")
    ap.add_argument("--screenshot", type=Path, help="save the running screen here")
    ap.add_argument("--timeout-s", type=float, default=300.0)
    args = ap.parse_args()
    if why := why_no_browser():
        print(f"bench_screen_latency: {why}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="screen-bench-") as tmp:
        url, stop = start_fake() if args.fake else start_serve(Path(tmp))
        try:
            shown, encoded = measure(url, args.frames, args.screenshot, args.timeout_s)
        finally:
            stop()
    source = "fake service, 1920 x 1080 frames" if args.fake else "run-cell serve --dry-run"
    print(f"{len(shown)} frames ({source}), {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}:")
    print(f"  capture -> shown in Chromium: {_figures(shown)}")
    print(f"  of which capture -> JPEG ready in the service (locate, annotate, encode): {_figures(encoded)}")
    return 0


def _figures(ms: list[float]) -> str:
    return (
        f"median {statistics.median(ms):.0f} ms, p95 {statistics.quantiles(ms, n=20)[18]:.0f} ms, max {max(ms):.0f} ms"
    )


if __name__ == "__main__":
    sys.exit(main())

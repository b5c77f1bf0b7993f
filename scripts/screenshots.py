#!/usr/bin/env python3
"""Screenshots of the operator screen for the docs, at 1920 x 1080, 1280 x 720 and 1024 x 600.

Starts `run-cell serve --dry-run` twice in headless Chromium: once as shipped (the live view
between jobs, a continuous run, the recalibration dialog and a picture full size), and once
with the simulated camera bumped 0.8 mm after calibration (`[sim] camera_bumped_mm`), so the
drift watch raises its real alarm. Writes into --out (default docs/):

    screen.png                      running at the first size, 1920 x 1080 (the README's picture)
    screen-idle-WxH.png             Ready, the live camera view
    screen-running-WxH.png          a continuous run with picks, at the other sizes
    screen-fault-WxH.png            the drift alarm in operator words
    screen-camera-check-1280x720.png the camera check on the live view
    screen-recalibrate-1280x720.png the recalibration report
    screen-picture-1280x720.jpg     its numbered plate at full size
    screen-teach-1280x720.png       the Teach page: L brackets (sim.teach_family) learnt, outlines and jaws

    .venv/bin/python scripts/screenshots.py [--out docs] [--sizes 1920x1080,1280x720,1024x600] [--only teach]

Needs the test extras (playwright) and the system Chromium (Debian package `chromium`).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.browser import launch, why_no_browser  # noqa: E402

SIZES = "1920x1080,1280x720,1024x600"
BUMPED = "[sim]\ncamera_bumped_mm = [0.8, 0.0]\ncamera_bumped_at_pick = 0\n"
TEACH = '[sim]\nteach_family = "l-bracket"\ntaught_parts_per_type = 4\n'
RECIPE = 'description = "bolts only: nuts stay on the table"\n\n[pick.bolt]\npick_above_table_mm = 3.5\nbin_robot_mm = [-200.0, 60.0, 60.0]\n'


def poll(page, expression: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expression):
        if time.monotonic() > deadline:
            raise SystemExit(f"screenshots: not true within {timeout_s} s: {expression}")
        time.sleep(0.1)


def open_screen(browser, url: str, size: tuple[int, int]):
    page = browser.new_page(viewport={"width": size[0], "height": size[1]})
    page.goto(url)
    poll(page, "window.screenStats && screenStats.states > 0")
    return page


def key_is(key: str) -> str:
    return f"screenStats.lastState && screenStats.lastState.display.key === '{key}'"


def shoot(page, path: Path) -> None:
    page.wait_for_timeout(300)  # the last frame decoded and drawn
    page.screenshot(path=str(path), **({"quality": 80} if path.suffix == ".jpg" else {}))
    print(f"wrote {path}")


def click(page, name: str) -> None:
    page.get_by_role("button", name=name, exact=True).click()


def _size(text: str) -> tuple[int, int]:
    width, height = text.split("x")
    return int(width), int(height)


def shipped(browser, url: str, sizes: list[tuple[int, int]], out: Path) -> None:
    """Idle with the live view, running, then back to Ready; the recalibration dialog at 1280 x 720."""
    for w, h in sizes:
        page = open_screen(browser, url, (w, h))
        poll(page, "screenStats.lastLive && screenStats.liveFrames > 0")
        shoot(page, out / f"screen-idle-{w}x{h}.png")
        click(page, "Start continuous")
        poll(  # this job's picks: its rate is known from its second pick on
            page,
            f"{key_is('running')} && screenStats.lastState.parts_per_min !== null "
            "&& screenStats.lastState.last_picks.length >= 3 && !screenStats.lastLive",
        )
        shoot(page, out / ("screen.png" if (w, h) == sizes[0] else f"screen-running-{w}x{h}.png"))
        click(page, "Stop")
        page.click("#confirm-yes")
        poll(page, key_is("stopped"))
        page.close()
    page = open_screen(browser, url, (1280, 720))
    page.click("#check-toggle")
    poll(page, "!document.getElementById('check-readings').hidden")
    shoot(page, out / "screen-camera-check-1280x720.png")
    page.click("#check-toggle")
    page.click("#recal-open")
    page.click("#recal-capture")
    poll(page, "!document.getElementById('recal-report').hidden", 120)
    poll(
        page,
        "document.getElementById('rep-plate').naturalWidth > 0 && document.getElementById('rep-dev').naturalWidth > 0",
    )
    shoot(page, out / "screen-recalibrate-1280x720.png")
    page.click("#rep-plate")
    poll(page, "document.getElementById('picture').open && document.getElementById('picture-img').naturalWidth > 0")
    shoot(page, out / "screen-picture-1280x720.jpg")
    page.keyboard.press("Escape")
    page.click("#recal-reject")
    poll(page, "!document.getElementById('recal').open")
    page.close()


def bumped(browser, url: str, sizes: list[tuple[int, int]], out: Path) -> None:
    """The drift alarm: the camera moved after calibration; the first frame of a job raises it."""
    page = open_screen(browser, url, sizes[0])
    click(page, "Start")
    poll(page, key_is("fault"), 120)
    page.close()
    for w, h in sizes:
        page = open_screen(browser, url, (w, h))
        poll(page, "screenStats.frames > 0")
        if (w, h) == sizes[0]:
            page.click("#alarm-details summary")  # the technical text behind the operator's words
        shoot(page, out / f"screen-fault-{w}x{h}.png")
        page.close()


def teach(browser, url: str, out: Path) -> None:
    """The Teach page: one frame of the simulated L brackets, learnt, before Confirm."""
    from cell.sim.cell import teach_family

    page = browser.new_page(viewport={"width": 1280, "height": 720})
    page.goto(url + "teach")
    poll(page, "window.teachStats && teachStats.loads > 0")
    page.fill("#teach-type", "bracket-l")
    page.fill("#teach-height", f"{teach_family('l-bracket', 0).height_mm:.2f}")
    page.click("#teach-take")
    poll(page, "teachStats.learns === 1 && teachStats.picturesShown >= 1", 120)
    shoot(page, out / "screen-teach-1280x720.png")
    page.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument("--sizes", default=SIZES, help=f"comma-separated WxH (default {SIZES})")
    ap.add_argument("--only", choices=("all", "teach"), default="all", help="teach: the Teach page's picture alone")
    args = ap.parse_args()
    if why := why_no_browser():
        print(f"screenshots: {why}", file=sys.stderr)
        return 2
    sizes = [_size(s) for s in args.sizes.split(",")]
    args.out.mkdir(parents=True, exist_ok=True)
    from playwright.sync_api import sync_playwright

    from tests.serve_process import ServeProcess

    with tempfile.TemporaryDirectory(prefix="screenshots-") as tmp, sync_playwright() as p:
        browser = launch(p)
        work = Path(tmp) / "teach"
        work.mkdir()
        (work / "teach.toml").write_text(TEACH)
        serve = ServeProcess(work, "--config", str(work / "teach.toml"))
        try:
            teach(browser, serve.url, args.out)
        finally:
            serve.stop()
        if args.only == "teach":
            browser.close()
            return 0
        work = Path(tmp) / "shipped"
        (work / "recipes").mkdir(parents=True)
        (work / "recipes" / "bolts-only.toml").write_text(RECIPE)
        serve = ServeProcess(work)
        try:
            shipped(browser, serve.url, sizes, args.out)
        finally:
            serve.stop()
        work = Path(tmp) / "bumped"
        work.mkdir()
        (work / "bumped.toml").write_text(BUMPED)
        serve = ServeProcess(work, "--config", str(work / "bumped.toml"))
        try:
            bumped(browser, serve.url, sizes, args.out)
        finally:
            serve.stop()
        browser.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The Teach page in a real browser (headless system Chromium through Playwright): capture a frame of the
simulated cell's L brackets, name and height, the picture with the outlines and jaws and the figures,
Confirm; the recipe file has the type. The real line service in-process, the screen's real server.

Skips, saying why, without Playwright or a Chromium."""

from __future__ import annotations

import contextlib
import time

import pytest

from cell.commands.serve import open_service
from cell.recipes import load_recipe_file
from cell.web.config import WebConfig
from cell.web.server import WebServer
from tests.browser import launch, why_no_browser
from tests.test_teach_screen import HEIGHT_MM, teach_config

pytestmark = [
    pytest.mark.skipif(why_no_browser() is not None, reason=str(why_no_browser())),
    pytest.mark.slow,  # a browser
    pytest.mark.timeout(180),
]

TIMEOUT_S = 20.0


def wait(page, expression: str, timeout_s: float = TIMEOUT_S) -> None:
    """Until the JS expression is true, polled from here (the page's CSP forbids wait_for_function's eval)."""
    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expression):
        assert time.monotonic() < deadline, f"not true within {timeout_s} s: {expression}"
        time.sleep(0.05)


def test_capture_see_the_outlines_and_confirm_in_a_browser(tmp_path):
    from playwright.sync_api import sync_playwright

    cfg = teach_config(tmp_path)
    with contextlib.ExitStack() as stack:
        service = open_service(cfg, True, stack)
        service.start()
        server = WebServer(service, cfg, WebConfig(live_interval_s=0), "127.0.0.1", 0)
        server.start()
        stack.callback(server.stop)
        with sync_playwright() as p:
            browser = launch(p)
            try:
                context = browser.new_context(viewport={"width": 1280, "height": 900})
                page = context.new_page()
                page.set_default_timeout(TIMEOUT_S * 1000)
                errors: list[str] = []
                page.on("console", lambda m: m.type == "error" and errors.append(m.text))
                page.on("pageerror", lambda e: errors.append(str(e)))
                page.goto(server.url)
                page.click("#teach-link")
                wait(page, "window.teachStats && teachStats.loads > 0")
                assert page.input_value("#teach-recipe") == "taught-parts"  # none prepared: a new recipe's id
                page.fill("#teach-type", "bracket")
                page.fill("#teach-height", f"{HEIGHT_MM:.4f}")
                page.click("#teach-take")  # captures, then teaches at once: name and height are given
                wait(page, "teachStats.captures === 1 && teachStats.learns === 1 && teachStats.picturesShown >= 1")
                assert page.inner_text("#teach-say").startswith('Learnt "bracket"')
                assert page.inner_text("#fig-examples").startswith("3 from 1 frame(s)")
                assert page.inner_text("#fig-symmetry") == "none"
                assert "worst misfit" in page.inner_text("#fig-consistency")
                assert "jaws close along" in page.inner_text("#fig-grip")
                size = page.evaluate(
                    "(() => { const i = document.querySelector('#teach-pictures img'); "
                    "return [i.naturalWidth, i.getBoundingClientRect().width]; })()"
                )
                assert size[0] > 100 and size[1] > 300, size  # the frame about the examples, shown large
                page.fill("#teach-recipe", "brackets")
                wait(page, "document.querySelectorAll('#teach-bin-of option').length === 2")  # bolt's, nut's
                page.select_option("#teach-bin-of", "nut")  # the nut's bin, chosen from the list
                assert page.is_checked("#teach-bin-shared")
                page.click("#teach-ok")
                wait(page, "teachStats.confirmed !== null")
                assert page.inner_text("#message") == 'Added "bracket" to recipe brackets.'
                assert page.inner_text("#teach-said").startswith("bracket: into the bin at robot (200, 60, 60) mm")
                assert page.is_disabled("#teach-ok") and page.is_hidden("#teach-result")
                assert errors == []
                context.close()
            finally:
                browser.close()
    recipe, shapes = load_recipe_file(cfg.service.machine_vision.recipes_dir / "brackets.toml")
    assert list(recipe.types) == ["bracket"] and [m.name for m in shapes] == ["bracket"]
    assert recipe.types["bracket"].bin_robot_mm == cfg.planning.nut.bin_robot_mm

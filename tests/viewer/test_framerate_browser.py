"""The 3D page's frame counter and the display while a view moves, in a real browser (Debian's
headless Chromium through Playwright, software WebGL) on the reopened `tiny` run: the counter's
reports reach the viewer as the tab's, an orbit switches the scene to its moving display and
back once the view rests, and a page slowed to ~5 frames/s gets a lighter moving display,
measured by the frames it drew (framerate.py, motion.py)."""

from __future__ import annotations

import math
import threading
import time

import pytest

from tests.viewer.test_viewer_browser import CHROMIUM, reopened_tiny, wait_for

pytestmark = pytest.mark.browser

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync"]
VIEW = {"width": 1400, "height": 900}


@pytest.fixture(scope="module")
def page_on_tiny(tiny_run, tmp_path_factory):
    """(viewer reopening a copy of the `tiny` run, a Chromium page on it, its client id)."""
    app = reopened_tiny(tiny_run, tmp_path_factory, "fr_browser")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=FLAGS)
        page = browser.new_page(viewport=VIEW)
        page.goto(app.url)
        client = wait_for(lambda: list(app.server.get_clients())[:1], 60, "the tab as a client")[0]
        yield app, page, client
        browser.close()
    app.stop()


def orbit(page, seconds: float) -> None:
    """Left-drag a circle over the 3D view (left of the panel) for `seconds`."""
    cx, cy, r = 400, 450, 150
    page.mouse.move(cx + r, cy)
    page.mouse.down()
    a, t0 = 0.0, time.time()
    while time.time() - t0 < seconds:
        a += 0.15
        page.mouse.move(cx + r * math.cos(a), cy + 0.6 * r * math.sin(a))
    page.mouse.up()


def test_the_counter_reports_and_a_slow_page_gets_a_lighter_moving_display(page_on_tiny):
    app, page, client = page_on_tiny
    mo = app.motion
    # the counter iframe posts the page's frames, tagged with this tab's client id
    wait_for(lambda: app.view_rate.drawing(client, time.monotonic()), 30, "the counter's reports")
    wait_for(lambda: app.scene.displayed_points() > 0 or app.wait_idle(), 60, "the reopened cloud")
    # each frame of the page now spins 200 ms: a machine without GPU under a heavy cloud
    page.evaluate("(function spin() { const t = performance.now(); while (performance.now() - t < 200);"
                  " requestAnimationFrame(spin); })()")
    seen = []
    watch = threading.Event()

    def watcher():
        while not watch.is_set():
            seen.append(mo.moving)
            time.sleep(0.05)
    t = threading.Thread(target=watcher, daemon=True)
    t.start()
    try:
        orbit(page, 6.0)
        wait_for(lambda: mo.governor.budget is not None or mo.governor.shed > 0, 30,
                 "the governor to lighten the moving display")
    finally:
        watch.set()
        t.join()
    assert any(seen), "the scene never switched to its moving display during the orbit"
    assert app.view_rate.source == "drawn"
    note = app.recon.g_budget_note.content
    assert note.startswith("While a view moves:") and "the page drew" in note, note
    # the views rest: the display at rest is back, the budget the operator's
    wait_for(lambda: not mo.moving, 10, "the display at rest")
    assert not app.scene.moving and app.scene.settings.budget == 150_000

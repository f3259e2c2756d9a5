"""The image workspace in a real browser (Debian's headless Chromium through Playwright), on the
reopened `tiny` run (three 400 px images): each tab clicks for its own GCP, N then a click
records the new GCP, the wheel zooms at the cursor and a drag pans with the pixel under the
cursor held, and an arrow key nudges by 0.1 px."""

from __future__ import annotations


import pytest

from tests.viewer.test_viewer_browser import CHROMIUM, reopened_tiny, wait_for

pytestmark = pytest.mark.browser

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]
VIEW = {"width": 1400, "height": 900}
AIM = 1e-4      # image px: Chromium carries a mouse position as a float32 (1e-6 px off here)



@pytest.fixture(scope="module")
def ws_browser(tiny_run, tmp_path_factory):
    """(viewer reopening a copy of the `tiny` run, a Playwright browser context)."""
    app = reopened_tiny(tiny_run, tmp_path_factory, "ws_browser")
    from playwright.sync_api import sync_playwright

    wait_for(lambda: app.models or app.wait_idle(), 60, "the reopened models")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=FLAGS, headless=True)
        ctx = browser.new_context(viewport=VIEW)
        yield app, ctx
        browser.close()
    app.stop()


def open_tab(app, ctx):
    """A new tab on the workspace, once its state and canvases are drawn."""
    page = ctx.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(app.workspace.url)
    page.wait_for_function("window.workspace && window.workspace.tab.data && "
                           "document.querySelectorAll('#views canvas').length > 0", timeout=20_000)
    page.errors = errors
    return page


def choose(page, gid: str) -> None:
    """Select a GCP in this tab by clicking its row of the list."""
    page.locator(f'#gcps tr[data-gcp="{gid}"]').click()
    assert page.evaluate("workspace.selected()") == gid


def settle(page) -> None:
    """Let the tab's queued edits finish and its state catch up."""
    page.evaluate("workspace.idle()")
    page.wait_for_timeout(100)


def centre_of(page, image: str) -> tuple[float, float]:
    box = page.locator(f'canvas[data-image="{image}"]').bounding_box()
    return box["x"] + 0.5 * box["width"] + 0.37, box["y"] + 0.5 * box["height"] - 0.21


def test_two_tabs_each_click_for_their_own_gcp(ws_browser):
    app, ctx = ws_browser
    s = app.session
    a, b = (g.id for g in s.gcps[:2])
    t1, t2 = open_tab(app, ctx), open_tab(app, ctx)
    try:
        choose(t1, a)
        choose(t2, b)
        image = sorted(s.get(b).observations)[0]
        a_before = dict(s.get(a).observations)
        x, y = centre_of(t2, image)
        want = t2.evaluate(f"workspace.imageAt({image!r}, {x}, {y})")
        t2.mouse.click(x, y)
        settle(t2)
        wait_for(lambda: s.get(b).observations[image] == pytest.approx(tuple(want), abs=AIM), 10, "tab 2's click")
        assert s.get(a).observations == a_before               # tab 1's GCP is untouched
        assert t1.evaluate("workspace.selected()") == a        # and tab 1 still works on it
        # tab 1 sees tab 2's edit within a poll, and its own click goes to its own GCP
        t1.wait_for_function(f"workspace.tab.data.gcps.find(g => g.id === {b!r}).images[{image!r}].observed[0] "
                             f"=== {round(want[0], 3)}", timeout=5_000)
        x1, y1 = centre_of(t1, image)
        want1 = t1.evaluate(f"workspace.imageAt({image!r}, {x1}, {y1})")
        t1.mouse.click(x1, y1)
        settle(t1)
        wait_for(lambda: s.get(a).observations.get(image) == pytest.approx(tuple(want1), abs=AIM), 10, "tab 1's click")
        assert s.get(b).observations[image] == pytest.approx(tuple(want), abs=AIM)
        assert not t1.errors and not t2.errors, t1.errors + t2.errors
    finally:
        t1.close()
        t2.close()


def test_n_then_a_click_records_the_new_gcp(ws_browser):
    app, ctx = ws_browser
    s = app.session
    page = open_tab(app, ctx)
    try:
        first, second = s.ids[2], s.ids[3]
        choose(page, first)
        image = sorted(s.get(second).observations)[-1]
        before = {g: dict(s.get(g).observations) for g in (first, second)}
        x, y = centre_of(page, image)
        page.mouse.move(x, y)
        page.keyboard.press("n")
        page.mouse.click(x, y)                        # at once: no stale selection
        settle(page)
        assert page.evaluate("workspace.selected()") == second
        want = page.evaluate(f"workspace.imageAt({image!r}, {x}, {y})")
        wait_for(lambda: s.get(second).observations[image] != before[second][image], 10, "the click")
        assert s.get(second).observations[image] == pytest.approx(tuple(want), abs=AIM)
        assert s.get(first).observations == before[first]
    finally:
        page.close()


def test_the_wheel_zooms_at_the_cursor_and_a_drag_pans_without_placing(ws_browser):
    app, ctx = ws_browser
    s = app.session
    page = open_tab(app, ctx)
    try:
        gid = s.ids[4]
        choose(page, gid)
        image = sorted(s.get(gid).observations)[0]
        box = page.locator(f'canvas[data-image="{image}"]').bounding_box()
        # whole CSS pixels: Chromium gives a wheel event the cursor's position rounded to one
        x, y = round(box["x"] + 0.3 * box["width"]), round(box["y"] + 0.65 * box["height"])
        page.mouse.move(x, y)
        p0 = page.evaluate(f"workspace.imageAt({image!r}, {x}, {y})")
        s0 = page.evaluate(f"workspace.view({image!r}).s")
        n_undo = len(s._undo)
        for dy in (-240, -240, 120):
            page.mouse.wheel(0, dy)
            page.wait_for_timeout(50)
            p = page.evaluate(f"workspace.imageAt({image!r}, {x}, {y})")
            assert p == pytest.approx(p0, abs=1e-6)          # the pixel under the cursor stays
        s1 = page.evaluate(f"workspace.view({image!r}).s")
        assert s1 > 1.5 * s0
        page.mouse.down()
        page.mouse.move(x + 60, y - 35, steps=6)
        page.mouse.up()
        p = page.evaluate(f"workspace.imageAt({image!r}, {x + 60}, {y - 35})")
        assert p == pytest.approx(p0, abs=1e-6)              # the grabbed pixel follows the cursor
        settle(page)
        assert len(s._undo) == n_undo                         # a drag places nothing
        page.mouse.click(x + 60, y - 35)                      # a click there places it on that pixel
        settle(page)
        wait_for(lambda: s.get(gid).observations[image] == pytest.approx(tuple(p0), abs=AIM), 10, "the click")
    finally:
        page.close()


def test_an_arrow_key_nudges_the_observation_by_a_tenth_of_a_pixel(ws_browser):
    app, ctx = ws_browser
    s = app.session
    page = open_tab(app, ctx)
    try:
        gid = s.ids[5]
        choose(page, gid)
        image = sorted(s.get(gid).observations)[1]
        c0, r0 = s.get(gid).observations[image]
        page.mouse.move(*centre_of(page, image))               # the image under the cursor has the keys
        page.keyboard.press("ArrowRight")
        settle(page)
        wait_for(lambda: s.get(gid).observations[image] != (c0, r0), 10, "the nudge")
        assert s.get(gid).observations[image] == pytest.approx((c0 + 0.1, r0), abs=1e-9)
        page.keyboard.press("Shift+ArrowUp")
        settle(page)
        wait_for(lambda: s.get(gid).observations[image][1] != r0, 10, "the second nudge")
        assert s.get(gid).observations[image] == pytest.approx((c0 + 0.1, r0 - 1.0), abs=1e-9)
        page.keyboard.press("Control+z")                       # the nudges in a row are one step
        settle(page)
        wait_for(lambda: s.get(gid).observations[image] == (c0, r0), 10, "the undo")
    finally:
        page.close()


def test_after_an_upgrade_a_gcp_without_observations_is_predicted_from_its_surveyed_position(ws_browser):
    """With the reopened run's upgrade, a new GCP with no observation is predicted in every
    image from its surveyed position (its view says so, and Enter does not record it: that
    pixel is where the upgrade puts the survey, not what the image shows), and a placed GCP's
    views say how far each observation lies from where its surveyed position projects."""
    from aerec_viewer.gcp_session import new_gcp, undo

    app, ctx = ws_browser
    s = app.session
    up = wait_for(lambda: app.saved_upgrade or app.wait_idle(), 60, "the run's upgrade")
    placed = next(g for g in s.gcps if len(g.observations) >= 2)
    enu = up.frame.geodetic_to_enu(placed.llh[None])[0] + [3.0, 2.0, 0.0]
    lon, lat, h = up.frame.enu_to_geodetic(enu[None])[0]
    app.call(lambda: (new_gcp(s, "G-SURVEY", x=lon, y=lat, h=h, role="check"), app.gcp.changed()))
    n_undo = len(s._undo)
    page = open_tab(app, ctx)
    try:
        choose(page, "G-SURVEY")
        images = list(s.images)
        page.wait_for_function("[...document.querySelectorAll('.view .what')].every(e => "
                               "/^G-SURVEY predicted at .* from its surveyed position/.test(e.textContent))",
                               timeout=10_000)
        page.mouse.move(*centre_of(page, images[0]))
        page.keyboard.press("Enter")
        settle(page)
        page.wait_for_function("/click the point itself/.test(document.body.textContent)", timeout=10_000)
        assert images[0] not in s.get("G-SURVEY").observations
        choose(page, placed.id)
        page.wait_for_function("[...document.querySelectorAll('.view .what')].some(e => "
                               "/px from its surveyed position/.test(e.textContent))", timeout=10_000)
        assert page.locator('canvas.icon[data-icon="surveyed"]').count() == 1
        assert not page.errors, page.errors
    finally:
        page.close()
        while len(s._undo) >= n_undo:
            app.call(lambda: (undo(s), app.gcp.changed()))
    assert "G-SURVEY" not in s.ids

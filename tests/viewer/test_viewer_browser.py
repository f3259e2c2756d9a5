"""The viewer in a real browser: Debian's headless Chromium (SwiftShader WebGL) driven by
Playwright. Loads the page, waits for the client, clicks GUI buttons, clicks a known pixel of the
image plane and checks the pixel the server recorded, checks a second tab sees the same state,
runs the upgrade, and saves screenshots (pytest's tmp dir; copies in $AEREC_SHOTS when set)."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from aerec_viewer.views import DRAG_GUARD_S
from aerec_viewer.display import quat_to_matrix
from aerec_viewer.picking import LOUPE_PX
from recon_core.events import TileRegistered

pytestmark = pytest.mark.browser

CHROMIUM = Path("/usr/bin/chromium")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
         "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync"]
SHOTS = Path(os.environ["AEREC_SHOTS"]) if os.environ.get("AEREC_SHOTS") else None   # a folder to keep them
VIEW = {"width": 1400, "height": 900}


def wait_for(cond, timeout: float, what: str, step: float = 0.1):
    t0 = time.time()
    while time.time() - t0 < timeout:
        v = cond()
        if v:
            return v
        time.sleep(step)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def reopened_tiny(tiny_run, tmp_path_factory, name: str):
    """A started viewer reopening a copy of the `tiny` run (skips without Chromium)."""
    if not CHROMIUM.exists():
        pytest.skip("/usr/bin/chromium is not installed")
    from aerec_viewer.app import ViewerApp

    state, _ = tiny_run
    out = tmp_path_factory.mktemp(name) / "out"
    shutil.copytree(state.out, out)
    return ViewerApp(out, state.site.root, None, mode="reopen", port=0).start()


def project(client, p: np.ndarray) -> tuple[float, float]:
    """Screen position (CSS px) of a world point in a client's current camera (OpenCV camera
    convention of viser: +z forward, +y down; fov is vertical)."""
    cam = client.camera
    R = quat_to_matrix(cam.wxyz)
    pc = R.T @ (np.asarray(p, float) - cam.position)
    f = (VIEW["height"] / 2) / np.tan(cam.fov / 2)
    return VIEW["width"] / 2 + f * pc[0] / pc[2], VIEW["height"] / 2 + f * pc[1] / pc[2]


@pytest.fixture(scope="module")
def browser_app(tmp_path_factory):
    if not CHROMIUM.exists():
        pytest.skip("/usr/bin/chromium is not installed")
    from playwright.sync_api import sync_playwright

    from aerec_viewer.app import ViewerApp
    from tests.viewer.test_viewer import _small_site

    root = tmp_path_factory.mktemp("browser")
    site, cfg = _small_site(root)
    app = ViewerApp(root / "out", site, cfg, mode="run", port=0, until="sparse")
    shots = root / "shots"
    shots.mkdir()
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=FLAGS, headless=True)
        ctx = browser.new_context(viewport=VIEW)
        page = ctx.new_page()
        t0 = time.time()
        page.goto(app.url)
        wait_for(lambda: app.server.get_clients(), 30, "the page to register as a client")
        t_client = time.time() - t0
        real, held = app.worker.handle, []

        def hold_half_way(ev):                 # pause once half of the tiles are registered
            if isinstance(ev, TileRegistered) and not held and ev.order + 1 >= ev.total_tiles // 2:
                held.append(ev.order)
                app.worker.pause()
            real(ev)

        app.worker.handle = hold_half_way
        app.start()
        yield app, page, ctx, shots, t_client
        browser.close()
    app.stop()


def shot(page, shots: Path, name: str) -> Path:
    path = shots / f"{name}.png"
    page.screenshot(path=str(path))
    if SHOTS is not None:
        SHOTS.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, SHOTS / path.name)
    return path


def test_live_reconstruction_then_pick_a_pixel_then_upgrade(browser_app):
    app, page, ctx, shots, t_client = browser_app
    assert t_client < 20
    # during SfM: the worker is held half way (as the Pause button does); the panel offers
    # Resume, and the browser's click on it releases the reconstruction
    wait_for(lambda: app.worker.paused and app.scene.displayed_points() > 0, 120,
             "the first half of the tiles on the client")
    page.get_by_role("button", name="Resume").wait_for(timeout=20_000)
    time.sleep(2.0)
    shot(page, shots, "1_during_sfm")
    snap = app.worker.snapshot()
    assert snap.status == "paused" and 0 < len(snap.groups[0].tiles) < snap.groups[0].total_tiles
    page.get_by_role("button", name="Resume").click()
    wait_for(lambda: not app.worker.paused, 20, "the Resume button click to reach the server")
    assert app.worker.join(240), "the reconstruction did not finish"
    app.wait_idle()
    time.sleep(2.0)
    shot(page, shots, "2_after_sfm")
    # the rendered frame is not blank (WebGL works headless)
    client = next(iter(app.server.get_clients().values()))
    img = np.asarray(client.get_render(300, 460))
    assert img.std() > 5

    # GUI: open the GCP tab, select a GCP, press "Look at the image plane"
    page.get_by_role("tab", name="GCPs").click()
    gid = app.session.ids[0]
    app.call(lambda: app.gcp_panel.select_id(gid))
    page.get_by_role("button", name="Look at the image plane").click()
    plane = app.picking.plane
    top = plane.position + np.array([0.0, 0.0, 1.0])
    wait_for(lambda: np.linalg.norm(client.camera.position[:2] - plane.position[:2])
             < 0.01 * plane.render_width and client.camera.position[2] > top[2], 20,
             "the camera to move above the image plane (GUI button click)")
    time.sleep(1.0)                      # let the client finish its camera transition
    win = plane.window
    target = (win.col0 + 0.43 * win.width, win.row0 + 0.57 * win.height)
    x, y = project(client, plane.point_of(*target))
    assert 0 < x < 950 and 0 < y < VIEW["height"], (x, y)
    before = app.gcp.last_click
    view_before = client.camera.position.copy()
    # the first click opens the loupe there: the plane shows the full-resolution pixels around
    # it, enlarged, and this tab's camera goes straight above it
    page.mouse.click(x, y)
    wait_for(lambda: app.picking.loupe is not None and app.picking.plane.window == app.picking.loupe[0], 20,
             "the first click to open the loupe")
    assert app.gcp.last_click is before                      # nothing recorded
    loupe = app.picking.plane
    assert loupe.window.width < 0.2 * win.width
    wait_for(lambda: np.linalg.norm(client.camera.position[:2] - loupe.position[:2])
             < 0.01 * loupe.render_width, 20, "the camera to move above the loupe")
    time.sleep(1.5)
    shot(page, shots, "3a_loupe")
    aim = (app.picking.loupe[1][0] + 0.31, app.picking.loupe[1][1] - 0.42)   # the exact pixel, seen enlarged
    x, y = project(client, loupe.point_of(*aim))
    page.mouse.click(x, y)
    wait_for(lambda: app.gcp.last_click is not before and app.gcp.last_click is not None, 20,
             "the click in the loupe to reach the server")
    got_gid, image, col, row = app.gcp.last_click
    px_per_css = loupe.window.width / (loupe.render_width * (VIEW["height"] / 2) / np.tan(client.camera.fov / 2)
                                       / np.linalg.norm(client.camera.position - loupe.position))
    assert px_per_css < 0.15, px_per_css                 # a tenth of a pixel per screen pixel
    assert got_gid == gid and image == win.image
    assert abs(col - aim[0]) <= 1.5 * px_per_css and abs(row - aim[1]) <= 1.5 * px_per_css, \
        (col, row, aim, px_per_css)
    assert abs(col - target[0]) < 0.5 * LOUPE_PX and abs(row - target[1]) < 0.5 * LOUPE_PX
    assert np.allclose(app.session.get(gid).observations[image], (col, row))
    # then back to the whole image, and to the view this tab had
    wait_for(lambda: app.picking.loupe is None and app.picking.plane.window == win, 20, "the loupe to close")
    wait_for(lambda: np.linalg.norm(client.camera.position - view_before) < 1e-3 * plane.render_width,
             20, "the view before the loupe")
    time.sleep(1.5)
    shot(page, shots, "3_gcp_pick")

    # a press that wobbles by a few pixels and is released where it was pressed orbits the view
    # and still reaches the server as a click: it must not record anything
    recorded = dict(app.session.get(gid).observations)
    x2, y2 = project(client, plane.point_of(win.col0 + 0.6 * win.width, win.row0 + 0.4 * win.height))
    page.mouse.move(x2, y2)
    page.mouse.down()
    page.mouse.move(x2 + 3, y2 + 1, steps=3)
    page.mouse.move(x2, y2, steps=3)                 # back where it was pressed
    page.mouse.up()
    # viser does send that click: the guard refuses it and says so (waited for, not slept on:
    # a loaded machine delays the note)
    wait_for(lambda: any("moved during that click" in t for _, t in app.worker.snapshot().messages),
             30, "the drag guard's note")
    app.wait_idle()
    assert app.session.get(gid).observations == recorded and app.gcp.last_click[2:] == (col, row)
    time.sleep(DRAG_GUARD_S)

    # safe editing from the browser: Undo reverts the click, Redo re-applies it; Delete only
    # asks for confirmation (the GCP stays)
    after_click = app.session.get(gid).observations.get(image)
    page.get_by_role("button", name="Undo:").click()
    wait_for(lambda: app.session.get(gid).observations.get(image) != after_click, 20, "the Undo click")
    page.get_by_role("button", name="Redo:").click()
    wait_for(lambda: app.session.get(gid).observations.get(image) == after_click, 20, "the Redo click")
    page.get_by_role("button", name="Delete the selected GCP").click()
    page.get_by_role("button", name=f"Confirm: delete {gid}").wait_for(timeout=20_000)
    assert gid in app.session.ids

    # a second tab sees the same state (server-wide GUI and scene)
    page2 = ctx.new_page()
    page2.goto(app.url)
    wait_for(lambda: len(app.server.get_clients()) >= 2, 60, "the second tab")
    # the second tab's message list (its Reconstruction tab is open) shows the newest message
    # (the list shows the last few: on a slow page the point budget's note may come after the pick)
    newest = [t for lvl, t in app.worker.snapshot().messages if lvl != "debug"][-1]
    page2.get_by_text(newest[:40]).filter(visible=True).first.wait_for(timeout=60_000)
    # the GCP list is shared: the second tab chooses the next GCP; the first tab's next click
    # must not land on it (it records nothing and says so)
    page2.get_by_role("tab", name="GCPs").click()
    page2.get_by_role("button", name="Next GCP").click()
    wait_for(lambda: app.gcp_panel.selected() != gid, 20, "the second tab's Next GCP")
    other = app.gcp_panel.selected()
    held = {g: dict(app.session.get(g).observations) for g in (gid, other)}
    x3, y3 = project(client, app.picking.plane.point_of(win.col0 + 0.3 * win.width, win.row0 + 0.3 * win.height))
    page.mouse.click(x3, y3)
    wait_for(lambda: any(f"another tab changed the GCP to {other}" in t
                         for _, t in app.worker.snapshot().messages), 20, "the refused click")
    assert {g: dict(app.session.get(g).observations) for g in (gid, other)} == held and app.picking.loupe is None
    app.call(lambda: app.gcp_panel.select_id(gid))
    page2.close()

    # upgrade from the browser, then the Euclidean scene and the residual table
    page.get_by_role("tab", name="Results").click()
    page.get_by_role("button", name="Upgrade to Euclidean").click()
    wait_for(lambda: app.frame == "euclidean", 30, "the upgrade button to reach the server")
    app.wait_idle()
    app.call(lambda: app.views.frame_client(client))
    page.get_by_role("cell", name="check").first.wait_for(timeout=15_000)
    time.sleep(2.5)
    shot(page, shots, "4_after_upgrade")
    assert "Euclidean" in app.recon.g_frame.content


    # keyboard: N selects the next GCP, P the previous one (viser commands with hotkeys; the
    # camera keeps W A S D Q E and the arrows)
    if app.gcp_panel.shortcuts:
        page.get_by_role("tab", name="GCPs").click()
        page.mouse.click(200, 820)                   # focus the scene (empty background)
        gp = app.gcp_panel
        start = gp.selected()
        expected = app.call(lambda: gp.neighbour(gp.selected(), +1))[0]
        page.keyboard.press("n")
        wait_for(lambda: gp.selected() != start, 20, "the N key to select the next GCP")
        nxt = gp.selected()
        assert nxt == expected
        back = app.call(lambda: gp.neighbour(nxt, -1))[0]
        page.keyboard.press("p")
        wait_for(lambda: gp.selected() == back, 20, "the P key to select the previous GCP")


def test_drag_the_handle_in_the_loupe_to_adjust_an_observation(browser_app, tiny_run, tmp_path):
    """In the loupe, the selected GCP's observation carries a drag handle (arrows and a square
    in the image plane): a mouse drag of 2 image pixels along the columns moves the observation
    by 2 pixels, to a tenth of a pixel, and says so; no click is recorded on the way."""
    from aerec_viewer.app import ViewerApp

    ctx = browser_app[2]                  # one Playwright per process: the module's browser
    state, _ = tiny_run
    out = tmp_path / "out"
    shutil.copytree(state.out, out)
    app = ViewerApp(out, state.site.root, None, mode="reopen", port=0)
    app.start()
    try:
        page = ctx.new_page()
        try:
            page.goto(app.url)
            client = wait_for(lambda: next(iter(app.server.get_clients().values()), None), 60, "the client")
            gp = app.gcp_panel
            gid = next(g.id for g in app.session.gcps if len(g.observations) >= 2)
            app.call(lambda: gp.refresh(select=gid))
            im = sorted(app.session.get(gid).observations)[0]
            ob = app.session.get(gid).observations[im]
            app.call(lambda: gp.jump_to(im, client))
            app.wait_idle()
            wait_for(lambda: app.marks.drag_handle is not None and app.picking.loupe is not None, 20, "the drag handle")
            pl = app.picking.plane
            time.sleep(2.0)                      # the camera's move above the loupe
            shot(page, tmp_path, "6_drag_handle")
            lift = 0.004 * pl.render_width
            x0, y0 = project(client, pl.point_of(ob[0] + 3.0, ob[1], lift=lift))     # on the column arrow
            x1, y1 = project(client, pl.point_of(ob[0] + 5.0, ob[1], lift=lift))
            n_undo = len(app.session._undo)
            page.mouse.move(x0, y0)
            page.mouse.down()
            page.mouse.move(x1, y1, steps=8)
            page.mouse.up()
            wait_for(lambda: app.session.get(gid).observations[im] != ob, 20, "the drag to reach the server")
            app.wait_idle()                       # the edit is made before its note: let it finish
            c, r = app.session.get(gid).observations[im]
            assert abs(c - (ob[0] + 2.0)) < 0.1 and abs(r - ob[1]) < 0.1, ((c, r), ob)
            assert len(app.session._undo) == n_undo + 1
            assert any(f"{gid}: moved in {im}" in t and "dragged" in t for _, t in app.worker.snapshot().messages)
        finally:
            page.close()
    finally:
        app.stop()

"""The first run of `aerec view` in a real browser (Debian's headless Chromium via Playwright):
the page is served at once, then becomes the viewer. Its own module: Playwright's sync API
cannot start while another module's browser fixture is open."""

from __future__ import annotations

import time

import pytest

from tests.viewer.test_viewer_browser import CHROMIUM, FLAGS, SHOTS, VIEW, wait_for

pytestmark = pytest.mark.browser


def test_first_demo_serves_a_page_at_once_and_the_viewer_takes_it_over(tmp_path):
    """`aerec view` with no cached demo: the page is served within seconds and shows the
    generation's progress; when the site is ready the viewer takes over the same address and the
    open page becomes the viewer without a reload. (AEREC_DEMO_PRESET=tiny2 keeps it short.)"""
    import os
    import subprocess
    import sys
    import threading

    if not CHROMIUM.exists():
        pytest.skip("/usr/bin/chromium is not installed")
    from playwright.sync_api import sync_playwright

    env = dict(os.environ, AEREC_CACHE=str(tmp_path / "cache"), AEREC_DEMO_PRESET="tiny2")
    t0 = time.time()
    proc = subprocess.Popen([sys.executable, "-m", "aerec_viewer", "--port", "0", "--preset", "tiny",
                             "--no-browser-hint"], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    try:
        url = wait_for(lambda: next((ln.split("open ")[-1].split()[0] for ln in lines
                                     if ln.startswith("aerec view: preparing")), None), 30,
                       "the preparation page's address")
        t_url = time.time() - t0
        assert t_url < 15, t_url
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=FLAGS, headless=True)
            page = browser.new_context(viewport=VIEW).new_page()
            page.goto(url)
            page.get_by_text("preparing the demo").first.wait_for(timeout=20_000)
            page.screenshot(path=str(tmp_path / "0_demo_preparation.png"))
            if SHOTS is not None:
                SHOTS.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(SHOTS / "0_demo_preparation.png"))
            # the same page, not reloaded, becomes the viewer
            page.get_by_role("tab", name="GCPs").wait_for(timeout=240_000)
            page.get_by_text("AE-Rec · synth-tiny2").first.wait_for(timeout=30_000)
            browser.close()
        assert any(ln.startswith("aerec view: reconstructing") for ln in lines), lines[-5:]
    finally:
        proc.terminate()
        proc.wait(20)

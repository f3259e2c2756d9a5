"""Viewer figures: launch -> first points on a connected client, tile registration -> its points
on the client, and bytes sent per update.

A minimal websocket client (the viser wire protocol: 16-byte header, zstd msgpack, raw binary
buffers) connects like a browser tab (it sends a camera message, which is what registers a
client) and timestamps every frame it receives. With --browser, headless Chromium is also
connected and the time until the first points are rendered on its screen is measured.

    python bench/bench_viewer.py                      # the demo site (generated on first use)
    python bench/bench_viewer.py --site ../shared/data/reunion_pair --tile-size 400
    python bench/bench_viewer.py --cold               # `aerec view` from a bare cache
    python bench/bench_viewer.py --fps OUT            # frames drawn per second while orbiting
    python bench/bench_viewer.py --fps OUT --budgets 150000,40000
    python bench/bench_viewer.py --fps OUT --duration 60 --tabs 2   # the governor at work
    python bench/bench_viewer.py --fps OUT --duration 60 --load 1   # on a machine doing other work
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from aerec_viewer.framerate import drawn_rate  # noqa: E402


class WireClient:
    """Connects to a viser server like a browser tab and logs (t, bytes, messages) per frame."""

    def __init__(self, port: int):
        import msgspec
        import viser
        import zstandard
        from viser import _messages
        from websockets.sync.client import connect

        self.frames: list[tuple[float, int, list[tuple[str, str]]]] = []
        self._ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                           max_size=None)
        self._dec = zstandard.ZstdDecompressor()
        self._msgpack = msgspec.msgpack
        cam = _messages.ViewerCameraMessage(
            wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, 10.0), fov=1.3, near=0.01, far=1e5,
            image_height=900, image_width=1400, look_at=(0.0, 0.0, 0.0), up_direction=(0.0, 0.0, 1.0))
        self._ws.send(msgspec.msgpack.encode(cam.as_serializable_dict()))
        self._stop = False
        self._thread = threading.Thread(target=self._recv, daemon=True)
        self._thread.start()

    def _recv(self) -> None:
        while not self._stop:
            try:
                raw = self._ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            except Exception:
                return
            t = time.time()
            n_inner = int.from_bytes(raw[0:8], "little")
            n_comp = int.from_bytes(raw[8:16], "little")
            inner = self._msgpack.decode(self._dec.decompress(raw[16:16 + n_comp], max_output_size=n_inner))
            msgs = [(m.get("type", "?"), str(m.get("name", ""))) for m in inner["messages"]]
            self.frames.append((t, len(raw), msgs))

    def close(self) -> None:
        self._stop = True
        self._thread.join(2.0)
        self._ws.close()

    def first(self, mtype: str, after: float = 0.0, name: str | None = None) -> float | None:
        for t, _, msgs in self.frames:
            if t >= after and any(m == mtype and (name is None or n == name) for m, n in msgs):
                return t
        return None


def pct(v: list[float], q: float) -> float:
    return float(np.percentile(v, q)) if v else float("nan")


def run(args) -> None:
    from aerec_viewer.app import ViewerApp
    from aerec_viewer.cli import demo_site
    from recon_core.config import preset
    from recon_core.events import PointsAdded, TileRegistered

    t_gen = time.time()
    site = Path(args.site) if args.site else demo_site()
    t_gen = time.time() - t_gen
    cfg = preset(args.preset)
    if args.tile_size:
        cfg = cfg.with_overrides({"tiling.tile_size": args.tile_size})
    out = Path(tempfile.mkdtemp(prefix="bench_viewer_"))
    reg: dict[str, float] = {}
    batches: list[tuple[float, str | None]] = []        # (t_added of a sparse batch, tile before it)
    last_tile: list[str | None] = [None]

    t0 = time.time()
    app = ViewerApp(out, site, cfg, mode="run", port=0, until=args.until)
    real = app.worker.handle

    def spy(ev):
        if isinstance(ev, TileRegistered):
            reg[ev.tile_id] = time.time()
            last_tile[0] = ev.tile_id
        real(ev)
        if isinstance(ev, PointsAdded) and ev.kind == "sparse":
            st = app.worker._groups[ev.group].sparse
            batches.append((st.batches[-1].t_added, last_tile[0]))

    app.worker.handle = spy
    client = WireClient(app.port)
    browser = None
    if args.browser:
        browser = BrowserProbe(app.url)
    app.start()
    t_launch_done = time.time() - t0
    while not app.worker.done.is_set():
        time.sleep(0.2)
    app.wait_idle()
    time.sleep(1.0)
    snap = app.worker.snapshot()

    # a late tab: everything it must download to catch up
    late = WireClient(app.port)
    time.sleep(3.0)
    late.close()
    client.close()
    t_screen = browser.finish() if browser else None
    app.stop()

    first_points = client.first("PointCloudMessage")
    print(f"site: {site} ({'generated in %.1f s' % t_gen if t_gen > 1 else 'cached'}), "
          f"preset {args.preset}, tile size {cfg.tiling.tile_size}, until {args.until}")
    print(f"status {snap.status}; tiles registered {sum(len(g.tiles) for g in snap.groups.values())}, "
          f"points {snap.n_points:,}")
    print(f"viewer constructed and started in {t_launch_done:.2f} s")
    if first_points:
        print(f"launch -> first points on the connected client: {first_points - t0:.2f} s "
              f"(the worker had its first points {snap.t_first_points - t0:.2f} s after launch)")
    if t_screen is not None:
        print(f"launch -> first points rendered in headless Chromium: {t_screen - t0:.2f} s")

    # tile registration -> the first chunk holding the points added with it (the batch itself,
    # or a newer model that includes them) on the client; tiles that added no point are skipped
    delays, lag = [], []
    for t_added, tile in batches:
        if tile is None or tile not in reg:
            continue
        entry = next((e for e in app.scene.sent_log if max(e["t_added"]) >= t_added), None)
        if entry is None:
            continue
        t_recv = client.first("PointCloudMessage", after=entry["t_sent"] - 0.05, name=entry["name"])
        if t_recv is not None:
            delays.append(t_recv - reg[tile])
            lag.append(entry["t_sent"] - reg[tile])
    if delays:
        print(f"tile registered -> its points on the client: median {statistics.median(delays) * 1000:.0f} ms, "
              f"p90 {pct(delays, 90) * 1000:.0f} ms, max {max(delays) * 1000:.0f} ms "
              f"over {len(delays)} tiles (viewer update rate {app.update_hz:g} Hz)")
        print(f"  of which registration -> chunk sent by the viewer: median "
              f"{statistics.median(lag) * 1000:.0f} ms, max {max(lag) * 1000:.0f} ms")

    busy = [dt for _, dt, sent in app.tick_log if sent is not None]
    if busy:
        print(f"viewer updates that changed something: {len(busy)}, duration median "
              f"{statistics.median(busy) * 1000:.0f} ms, p90 {pct(busy, 90) * 1000:.0f} ms, "
              f"max {max(busy) * 1000:.0f} ms")
    sizes = [n for _, n, _ in client.frames]
    kinds: dict[str, int] = {}
    for _, _, m in client.frames:
        for t, _ in m:
            kinds[t] = kinds.get(t, 0) + 1
    print(f"websocket frames (one per viewer update): {len(sizes)}, total {sum(sizes) / 1e6:.2f} MB; "
          f"per frame median {statistics.median(sizes) / 1e3:.1f} kB, p90 {pct(sizes, 90) / 1e3:.1f} kB, "
          f"max {max(sizes) / 1e3:.1f} kB")
    top = sorted(kinds.items(), key=lambda kv: -kv[1])[:6]
    print("messages: " + ", ".join(f"{k} x{v}" for k, v in top))
    n_sent = sum(e["n"] for e in app.scene.sent_log)
    b_pts = sum(e["bytes"] for e in app.scene.sent_log)
    print(f"point payload: {n_sent:,} points in {len(app.scene.sent_log)} chunks, {b_pts / 1e6:.2f} MB "
          f"({b_pts / max(n_sent, 1):.0f} B per point: float32 xyz + RGB); "
          f"{n_sent / max(snap.n_points, 1):.2f} x the final cloud (rebuilds at each global BA)")
    lsz = sum(n for _, n, _ in late.frames)
    print(f"a tab opened at the end downloads {lsz / 1e6:.2f} MB in {len(late.frames)} frames")
    if not args.keep:
        shutil.rmtree(out, ignore_errors=True)


def cold(args) -> None:
    """`aerec view` (no argument) from a bare cache, as a new user's first run: command ->
    page served, -> first points on a connected client (reconnecting when the preparation page
    hands its address over to the viewer)."""
    import os
    import subprocess
    import urllib.request

    cache = Path(tempfile.mkdtemp(prefix="bench_cold_cache_"))
    # an empty numba cache too: a fresh machine compiles the renderer's and the solver's kernels
    env = {**os.environ, "AEREC_CACHE": str(cache), "NUMBA_CACHE_DIR": str(cache / "numba")}
    t0 = time.time()
    proc = subprocess.Popen([sys.executable, "-m", "aerec_viewer", "--port", "0", "--no-browser-hint"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines: list[tuple[float, str]] = []
    threading.Thread(target=lambda: [lines.append((time.time(), ln)) for ln in iter(proc.stdout.readline, "")],
                     daemon=True).start()
    t_page = t_points = t_screen = None
    client = browser = None
    try:
        port = None
        while port is None and time.time() - t0 < 120 and proc.poll() is None:
            for _, ln in list(lines):
                if "http://" in ln:
                    port = int(ln.split("http://", 1)[1].split("/")[0].split(":")[1].split()[0].rstrip(";"))
                    break
            time.sleep(0.05)
        if port is None:
            raise SystemExit("no address printed:\n" + "".join(ln for _, ln in lines[-20:]))
        browser = BrowserProbe(f"http://127.0.0.1:{port}/") if args.browser else None
        while t_page is None and time.time() - t0 < 120:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as r:
                    if r.status == 200:
                        t_page = time.time()
            except OSError:
                time.sleep(0.05)
        while t_points is None and time.time() - t0 < args.cold_timeout and proc.poll() is None:
            if client is None or not client._thread.is_alive():
                try:
                    client = WireClient(port)
                except OSError:
                    time.sleep(0.3)
                    continue
            t_points = client.first("PointCloudMessage")
            time.sleep(0.2)
        if browser is not None:
            while browser.t_points is None and time.time() - t0 < args.cold_timeout:
                time.sleep(0.2)
            t_screen = browser.finish()
    finally:
        if client is not None:
            client.close()
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
        shutil.rmtree(cache, ignore_errors=True)
    ready = next((t for t, ln in lines if "reconstructing" in ln), None)
    print(f"aerec view from a bare cache, numba's included (demo preset "
          f"{os.environ.get('AEREC_DEMO_PRESET') or 'the default'}):")
    print(f"  command -> page served: {t_page - t0:.1f} s" if t_page else "  page never served")
    if ready:
        print(f"  command -> demo site generated, viewer started: {ready - t0:.1f} s")
    print(f"  command -> first points on a connected client: {t_points - t0:.1f} s" if t_points
          else f"  no points within {args.cold_timeout:.0f} s")
    if args.browser:
        print(f"  command -> first points on a headless Chromium screen: {t_screen - t0:.1f} s"
              if t_screen else "  no points seen on the Chromium screen")


# Counts the frames the page draws: a frame clears the canvas (viser 1.1.1: once, or 4 times within
# a millisecond with its default lights' shadow cascades; frames are > 30 ms apart in software
# WebGL); viser renders on demand, so
# requestAnimationFrame alone would count frames that draw nothing.
COUNT_RENDERS = """
  window.__renders = [];
  for (const C of [WebGL2RenderingContext, WebGLRenderingContext]) {
    const clear = C.prototype.clear;
    C.prototype.clear = function (m) { window.__renders.push(performance.now()); return clear.call(this, m); };
  }"""


def orbit_fps(page, seconds: float = 6.0) -> tuple[float, int, float]:
    """Frames drawn per second while the mouse orbits the view (left button held, a circle
    traced as fast as the page takes the moves), the number of moves it took, and the rate the
    viewer's counter iframe counted (its requestAnimationFrame callbacks; nan without it)."""
    w = page.viewport_size["width"] - 520          # left of the control panel
    h = page.viewport_size["height"]
    cx, cy, r = w / 2, h / 2, min(w, h) / 5
    page.mouse.move(cx + r, cy)
    page.mouse.down()
    t0 = page.evaluate("performance.now()")
    n, a, start = 0, 0.0, time.time()
    while time.time() - start < seconds:
        a += 0.12
        page.mouse.move(cx + r * np.cos(a), cy + 0.6 * r * np.sin(a))
        n += 1
    t1 = page.evaluate("performance.now()")
    page.mouse.up()
    # viser clears the canvas several times per frame (4 here): a frame is a run of clears
    drawn = page.evaluate(f"""(() => {{ const a = window.__renders.filter(t => t >= {t0} && t <= {t1});
        let n = 0; for (let i = 0; i < a.length; i++) if (i === 0 || a[i] - a[i - 1] > 4) n++; return n; }})()""")
    counter = next((f for f in page.frames if "frames.html" in f.url), None)
    iframe = float("nan")
    if counter is not None and hasattr(page, "counted"):
        time.sleep(1.0)              # its report of the last frames (every 0.5 s)
        # the iframe's clock is the page's shifted by their time origins
        shift = counter.evaluate("performance.timeOrigin") - page.evaluate("performance.timeOrigin")
        iv = np.diff([t + shift for t in page.counted if t0 <= t + shift <= t1]) / 1000.0
        iframe = drawn_rate(iv) if len(iv) > 2 else float("nan")      # as the viewer reads it
    return drawn * 1000.0 / max(t1 - t0, 1.0), n, iframe


def fps(args) -> None:
    """`aerec view OUT --point-budget N` for each budget, headless Chromium at 1600 x 1000 with
    software WebGL: frames drawn per second while orbiting, once the points are on the screen."""
    import os
    import re
    import subprocess

    from playwright.sync_api import sync_playwright

    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
             "--disable-quic", "--no-first-run", "--disable-background-networking",
             "--disable-component-update", "--disable-sync"]
    print(f"frames drawn per second while orbiting, {args.fps}, headless Chromium 1600 x 1000, "
          f"software WebGL, {os.cpu_count()} cores:")
    for budget in [int(b) for b in args.budgets.split(",")]:
        cmd = [sys.executable, "-m", "aerec_viewer", str(args.fps), "--port", "0", "--no-browser-hint"]
        if budget:
            cmd += ["--point-budget", str(budget)]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        lines: list[str] = []
        threading.Thread(target=lambda: [lines.append(ln) for ln in iter(proc.stdout.readline, "")],
                         daemon=True).start()
        try:
            url = None
            for _ in range(600):
                url = next((m.group(0) for ln in lines for m in [re.search(r"http://\S+", ln)] if m), None)
                if url or proc.poll() is not None:
                    break
                time.sleep(0.1)
            if url is None:
                raise SystemExit("the viewer printed no address:\n" + "".join(lines[-20:]))
            with sync_playwright() as pw:
                b = pw.chromium.launch(executable_path="/usr/bin/chromium", args=flags, headless=True)
                pages = []
                for _ in range(args.tabs):
                    page = b.new_page(viewport={"width": 1600, "height": 1000})
                    page.add_init_script(COUNT_RENDERS)
                    page.counted = []                # what the counter iframe posts to the viewer
                    page.on("request", lambda r, c=page.counted: c.extend(json.loads(r.post_data)["frames"])
                            if r.url.endswith("/api/frames") and r.post_data else None)
                    page.goto(url.rstrip(";"))
                    pages.append(page)
                time.sleep(args.settle)              # the cloud arrives, textures upload
                # --load K: K busy processes beside the browser (a machine doing other work)
                burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                           for _ in range(args.load)]
                shown = """() => { const t = document.body.innerText;
                    const m = t.match(/points displayed\\s*([\\d,]+)/); return m ? m[1] : '?'; }"""
                rates, labels, counted = [], [], []
                t_end = time.time() + args.duration
                k = 0
                # --duration: orbits for that long (tabs in turn, `between` apart), else `repeats`
                while (k < args.repeats) if not args.duration else (k == 0 or time.time() < t_end):
                    if k:
                        time.sleep(args.between)     # the viewer may adapt its budget in between
                    page = pages[k % len(pages)]
                    labels.append(page.evaluate(shown))
                    r, _, iframe = orbit_fps(page, args.seconds)
                    rates.append(r)
                    counted.append(iframe)
                    if args.duration:
                        print(f"    t {time.time() - t_end + args.duration:5.1f} s tab {k % len(pages)}: "
                              f"drawn {r:.1f} fps (the counter iframe, as the viewer reads it: {iframe:.1f}), "
                              f"1-min load {os.getloadavg()[0]:.1f}", flush=True)
                    k += 1
                for p in burners:
                    p.kill()
                label = " -> ".join(dict.fromkeys(labels))
                if args.shots:
                    Path(args.shots).mkdir(parents=True, exist_ok=True)
                    pages[0].screenshot(path=str(Path(args.shots) / f"fps_{budget or 'default'}.png"))
                b.close()
        finally:
            proc.terminate()
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
        notes = [ln.strip() for ln in lines if "budget" in ln.lower()]
        if args.duration:
            n = len(pages)
            before, after = rates[:n], rates[-n:]
            print(f"  {n} tab(s), {len(rates)} orbits in {args.duration:.0f} s: drawn before the governor "
                  f"{', '.join(f'{r:.1f}' for r in before)} fps; after (the last orbit of each tab) "
                  f"{', '.join(f'{r:.1f}' for r in after)} fps")
        print(f"  budget {budget or 'default':>8}: first orbit {rates[0]:.1f} fps, last {rates[-1]:.1f} "
              f"(runs {', '.join(f'{r:.1f}' for r in rates)}), points displayed {label}"
              + (f"; viewer said: {notes[-1]}" if notes else ""))


class BrowserProbe:
    """Headless Chromium on the page; a thread notes when points first appear on its screen."""

    def __init__(self, url: str):
        self.url = url
        self.t_points: float | None = None
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from playwright.sync_api import sync_playwright

        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                 "--disable-quic", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path="/usr/bin/chromium", args=flags, headless=True)
            page = b.new_page(viewport={"width": 1000, "height": 700})
            page.goto(self.url)
            # the scene starts empty: points (and tiles) change the canvas left of the panel
            import cv2

            def grab():
                png = page.screenshot()
                img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
                return img[200:650, 150:560].astype(np.int16)

            time.sleep(2.0)
            base = grab()
            while not self._done.is_set() and self.t_points is None:
                t = time.time()
                if (np.abs(grab() - base) > 30).mean() > 0.002:
                    self.t_points = t
                time.sleep(0.2)
            self._done.wait(120)
            b.close()

    def finish(self) -> float | None:
        self._done.set()
        self._thread.join(30)
        return self.t_points


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--site", default=None, help="site folder (default: the demo site)")
    p.add_argument("--preset", default="tiny")
    p.add_argument("--tile-size", type=int, default=None)
    p.add_argument("--until", default="sparse", help="last pipeline stage (default sparse)")
    p.add_argument("--browser", action="store_true", help="also time the first points on a "
                                                          "headless Chromium screen")
    p.add_argument("--keep", action="store_true", help="keep the output folder")
    p.add_argument("--cold", action="store_true", help="time `aerec view` (no argument) from a "
                                                        "bare cache: page served, first points")
    p.add_argument("--cold-timeout", type=float, default=900.0)
    p.add_argument("--fps", type=Path, default=None, metavar="OUT",
                   help="frames drawn per second while orbiting the finished OUT")
    p.add_argument("--budgets", default="0", help="--fps: point budgets to try (0: the viewer's default)")
    p.add_argument("--seconds", type=float, default=6.0, help="--fps: orbit time per measurement")
    p.add_argument("--repeats", type=int, default=3, help="--fps: measurements per budget")
    p.add_argument("--between", type=float, default=12.0, help="--fps: seconds between measurements")
    p.add_argument("--settle", type=float, default=25.0, help="--fps: seconds for the scene to load")
    p.add_argument("--tabs", type=int, default=1, help="--fps: browser tabs on the viewer")
    p.add_argument("--load", type=int, default=0,
                   help="--fps: this many busy processes run beside the browser while it orbits")
    p.add_argument("--duration", type=float, default=0.0,
                   help="--fps: orbit this long (tabs in turn) instead of --repeats times")
    p.add_argument("--shots", default=None, help="--fps: save a screenshot per budget here")
    args = p.parse_args()
    if args.fps:
        fps(args)
    else:
        cold(args) if args.cold else run(args)


if __name__ == "__main__":
    main()

"""`aerec view [SITE_OR_OUT]`: the browser viewer, registered through the `aerec.commands` entry point.

- no argument: the bundled demo site, generated offline on first use into the cache folder
  ($AEREC_CACHE, else $XDG_CACHE_HOME/aerec, else ~/.cache/aerec) as `demo_site/`, reconstructed
  into `demo_site_aerec_out/` beside it;
- a folder with `images/`: a site, reconstructed live into OUT (default
  `<site>/../<site name>_aerec_out`, or `<cache>/runs/<site name>_aerec_out` when the site's
  parent is not writable; `--out` to choose);
- a folder with `report.json` or `affine/`: a finished OUT, reopened without recomputing (the
  report names the site; `--site` when it moved).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


def cache_dir() -> Path:
    base = os.environ.get("AEREC_CACHE")
    if base:
        return Path(base)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "aerec"


# The demo of `aerec view`: the `mini` preset (6 images of 800 px in two date groups), shipped
# in assets/demo_site (6 MB) so that nothing is generated or compiled before the first points;
# generated on first use (10 s) when the assets are not there (an install from a wheel).
# Tiles of DEMO_TILE_SIZE px: 9 per image, registered one by one on the page.
DEFAULT_DEMO = "mini"
DEMO_TILE_SIZE = 400
ASSET_DEMO = Path(__file__).resolve().parents[1] / "assets" / "demo_site"


def demo_preset() -> str:
    """The synthetic preset of the demo: `mini`, or $AEREC_DEMO_PRESET (`demo` for a larger
    one, `tiny2` for a toy in seconds)."""
    from recon_core.errors import InputError
    from recon_core.synthetic.generator import PRESETS

    name = os.environ.get("AEREC_DEMO_PRESET") or DEFAULT_DEMO
    if name not in PRESETS:
        raise InputError(None, f"AEREC_DEMO_PRESET={name!r} is not a synthetic preset; choose "
                               f"from {', '.join(sorted(PRESETS))}")
    return name


def _demo_dir() -> Path:
    if demo_preset() == DEFAULT_DEMO and (ASSET_DEMO / "images").is_dir():
        return ASSET_DEMO
    name = "demo_site" if demo_preset() == DEFAULT_DEMO else f"demo_site_{demo_preset()}"
    return cache_dir() / name


_WARMUP = ("import sys\n"
           "from recon_core.synthetic.generator import warm_render_kernel\n"
           "warm_render_kernel()\n"
           "print('render', flush=True)\n"
           "from recon_core.sparse.bundle import warm_compiled_kernels\n"
           "warm_compiled_kernels()\n"
           "from recon_core.dense.mgm import warm_compiled_kernels as warm_mgm\n"
           "warm_mgm()\n")


_WARM_BA = ("from recon_core.sparse.bundle import warm_compiled_kernels\nwarm_compiled_kernels()\n"
            "from recon_core.dense.mgm import warm_compiled_kernels as warm_mgm\nwarm_mgm()\n")


def _start_ba_warmup():
    """A second process compiling the bundle adjustment's kernels, then MGM's, into numba's cache
    while this one detects and matches features (a few seconds each): on a fresh machine the
    first adjustment and the dense stage then load them instead of compiling them on the way.
    A no-op when cached."""
    import subprocess
    import threading

    try:
        p = subprocess.Popen([sys.executable, "-c", _WARM_BA], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    except OSError:
        return
    threading.Thread(target=p.wait, daemon=True, name="aerec-ba-warmup-reaper").start()


def _start_warmup():
    """A second process compiling numba kernels into the cache on a fresh machine: the render
    kernel while this process builds the scene (each compile is single-threaded), then the
    bundle adjustment's while the images render, so neither compile is on the way to the
    first points."""
    import subprocess

    try:
        return subprocess.Popen([sys.executable, "-c", _WARMUP], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, text=True)
    except OSError:
        return None


def _wait_render_warm(warm, timeout: float = 120.0) -> None:
    """Wait until the warm-up says the render kernel is cached (or has ended, or timeout):
    waiting costs less than compiling it a second time beside it."""
    import select

    if warm is None:
        return
    try:
        ready, _, _ = select.select([warm.stdout], [], [], timeout)
        if ready:
            warm.stdout.readline()
    except (OSError, ValueError):
        pass


def demo_site(progress=None) -> Path:
    """The demo site, generated (offline, seed 0) on first use; atomic (io.files.atomic_folder)."""
    site = _demo_dir()
    if (site / "images").is_dir():
        return site
    from recon_core.io.files import atomic_folder
    from recon_core.synthetic.generator import generate_site

    warm = _start_warmup()
    try:
        with atomic_folder(site) as tmp:
            try:
                generate_site(tmp, preset=demo_preset(), seed=0, progress=progress,
                              before_render=lambda: _wait_render_warm(warm))
            except BaseException:
                if warm is not None and warm.poll() is None:
                    warm.kill()
                raise
            if warm is not None:          # it goes on compiling the BA kernels: reap it when done
                import threading

                threading.Thread(target=warm.wait, daemon=True, name="aerec-warmup-reaper").start()
    except OSError:
        if not (site / "images").is_dir():
            raise
        # another process won the race: its site is the same (seed 0)
    return site


def demo_cached() -> bool:
    return (_demo_dir() / "images").is_dir()


def _demo_progress():
    """A progress printer for the first-run generation of the demo site (None when cached)."""
    if demo_cached():
        return None
    from recon_core.cli import ProgressPrinter

    print(f"aerec view: generating the demo site into {cache_dir()} (first run only, offline)",
          file=sys.stderr)
    return ProgressPrinter(True)


class DemoPreparation:
    """The page served while the demo site is generated on first use: the browser shows the
    generation's progress at once, and the viewer takes over the same address when the site is
    ready (the page reconnects by itself)."""

    # share of the whole generation per stage (rendering dominates)
    WEIGHTS = {"cameras": 0.02, "accel": 0.08, "render": 0.73, "rpc": 0.02, "gt_dsm": 0.1, "gcps": 0.05}

    def __init__(self, host: str, port: int):
        import viser

        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        from recon_core.synthetic.generator import PRESETS

        groups = PRESETS[demo_preset()].groups
        views = " and ".join(sorted({str(n) for n in groups}))
        gui = self.server.gui
        gui.add_markdown(f"## AE-Rec: preparing the demo\n\nFirst run only, offline: rendering "
                         f"{sum(groups)} synthetic Pleiades-like images of a procedural city "
                         f"({len(groups)} date(s), {views} views each). The reconstruction starts "
                         "on this page as soon as they are ready; keep it open.")
        self.bar = gui.add_progress_bar(0.0, animated=True)
        self.md = gui.add_markdown("starting")
        self._done: dict[str, float] = {}
        self._t0 = time.time()

    def progress(self, stage, done=None, total=None, message: str = "") -> None:
        """generate_site's progress(stage, done, total): one bar over the whole generation."""
        if not isinstance(stage, str) or not total:
            return
        assert done is not None                  # given with total
        from recon_core.synthetic.generator import PRESETS

        self._done[stage] = min(1.0, float(done) / float(total))
        n_img = max(1, PRESETS[demo_preset()].n_images)
        whole = 0.0
        for k, v in self._done.items():
            key = k.split()[0]
            share = self.WEIGHTS.get(key, 0.0) / (n_img if key == "render" else 1)
            whole += share * v
        self.bar.value = float(100.0 * min(whole, 0.99))
        self.md.content = f"{stage}: {100 * self._done[stage]:.0f} % · {time.time() - self._t0:.0f} s"

    def close(self, ok: bool = True) -> None:
        if ok:
            self.md.content = "the demo site is ready: starting the reconstruction"
            self.bar.value = 100.0
        else:
            self.md.content = "**the demo could not be generated**: see the terminal"
        time.sleep(0.3)
        self.server.stop()


def is_out_folder(p: Path) -> bool:
    from recon_core.io.layout import OutLayout

    return OutLayout(p).is_output()


def default_out(site: Path) -> Path:
    """<site>/../<name>_aerec_out, or the cache when the site's parent is not writable (and for
    the shipped demo: its outputs do not belong in the repository)."""
    site = site.resolve()
    if site == ASSET_DEMO.resolve():
        return cache_dir() / "runs" / "demo_aerec_out"
    cand = site.parent / f"{site.name}_aerec_out"
    if os.access(site.parent, os.W_OK) or (cand.exists() and os.access(cand, os.W_OK)):
        return cand
    return cache_dir() / "runs" / f"{site.name}_aerec_out"


def resolve_target(target: Path | None, out: Path | None, site: Path | None
                   ) -> tuple[str, Path | None, Path]:
    """(mode, site, out) for the command-line arguments. mode: "run" or "reopen"."""
    from recon_core.errors import InputError

    if target is None:
        s = site or demo_site(progress=_demo_progress())
        return "run", s, out or default_out(s)
    target = Path(target)
    if not target.is_dir():
        raise InputError(target, "is neither a site folder (with images/) nor an output folder "
                                 "(with report.json)")
    if (target / "images").is_dir():
        return "run", target, out or default_out(target)
    if is_out_folder(target):
        return "reopen", site, target
    raise InputError(target, "is neither a site folder (with images/) nor an output folder "
                             "(with report.json or affine/)")


def cmd_view(args) -> int:
    from recon_core.config import preset

    from .app import ViewerApp

    check_view_options(args)
    reference = None
    if getattr(args, "reference_ortho", None) is not None:
        from recon_core.euclidean.ground_reference import open_ground_reference

        reference = open_ground_reference(args.reference_ortho, args.reference_dem)
    prep = None
    demo_preset()                             # an unknown AEREC_DEMO_PRESET: one line, now
    if args.target is None and args.site is None and not demo_cached():
        # serve a page at once: generating the demo takes minutes on a small machine
        prep = DemoPreparation(args.host, args.port)
        print(f"aerec view: preparing the demo site (first run only); open http://"
              f"{'localhost' if args.host in ('127.0.0.1', '0.0.0.0') else args.host}:{prep.port}",
              flush=True)
        printer = _demo_progress()

        def both(*a, **k):
            prep.progress(*a, **k)
            if printer is not None:
                printer(*a, **k)
        ok = False
        try:
            demo_site(progress=both)
            ok = True
        finally:
            prep.close(ok)
            if printer is not None:
                printer.close()
        args.port = prep.port                 # the viewer takes over the page's address
    mode, site, out = resolve_target(args.target, args.out, args.site)
    if reference is not None:
        from recon_core.euclidean.ground_reference import check_reference_files
        from recon_core.io.site import load_site

        where = site if site is not None else _site_of(out)
        if where is not None:
            check_reference_files(load_site(where), ortho=reference, dem=reference.dem)
    # the viewer writes into OUT (its GCP set, the upgrade, the DSM): it holds OUT's lock for
    # its whole session, so a second job on OUT is refused naming it (recon_core.io.lock)
    from recon_core.errors import InputError
    from recon_core.io.lock import out_lock

    if site is not None:
        from recon_core.preflight import refuse_nested

        refuse_nested(site, out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(out, f"cannot create the output folder ({exc.strerror or exc})") from None
    lock = out_lock(out)
    lock.__enter__()
    if mode == "run":
        _start_ba_warmup()
    cfg = None
    if mode == "run" or args.preset or args.tile_size:
        cfg = preset(args.preset or "default")
        tile = args.tile_size or (DEMO_TILE_SIZE if args.target is None and args.site is None
                                  and demo_preset() == DEFAULT_DEMO else None)
        if tile:
            cfg = cfg.with_overrides({"tiling.tile_size": tile})
    app = ViewerApp(out, site, cfg, mode=mode, host=args.host, port=args.port,
                    budget=args.point_budget, reference=reference)
    app.start()
    what = "reopening" if mode == "reopen" else "reconstructing"
    print(f"aerec view: {what} {app.site.root} -> {out}")
    print(f"aerec view: open {app.url}")
    print(f"aerec view: image workspace (GCPs side by side in the images) at {app.workspace.url}")
    if not args.no_browser_hint:
        if args.host in ("127.0.0.1", "localhost"):
            ws = app.workspace.port
            print("  (bound to this machine only; from another machine use "
                  f"`ssh -L {app.port}:127.0.0.1:{app.port} -L {ws}:127.0.0.1:{ws} HOST` or --host 0.0.0.0)")
        print("  Ctrl-C to quit; picked GCPs are saved to "
              f"{app.session.path} after every change.")
    sys.stdout.flush()
    console = ConsoleProgress(app.worker, out)
    try:
        while True:
            time.sleep(1.0)
            console.poll()
    except KeyboardInterrupt:
        print("aerec view: stopping", file=sys.stderr)
    finally:
        app.stop()
        lock.__exit__(None, None, None)
    return 0


class ConsoleProgress:
    """What the reconstruction does, told on the terminal too (the page is not the only place
    a user looks): each stage as it starts and ends, the first points, and one closing line with
    where the outputs are and what to do next."""

    def __init__(self, worker, out: Path):
        self.worker, self.out = worker, out
        self.stage: str | None = None
        self.finished: set[str] = set()
        self.first_told = False
        self.status_told: str | None = None

    def poll(self) -> None:
        snap = self.worker.snapshot()
        t = time.time() - snap.t_start
        if snap.t_first_points is not None and not self.first_told:
            self.first_told = True
            self._say(f"first points at {snap.t_first_points - snap.t_start:.1f} s")
        for stage, seconds in snap.stages_finished.items():
            if stage not in self.finished:
                self.finished.add(stage)
                self._say(f"{stage} done ({seconds:.0f} s)")
        if snap.stage and snap.stage != self.stage and snap.stage not in self.finished \
                and snap.status == "running":
            self.stage = snap.stage
            self._say(f"{snap.stage}: running ({t:.0f} s since the start)")
        if snap.status in ("done", "failed", "reopened", "stopped") and snap.status != self.status_told:
            self.status_told = snap.status
            if snap.status == "done" and snap.awaiting_gcps:
                self._say(f"affine reconstruction finished in {t:.0f} s; outputs in {self.out}")
                from recon_core.euclidean.control import need_words

                self._say(f"next: place {need_words()} in the GCP tab of the page, then press Upgrade")
            elif snap.status == "done":
                self._say(f"finished in {t:.0f} s; outputs in {self.out}")
                self._say("next: the DSM and its height-error map are in the page's Results tab; "
                          "check points and the GCPs' residuals in its upgrade report; "
                          f"{self.out}/dsm.tif and cloud.laz open in QGIS or CloudCompare")
            elif snap.status == "failed":
                self._say(f"stopped in the {snap.failed_stage or 'run'}: {snap.error}")
                if snap.hint:
                    self._say(f"next: {snap.hint}")
            elif snap.status == "reopened":
                self._say(f"reopened {self.out}")

    @staticmethod
    def _say(text: str) -> None:
        print(f"aerec view: {text}", flush=True)


def check_view_options(args) -> None:
    """The viewer's options, before anything starts: one line naming the option (a port out of
    range, a tile size or preset the pipeline refuses, an output folder that is a file)."""
    from recon_core.config import PRESETS, preset
    from recon_core.errors import InputError
    from recon_core.preflight import check_config

    if not 0 <= args.port <= 65535:
        raise InputError(None, f"--port {args.port}: a port is 0-65535 (0: any free one)")
    budget = getattr(args, "point_budget", None)
    if budget is not None and not 10_000 <= budget <= 2_000_000:
        raise InputError(None, f"--point-budget {budget}: points displayed are 10000-2000000")
    if args.preset is not None and args.preset not in PRESETS:
        raise InputError(None, f"--preset {args.preset!r}: choose one of {', '.join(sorted(PRESETS))}")
    if args.tile_size is not None:
        try:
            check_config(preset(args.preset or "default").with_overrides({"tiling.tile_size": args.tile_size}))
        except InputError as exc:
            raise InputError(None, f"--tile-size {args.tile_size}: {exc.problem.split(': ', 1)[-1]}") from None
    for opt, path in (("--out", args.out), ("--site", args.site)):
        if path is not None and path.exists() and not path.is_dir():
            raise InputError(path, f"{opt} names a file; it must be a folder")
    if args.target is not None and not args.target.exists():
        raise InputError(args.target, "no such site or output folder")
    if getattr(args, "reference_dem", None) is not None and getattr(args, "reference_ortho", None) is None:
        raise InputError(args.reference_dem, "--reference-dem gives heights to points clicked on "
                                             "--reference-ortho: give the orthoimage too")


def _site_of(out: Path) -> Path | None:
    """The site a finished OUT was made from (its report says), or None."""
    import json

    try:
        site = json.loads((Path(out) / "report.json").read_text()).get("site")
    except (OSError, ValueError):
        return None
    return Path(site) if site and Path(site).is_dir() else None


def register(subparsers) -> None:
    """Add the `view` subcommand to the `aerec` command (entry point `aerec.commands`)."""
    s = subparsers.add_parser("view", help="browser viewer: live reconstruction, GCP picking, "
                                           "Euclidean upgrade, DSM and error maps")
    s.add_argument("target", type=Path, nargs="?", default=None,
                   help="site folder (reconstruct it) or output folder (reopen it); "
                        "none: the demo site")
    s.add_argument("--out", type=Path, default=None, help="output folder for a site")
    s.add_argument("--site", type=Path, default=None,
                   help="the site of a reopened OUT, when report.json's path moved")
    s.add_argument("--host", default="127.0.0.1", help="interface to serve on (default 127.0.0.1)")
    s.add_argument("--port", type=int, default=8080, help="port (a busy one moves to the next)")
    s.add_argument("--tile-size", type=int, default=None, help="tile side d in pixels")
    s.add_argument("--preset", default=None, help="parameter preset (default, tiny)")
    s.add_argument("--point-budget", type=int, default=None, metavar="N",
                   help="points displayed at most when the view rests, 10000-2000000 (default "
                        "150000; while a view moves, fewer as the page's frame rate asks)")
    s.add_argument("--reference-ortho", type=Path, default=None, metavar="TIF",
                   help="a georeferenced orthoimage of the site (a national orthophoto, any "
                        "GeoTIFF): shown last in the GCP tab's image list; a click on it gives a "
                        "GCP its ground position (no survey needed)")
    s.add_argument("--reference-dem", type=Path, default=None, metavar="TIF",
                   help="with --reference-ortho: a DEM giving those GCPs their height (ellipsoidal: "
                        "convert a geoid-based DEM such as SRTM first)")
    s.add_argument("--no-browser-hint", action="store_true",
                   help="print only the URL, not the ssh-tunnel and save-file hints")
    s.set_defaults(func=cmd_view)


def main(argv: list[str] | None = None) -> int:
    """`python -m aerec_viewer [SITE_OR_OUT] ...`: the same as `aerec view ...`."""
    from recon_core.errors import AerecError

    p = argparse.ArgumentParser(prog="python -m aerec_viewer")
    sub = p.add_subparsers(dest="command")
    register(sub)
    args = p.parse_args(["view", *(sys.argv[1:] if argv is None else argv)])
    try:
        return int(args.func(args) or 0)
    except AerecError as exc:
        print(f"aerec view: error: {exc}", file=sys.stderr)
        return 2

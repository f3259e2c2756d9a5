"""The `aerec` command: thin wrappers over the library, with progress bars and one-line errors."""

from __future__ import annotations

import argparse
import errno
import math
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from recon_core.errors import AerecError

if TYPE_CHECKING:
    from tqdm import tqdm


class ProgressPrinter:
    """Turns StageProgress events (or progress(stage, done, total) calls) into tqdm bars."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self._bars: dict[str, tqdm] = {}

    def __call__(self, stage, done=None, total=None, message: str = "") -> None:
        from recon_core.events import Message, StageDone, StageProgress, TileRegistered

        if isinstance(stage, TileRegistered):    # the registration loop: tiles registered / total
            ev = stage
            stage, done, total, message = f"sfm [g{ev.group}]", ev.order + 1, ev.total_tiles, ev.tile_id
        elif isinstance(stage, StageProgress):
            ev = stage
            stage, done, total, message = ev.stage, ev.done, ev.total, ev.message
            if ev.group is not None:
                stage = f"{stage} [g{ev.group}]"
        elif isinstance(stage, Message):       # warnings and errors even with --quiet
            if stage.level in ("warning", "error") or (self.enabled and stage.level != "debug"):
                self._write(f"{stage.level}: {stage.text}")
            return
        elif isinstance(stage, StageDone):
            return
        elif not isinstance(stage, str):
            return
        if not self.enabled:
            return
        from tqdm import tqdm

        bar = self._bars.get(stage)
        if bar is None or bar.total != total:
            if bar is not None:
                bar.close()
            # no rate: counts arrive in jumps (points by the million, tiles one by one), and
            # tqdm's items/s of such jumps is meaningless
            bar = tqdm(total=total, desc=stage, leave=True, dynamic_ncols=True, file=sys.stderr,
                       bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} "
                                  "[{elapsed}<{remaining}{postfix}]")
            self._bars[stage] = bar
        assert done is not None and total is not None   # a progress count names both
        bar.n = done
        if message:
            bar.set_postfix_str(message, refresh=False)
        bar.refresh()
        if done >= total:
            bar.close()
            self._bars.pop(stage, None)

    def _write(self, text: str) -> None:
        from tqdm import tqdm

        tqdm.write(text, file=sys.stderr)

    def close(self) -> None:
        for bar in self._bars.values():
            bar.close()
        self._bars.clear()


def cmd_info(args) -> int:
    from recon_core.config import Config
    from recon_core.errors import InputError
    from recon_core.io.site import load_site
    from recon_core.model.grouping import group_by_date
    from recon_core.preflight import check_config

    try:                      # the grouping options under the rules `aerec run` holds them to
        check_config(Config().with_overrides({"grouping.max_gap_days": args.max_gap_days,
                                              "grouping.max_span_days": args.max_span_days}), until="sparse")
    except InputError as exc:
        raise InputError(None, f"--max-gap-days / --max-span-days: {exc.problem}") from None
    site = load_site(args.site, require_times=False)
    print(f"site {site.name} at {site.root}")
    print(f"{len(site.images)} image(s):")
    for im in site.images:
        t = im.acquired.strftime("%Y-%m-%d %H:%M:%S") if im.acquired else "NO TIME"
        print(f"  {im.name:24s} {im.width:6d} x {im.height:<6d} {im.bands} band {im.dtype:8s} "
              f"{t} ({im.time_source}) rpc={'yes' if im.has_rpc else 'no'}" + _sensor(im.path)
              + (f" view {im.view.incidence_deg:g} deg from vertical, azimuth {im.view.azimuth_deg:g}"
                 if im.view is not None else ""))
    missing = [im.name for im in site.images if im.acquired is None]
    if missing:
        print(f"groups: cannot group, no acquisition time for {', '.join(missing)}")
    else:
        groups = group_by_date(site.images, args.max_gap_days, args.max_span_days)
        cap = "no span cap" if args.max_span_days is None else f"span cap {args.max_span_days:g} d"
        print(f"{len(groups)} date group(s) (gap < {args.max_gap_days:g} d, {cap}):")
        for g in groups:
            print(f"  {g.describe()}: {', '.join(im.name for im in g.images)}")
    if not (site.root / "gcps.geojson").exists():
        for csv in sorted(site.root.glob("*.csv")):
            print(f"note: {csv.name} is not read (the site's GCPs are gcps.geojson): "
                  f"aerec gcps convert {csv} {site.root / 'gcps.geojson'}")
    n_ctrl = sum(g.role == "control" and g.enabled for g in site.gcps)
    n_off = sum(not g.enabled for g in site.gcps)
    print(f"{len(site.gcps)} GCP(s): {n_ctrl} control, {len(site.gcps) - n_ctrl - n_off} check"
          + (f", {n_off} disabled" if n_off else ""))
    for g in site.gcps:
        print(f"  {g.id:10s} {g.role:7s} lon {g.lon:.7f} lat {g.lat:.7f} h {g.h:8.2f} m, "
              f"seen in {len(g.observations)} image(s)" + ("" if g.enabled else ", disabled"))
    print(f"ground-truth DSM: {'yes' if site.gt_dsm else 'no'}")
    print(f"site.json: {site.hints if site.hints else 'none'}")
    if not missing:
        # what `aerec run` would refuse or warn about, as warnings here
        from recon_core.config import Config
        from recon_core.errors import InputError
        from recon_core.preflight import gcp_findings, refuse_gcps_off_the_images
        from recon_core.sparse.features import group_tone_curves

        try:
            refuse_gcps_off_the_images(site.root / "gcps.geojson", site.gcps, site)
        except InputError as exc:
            print(f"warning: `aerec run` would refuse: {exc.problem}")
        for level, _, text in gcp_findings(groups, site.gcps, Config()):
            if level == "error":
                print(f"warning: `aerec run` would refuse: {text}")
            elif level in ("warning", "joint"):
                print(f"warning: {text}")
        for g in groups:
            for w in group_tone_curves(g.images)[1]:
                print(f"warning: group {g.index}: {w}")
        from recon_core.memory import HEADROOM, available_mb, estimate

        est, have = estimate(site, Config()), available_mb()
        print("memory (estimated peak per stage): " + ", ".join(f"{e.stage} {e.mb / 1024:.1f} GB" for e in est)
              + (f"; {have / 1024:.1f} GB available" if have is not None else ""))
        for e in est:
            if have is not None and e.mb > HEADROOM * have:
                print(f"warning: `aerec run` would refuse: the {e.stage} stage would need about "
                      f"{e.mb / 1024:.1f} GB ({e.what})")
    return 0


def _sensor(image_path: Path) -> str:
    """' sensor PHR 1A' from the time sidecar `aerec site init` writes, else ''."""
    import json

    side = Path(image_path).with_suffix(".json")
    try:
        sat = json.loads(side.read_text()).get("satellite") if side.is_file() else None
    except (OSError, ValueError, AttributeError):
        sat = None
    return f" sensor {sat}" if sat else ""


def cmd_run(args) -> int:
    from recon_core.config import METHODS, PRESETS, preset
    from recon_core.errors import InputError
    from recon_core.events import EventBus, Message
    from recon_core.io.lock import out_lock
    from recon_core.pipeline import run
    from recon_core.preflight import check_config, preflight

    if args.preset not in PRESETS:
        raise InputError(None, f"unknown --preset {args.preset!r}; choose from {', '.join(sorted(PRESETS))}")
    if args.tile_size is not None and args.tile_size < 64:
        raise InputError(None, f"--tile-size must be at least 64 px, not {args.tile_size}")
    if args.workers is not None and args.workers < 1:
        raise InputError(None, f"--workers must be at least 1, not {args.workers}")
    if args.seed is not None and not 0 <= args.seed < 2 ** 63:
        raise InputError(None, f"--seed must be >= 0 and < 2^63, not {args.seed}")
    if not str(args.out).strip():
        raise InputError(None, "--out is empty: name the output folder")
    args.out = Path(args.out)
    cfg = preset(args.preset)
    if args.config is not None:
        from recon_core.config import config_from_toml

        cfg = config_from_toml(args.config)
    overrides = dict(METHODS[args.method])
    if args.tile_size:
        overrides["tiling.tile_size"] = args.tile_size
    if args.seed is not None:
        overrides["seed"] = args.seed
    if args.reference_dem is not None:
        overrides["upgrade.reference_dem"] = str(args.reference_dem.expanduser().resolve())
    if args.reference_dem_degree is not None:
        overrides["upgrade.reference_dem_degree"] = args.reference_dem_degree
        if args.reference_dem is None and not cfg.upgrade.reference_dem:
            print("aerec: warning: --reference-dem-degree has no effect without a reference DEM "
                  "(--reference-dem FILE)", file=sys.stderr)
    if args.scheduler:
        overrides["dense.scheduler"] = args.scheduler
    if args.workers:
        overrides["dense.workers"] = args.workers
    cfg = cfg.with_overrides(overrides)
    try:
        check_config(cfg, args.stage)
    except InputError as exc:          # name where the value came from
        where = args.config if args.config is not None else None
        raise InputError(where, exc.problem + ("" if where else " (from the command line)")) from None
    if cfg.dense.scheduler:            # from --scheduler or from --config: named as it was given
        probe_scheduler(cfg.dense.scheduler, option="--scheduler" if args.scheduler else
                        f"dense.scheduler (in {args.config})")
    prog = ProgressPrinter(not args.quiet)
    for w in preflight(args.site, args.out, cfg, until=args.stage, redo_from=args.redo_from):
        prog(Message("warning", w))
    # one job per output folder (recon_core.io.lock): another one is refused before any compute
    with out_lock(args.out, wait=args.wait, on_wait=lambda text: print(f"aerec: {text}", file=sys.stderr)):
        t0 = time.time()
        try:
            state = run(args.site, args.out, cfg, until=args.stage, bus=EventBus(prog),
                        resume=not args.restart, redo_from=args.redo_from)
        finally:
            prog.close()
    print_summary(state.report)
    print(f"done in {time.time() - t0:.1f} s; outputs in {args.out} (report.json)")
    hint = next_step(state.report, args.site, args.out)
    if hint:
        print(hint)
    return 0


_PROBE = '''
import sys
from distributed import Client
c = Client(sys.argv[1], timeout="{t}s")
n = len(c.scheduler_info().get("workers", {{}}))
c.close()
print(n)
'''


def probe_scheduler(address: str, timeout_s: float = 20.0, option: str = "--scheduler") -> int:
    """Check --scheduler before any compute: dask.distributed installed, the address well formed,
    a Dask scheduler answering there (in a child process with a deadline: a client talking to
    something that is not a scheduler waits forever), with at least one worker. Returns the
    number of workers; raises InputError naming `option`, where the address came from."""
    import re
    import subprocess
    import sys

    from recon_core.errors import InputError

    try:
        import distributed  # noqa: F401
    except ImportError:
        raise InputError(None, f"{option} needs dask.distributed: pip install 'aerec[dask]'") from None
    if not re.fullmatch(r"(tcp|tls|inproc|ucx)://(\[[0-9a-fA-F:]+\]|[^\s:/\[\]]+)(:\d+)?"
                        r"|[^\s:/]+:\d+", address):
        raise InputError(None, f"{option} {address!r} is not an address like tcp://host:8786")
    code = _PROBE.format(t=max(1, int(timeout_s) - 5))
    try:
        done = subprocess.run([sys.executable, "-c", code, address], capture_output=True, text=True,
                              timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise InputError(None, f"{option} {address}: no Dask scheduler answered within "
                               f"{timeout_s:g} s (is it a Dask scheduler's address and port?)") from None
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no answer"])[-1]
        raise InputError(None, f"{option} {address}: cannot reach a Dask scheduler ({last[:200]})")
    try:
        n = int(done.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        raise InputError(None, f"{option} {address}: unexpected answer from the scheduler") from None
    if n < 1:
        raise InputError(None, f"{option} {address}: the scheduler has no worker; start "
                               f"`dask worker {address}` on the machines that should compute")
    return n


def cmd_gcps(args) -> int:
    """`aerec gcps convert SRC DST`: gcps.geojson <-> CSV (recon_core.io.gcps_csv)."""
    from recon_core.errors import InputError
    from recon_core.io.gcps import check_observation, read_gcps_geojson, write_gcps_geojson
    from recon_core.io.gcps_csv import read_gcps_csv, write_gcps_csv

    kinds = {".csv": "csv", ".geojson": "geojson", ".json": "geojson"}
    for p in (args.src, args.dst):
        if p.suffix.lower() not in kinds:
            raise InputError(p, "must end in .csv, .geojson or .json")
    if args.src.resolve() == args.dst.resolve():
        raise InputError(args.dst, "is the input file; write to another file")
    if args.epsg is not None and args.epsg not in (4326, 4979):
        from recon_core.io.checks import projected_epsg

        projected_epsg(args.epsg, None, "--epsg")    # E, N need a projected CRS in metres
    images = None
    if args.site is not None:
        from recon_core.io.site import load_site

        images = {im.name: im for im in load_site(args.site, require_times=False, read_gcps=False).images}
    if kinds[args.src.suffix.lower()] == "csv":
        gcps = read_gcps_csv(args.src, args.epsg)
        if images is not None:                 # the GeoJSON reader's checks
            for g in gcps:
                for im, cr in g.observations.items():
                    check_observation(args.src, g.id, im, cr, images)
    else:
        gcps = read_gcps_geojson(args.src, images)
    from recon_core.io.files import writable_folder

    writable_folder(args.dst.parent if str(args.dst.parent) else Path("."), create=False)
    if kinds[args.dst.suffix.lower()] == "csv":
        picked = [g.id for g in gcps if g.affine_picked]
        if picked:
            raise InputError(args.src, f"{', '.join(picked)} carry positions picked on a cloud "
                                       "(the viewer's working set), which CSV cannot hold; convert "
                                       "the site's gcps.geojson, or forget the picks in the viewer")
        off = [g.id for g in gcps if not g.enabled]
        if off:
            raise InputError(args.src, f"{', '.join(off)} {'is' if len(off) == 1 else 'are'} disabled "
                                       "(\"enabled\": false), which CSV cannot hold; enable them or "
                                       "delete them first")
        write_gcps_csv(args.dst, gcps, args.epsg)
    else:
        write_gcps_geojson(args.dst, gcps)
    n_obs = sum(len(g.observations) for g in gcps)
    print(f"{len(gcps)} GCP(s), {n_obs} observation(s): {args.src} -> {args.dst}")
    return 0


def cmd_site(args) -> int:
    """`aerec site init SITE PRODUCT...`: a site from vendor products (recon_core.io.products)."""
    from recon_core.errors import InputError
    from recon_core.io.products import init_site
    from recon_core.model.images import ViewAngles

    times = {}
    for t in args.time:
        name, sep, when = t.partition("=")
        if not sep or not name or not when:
            raise InputError(None, f"--time {t!r}: give NAME=YYYY-MM-DDTHH:MM:SSZ")
        times[name] = when
    views = {}
    for v in args.view:
        name, sep, text = v.partition("=")
        parts = text.split(",")
        try:
            inc, az = (float(x) for x in parts) if len(parts) == 2 else (None, None)
        except ValueError:
            inc = az = None
        if not sep or not name or inc is None or not 0.0 <= inc < 90.0 or az is None or not math.isfinite(az):
            raise InputError(None, f"--view {v!r}: give NAME=INCIDENCE,AZIMUTH (degrees: from the vertical, "
                                   "0 to 90; of the direction to the satellite, clockwise from north)")
        views[name] = ViewAngles(inc, az % 360.0)
    images, notes = init_site(args.site, args.products, band=args.band, times=times, gcps=args.gcps,
                              name=args.name, views=views)
    print(f"wrote {args.site} with {len(images)} image(s) (VRTs of the products, no pixel copied):")
    for im in images:
        tiles = f", {len(im.files)} tiles" if len(im.files) > 1 else ""
        print(f"  {im.name}: {im.width} x {im.height} px{tiles}, {im.satellite or 'sensor unknown'}, "
              f"{im.acquired:%Y-%m-%d %H:%M:%S} UTC from {im.time_source}"
              + (f", view {im.view.incidence_deg:g} deg from vertical, azimuth {im.view.azimuth_deg:g} "
                 f"from {im.view_source}" if im.view is not None else ", no viewing direction"))
    for n in notes:
        print(f"note: {n}")
    if args.gcps is None:
        print(f"next: `aerec info {args.site}`, then add GCPs ({args.site}/gcps.geojson, "
              "`aerec gcps convert`, or the viewer)")
    return 0


def cmd_config(args) -> int:
    from recon_core.config import PRESETS, config_to_toml, preset
    from recon_core.errors import InputError

    if args.preset not in PRESETS:
        raise InputError(None, f"unknown --preset {args.preset!r}; choose from {', '.join(sorted(PRESETS))}")
    print(config_to_toml(preset(args.preset, args.method)), end="")
    return 0


def cmd_eval(args) -> int:
    """`aerec eval DSM GT [--out DIR] [--max-shift M] [--step M]`."""
    from recon_core.evaluation.evaluate import run_cli

    return run_cli(args)


def next_step(report: dict, site, out) -> str | None:
    """What to do after a run, in one line: place GCPs after an affine reconstruction, open the
    viewer after a whole one."""
    st = report.get("stages", {})
    if "dense" in st and "upgrade" not in st:
        from recon_core.euclidean.control import need_words

        return (f"next: `aerec run {site} --out {out}` continues from the upgrade, which needs {need_words()}: in "
                f"{report.get('gcp_file') or Path(site) / 'gcps.geojson'}, or placed in the viewer "
                f"(`aerec view {out}`, GCP tab)")
    if "sparse" in st and "dense" not in st:
        return f"next: `aerec run {site} --out {out}` goes on with the dense cloud (finished stages are kept)"
    if "dsm" in st:
        return (f"next: look at it in the browser (`aerec view {out}`), or open {out}/dsm.tif and "
                f"{out}/cloud.laz in QGIS or CloudCompare")
    return None


def print_summary(report: dict) -> None:
    """What a user looks for at the end of a run: per date group the tiles and points, then the
    accuracy at the check points, the DSM, and its scores against the ground truth or another
    tool's DSM when the site has one."""
    st = report.get("stages", {})
    sparse = st.get("sparse", {})
    for g, s in sparse.get("groups", {}).items():
        if "error" in s:
            print(f"group {g}: FAILED: {s['error']}")
            continue
        t = s.get("timings_s", {})
        print(f"group {g}: tiles registered {s['tiles_registered']}/{s['tiles_total']}, "
              f"points {s['points']}, mean reprojection error {s['mean_reproj_px']:.3f} px; "
              + ", ".join(f"{k} {v:.1f} s" for k, v in t.items()))
    for g, d in (st.get("dense") or {}).get("groups", {}).items():
        if isinstance(d, dict) and "points" in d:
            print(f"group {g}: dense cloud of {d['points']:,} points from {d.get('pairs_matched', '?')} tile pairs")
    told = {}
    for g, u in st.get("upgrade", {}).get("groups", {}).items():
        if "error" in u:
            print(f"group {g}: not upgraded: {u['error']}")
            continue
        c = (u.get("stats") or {}).get("check") or {}
        line = (f"{u.get('n_control_used', '?')} control GCPs; " + (
            f"{c['n']} check points: RMSE E {c['rmse_E_m']:.3f} N {c['rmse_N_m']:.3f} U {c['rmse_U_m']:.3f} m, "
            f"CE90 {c['ce90_m']:.2f} m, LE90 {c['le90_m']:.2f} m" if c.get("n") else
            "no check point (give some GCPs \"role\": \"check\" to measure the accuracy)"))
        cond = u.get("conditioning") or {}
        held, alone = (cond.get("with_images") or {}), (cond.get("gcp_only") or {})
        if held.get("height_scale_sigma") is not None:
            a = alone.get("height_scale_sigma")
            line += (f"; height scale held to +-{100 * held['height_scale_sigma']:.2f} % by {cond['images']} images' "
                     f"viewing directions (the GCPs alone: " + (f"+-{100 * a:.2f} %)" if a is not None else "not fixed)"))
        told.setdefault(line, []).append(g)
    for line, gs in told.items():
        who = f"group {gs[0]}" if len(gs) == 1 else f"groups {', '.join(gs)} (one joint upgrade)"
        print(f"{who}: {line}")
    d = st.get("dsm", {})
    if d.get("width"):
        print(f"DSM: {d['width']} x {d['height']} cells at {d['resolution_m']:g} m, "
              f"{100 * d.get('valid_fraction', 0):.1f} % valid")
    ev = st.get("eval", {})
    for k in ("aligned", "unaligned"):
        if k in ev:
            e = ev[k]
            print(f"DSM vs ground truth ({k}): median |error| {e['median_abs_err_m']:.3f} m, "
                  f"completeness (within 1 m) {e['completeness_pct']:.1f} %")
    for name, r in (ev.get("references") or {}).items():
        a, u = r["aligned"], r["unaligned"]
        print(f"DSM vs {name} (agreement with another tool, not accuracy): median |diff| "
              f"{a['median_abs_err_m']:.3f} m, completeness (within 1 m) {a['completeness_pct']:.1f} % (aligned); "
              f"{u['median_abs_err_m']:.3f} m, {u['completeness_pct']:.1f} % (unaligned)")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("aerec")
    except PackageNotFoundError:
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="aerec", description="AE-Rec: affine-to-Euclidean 3D "
                                "reconstruction from optical satellite images with 4 GCPs.")
    p.add_argument("--version", action="version", version=f"aerec {_version()}")
    sub = p.add_subparsers(dest="command", required=True)

    _add_info(sub)
    _add_run(sub)
    _add_config(sub)
    _add_site(sub)
    _add_gcps(sub)
    _add_eval(sub)
    _add_plugin_commands(sub)
    return p


def _add_info(sub) -> None:
    """`aerec info`'s arguments."""
    s = sub.add_parser("info", help="describe a site: images, dates, groups, GCPs, RPC/GT presence")
    s.add_argument("site", type=Path, help="the site folder (images/, gcps.geojson, site.json)")
    s.add_argument("--max-gap-days", type=float, default=15.0,
                   help="images closer in time than this form one date group (grouping.max_gap_days)")
    s.add_argument("--max-span-days", type=float, default=30.0,
                   help="a date group spans at most this many days (grouping.max_span_days)")
    s.set_defaults(func=cmd_info)


def _add_run(sub) -> None:
    """`aerec run`'s arguments."""
    s = sub.add_parser("run", help="reconstruct a site (resumes finished stages)")
    s.add_argument("site", type=Path, help="the site folder (docs/site-format.md)")
    s.add_argument("--out", required=True, help="output folder")
    s.add_argument("--stage", default=None, help="stop after this stage (default: run all)")
    s.add_argument("--preset", default="default", help="parameter preset (default, tiny)")
    s.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="parameters from a TOML file (see `aerec config --dump`); replaces --preset; "
                        "the options below override it")
    s.add_argument("--method", choices=("default", "paper"), default="default",
                   help="paper: the paper's plain path, every correction beyond it off (the "
                        "baseline of the accuracy figures; applied over --preset and --config)")
    s.add_argument("--tile-size", type=int, default=None, help="tile side d in pixels (default 1000)")
    s.add_argument("--reference-dem", type=Path, default=None, metavar="FILE",
                   help="a coarse DEM of the site (GeoTIFF: SRTM, Copernicus GLO-30) that holds the bend "
                        "3 views of one date cannot see over a wide site (upgrade.reference_dem)")
    s.add_argument("--reference-dem-degree", type=int, choices=(2, 3), default=None,
                   help="the degree of the bend taken from it: 2 (default) or 3, for a DEM whose errors do "
                        "not reach over kilometres, such as Copernicus GLO-30 (upgrade.reference_dem_degree)")
    s.add_argument("--seed", type=int, default=None,
                   help="the seed of every random choice (RANSAC, samples; default: the configuration's, 0)")
    s.add_argument("--workers", type=int, default=None, help="local dense worker processes (default: all cores)")
    s.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="send dense tile-pair work to a Dask distributed scheduler (tcp://host:8786)")
    s.add_argument("--restart", action="store_true", help="ignore finished stages and recompute")
    s.add_argument("--wait", action="store_true",
                   help="another job using the output folder: wait for it to end instead of refusing")
    s.add_argument("--redo-from", default=None, metavar="STAGE",
                   help="recompute this stage and the later ones (sparse, dense, upgrade, dsm, eval)")
    s.add_argument("--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=cmd_run)


def _add_config(sub) -> None:
    """`aerec config`'s arguments."""
    s = sub.add_parser("config", help="print the parameters of a run (TOML, each with its comment)")
    s.add_argument("--dump", action="store_true", help="print the defaults (or --preset's)")
    s.add_argument("--preset", default="default", help="the preset whose values are printed (default, tiny)")
    s.add_argument("--method", choices=("default", "paper"), default="default",
                   help="paper: the paper's plain path (every correction beyond it off)")
    s.set_defaults(func=cmd_config)


def _add_site(sub) -> None:
    """`aerec site`'s arguments."""
    s = sub.add_parser("site", help="make a site from vendor products (no pixel copied)")
    s.add_argument("action", choices=["init"], help="init: write a new site")
    s.add_argument("site", type=Path, help="the new site folder (must not exist or be empty)")
    s.add_argument("products", type=Path, nargs="+",
                   help="product folders or image files (DIMAP, Maxar, NITF, GeoTIFF, JPEG 2000, VRT)")
    s.add_argument("--band", type=int, default=None, help="the band to use of a multi-band product (1-based)")
    s.add_argument("--time", action="append", default=[], metavar="NAME=ISO8601",
                   help="an image's acquisition time (UTC), where its metadata has none; repeatable")
    s.add_argument("--view", action="append", default=[], metavar="NAME=INCIDENCE,AZIMUTH",
                   help="an image's viewing direction at its centre (degrees from the vertical; azimuth of "
                        "the direction to the satellite, clockwise from north), where its metadata has none "
                        "(it holds the upgrade's height scale); repeatable")
    s.add_argument("--gcps", type=Path, default=None, help="a gcps.geojson to copy into the site")
    s.add_argument("--name", default=None, help="the site's name (site.json)")
    s.set_defaults(func=cmd_site)


def _add_gcps(sub) -> None:
    """`aerec gcps`'s arguments."""
    s = sub.add_parser("gcps", help="convert a GCP list between gcps.geojson and CSV")
    s.add_argument("action", choices=["convert"], help="convert: from SRC to DST")
    s.add_argument("src", type=Path, help="gcps.geojson or .csv")
    s.add_argument("dst", type=Path, help=".geojson or .csv (written atomically)")
    s.add_argument("--epsg", type=int, default=None,
                   help="CSV: the projected EPSG of x, y (E, N) when the file has no epsg column; "
                        "for a CSV output, write E, N in it instead of lon, lat")
    s.add_argument("--site", type=Path, default=None,
                   help="check the observations against this site's images (names, pixel bounds)")
    s.set_defaults(func=cmd_gcps)


def _add_eval(sub) -> None:
    """`aerec eval`'s arguments."""
    s = sub.add_parser("eval", help="score a DSM against a ground-truth (or reference) DSM",
                       description="Evaluate a DSM against a ground-truth DSM (align3d-style "
                                   "alignment and metrics).")
    from recon_core.evaluation.evaluate import add_arguments

    add_arguments(s)
    s.set_defaults(func=cmd_eval)


def _add_plugin_commands(sub) -> None:
    """Subcommands contributed by other packages through the `aerec.commands` entry point group.

    The viewer registers `aerec view` this way, so the core never imports the viewer.
    """
    from importlib.metadata import entry_points

    for ep in entry_points(group="aerec.commands"):
        try:
            register = ep.load()
        except Exception as exc:  # a broken optional plugin must not break the core commands
            print(f"aerec: warning: command plugin {ep.name} failed to load ({exc})", file=sys.stderr)
            continue
        register(sub)


_MACHINE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.EFBIG}


_INTERRUPTED = False


def _terminate(signum, frame) -> None:
    global _INTERRUPTED
    _INTERRUPTED = True
    raise KeyboardInterrupt          # SIGTERM ends a run as Ctrl-C does: cleanup runs


def _stdout_reader_gone() -> bool:
    """Is stdout a pipe whose reader has closed it (poll reports an error on its write end)?"""
    import select

    try:
        p = select.poll()
        p.register(sys.stdout.fileno(), select.POLLOUT)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in p.poll(0))
    except (OSError, ValueError, AttributeError):
        return False


def _disk_full(exc: BaseException) -> bool:
    """The machine, not the input: a full disk, a quota, a file system gone read-only, also as
    numpy's short write ("N requested and M written"), numpy's failed allocation of a file's
    space ("Not enough free space to write N bytes", no errno) or GDAL's "Write error"."""
    if isinstance(exc, OSError) and exc.errno in _MACHINE_ERRNOS:
        return True
    text = str(exc)
    return ("requested and" in text and "written" in text) or "Write error" in text \
        or "No space left" in text or "Not enough free space" in text


def main(argv: list[str] | None = None) -> int:
    import signal
    import threading

    global _INTERRUPTED
    _INTERRUPTED = False
    args = build_parser().parse_args(argv)
    import warnings

    # an image without a geotransform (sensor geometry, as every raw product) is the norm here
    warnings.filterwarnings("ignore", message=".*not georeferenced.*")
    warnings.filterwarnings("ignore", message=".*no geotransform.*")
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)
        signal.signal(signal.SIGINT, _terminate)
    try:
        return int(args.func(args) or 0)
    except AerecError as exc:
        print(f"aerec: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("aerec: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:               # `aerec info SITE | head`: the reader left, not an error
        if not _stdout_reader_gone():
            raise                         # another pipe broke (a worker's): a real failure
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except OSError:
            pass
        return 0
    except OSError as exc:
        if exc.errno in _PATH_ERRNOS and not _disk_full(exc):
            # a path the system cannot take (a name too long, a loop of links, a file where a
            # folder is needed): the input's problem, one line
            where = f"{exc.filename}: " if exc.filename else ""
            print(f"aerec: error: {where}{exc.strerror or exc}", file=sys.stderr)
            return 2
        return _last_resort(exc)
    except Exception as exc:
        return _last_resort(exc)


_PATH_ERRNOS = {errno.ENAMETOOLONG, errno.ELOOP, errno.ENOTDIR, errno.EISDIR, errno.ENOENT}


def _last_resort(exc: BaseException) -> int:
    """An unexpected exception: an interrupt that arrived inside compiled code, or the machine
    failing a write (one line, exit 1); anything else is a bug and keeps its traceback."""
    if _INTERRUPTED:
        # the signal arrived inside compiled code (numba re-raises it as a SystemError)
        print("aerec: interrupted", file=sys.stderr)
        return 130
    if not _disk_full(exc):
        raise exc
    # the machine, not the input: a full disk, a quota, a file system gone read-only.
    # Outputs are written atomically, so nothing half-written is left; finished stages
    # are reused by the next run.
    filename = getattr(exc, "filename", None)
    where = f"{filename}: " if filename else ""
    what = getattr(exc, "strerror", None) or f"a write failed ({exc}): is the disk full?"
    print(f"aerec: error: {where}{what} (nothing half-written was kept; "
          "free space or fix the folder, then rerun: finished stages are reused)", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())

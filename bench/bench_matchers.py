"""The stereo matchers side by side on the same sparse reconstruction: OpenCV's SGBM (the default),
the built-in MGM (census + MGM, the paper's matcher) and CNES's pandora (census + SGM, as CARS
sets it; `pip install 'aerec[pandora]'`). Prints one table; asserts nothing.

    python bench/bench_matchers.py                                 # every site found, sgbm and mgm
    python bench/bench_matchers.py --sites gizeh,reunion --matchers sgbm,mgm,pandora
    python bench/bench_matchers.py --table-only                    # reprint from results.json

Sites as in bench_accuracy.py: `omaha` (../shared/data/omaha_3dates: an independent simulator's
ground truth), `gizeh`, `reunion` (real Pleiades pairs scored against s2p's DSM: agreement, not
accuracy) and `demo` (this project's synthetic preset, generated under --root/sites or copied
there). Each site's sparse stage runs once (default configuration) under --root/<site>/sparse;
each matcher's OUT starts from a copy of it, so only the matcher differs.

Figures per site and matcher:
- ME / CP: the fused DSM's median |error| and completeness (< 1 m), aligned (bench_accuracy's).
- edges ME / CP: the same on the reference's "edge" cells: within EDGE_RADIUS_M of a wall, two
  neighbouring cells of the reference whose heights differ by EDGE_STEP_M or more; on omaha and
  demo the reference is the ground truth, on gizeh and reunion s2p's DSM (whose own noise makes
  some of its "walls").
- matcher s / pair and worker s / pair: the matcher's own time and the dense job's time (rectify,
  match, NCC check, triangulate) per matched tile pair; the dense stage runs with one worker
  (dense.workers = 1, which changes no result), in a process of its own.
- dense peak MB: that process's peak resident memory during the dense stage above what it held
  before, and the absolute peak. It runs one job at a time (a reference tile, matched with each
  of its partner tiles in turn, its points gathered and triangulated): what one worker needs;
  the matcher's share is the difference between the two matchers.
Times are wall-clock on whatever else the machine runs: compare the two matchers of one run.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

EDGE_RADIUS_M = 1.5
EDGE_STEP_M = 2.0


def _config(site_name: str, matcher: str, tile: int | None):
    from recon_core.config import preset

    cfg = preset("default").with_overrides({"dense.matcher": matcher})
    if tile:
        cfg = cfg.with_overrides({"tiling.tile_size": tile})
    return cfg


def _status() -> dict:
    out = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        k, _, v = line.partition(":")
        if k in ("VmRSS", "VmHWM"):
            out[k] = int(v.split()[0]) / 1024.0
    return out


def dense_child(site_name: str, out: Path, matcher: str, root: Path) -> None:
    """In a process of its own: reload the sparse stage, reset the peak RSS, run the dense
    stage with one worker; print one JSON line."""
    from bench_accuracy import site_for

    from recon_core.pipeline import run

    site, tile, _ = site_for(site_name, root, 0)
    cfg = _config(site_name, matcher, tile).with_overrides({"dense.workers": 1})
    run(site, out, cfg, until="sparse", resume=True)
    before = _status()
    try:
        Path("/proc/self/clear_refs").write_text("5")      # reset VmHWM to the current RSS
        reset = True
    except OSError:
        reset = False
    t0 = time.time()
    state = run(site, out, cfg, until="dense", resume=True)
    wall = time.time() - t0
    after = _status()
    dense = state.report["stages"]["dense"]
    print(json.dumps({"rss_before_mb": before["VmRSS"], "peak_mb": after["VmHWM"], "peak_reset": reset,
                      "dense_wall_s": wall, "dense": dense}))


def edge_figures(dsm: Path, reference: Path) -> dict:
    """ME / CP of the DSM on the reference's edge cells (module docstring), with the DSM's
    alignment on the reference (evaluate_dsm's)."""
    import numpy as np
    from scipy import ndimage

    from recon_core.evaluation.evaluate import aligned_error, evaluate_dsm, read_raster

    ev = evaluate_dsm(dsm, reference, None)
    gt = read_raster(reference, "reference")
    h = gt.values.astype(np.float64)
    cell = abs(gt.transform.a)
    valid = np.isfinite(h)
    # seeds: both cells of every pair of 4-neighbours whose heights differ by EDGE_STEP_M or more
    # (a wall: at 0.5 m cells, a slope of 76 degrees and more); edges: within EDGE_RADIUS_M of one
    seed = np.zeros(h.shape, bool)
    jx = np.nan_to_num(np.abs(np.diff(h, axis=1)), nan=0.0) >= EDGE_STEP_M
    jy = np.nan_to_num(np.abs(np.diff(h, axis=0)), nan=0.0) >= EDGE_STEP_M
    seed[:, 1:] |= jx
    seed[:, :-1] |= jx
    seed[1:, :] |= jy
    seed[:-1, :] |= jy
    r = max(1, int(round(EDGE_RADIUS_M / cell)))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    edge = ndimage.binary_dilation(seed, structure=(xx ** 2 + yy ** 2) <= r * r) & valid
    e = aligned_error(dsm, ev["alignment"], gt)
    a = np.abs(e[edge])
    n = int(edge.sum())
    seen = np.isfinite(a)
    return {"edge_cells_pct": 100.0 * n / max(int(valid.sum()), 1),
            "edge_me_m": float(np.median(a[seen])) if seen.any() else None,
            "edge_cp_pct": 100.0 * float(np.sum(a[seen] < 1.0)) / max(n, 1),
            "aligned": (ev["aligned"]["median_abs_err_m"], ev["aligned"]["completeness_pct"]),
            "cell_m": cell}


def run_site(site_name: str, matchers: list[str], root: Path, results: dict, store: Path, rerun: bool) -> None:
    from bench_accuracy import site_for

    from recon_core.events import EventBus
    from recon_core.pipeline import run

    found = site_for(site_name, root, 0)
    if found is None:
        print(f"{site_name}: absent, skipped", flush=True)
        return
    site, tile, reference = found
    reference = reference or (site / "gt_dsm.tif")
    base = root / site_name / "sparse"
    t0 = time.time()
    run(site, base, _config(site_name, "sgbm", tile), until="sparse", resume=True, bus=EventBus(lambda ev: None))
    print(f"{site_name}: sparse stage ready in {time.time() - t0:.0f} s ({base})", flush=True)
    for m in matchers:
        key = f"{site_name}|{m}"
        if key in results and not rerun:
            continue
        out = root / site_name / m
        if out.exists():
            shutil.rmtree(out)
        shutil.copytree(base, out, ignore=shutil.ignore_patterns(".aerec.lock"))
        t0 = time.time()
        child = subprocess.run([sys.executable, __file__, "--dense-child", site_name, str(out), m,
                                "--root", str(root)], capture_output=True, text=True)
        if child.returncode != 0:
            print(f"{key}: dense stage failed:\n{child.stderr[-3000:]}", flush=True)
            continue
        mem = json.loads(child.stdout.strip().splitlines()[-1])
        print(f"{key}: dense stage {time.time() - t0:.0f} s", flush=True)
        state = run(site, out, _config(site_name, m, tile), resume=True, bus=EventBus(lambda ev: None))
        groups = mem["dense"]["groups"].values()
        pairs = sum(g["pairs_matched"] for g in groups)
        fig = {"matched_pairs": pairs,
               "tile_pairs": sum(g["tile_pairs"] for g in groups),
               "points": sum(g["points"] for g in groups),
               "matcher_s_per_pair": sum(g["matcher_kernel_s"] for g in groups) / max(pairs, 1),
               "worker_s_per_pair": sum(g["job_s"] for g in groups) / max(pairs, 1),
               "dense_wall_s": mem["dense_wall_s"],
               "dense_peak_above_mb": mem["peak_mb"] - mem["rss_before_mb"] if mem["peak_reset"] else None,
               "dense_peak_mb": mem["peak_mb"],
               "total_wall_s": time.time() - t0}
        fig.update(edge_figures(state.layout.dsm, reference))
        results[key] = fig
        store.write_text(json.dumps(results, indent=1))
        print(f"{key}: done", flush=True)


def fmt(v, spec=".3f"):
    return "-" if v is None else format(v, spec)


def print_table(results: dict, sites: list[str], matchers: list[str]) -> None:
    print(f"\nedge cells: within {EDGE_RADIUS_M:g} m of a step >= {EDGE_STEP_M:g} m between neighbouring cells of the reference "
          "(omaha, demo: ground truth; gizeh, reunion: s2p's DSM, agreement not accuracy)")
    print("| site | matcher | ME / CP aligned | edges ME / CP (edge cells, % of ref) | matcher s / pair "
          "| worker s / pair | dense peak MB (above start / absolute) | pairs matched | points |")
    print("|---|---|---|---|---|---|---|---|---|")
    for s in sites:
        for m in matchers:
            v = results.get(f"{s}|{m}")
            if not v:
                continue
            a = v["aligned"]
            print(f"| {s} | {m} | {fmt(a[0])} m / {fmt(a[1], '.1f')} % | {fmt(v['edge_me_m'])} m / "
                  f"{fmt(v['edge_cp_pct'], '.1f')} % ({fmt(v['edge_cells_pct'], '.1f')} %) | "
                  f"{fmt(v['matcher_s_per_pair'], '.2f')} | {fmt(v['worker_s_per_pair'], '.2f')} | "
                  f"{fmt(v['dense_peak_above_mb'], '.0f')} / {fmt(v['dense_peak_mb'], '.0f')} | "
                  f"{v['matched_pairs']} / {v['tile_pairs']} | {v['points']:,} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sites", default="gizeh,reunion,omaha,demo")
    ap.add_argument("--matchers", default="sgbm,mgm")
    ap.add_argument("--root", type=Path, default=Path("/tmp/aerec_matchers"))
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--rerun", action="store_true", help="run again what results.json already has")
    ap.add_argument("--rescore-edges", action="store_true", help="recompute the edge figures of the kept DSMs")
    ap.add_argument("--dense-child", nargs=3, metavar=("SITE", "OUT", "MATCHER"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.dense_child:
        s, out, m = args.dense_child
        dense_child(s, Path(out), m, args.root)
        return 0
    sites, matchers = args.sites.split(","), args.matchers.split(",")
    from recon_core.dense.matchers import MATCHERS
    from recon_core.extras import missing_packages

    for m in matchers:
        if m not in MATCHERS:
            raise SystemExit(f"unknown matcher {m!r}; choose from {', '.join(MATCHERS)}")
        if missing_packages(m):
            raise SystemExit(f"{m}: needs {' and '.join(missing_packages(m))}: pip install 'aerec[{m}]'")
    args.root.mkdir(parents=True, exist_ok=True)
    store = args.root / "results.json"
    results = json.loads(store.read_text()) if store.exists() else {}
    if args.rescore_edges:                  # the edge figures again, from the DSMs kept
        from bench_accuracy import site_for

        for key, fig in results.items():
            s, m = key.split("|")
            found = site_for(s, args.root, 0)
            if found is not None and (args.root / s / m / "dsm.tif").exists():
                fig.update(edge_figures(args.root / s / m / "dsm.tif", found[2] or found[0] / "gt_dsm.tif"))
        store.write_text(json.dumps(results, indent=1))
    elif not args.table_only:
        for s in sites:
            run_site(s, matchers, args.root, results, store, args.rerun)
    print_table(results, sites, matchers)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark the pipeline on a synthetic preset or a real site; prints figures, asserts nothing.

    python bench/bench_pipeline.py --preset demo                 # generates /tmp/aerec_bench/demo
    python bench/bench_pipeline.py --preset demo --until sparse  # the sparse issue's figures
    python bench/bench_pipeline.py --site ../shared/data/reunion_pair --tile-size 400 \
        --reference ../shared/data/reunion_pair/ref_dsm_s2p.tif

Figures: seconds per stage (features, matching, SfM, of which BA; dense, of which the SGBM
kernel; upgrade; DSM; eval), peak memory of this process per stage (not the dense workers):
its anonymous memory, what the machine must have, and its RSS high-water mark, which also
counts pages of memory-mapped files (clouds, grids on disk) that the kernel can drop), tiles registered, points, reprojection error, for synthetic sites the sparse
and dense structure against the truth up to one best-fit affine map, GCP check residuals and
the DSM metrics.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon_core.config import preset as make_preset  # noqa: E402
from recon_core.events import BundleAdjusted, EventBus, Message, StageDone, StageProgress, TileRegistered  # noqa: E402
from recon_core.pipeline import run  # noqa: E402


def peak_rss_mb() -> float:
    """RSS high-water mark of this process. The dense workers are not included: they are
    children of the forkserver, not of this process (each holds one job: a few tiles)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class AnonPeak:
    """Peak anonymous memory (RssAnon, Linux) of this process, sampled every 0.1 s by a thread;
    `take()` returns the peak since the last call. The RSS high-water mark also counts mapped
    file pages (the clouds and the DSM stage's grids are read through memory maps), which the
    kernel can drop: it overstates what the machine must have."""

    def __init__(self):
        import threading

        self.peak = self.since = 0.0
        threading.Thread(target=self._run, daemon=True).start()

    @staticmethod
    def now_mb() -> float:
        try:
            with open("/proc/self/status") as f:
                for line in f:
                    if line.startswith("RssAnon:"):
                        return int(line.split()[1]) / 1024.0
        except OSError:
            pass
        return float("nan")

    def _run(self):
        while True:
            v = self.now_mb()
            self.peak, self.since = max(self.peak, v), max(self.since, v)
            time.sleep(0.1)

    def take(self) -> float:
        v, self.since = max(self.since, self.now_mb()), 0.0
        return v


def ensure_site(preset: str, seed: int, root: Path) -> Path:
    from recon_core.synthetic.generator import generate_site

    site = root / f"{preset}_s{seed}"
    if not (site / "site.json").exists():
        t0 = time.time()
        generate_site(site, preset=preset, seed=seed)
        print(f"generated {preset} site in {time.time() - t0:.1f} s -> {site}")
    return site


def truth_figures(site: Path, state, rpc_truth: bool = False) -> dict:
    from recon_core.euclidean.georef import frame_for
    from recon_core.bend.metric import warped_model
    from recon_core.synthetic.truth import sparse_vs_truth

    from recon_core.synthetic.truth import has_truth_cameras

    if not has_truth_cameras(site, rpc_truth):
        return {}
    from recon_core.evaluation.colormap import save_png
    from recon_core.synthetic.truth import residual_map

    from recon_core.model.sparse_model import merge_joint

    frame = frame_for(state.gcps)
    # date groups of one joint reconstruction: each point's truth from all its views (a
    # group's weak-baseline points would otherwise get an ill-conditioned truth)
    joint = merge_joint([state.models[g] for g in sorted(state.models)])
    maps = state.upgrade[0] if state.upgrade else {}
    out = {}
    for g, m in state.models.items():
        # after the metric bend step when the upgrade applied one (the SfM's structure in brackets)
        warp = getattr(maps.get(g), "warp", None)
        before = sparse_vs_truth(site, m, frame, views=joint) if warp is not None else None
        if warp is not None:
            m = warped_model(m, warp)
        r = sparse_vs_truth(site, m, frame, views=joint)
        png = state.layout.root / "bench" / f"sparse_residual_u_g{g}.png"
        save_png(png, residual_map(r["truth"], r["residuals"][:, 2]))
        out[g] = {"sparse_affine_rms_m": r["rms_m"], "sparse_rms_xyz_m": r["rms_xyz_m"],
                  "sparse_p95_m": r["p95_m"], "n": r["n"], "bend": r["bend"], "map": png,
                  "before_metric_step": None if before is None else (before["rms_m"], before["rms_xyz_m"])}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default=None, help="synthetic preset: tiny, demo, large")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--site", type=Path, default=None, help="a site folder instead of a preset")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--until", default=None)
    ap.add_argument("--tile-size", type=int, default=None)
    ap.add_argument("--config-preset", default="default")
    ap.add_argument("--config", type=Path, default=None, help="a TOML configuration (as `aerec config` writes)")
    ap.add_argument("--reference", type=Path, default=None, help="reference DSM to compare with (aerec eval)")
    ap.add_argument("--root", type=Path, default=Path("/tmp/aerec_bench"))
    ap.add_argument("--rpc-truth", action="store_true",
                    help="the images' RPCs are the true cameras (a simulator's site such as "
                         "omaha_3dates): score the sparse structure against them")
    ap.add_argument("--log", action="store_true", help="print progress lines with timestamps as it runs")
    ap.add_argument("--redo-from", default=None, help="with --resume: recompute this stage and every later one")
    ap.add_argument("--resume", action="store_true",
                    help="reuse the finished stages of OUT (their seconds are those of the earlier run)")
    args = ap.parse_args(argv)

    site = args.site or ensure_site(args.preset or "demo", args.seed, args.root)
    out = args.out or args.root / f"out_{site.name}"
    cfg = make_preset(args.config_preset)
    if args.config:
        from recon_core.config import config_from_toml
        cfg = config_from_toml(args.config)
    if args.tile_size:
        cfg = cfg.with_overrides({"tiling.tile_size": args.tile_size})
    ba = {"seconds": 0.0, "runs": 0}
    t_start = time.time()
    last = {}
    peaks: list[str] = []
    anon = AnonPeak()

    def log(text):
        print(f"[{time.time() - t_start:7.1f} s] {text}", flush=True)

    def listen(ev):
        if isinstance(ev, BundleAdjusted):
            if ev.repeat:                      # the same adjustment, told to another group
                return
            ba["seconds"] += ev.seconds
            ba["runs"] += 1
            ba[ev.scope] = ba.get(ev.scope, 0.0) + ev.seconds
            if args.log and ev.scope == "global":
                log(f"group {ev.group} global BA: {ev.n_cameras} cameras, {ev.n_points} points, "
                    f"{ev.seconds:.1f} s, RMS {ev.rms_px:.3f} px")
        elif args.log and isinstance(ev, StageProgress):
            key = (ev.stage, ev.group)
            if ev.done in (0, ev.total) or time.time() - last.get(key, 0.0) > 60:
                last[key] = time.time()
                log(f"group {ev.group} {ev.stage} {ev.done}/{ev.total} {ev.message}")
        elif args.log and isinstance(ev, TileRegistered):
            key = ("sfm", ev.group)
            if time.time() - last.get(key, 0.0) > 60:
                last[key] = time.time()
                log(f"group {ev.group} sfm: {ev.order + 1} tiles registered of {ev.total_tiles}")
        elif isinstance(ev, StageDone) and ev.group is None:
            a = anon.take()
            peaks.append(f"{ev.stage} {a:.0f} MB")
            if args.log:
                log(f"StageDone: {ev.stage}; peak anonymous memory in it {a:.0f} MB, RSS high-water "
                    f"mark so far {peak_rss_mb():.0f} MB")
        elif args.log and isinstance(ev, (StageDone, Message)):
            log(f"{type(ev).__name__}: {getattr(ev, 'stage', '')} {getattr(ev, 'text', '')}".strip())

    t0 = time.time()
    state = run(site, out, cfg, until=args.until, bus=EventBus(listen), resume=args.resume,
                redo_from=args.redo_from)
    wall = time.time() - t0
    st = state.report["stages"]
    print(f"\n== {site} (tile size {cfg.tiling.tile_size}) total {wall:.1f} s ==")
    for g, s in st["sparse"]["groups"].items():
        if "error" in s:
            print(f"group {g}: {s['error']}")
            continue
        t = s["timings_s"]
        rf = s.get("tie_point_refinement")
        refined = (f"tie points refined {t.get('refine', 0.0):.1f} s ({rf['refined']} of {rf['candidates']}, "
                   f"median move {rf['median_shift_px']:.2f} px), " if rf else "")
        print(f"group {g} sparse: features {t['features']:.1f} s, matching {t['matching']:.1f} s, "
              f"{refined}SfM {t['sfm']:.1f} s; tiles {s['tiles_registered']}/{s['tiles_total']}, "
              f"points {s['points']}, mean reprojection {s['mean_reproj_px']:.3f} px "
              f"(RMS {s['rms_reproj_px']:.3f})")
    print(f"bundle adjustment: {ba['seconds']:.1f} s in {ba['runs']} runs (inside SfM; global "
          f"{ba.get('global', 0.0):.1f} s, local {ba.get('local', 0.0):.1f} s)")
    for g, f in truth_figures(site, state, args.rpc_truth).items():
        print(f"group {g} sparse vs truth (one best-fit affine map): RMS {f['sparse_affine_rms_m']:.3f} m "
              f"(E/N/U {', '.join(f'{v:.3f}' for v in f['sparse_rms_xyz_m'])}), p95 {f['sparse_p95_m']:.3f} m, "
              f"{f['n']} points")
        if f["before_metric_step"]:
            rms, xyz = f["before_metric_step"]
            print(f"group {g}   (the SfM's structure, before the metric bend step: RMS {rms:.3f} m, "
                  f"E/N/U {', '.join(f'{v:.3f}' for v in xyz)})")
        b = f["bend"]
        print(f"group {g} vertical residual over the site: RMS {b['rms_u_m']:.3f} m, of which a quadratic "
              f"surface (dome/saddle) {b['quadratic_rms_m']:.3f} m RMS ({b['quadratic_range_m']:.2f} m "
              f"peak to peak), the rest {b['rest_rms_m']:.3f} m; local (minus the mean of its 150 m "
              f"cell: point noise) {b['local_rms_m']:.3f} m; map: {f['map']}")
    if "dense" in st:
        for g, d in st["dense"]["groups"].items():
            print(f"group {g} dense: {d['pairs_matched']}/{d['tile_pairs']} tile pairs matched "
                  f"({d.get('pairs_not_needed', 0)} not needed: their cores do not overlap), {d['points']} points, "
                  f"views {d['views_histogram']}, wall {d['wall_s']:.1f} s, SGBM kernel {d['matcher_kernel_s']:.1f} s, "
                  f"job CPU / kernel = {d['overhead_ratio_cpu'] or float('nan'):.2f}, "
                  f"rectified row error {d['median_rectified_row_err_px'] or float('nan'):.3f} px")
        print(f"dense stage: {st['dense']['seconds']:.1f} s")
    if "upgrade" in st:
        for g, u in st["upgrade"]["groups"].items():
            if "error" in u:
                print(f"group {g} upgrade: {u['error']}")
                continue
            mb = u.get("metric_bend") or {}
            if mb:
                shares = ", ".join(f"{v:.3f}" for v in mb.get("warp_shares", []))
                print(f"group {g} metric bend step: {'applied' if mb['applied'] else 'not applied'}"
                      + (f" ({mb['reason']})" if mb.get("reason") else "")
                      + (f"; {mb['warps_seen']} warps seen (shares {shares}), range x{mb.get('implied_range_factor') or float('nan'):.3f} "
                         f"of an orbit at {mb['altitude_km']:g} km, warp {mb['warp_rms_m']:.3f} m RMS, "
                         f"{mb['warp_max_m']:.3f} m max" if "warps_seen" in mb else ""))
            gb = u.get("gcp_bend") or {}
            if gb:
                print(f"group {g} bend fitted to the GCPs: {'applied' if gb.get('applied') else 'not applied'}"
                      + (f" ({gb['reason']})" if gb.get("reason") else "")
                      + (f"; {gb['inliers']} of {gb['control_gcps']} control GCPs agree; leave-one-out "
                         + ", ".join(f"{v:.3f} m with the {k} warps" for k, v in gb["loo_rms_m"].items())
                         + f", {gb['loo_rms_affine_m']:.3f} m affine" if "loo_rms_m" in gb else "")
                      + (f"; warp at most E/N/U {', '.join(f'{v:.2f}' for v in gb['warp_max_m'])} m"
                         if gb.get("applied") else ""))
            db = u.get("dem_bend") or {}
            if db:
                print(f"group {g} bend from the reference DEM: {'applied' if db.get('applied') else 'not applied'}"
                      + (f" ({db['reason']})" if db.get("reason") else "")
                      + (f"; {db['cells']} cells of {db['cell_m']:g} m, scatter {db['cell_scale_m']:.2f} m, "
                         f"degree {db.get('degree', 2)}"
                         + (f" (asked {db['degree_asked']})" if db.get("degree_asked", 2) != db.get("degree", 2) else "")
                         + ", bend "
                         f"{db['bend_range_m']:.2f} m peak to peak (standard error at the edge {db['bend_sigma_m']:.2f} m), "
                         f"the DEM's offset {db['offset_m']:.2f} m and tilt {db['tilt_m'][0]:.2f} / {db['tilt_m'][1]:.2f} m "
                         "left to the GCPs" if "bend_range_m" in db else ""))
            c = u["stats"].get("check", {})
            if c.get("n"):
                print(f"group {g} upgrade: {u['n_control_used']} control GCPs; {c['n']} check points: "
                      f"RMSE E {c['rmse_E_m']:.3f} N {c['rmse_N_m']:.3f} U {c['rmse_U_m']:.3f} m, "
                      f"CE90 {c['ce90_m']:.3f} m, LE90 {c['le90_m']:.3f} m")
    if "dsm" in st:
        d = st["dsm"]
        print(f"DSM: {d['width']} x {d['height']} at {d['resolution_m']} m, {d['points']} points, "
              f"valid {100 * d['valid_fraction']:.1f} % ({st['dsm']['seconds']:.1f} s)")
        nm = d.get("noise_model") or {}
        if nm:
            ranked = [(g, d["groups"][str(g)]) for g in d["group_order"]]
            print("fusion noise model: " + nm["rule"]
                  + (f"; matching precision {nm['matching_precision_px']:.3f} px" if nm.get("matching_precision_px") else "")
                  + "; groups (rank order) " + ", ".join(
                      f"{g}: noise {r['noise_m']:.3f} m"
                      + (f" ({r['geometry_m_per_px']:.2f} m/px)" if r.get("geometry_m_per_px") else "")
                      for g, r in ranked if r.get("noise_m") is not None))
    if "eval" in st and "aligned" in st["eval"]:
        for k in ("aligned", "unaligned"):
            e = st["eval"][k]
            print(f"vs GT ({k}): median |error| {e['median_abs_err_m']:.3f} m, completeness "
                  f"{e['completeness_pct']:.1f} %, RMSE {e['rmse_m']:.3f} m, NMAD {e['nmad_m']:.3f} m")
        groups = st["eval"].get("groups") or {}
        if groups:
            print("each group's DSM alone (aligned; unaligned): " + ", ".join(
                f"group {g} {v['aligned']['median_abs_err_m']:.3f} m / {v['aligned']['completeness_pct']:.1f} %; "
                f"{v['unaligned']['median_abs_err_m']:.3f} m" for g, v in sorted(groups.items())
                if "aligned" in v and "unaligned" in v))
            for g, v in sorted(groups.items()):
                sc = v.get("fused_vs_group_same_cells") or {}
                if sc.get("cells"):
                    print(f"fused vs group {g} on the {sc['cells_pct_of_gt']:.1f} % of cells both cover: "
                          f"median |error| {sc['a']['median_abs_err_m']:.3f} m vs {sc['b']['median_abs_err_m']:.3f} m, "
                          f"within 1 m {sc['a']['within_pct']:.1f} % vs {sc['b']['within_pct']:.1f} %")
        classes = (st["eval"].get("by_agreement") or {}).get("classes") or {}
        if classes:
            print("fused DSM by date groups agreeing (aligned): " + "; ".join(
                f"{k}: {v['cells_pct_of_gt']:.1f} % of GT cells, median |error| {v['median_abs_err_m']:.3f} m, "
                f"within 1 m {v['within_pct']:.1f} %" for k, v in sorted(classes.items(), key=lambda kv: int(kv[0]))))
        a = st["eval"]["alignment"]
        print(f"alignment (DSM - GT): dx {a['dx_m']:+.2f} dy {a['dy_m']:+.2f} dz {a['dz_m']:+.2f} m")
    if args.reference and (out / "dsm.tif").exists():
        from recon_core.evaluation.evaluate import evaluate_dsm

        r = evaluate_dsm(out / "dsm.tif", args.reference, out / "eval_reference")
        for k in ("aligned", "unaligned"):
            e = r[k]
            print(f"vs reference ({k}): median |diff| {e['median_abs_err_m']:.3f} m, within 1 m "
                  f"{e['completeness_pct']:.1f} %, RMSE {e['rmse_m']:.3f} m")
    print("seconds per stage: " + ", ".join(f"{k} {v.get('seconds', 0):.1f}" for k, v in st.items()))
    print(f"peak memory, main process: anonymous {anon.peak:.0f} MB (stage by stage: {', '.join(peaks)}); "
          f"RSS high-water mark {peak_rss_mb():.0f} MB (with pages of mapped files)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The vertical bend held by a reference DEM (recon_core.bend.dem) on a synthetic site,
against DEMs of several kinds simulated from the site's truth (recon_core.synthetic.ref_dem):
prints, per DEM, the bend found, the sparse heights against their truth under the upgrade's own
map, and the check points. Asserts nothing.

    python bench/bench_dem.py --site /tmp/aerec_bench/wide_s0 --out /tmp/aerec_bench/out_wide_s0 [--degree 3]

OUT must hold finished sparse and dense stages of SITE (and the GCP roles to use: OUT/gcps.geojson when
there is one); the upgrade is re-run for each DEM in a scratch copy (OUT/../<name>_dem_bench,
hard links to OUT's sparse files), so OUT itself is never touched.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CASES = {
    "none": None,
    "30 m cells, noise 2 m over 300 m": {},
    "the same, noise 4 m over 1 km": dict(noise_m=4.0, corr_m=1000.0),
    "bare earth (each block's 10th percentile)": dict(percentile=10.0),
    "roofs (each block's 90th percentile)": dict(percentile=90.0),
    "+ a long wave of 1 m over 20 km": dict(longwave_m=1.0, longwave_km=20.0),
    "+ a long wave of 2 m over 40 km": dict(longwave_m=2.0, longwave_km=40.0, seed=1),
    "90 m cells (SRTM-3), noise 4 m over 1 km": dict(cell_m=90.0, arcsec=3.0, noise_m=4.0, corr_m=1000.0),
}


def scratch_copy(out: Path) -> Path:
    s = out.parent / f"{out.name}_dem_bench"
    shutil.rmtree(s, ignore_errors=True)
    (s / "stages").mkdir(parents=True)
    shutil.copytree(out / "affine", s / "affine", copy_function=lambda a, b: Path(b).hardlink_to(a))
    for stage in ("sparse", "dense"):      # the upgrade runs after both; dense is not redone
        if (out / "stages" / f"{stage}.json").exists():
            shutil.copy(out / "stages" / f"{stage}.json", s / "stages" / f"{stage}.json")
    for name in ("gcps.geojson", "report.json"):     # the GCP roles; the stages' summaries
        if (out / name).exists():
            shutil.copy(out / name, s / name)
    return s


def main(argv=None) -> int:
    from recon_core.config import Config
    from recon_core.euclidean.georef import frame_for
    from recon_core.geometry.enu_map import EnuMap
    from recon_core.pipeline import run
    from recon_core.synthetic.ref_dem import simulate_reference_dem
    from recon_core.synthetic.truth import sparse_vs_truth

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--site", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cases", nargs="*", default=None, help="a subset of the DEMs (their index, from 0)")
    ap.add_argument("--degree", type=int, default=2, help="upgrade.reference_dem_degree (2 or 3)")
    args = ap.parse_args(argv)
    s = scratch_copy(args.out)
    state = run(args.site, s, Config(), until="sparse", resume=True)
    m = state.models[0]
    X = m.X[m.point_ids()]
    T = sparse_vs_truth(args.site, m, frame_for(state.gcps))["truth"]
    names = list(CASES) if args.cases is None else [list(CASES)[int(i)] for i in args.cases]
    print(f"{args.site}: {len(X)} sparse points; DEMs simulated from its gt_dsm.tif")
    for k, name in enumerate(names):
        cfg = s / f"dem_{k}.toml"
        if CASES[name] is None:
            cfg.write_text("")
        else:
            dem = simulate_reference_dem(args.site / "gt_dsm.tif", s / f"dem_{k}.tif", **CASES[name])
            cfg.write_text(f'[upgrade]\nreference_dem = "{dem}"\nreference_dem_degree = {args.degree}\n')
        p = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_pipeline.py"), "--site", str(args.site),
                            "--out", str(s), "--resume", "--until", "upgrade", "--config", str(cfg)],
                           capture_output=True, text=True)
        if p.returncode:
            print(f"{name}: the run failed: {p.stderr.strip().splitlines()[-1:]}")
            continue
        r = json.loads((s / "upgrade" / "group_0.json").read_text())
        d, c = r.get("dem_bend") or {}, r["stats"]["check"]
        du = (EnuMap.from_record(r)(X) - T)[:, 2] if len(T) == len(X) else np.full(1, np.nan)
        bend = (f"degree {d.get('degree', 2)} bend {d['bend_range_m']:.1f} m peak to peak (standard error at the edge {d['bend_sigma_m']:.2f} m, "
                f"cells scatter {d['cell_scale_m']:.2f} m)" if d.get("applied") else
                f"not applied ({d['reason']})" if d else "no DEM")
        print(f"{name}: {bend}; sparse U vs truth RMS {np.sqrt(np.nanmean(du ** 2)):.2f} m, median abs "
              f"{np.nanmedian(np.abs(du)):.2f} m; check E / N / U {c['rmse_E_m']:.2f} / {c['rmse_N_m']:.2f} / "
              f"{c['rmse_U_m']:.2f} m", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

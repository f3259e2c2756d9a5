"""What sets the last of the bend on a pipeline run: the render-free harness on its own points.

The render-free harness (bench_bend.py, recon_core.synthetic.wide_site) leaves less bend than the
pipeline (`large`: 0.09 m against 0.20-0.22 m peak to peak). Its points are spread uniformly
and seen with 0.1 px of white noise; the pipeline's are where SIFT finds texture and seen with
the matcher's errors. This script reads a finished sparse stage of a synthetic site (OUT from
`aerec run` or bench_pipeline.py), takes the true position of each of its points (triangulated
by the true cameras from its observations) and the images that see it, and

  - prints the measured pixels' error against the true projections, and how much of it is
    correlated over 1000 px cells (each image's affine part removed) against what white noise
    would leave;
  - runs the harness's closing (grown in rings from a central patch, tied, the bend step and
    one round with the within-tile correction) on these points and views, seen with exact
    projections, with white noise of the measured pixels' RMS, and with the measured pixels.

Truth for benchmarks only.

    python bench/bench_bend_floor.py --site /tmp/aerec_bench/large_s0 --out /tmp/aerec_bench/out_large_final
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--site", type=Path, required=True, help="a synthetic site (with truth/)")
    ap.add_argument("--out", type=Path, required=True, help="OUT of a run whose sparse stage is done")
    ap.add_argument("--cell", type=float, default=1000.0, help="cell (px) of the correlated error")
    ap.add_argument("--harness", default="exact,white,measured",
                    help="comma-separated observations for the harness runs: exact, white, measured")
    ap.add_argument("--ring-step", type=float, default=300.0)
    a = ap.parse_args(argv)

    from recon_core.config import preset as make_preset
    from recon_core.euclidean.georef import frame_for
    from recon_core.synthetic.truth import bend_report, true_points_enu
    from recon_core.geometry import affine
    from recon_core.model.sparse_model import merge_joint
    from recon_core.pipeline import run
    from recon_core.synthetic.generator import load_truth_cameras

    if not (a.site / "truth" / "cameras.json").exists():
        print(f"{a.site}: no truth/cameras.json (not a synthetic site)", file=sys.stderr)
        return 2
    state = run(a.site, a.out, make_preset("default"), until="sparse", resume=True)
    frame = frame_for(state.gcps)
    m = merge_joint([state.models[g] for g in sorted(state.models)])
    o = m.obs
    ids, idx = m.point_ids(), m.active_obs()
    remap = np.full(len(m.X), -1)
    remap[ids] = np.arange(len(ids))
    key = np.unique(np.stack([o.track[idx], o.img[idx]], 1), axis=0, return_index=True)[1]
    ik = idx[key]
    Xt = true_points_enu(a.site, frame, m.images, o.img[ik], remap[o.track[ik]], o.xy[ik], len(ids))
    X = m.X[ids]
    ok = np.isfinite(Xt).all(1)
    A = affine.fit_affine_3d(X[ok], Xt[ok])
    cams = load_truth_cameras(a.site)
    llh = frame.enu_to_geodetic(Xt)
    measured, exact, names = [], [], []
    for i, k in m.views_per_image():
        p = remap[o.track[k]]
        good = ok[p]
        measured.append((p[good], o.xy[k][good]))
        exact.append((p[good], cams[m.images[i]].project(llh[p[good]])))
        names.append(m.images[i])

    print(f"{a.out}: {len(ids)} points, {len(names)} images; truth from the true cameras")
    r = (np.hstack([X[ok], np.ones((int(ok.sum()), 1))]) @ A.T) - Xt[ok]
    b = bend_report(Xt[ok], r[:, 2])
    print(f"the structure against the truth (one affine map for all groups): vertical quadratic "
          f"{b['quadratic_range_m']:.3f} m p-p (RMS {b['quadratic_rms_m']:.3f} of {b['rms_u_m']:.3f} m)")
    print(f"measured pixels against the true projections; their part correlated over {a.cell:g} px "
          "cells (each image's affine part removed), against white noise")
    sig = []
    for n, (p, xy), (_, uv) in zip(names, measured, exact):
        d = xy - uv
        H = np.hstack([xy / 1e4, np.ones((len(xy), 1))])
        d = d - H @ np.linalg.lstsq(H, d, rcond=None)[0]
        _, cell = np.unique(np.floor(xy / a.cell).astype(np.int64), axis=0, return_inverse=True)
        cell = cell.ravel()
        cnt = np.bincount(cell)
        mean = np.stack([np.bincount(cell, d[:, j]) / cnt for j in range(2)], 1)[cnt >= 100]
        rms = np.sqrt((d ** 2).mean(0))
        sig.append(float(np.sqrt((d ** 2).mean())))
        print(f"  {n}: {len(p)} points, RMS (col, row) {rms[0]:.3f} {rms[1]:.3f} px; cell means "
              f"{np.sqrt((mean ** 2).mean(0))[0]:.4f} {np.sqrt((mean ** 2).mean(0))[1]:.4f} px, "
              f"white noise would leave {rms[0] / np.sqrt(np.median(cnt)):.4f} "
              f"{rms[1] / np.sqrt(np.median(cnt)):.4f}")

    if a.harness:
        from bench_bend import closing

        from recon_core.synthetic.wide_site import WideSite, observe_in_tiles

        tsize = state.cfg.tiling.tile_size
        variants = {"exact": None, "white": float(np.median(sig)), "measured": "measured"}
        for v in a.harness.split(","):
            rng = np.random.default_rng(0)
            noise = variants[v]
            views = [(p, xy if noise == "measured" else uv + (rng.normal(0.0, noise, uv.shape) if noise else 0.0))
                     for (p, xy), (_, uv) in zip(measured, exact)]
            tiles, timg, oc, op, ox = observe_in_tiles(names, [cams[n] for n in names], views, tsize)
            used = np.unique(op)
            local = np.full(len(Xt), -1)
            local[used] = np.arange(len(used))
            site = WideSite(names, tiles, timg, Xt[used], oc, local[op], ox, np.zeros((len(names), 2)))
            label = {"exact": "exact projections", "measured": "the pipeline's measured pixels",
                     "white": f"exact projections + white noise {variants['white']:.2f} px"}[v]
            print(f"\nthe render-free harness (bench_bend.py --closing 1 --bend-step) on these points, "
                  f"tiles of d = {tsize}, {label}: {len(tiles)} tiles, {len(used)} points, {len(oc)} observations",
                  flush=True)
            noise_px = 0.0 if v == "exact" else float(np.median(sig))
            closing(site, 1, [], 0.01, noise_px, True, a.ring_step)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""How much the affine structure bends on a wide site, with and without the per-image tie.

Render-free (recon_core.synthetic.wide_site): points on the true scene, projected by the true
pushbroom cameras with pixel noise, observed in every d x d tile that contains them; a global
bundle adjustment of independent tile cameras starts from the truth and finds the bend on its
own; then the same adjustment with each image's tiles tied to one physical pushbroom model
(recon_core.bend.image_model), re-linearised `--rounds` times. Prints the structure against
the truth after one best-fit 3D affine map: RMS, the vertical RMS a quadratic surface explains,
and its peak-to-peak range.

    python bench/bench_bend.py --preset large --images img_00.tif,img_01.tif,img_02.tif
    python bench/bench_bend.py --preset large                 # all 9 images in one adjustment
    python bench/bench_bend.py --preset flat --sigma-tie 0.05,0.01 --noise 0
    python bench/bench_bend.py --preset flat --observability        # what 3 views can see
    python bench/bench_bend.py --preset flatfp --drive --seed 1      # the expected bend vs the actual
    python bench/bench_bend.py --preset flat --grow --sigma-tie 0.01   # incremental growth,
                                                                     # the within-tile correction
    python bench/bench_bend.py --preset large --closing 7   # the SfM's closing rounds (per round)
    python bench/bench_bend.py --preset large --closing 2 --bend-step   # ... each round starting
                                                      # with the bend step (the SfM's default)

--observability prints, for each quadratic warp of the structure, the pixel motion the images'
models cannot re-fit (bend.pushbroom.warp_observability), with the 1D perspective free and fixed
by physics at --altitude-km. --grow grows the model in rings from a central patch, with and
without the within-tile correction, then the tied closing adjustments. --closing N grows it
without the correction, makes one tied adjustment, then N closing rounds with the correction
refitted; --bend-step then repeats them each started by the bend step. --image-size N makes
every image N px a side (e.g. 20000: a 10 km scene; nothing is rendered). --physics then runs
the metric bend step, each image's 1D perspective fixed by physics in the frame of the best
affine map to the truth: comma-separated orbit altitudes in km, or 'true' for each image's own,
each followed by letters (see metric_step): e.g. 660ghpt is the pipeline's step.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon_core.synthetic.generator import PRESETS
from recon_core.synthetic.wide_site import image_ties, make_wide_site, structure_vs_truth


def line(tag: str, s: dict, extra: str = "") -> str:
    e, n, u = s["rms_enu_m"]
    return (f"{tag:<28} RMS {s['rms_m']:.3f} m (E/N/U {e:.2f}/{n:.2f}/{u:.2f})  quadratic "
            f"{s['quadratic_rms_m']:.3f} of {s['rms_u_m']:.3f} m, {s['quadratic_range_m']:.2f} m p-p  {extra}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="large")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--images", default="", help="comma-separated image names (default: all)")
    ap.add_argument("--points", type=int, default=30000)
    ap.add_argument("--noise", type=float, default=0.1, help="pixel noise (sigma, px)")
    ap.add_argument("--tile-size", type=int, default=1000)
    ap.add_argument("--sigma-tie", default="0.05,0.01",
                    help="comma-separated tie sigmas in px (the model's error against a pushbroom)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--max-nfev", type=int, default=300)
    ap.add_argument("--observability", action="store_true", help="how well the views see each warp (and stop)")
    ap.add_argument("--altitude-km", type=float, default=660.0, help="orbit altitude for --observability")
    ap.add_argument("--grow", action="store_true", help="also grow the model in rings, as the SfM does")
    ap.add_argument("--closing", type=int, default=0, help="grow, then this many closing rounds (and stop)")
    ap.add_argument("--image-size", type=int, default=0, help="every image this many px a side (cameras only)")
    ap.add_argument("--ring-step", type=float, default=300.0, help="ring width (m) of --grow and --closing")
    ap.add_argument("--bend-step", action="store_true", help="--closing: then rounds started by the bend step")
    ap.add_argument("--drive", action="store_true",
                    help="the expected bend (bend.drive) against the actual one (and stop)")
    ap.add_argument("--focal-plane", action="store_true",
                    help="sensors as real ones are: bowed, distorted lines and a drift (demofp's)")
    ap.add_argument("--physics", default="", help="--bend-step: then the metric bend step (see above)")
    a = ap.parse_args(argv)
    t0 = time.time()
    preset = PRESETS[a.preset]
    if a.focal_plane:
        preset = replace(preset, name=f"{preset.name}fp", bow_px=1.0, distortion_px=3.0, drift=10.0)
    if a.image_size:
        preset = replace(preset, name=f"{preset.name}-{a.image_size}px", image_size=(a.image_size,) * 2,
                         first_image_size=None)
    site = make_wide_site(preset, a.seed, images=[s for s in a.images.split(",") if s] or None,
                          n_points=a.points, noise_px=a.noise, d=a.tile_size)
    ext = np.ptp(site.X_true[:, :2], axis=0) / 1e3
    print(f"{preset.name} seed {a.seed} ({ext[0]:.1f} x {ext[1]:.1f} km): {len(site.names)} images, {len(site.tiles)} tiles of d = {a.tile_size}, "
          f"{len(site.X_true)} points, {len(site.obs_cam)} observations, noise {a.noise} px "
          f"({time.time() - t0:.1f} s)")
    for n, dz in zip(site.names, site.height_px_per_m):
        print(f"  {n}: parallax (col, row) {dz[0]:+.3f} {dz[1]:+.3f} px per m of height")
    if a.observability:
        from recon_core.synthetic.wide_site import observability

        for alt in (None, a.altitude_km * 1e3):
            o = observability(site, altitude_m=alt)
            print(f"quadratic warps, 1 m at {o['half_width_m']:.0f} m from the centre: RMS pixel motion "
                  "the image models cannot re-fit (px per m), and the warp's vertical share; "
                  + ("the models' 1D perspective free" if alt is None else
                     f"the 1D perspective fixed by physics (orbit at {a.altitude_km:g} km)"))
            for sv, w in zip(o["singular_px_per_m"], o["warps"]):
                big = ", ".join(f"{o['labels'][j]} {w[j]:+.2f}" for j in np.argsort(-np.abs(w))[:3])
                print(f"  {sv:9.5f} px/m   vertical {np.linalg.norm(w[6:]):.2f}   ({big})")
        return 0
    if a.drive:
        drive(site)
        return 0
    if a.closing:
        physics = [p for p in a.physics.split(",") if p]
        if any(p.startswith("true") for p in physics):
            from recon_core.synthetic.generator import design_cameras

            _, cams = design_cameras(preset, a.seed)
            site.altitudes_m = [float(cams[n].orbit_radius - np.linalg.norm(cams[n].target0)) for n in site.names]
        closing(site, a.closing, [float(s) for s in a.sigma_tie.split(",") if s][-1], a.noise, a.bend_step,
                a.ring_step, physics)
        return 0
    cams0 = site.best_tile_cameras(site.X_true)
    base = site.adjust(cams0, site.X_true, max_nfev=a.max_nfev)
    print(line("independent tile cameras", structure_vs_truth(base.X, site.X_true),
               f"[{base.rms_px:.4f} px, {base.iterations} it, {base.seconds:.1f} s]"))
    sigma_obs = max(base.rms_px / np.sqrt(2.0), 0.02)
    for sig in [float(s) for s in a.sigma_tie.split(",") if s]:
        cams, X = base.cams, base.X
        w = (sigma_obs / sig) ** 2
        secs, its = 0.0, 0
        for _ in range(a.rounds):
            res = site.adjust(cams, X, ties=image_ties(site, cams, X, w), max_nfev=a.max_nfev)
            cams, X = res.cams, res.X
            secs += res.seconds
            its += res.iterations
        print(line(f"tied, sigma_tie {sig} px", structure_vs_truth(X, site.X_true),
                   f"[{res.rms_px:.4f} px, weight {w:.1f}, {its} it, {secs:.1f} s]"))
    if a.grow:
        grow(site, sigma_obs, [float(s) for s in a.sigma_tie.split(",") if s][-1], a.rounds, a.ring_step)
    return 0


def drive(site) -> None:
    """The adjustment of independent tile cameras from the truth, put in the frame of its best
    affine map to the truth (as an upgrade would), then the bend the images' departures from
    affine make one expect (recon_core.bend.drive) against the actual quadratic bend."""
    from recon_core.bend.drive import expected_bend

    t0 = time.time()
    base = site.adjust(site.best_tile_cameras(site.X_true), site.X_true)
    A = np.hstack([base.X, np.ones((len(base.X), 1))])
    Y = A @ np.linalg.lstsq(A, site.X_true, rcond=None)[0]
    e, n = ((Y[:, :2] - Y[:, :2].mean(0)) / (np.ptp(Y[:, :2], axis=0).max() / 2)).T
    lin = np.column_stack([np.ones_like(e), e, n])
    B = np.hstack([lin, np.column_stack([e * e, e * n, n * n])])
    q = B @ np.linalg.lstsq(B, Y[:, 2] - site.X_true[:, 2], rcond=None)[0]
    q -= lin @ np.linalg.lstsq(lin, q, rcond=None)[0]
    d = expected_bend(Y, site.views_per_image(20000, 0))
    print(line("independent tile cameras", structure_vs_truth(base.X, site.X_true), f"[{time.time() - t0:.0f} s]"))
    if d is None:
        print("  no expected bend (fewer than 2 images)")
        return
    print(f"  actual quadratic bend (beyond an affine map) {q.std():.2f} m RMS, {np.abs(q).max():.2f} m at most; "
          f"expected {d.expected_rms_m:.2f} m RMS, {d.expected_edge_m:.2f} m at the edge "
          f"(departures {d.departure_px:.2f} px, their spread {d.spread_px:.2f} px, {d.dof} dof)")


def _gauge_and_obs(site, cams, on):
    """The registered tiles, the observations the closing adjustments use (registered tile,
    point in the model), and the gauge: one tile held, one row of a tile of another image."""
    reg = np.abs(cams).sum(axis=(1, 2)) > 0
    use = np.flatnonzero(on[site.obs_pt] & reg[site.obs_cam])
    fixed = np.zeros_like(cams, dtype=bool)
    first = int(np.flatnonzero(reg)[0])
    other = int(next(t for t in np.flatnonzero(reg) if site.tile_image[t] != site.tile_image[first]))
    fixed[first] = True
    fixed[other, 0] = True
    return reg, use, fixed


def _tied_adjustment(site, cams, X, on, reg, use, fixed, corr, weight, rng):
    """One global adjustment with the per-image ties (48 points sampled per tile), the
    observations moved by `corr` (the within-tile correction, or 0)."""
    from recon_core.bend.image_model import image_tie
    from recon_core.sparse.bundle import bundle_adjust

    oc, op = site.obs_cam[use], site.obs_pt[use]
    ties = []
    for i in range(len(site.names)):
        tids = np.flatnonzero(reg & (site.tile_image == i))
        samples = []
        for t in tids:
            k = op[oc == t]
            samples.append(X[rng.choice(k, 48, replace=False) if len(k) > 48 else k])
        ties.append(image_tie(cams[tids], samples, tids, weight))
    return bundle_adjust(cams, X, oc, op, site.obs_xy[use] - corr, np.flatnonzero(reg),
                         np.flatnonzero(on), fixed, max_nfev=50, ties=ties)


def grow(site, sigma_obs: float, sigma_tie: float, rounds: int, ring_step: float = 300.0) -> None:
    """The model grown in rings from the truth of a central patch (WideSite.grow: nothing else of
    the truth), with and without the within-tile correction, then `rounds` closing adjustments
    with the per-image tie (and the correction refitted before each, when it is on)."""
    from recon_core.bend.pushbroom import tile_corrections

    for corrected in (False, True):
        t0 = time.time()
        cams, X, on = site.grow(correction=corrected, step_m=ring_step)
        reg, use, fixed = _gauge_and_obs(site, cams, on)
        oc, op = site.obs_cam[use], site.obs_pt[use]
        tag = "with the correction" if corrected else "no correction"
        print(line(f"grown, {tag}", structure_vs_truth(X[on], site.X_true[on]),
                   f"[{int(reg.sum())} tiles, {time.time() - t0:.1f} s]"))
        rng = np.random.default_rng(0)
        for r in range(rounds):
            corr = tile_corrections(X[op], site.obs_xy[use], oc, site.tile_image[oc])[0] if corrected else 0.0
            res = _tied_adjustment(site, cams, X, on, reg, use, fixed, corr, (sigma_obs / sigma_tie) ** 2, rng)
            cams, X = res.cams, res.X
            print(line(f"  tied ({sigma_tie} px), round {r + 1}", structure_vs_truth(X[on], site.X_true[on]),
                       f"[{res.rms_px:.4f} px, {res.iterations} it]"))


def closing(site, rounds: int, sigma_tie: float, noise_px: float,
            bend: bool = False, ring_step: float = 300.0, physics: list[str] = ()) -> None:
    """The SfM's closing adjustments on a model grown without the correction (WideSite.grow):
    one tied adjustment, then `rounds` with the within-tile correction refitted; with `bend`,
    then the same rounds each started by the bend step (pushbroom.estimate_bend: the structure
    unbent, the tile cameras following), and one last step after the last round, as the SfM
    ends. Per round: the structure against the truth, and the quadratic coefficients (e^2, e n,
    n^2 over the site scaled to a unit square) of its vertical and east residuals."""
    from recon_core.bend.pushbroom import estimate_bend, tile_corrections

    t0 = time.time()
    cams0, X0, on = site.grow(correction=False, step_m=ring_step,
                              log=lambda text: print(f"  {text} [{time.time() - t0:.0f} s]", flush=True))
    print(f"grown in rings of {ring_step:g} m: {int(on.sum())} points, "
          f"{int((np.abs(cams0).sum(axis=(1, 2)) > 0).sum())} of {len(cams0)} tiles [{time.time() - t0:.0f} s]",
          flush=True)
    reg, use, fixed = _gauge_and_obs(site, cams0, on)
    oc, op = site.obs_cam[use], site.obs_pt[use]
    weight = (max(noise_px, 0.02) / np.sqrt(2.0) / sigma_tie) ** 2

    def adjust(cams, X, corr):
        res = _tied_adjustment(site, cams, X, on, reg, use, fixed, corr, weight, np.random.default_rng(0))
        return res.cams, res.X

    Xt = site.X_true[on]
    e, n = Xt[:, 0] - Xt[:, 0].mean(), Xt[:, 1] - Xt[:, 1].mean()
    scale = max(np.ptp(e), np.ptp(n))
    B = np.column_stack([np.ones_like(e), e / scale, n / scale, (e / scale) ** 2, e * n / scale ** 2,
                         (n / scale) ** 2])

    def report(tag, X):
        A = np.hstack([X[on], np.ones((int(on.sum()), 1))])
        r = A @ np.linalg.lstsq(A, Xt, rcond=None)[0] - Xt
        q = [np.linalg.lstsq(B, r[:, a], rcond=None)[0][3:] for a in (2, 0)]
        print(line(tag, structure_vs_truth(X[on], Xt),
                   "U quad " + " ".join(f"{v:+.2f}" for v in q[0]) + "  E quad "
                   + " ".join(f"{v:+.2f}" for v in q[1]) + f"  [{time.time() - t0:.0f} s]"), flush=True)

    cams1, X1 = adjust(cams0, X0, 0.0)
    report("grown, tied", X1)
    cams, X = cams1, X1
    for r in range(rounds):
        cams, X = adjust(cams, X, tile_corrections(X[op], site.obs_xy[use], oc, site.tile_image[oc])[0])
        report(f"  round {r + 1}", X)
    if not bend:
        return
    ids = np.flatnonzero(on)
    local = np.full(len(on), -1)
    local[ids] = np.arange(len(ids))
    img = site.tile_image[oc]
    images = []
    for i in range(len(site.names)):
        k = np.flatnonzero(img == i)
        _, first = np.unique(op[k], return_index=True)
        images.append((local[op[k[first]]], site.obs_xy[use][k[first]]))
    cnt = np.maximum(np.bincount(oc, minlength=len(cams1)), 1)[:, None]
    cams, X = cams1.copy(), X1.copy()
    for r in range(rounds):
        warp, info = estimate_bend(X[ids], images)
        cen = np.stack([np.bincount(oc, X[op, a], minlength=len(cams)) for a in range(3)], 1) / cnt
        cams[reg] = warp.follow(cams[reg], cen[reg])
        X[ids] += warp(X[ids])
        report(f"  bend step {r + 1} ({info['warps_seen']} warps)", X)
        g = tile_corrections(X[op], site.obs_xy[use], oc, site.tile_image[oc])[0]
        cams, X = adjust(cams, X, g)
        report(f"  bend step, round {r + 1}", X)
    # the SfM's last step, after its last adjustment (whose minimum is nearly flat along these
    # warps, so it drifts with the noise)
    warp, info = estimate_bend(X[ids], images)
    cams[reg] = warp.follow(cams[reg], np.stack([np.bincount(oc, X[op, a], minlength=len(cams))
                                                 for a in range(3)], 1)[reg] / cnt[reg])
    X[ids] += warp(X[ids])
    report(f"  final bend step ({info['warps_seen']} warps)", X)
    for alt in physics:
        metric_step(site, X, cams, ids, images, reg, use, oc, op, cnt, on, alt, adjust, report)


def metric_step(site, X, cams, ids, images, reg, use, oc, op, cnt, on, alt, adjust, report) -> None:
    """The bend step once more in the frame of an upgrade (here the best affine map to the truth),
    each image's 1D perspective fixed by physics (pushbroom.physical_depth at orbit altitude
    `alt` km, or 'true': each image's own; 'true*1.05': 5 % off). Letters after it: g the common
    range estimated too, h horizontal displacements only (the upgrade's east and north), p only
    their projective pair, t the metric step's share threshold (0.1) instead of the bend step's,
    r then a round's adjustment and the step again."""
    from recon_core.bend.pushbroom import estimate_bend, physical_depth, tile_corrections

    X, cams = X.copy(), cams.copy()
    base, factor, flags = re.fullmatch(r"(true|[0-9.]+)(?:\*([0-9.]+))?([ghprt]*)", alt).groups()
    for step in range(2 if "r" in flags else 1):
        A = np.hstack([X[ids], np.ones((len(ids), 1))])
        H = np.vstack([np.linalg.lstsq(A, site.X_true[ids], rcond=None)[0].T, [0, 0, 0, 1]])
        depth = []
        for i, (pts, xy) in enumerate(images):
            P = np.linalg.lstsq(np.hstack([X[ids][pts], np.ones((len(pts), 1))]), xy, rcond=None)[0].T
            h = (site.altitudes_m[i] if base == "true" else float(base) * 1e3) * float(factor or 1.0)
            depth.append(H[:3, :3].T @ physical_depth(P @ np.linalg.inv(H), h))
        warp, info = estimate_bend(X[ids], images, depth=depth, range_free="g" in flags,
                                   min_share=0.1 if "t" in flags else 0.02,
                                   directions=np.linalg.solve(H[:3, :3], np.eye(3)[:, :2]).T if "h" in flags else None,
                                   pair=H[:2, :3] if "p" in flags else None)
        shares = " ".join(f"{v:.4f}" for v in info["warp_shares"])
        cen = np.stack([np.bincount(oc, X[op, a], minlength=len(cams)) for a in range(3)], 1) / cnt
        cams[reg] = warp.follow(cams[reg], cen[reg])
        X[ids] += warp(X[ids])
        report(f"  metric step {step + 1}, {alt} km ({info['warps_seen']} warps)", X)
        print(f"    shares {shares}  range change {info['range_change']:+.4f}")
        if step == 0 and "r" in flags:
            g = tile_corrections(X[op], site.obs_xy[use], oc, site.tile_image[oc])[0]
            cams, X = adjust(cams, X, g)
            report("  metric step, round", X)


if __name__ == "__main__":
    sys.exit(main())

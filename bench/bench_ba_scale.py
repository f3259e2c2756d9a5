"""How one global bundle adjustment grows with the site: the dense reduced camera system against
the block-sparse one, on render-free synthetic sites of 1-20 km.

A site of S x S km at 0.5 m, three images (B/H -0.25, 0, +0.2, as a tri-stereo acquisition),
each cut into d x d tiles overlapping by d/3 as the pipeline cuts them; points on a rough
terrain, `--points` per tile-stride cell of each image's footprint, observed with 0.2 px noise
in every tile that contains them; the start is the truth moved by a seeded perturbation; the
gauge held as the SfM holds it; the per-image ties of the closing adjustments included
(`--no-ties` to leave them out). Each (size, solver) runs in its own process: printed are the
unknowns, the seconds of the whole adjustment and per LM iteration, the final robust cost (both
solvers must agree), and the peak anonymous memory of that process.

    python bench/bench_ba_scale.py [--km 2 5 10 20] [--solvers dense sparse superlu] [--iterations 3]
    (sparse: the block system factored by dense fronts, frontal.FrontalCholesky; superlu: the
    same system factored by SciPy's SuperLU, as before 2026-11-26)
    (the dense solver is skipped where its matrix alone would exceed --dense-max-gb)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def make_problem(km: float, points_per_cell: int, seed: int = 0, d: int = 1000):
    from recon_core.model.tiling import tile_image

    rng = np.random.default_rng(seed)
    gsd = 0.5
    size_m = km * 1000.0
    W = int(round(size_m / gsd))
    stride = d - d // 3
    n_pts = int(points_per_cell * (W / stride) ** 2)
    x = rng.uniform(0, size_m, n_pts)
    y = rng.uniform(0, size_m, n_pts)
    z = 30 * np.sin(x / 900.0) * np.cos(y / 1300.0) + rng.uniform(0, 25, n_pts)
    X = np.column_stack([x, y, z])
    cams, tiles_img, oc, op, ox = [], [], [], [], []
    for i, bh in enumerate((-0.25, 0.0, 0.2)):
        a = 0.01 * (i - 1)                          # a slight rotation between the images
        P = np.array([[np.cos(a), np.sin(a), 0.05 * i, 0.0],
                      [-np.sin(a), np.cos(a), bh, 0.0]]) / gsd
        P[1] *= -1.0
        P[1, 3] = W                                 # rows grow southward
        uv = X @ P[:, :3].T + P[:, 3] + rng.normal(0, 0.2, (n_pts, 2))
        for t in tile_image(f"im{i}", W, W, d):
            k = np.flatnonzero((uv[:, 0] >= t.col0) & (uv[:, 0] < t.col0 + t.width)
                               & (uv[:, 1] >= t.row0) & (uv[:, 1] < t.row0 + t.height))
            if len(k) < 20:
                continue
            cams.append(P)
            tiles_img.append(i)
            oc.append(np.full(len(k), len(cams) - 1))
            op.append(k)
            ox.append(uv[k])
    cams = np.array(cams)
    oc, op, ox = np.concatenate(oc), np.concatenate(op), np.concatenate(ox)
    fixed = np.zeros(cams.shape, bool)
    fixed[0] = True
    fixed[1, 0] = True
    start = cams + np.where(fixed, 0.0, rng.normal(0, 1e-5, cams.shape) * [1, 1, 1, 1e4])
    X0 = X + rng.normal(0, 0.5, X.shape)
    return start, X0, oc, op, ox, fixed, np.array(tiles_img)


def ties_for(cams, X, oc, op, tiles_img, weight=16.0, per_tile=48, seed=0):
    from recon_core.bend.image_model import image_tie

    rng = np.random.default_rng(seed)
    order = np.argsort(oc, kind="stable")
    bounds = np.searchsorted(oc[order], np.arange(len(cams) + 1))
    ties = []
    for i in np.unique(tiles_img):
        tids = np.flatnonzero(tiles_img == i)
        samples = []
        for t in tids:
            k = op[order[bounds[t]:bounds[t + 1]]]
            samples.append(X[rng.choice(k, min(per_tile, len(k)), replace=False)])
        ties.append(image_tie(cams[tids], samples, tids, weight))
    return ties


def one(km: float, solver: str, iterations: int, points: int, with_ties: bool) -> dict:
    from bench_pipeline import AnonPeak

    from recon_core.sparse.bundle import _robust, bundle_adjust, warm_compiled_kernels

    if solver == "superlu":                  # the block system as factored until 2026-11-26
        _use_superlu()
        solver = "sparse"
    warm_compiled_kernels()
    bundle_adjust(*_tiny_problem(), solver="sparse", max_nfev=1)
    peak = AnonPeak()
    start, X0, oc, op, ox, fixed, tiles_img = make_problem(km, points)
    t0 = time.perf_counter()
    ties = ties_for(start, X0, oc, op, tiles_img) if with_ties else None
    t_ties = time.perf_counter() - t0
    base = peak.take()
    t0 = time.perf_counter()
    res = bundle_adjust(start, X0, oc, op, ox, np.arange(len(start)), np.arange(len(X0)), fixed,
                        max_nfev=iterations, rel_tol=0.0, ties=ties, solver=solver)
    sec = time.perf_counter() - t0
    r = np.einsum("kij,kj->ki", res.cams[oc, :, :3], res.X[op]) + res.cams[oc, :, 3] - ox
    return dict(km=km, solver=solver, tiles=len(start), unknowns=int((~fixed).sum()), points=len(X0),
                observations=len(oc), seconds=sec, iterations=res.iterations, tie_seconds=t_ties,
                cost=res.cost_after, data_cost=0.5 * float(_robust((r * r).sum(1), "huber", 1.0)[0].sum()),
                anon_mb=peak.take(), anon_before_mb=base)


def _use_superlu() -> None:
    """The block system factored by SciPy's SuperLU on its diagonal pivots (the solver before
    frontal.FrontalCholesky), for comparison."""
    from scipy.sparse.linalg import splu

    from recon_core.sparse import bundle

    def factor(self, A):
        n = A.shape[0]
        if self.dense_factor:
            cf = bundle.scipy.linalg.cho_factor(A.toarray(order="F"), overwrite_a=True, check_finite=False)
            return lambda b: bundle.scipy.linalg.cho_solve(cf, b)
        lu = splu(A, permc_spec="NATURAL", options={"SymmetricMode": True, "DiagPivotThresh": 0.0})
        if self.dense_factor is None:
            self.dense_factor = n <= bundle.DENSE_FACTOR_MAX and lu.L.nnz + lu.U.nnz > bundle.DENSE_FILL * n * n
        return lu.solve

    bundle._BlockSystem._factor = factor


def _tiny_problem():
    """Compile the block kernels before timing (a 2 x 2 km site, few points)."""
    start, X0, oc, op, ox, fixed, _ = make_problem(1.0, 20)
    return start, X0, oc, op, ox, np.arange(len(start)), np.arange(len(X0)), fixed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--km", type=float, nargs="+", default=[2, 5, 10, 20])
    ap.add_argument("--solvers", nargs="+", default=["dense", "sparse"])
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--points", type=int, default=300, help="points per tile-stride cell")
    ap.add_argument("--no-ties", action="store_true")
    ap.add_argument("--dense-max-gb", type=float, default=6.0)
    ap.add_argument("--one", nargs=2, metavar=("KM", "SOLVER"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one:
        print(json.dumps(one(float(a.one[0]), a.one[1], a.iterations, a.points, not a.no_ties)))
        return
    print(f"one global BA, {a.iterations} LM iterations, {a.points} points per tile cell, "
          f"ties {'off' if a.no_ties else 'on'}; each run in its own process")
    print(f"{'km':>4} {'solver':7} {'tiles':>6} {'unknowns':>8} {'obs':>9} {'s total':>8} {'s/iter':>7} "
          f"{'final cost':>14} {'anon MB':>8}")
    for km in a.km:
        for solver in a.solvers:
            from recon_core.model.tiling import tile_image

            n_est = 3 * 8 * len(tile_image("x", int(km * 2000), int(km * 2000), 1000))   # unknowns
            if solver == "dense" and 8 * n_est ** 2 / 1e9 > a.dense_max_gb:
                print(f"{km:4g} {solver:7} skipped: its matrix alone would be ~{8 * n_est ** 2 / 1e9:.0f} GB")
                continue
            cmd = [sys.executable, __file__, "--one", str(km), solver, "--iterations", str(a.iterations),
                   "--points", str(a.points)] + (["--no-ties"] if a.no_ties else [])
            p = subprocess.run(cmd, capture_output=True, text=True)
            if p.returncode != 0:
                print(f"{km:4g} {solver:7} failed: {p.stderr.strip().splitlines()[-1:]}")
                continue
            r = json.loads(p.stdout.strip().splitlines()[-1])
            print(f"{km:4g} {solver:7} {r['tiles']:6d} {r['unknowns']:8d} {r['observations']:9d} "
                  f"{r['seconds']:8.1f} {r['seconds'] / max(r['iterations'], 1):7.2f} {r['cost']:14.6f} "
                  f"{r['anon_mb']:8.0f}", flush=True)


if __name__ == "__main__":
    main()

"""Benchmark of the fusion ICP: recon_core.euclidean.fusion.icp_refine against open3d's point-to-plane ICP
(when open3d is importable; it is not a dependency of the project).

Two independent noisy samplings of a procedural city (ground, boxes, walls, gable roofs) of
SIZE x SIZE metres; the second is moved by a known small rigid motion, as two date groups
upgraded by their own GCPs would be. Prints, per implementation, the wall time, the fitness,
the inlier RMSE and how far the recovered map is from undoing the known motion (max over the
target points, metres).

    python bench/bench_icp.py [--size 1500] [--spacing 1.0] [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon_core.euclidean.fusion import icp_refine  # noqa: E402
from recon_core.geometry.affine import apply_affine_3d as apply_rigid  # noqa: E402


def city(size: float, spacing: float, rng: np.random.Generator) -> np.ndarray:
    g = np.arange(0.0, size, spacing)
    X, Y = np.meshgrid(g, g)
    Z = 100.0 + 3.0 * np.sin(X / 400.0) * np.cos(Y / 300.0)
    walls = []
    for _ in range(int(size * size / 4000)):
        x0, y0 = rng.uniform(0, size - 40, 2)
        w, d = rng.uniform(8, 35, 2)
        h = rng.uniform(3, 40)
        m = (X >= x0) & (X < x0 + w) & (Y >= y0) & (Y < y0 + d)
        if rng.random() < 0.3:                                    # gable along x
            Z[m] += h * (1.0 - 0.3 * np.abs(Y[m] - y0 - d / 2) / (d / 2))
        else:
            Z[m] += h
        for xs, ys in [(np.arange(x0, x0 + w, spacing), [y0]), ([x0], np.arange(y0, y0 + d, spacing))]:
            A, B, C = np.meshgrid(xs, ys, np.arange(0.0, h, spacing))
            walls.append(np.column_stack([A.ravel(), B.ravel(), 100.0 + C.ravel()]))
    pts = np.vstack([np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])] + walls)
    pts += rng.normal(0.0, 0.15, pts.shape)
    return pts + [500_000.0, 4_650_000.0, 0.0]


def rigid(angle_deg: float, t, centre) -> np.ndarray:
    th = np.radians(angle_deg)
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1.0]])
    a = np.radians(0.02)                                           # a small tilt too
    R = R @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre + np.asarray(t, float)
    return T


def open3d_icp(src, tgt, max_corr_m=3.0, voxel_m=1.0, max_iter=60, n_src=200_000,
               n_tgt=500_000, seed=0):
    """The project's former ICP (open3d), for comparison only."""
    import open3d as o3d

    c = np.concatenate([src, tgt]).mean(axis=0)
    rng = np.random.default_rng(seed)

    def cloud(x, n_max):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(x - c)).voxel_down_sample(voxel_m)
        if len(pc.points) > n_max:
            pc = pc.select_by_index(np.sort(rng.choice(len(pc.points), n_max, replace=False)).tolist())
        return pc

    ps, pt = cloud(src, n_src), cloud(tgt, n_tgt)
    pt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=max(3 * voxel_m, 1.5), max_nn=30))
    reg = o3d.pipelines.registration
    res = reg.registration_icp(ps, pt, max_corr_m, np.eye(4), reg.TransformationEstimationPointToPlane(),
                               reg.ICPConvergenceCriteria(1e-9, 1e-9, max_iter))
    Tc = np.eye(4)
    Tc[:3, 3] = c
    return Tc @ np.asarray(res.transformation) @ np.linalg.inv(Tc), res.fitness, res.inlier_rmse


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=float, default=1500.0)
    ap.add_argument("--spacing", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    target = city(a.size, a.spacing, rng)
    rng_b = np.random.default_rng(1)
    source_true = city(a.size, a.spacing, np.random.default_rng(0)) + rng_b.normal(0, 0.15, target.shape)
    T_true = rigid(0.05, [0.8, -0.5, 0.4], target.mean(axis=0))
    source = apply_rigid(T_true, source_true)
    print(f"{len(target):,} target and {len(source):,} source points over {a.size:.0f} m; "
          f"known motion: 0.05 deg about z, 0.02 deg tilt, shift (0.8, -0.5, 0.4) m")
    impls = [("aerec (numpy + scipy cKDTree)", icp_refine)]
    try:
        import open3d  # noqa: F401
        impls.append(("open3d", open3d_icp))
    except ImportError as exc:
        print(f"open3d not importable ({exc}); only this project's ICP is timed")
    for name, fn in impls:
        times = []
        for _ in range(a.repeat):
            t0 = time.perf_counter()
            T, fit, rmse = fn(source, target)
            times.append(time.perf_counter() - t0)
        err = np.abs(apply_rigid(T @ T_true, target) - target).max()
        print(f"{name:32s} time min/median {min(times):6.2f} / {np.median(times):6.2f} s   "
              f"fitness {fit:.4f}  inlier RMSE {rmse:.3f} m  max error vs truth {err:.3f} m")


if __name__ == "__main__":
    main()

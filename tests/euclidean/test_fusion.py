"""Rigid ICP fusion of upgraded groups."""

from __future__ import annotations

import numpy as np

from recon_core.config import DsmConfig
from recon_core.euclidean.fusion import align_groups, icp_refine, rigid_summary
from recon_core.geometry.affine import apply_affine_3d as apply_rigid

X0, Y0 = 500_000.0, 4_650_000.0


def city(rng: np.random.Generator, spacing: float = 0.5) -> np.ndarray:
    """A 120 m square of ground at 100 m with boxes (roofs + walls) and a gable roof, in UTM."""
    g = np.arange(0, 120, spacing)
    X, Y = np.meshgrid(g, g)
    Z = np.full_like(X, 100.0)
    pts = []
    for (x0, y0, w, d, h) in [(10, 10, 20, 15, 12), (50, 20, 15, 30, 25), (80, 70, 25, 20, 8),
                              (20, 80, 12, 12, 30)]:
        m = (X >= x0) & (X < x0 + w) & (Y >= y0) & (Y < y0 + d)
        Z[m] = 100.0 + h
        pts.append(_walls(x0, y0, w, d, h, spacing))
    m = (X >= 60) & (X < 100) & (Y >= 5) & (Y < 15)            # gable roof
    Z[m] = 106.0 + 4.0 * (1 - np.abs(Y[m] - 10) / 5)
    pts.append(np.column_stack([X.ravel(), Y.ravel(), Z.ravel()]))
    xyz = np.vstack(pts) + rng.normal(0, 0.03, (sum(len(p) for p in pts), 3))
    return xyz + [X0, Y0, 0.0]


def _walls(x0, y0, w, d, h, s) -> np.ndarray:
    z = np.arange(100.0, 100.0 + h, s)
    out = []
    for xs, ys in [(np.arange(x0, x0 + w, s), [y0]), (np.arange(x0, x0 + w, s), [y0 + d]),
                   ([x0], np.arange(y0, y0 + d, s)), ([x0 + w], np.arange(y0, y0 + d, s))]:
        A, B, C = np.meshgrid(xs, ys, z)
        out.append(np.column_stack([A.ravel(), B.ravel(), C.ravel()]))
    return np.vstack(out)


def rigid(angle_deg: float, axis, t, centre) -> np.ndarray:
    """4x4 rotation about `centre` (Rodrigues) followed by translation t."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = np.radians(angle_deg)
    R = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre + t
    return T


def test_icp_recovers_small_rigid_motion():
    rng = np.random.default_rng(0)
    target = city(rng)
    T_true = rigid(0.3, [0.2, 0.3, 1.0], [0.5, -0.3, 0.2], target.mean(axis=0))
    source = apply_rigid(T_true, city(rng))               # independent noise, moved
    T, fitness, rmse = icp_refine(source, target, max_corr_m=3.0, voxel_m=1.0)
    err = apply_rigid(T @ T_true, target) - target         # T should undo T_true
    assert np.abs(err).max() < 0.05
    assert fitness > 0.95 and rmse < 0.5
    s = rigid_summary(np.linalg.inv(T))
    assert abs(s["rotation_deg"] - 0.3) < 0.02


def test_align_groups_refines_onto_the_largest_and_keeps_what_it_cannot_align():
    rng = np.random.default_rng(1)
    ref = city(rng, spacing=1.0)
    ref = np.vstack([ref, ref + rng.normal(0, 0.03, ref.shape)])    # the largest group
    T_true = rigid(0.3, [0, 0, 1], [0.5, 0.0, 0.0], ref.mean(axis=0))
    moved = apply_rigid(T_true, city(rng, spacing=1.0))
    far = ref[: len(moved)] + [5000.0, 0.0, 0.0]                      # no overlap
    Ts, report = align_groups({0: moved, 1: ref, 2: far}, DsmConfig())
    assert report["reference_group"] == 1 and np.array_equal(Ts[1], np.eye(4))
    r0 = report["icp"]["0"]
    assert r0["applied"] and r0["fitness"] > 0.9 and r0["reason"] is None
    assert abs(r0["rotation_deg"] - 0.3) < 0.03
    back = apply_rigid(np.linalg.inv(T_true), moved)                  # where the moved points belong
    assert np.abs(apply_rigid(Ts[0], moved) - back).max() < 0.1
    r2 = report["icp"]["2"]
    assert not r2["applied"] and "fitness" in r2["reason"] and np.array_equal(Ts[2], np.eye(4))
    # the threshold is the configuration's
    Ts, report = align_groups({0: moved, 1: ref}, DsmConfig(icp_min_fitness=1.01))
    assert not report["icp"]["0"]["applied"] and np.array_equal(Ts[0], np.eye(4))


def test_the_named_reference_wins_over_sample_sizes():
    rng = np.random.default_rng(4)
    a, b = city(rng, spacing=1.0), city(rng, spacing=1.0)
    Ts, report = align_groups({0: a[::2], 1: b}, DsmConfig(), reference=0)
    assert report["reference_group"] == 0 and np.array_equal(Ts[0], np.eye(4))

"""Rigid ICP fusion of upgraded groups."""

from __future__ import annotations

import numpy as np

from recon_core.fusion import apply_rigid, fuse_groups, icp_refine, rigid_summary

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


def test_fuse_groups_reports_and_merges():
    rng = np.random.default_rng(1)
    ref = city(rng, spacing=1.0)
    T_true = rigid(0.3, [0, 0, 1], [0.5, 0.0, 0.0], ref.mean(axis=0))
    moved = apply_rigid(T_true, city(rng, spacing=1.0))
    far = ref + [5000.0, 0.0, 0.0]                        # no overlap: must be kept as is
    rgb = np.full((len(ref), 3), 200, np.uint8)
    xyz, colors, report = fuse_groups([(ref, rgb), (moved, None), (far, None)], reference=0)
    assert xyz.shape == (len(ref) + len(moved) + len(far), 3) and colors.shape == xyz.shape
    assert (colors[len(ref):] == 128).all()
    assert report[0]["reference"] and report[1]["accepted"] and report[1]["fitness"] > 0.9
    assert abs(report[1]["rotation_deg"] - 0.3) < 0.03
    aligned = xyz[len(ref):len(ref) + len(moved)]
    back = apply_rigid(np.linalg.inv(T_true), moved)      # where the moved points belong
    assert np.abs(aligned - back).max() < 0.1
    assert not report[2]["accepted"] and "fitness" in report[2]["reason"]
    assert np.array_equal(xyz[-len(far):], far)

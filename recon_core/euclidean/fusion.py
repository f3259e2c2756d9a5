"""Rigid fusion of upgraded date groups by point-to-plane ICP (numpy + scipy's k-d tree).

ICP is rigid: it cannot upgrade a group. Every date group is upgraded to Euclidean by its own
>= 4 GCPs (upgrade.py); ICP only refines the alignment of the upgraded groups to a reference
group, starting from the identity (the GCP-based upgrade is the initial guess).

Coordinates may be large (UTM, ECEF): every cloud is moved to a local frame (a common centroid
subtracted, float64) first, and the centroid is folded back into T.

The ICP is written here on scipy's cKDTree rather than taken from open3d: open3d's wheel is
~900 MB and links system libraries (libusb, libGL, X11) that a fresh headless machine lacks,
for one registration step of a few hundred thousand points.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from recon_core.config import DsmConfig
from recon_core.errors import ReconstructionError


def voxel_downsample(xyz: np.ndarray, voxel_m: float) -> np.ndarray:
    """(n, 3) -> the centroid of the points in each occupied voxel of side voxel_m (sorted by
    voxel index, so the result does not depend on the input order)."""
    if voxel_m <= 0 or len(xyz) == 0:
        return xyz
    ijk = np.floor((xyz - xyz.min(axis=0)) / voxel_m).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0 ** 62:
        _, inv, counts = np.unique(np.ravel_multi_index(ijk.T, dims), return_inverse=True,
                                   return_counts=True)
    else:                                    # a far outlier: index the voxels by rows instead
        _, inv, counts = np.unique(ijk, axis=0, return_inverse=True, return_counts=True)
        inv = inv.ravel()
    out = np.empty((len(counts), 3))
    for k in range(3):
        out[:, k] = np.bincount(inv, weights=xyz[:, k], minlength=len(counts)) / counts
    return out


def estimate_normals(xyz: np.ndarray, tree: cKDTree, radius: float, max_nn: int = 30,
                     chunk: int = 100_000) -> np.ndarray:
    """Unit normals by PCA of each point's <= max_nn neighbours within `radius` (itself
    included); (0, 0, 1) where fewer than 3 neighbours are found. Orientation is arbitrary."""
    n = len(xyz)
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    k = min(max_nn, n)
    for a in range(0, n, chunk):
        p = xyz[a:a + chunk]
        d, j = tree.query(p, k=k, distance_upper_bound=radius, workers=-1)
        d, j = d.reshape(len(p), k), j.reshape(len(p), k)
        ok = np.isfinite(d)
        cnt = ok.sum(axis=1)
        nb = xyz[np.where(ok, j, 0)] * ok[..., None]                       # (m, k, 3), 0 if none
        mean = nb.sum(axis=1) / np.maximum(cnt, 1)[:, None]
        dev = (nb - mean[:, None, :]) * ok[..., None]
        cov = np.einsum("mki,mkj->mij", dev, dev)
        _, vec = np.linalg.eigh(cov)                                        # ascending eigenvalues
        good = cnt >= 3
        normals[a:a + chunk][good] = vec[good, :, 0]
    return normals


def _rotation(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector w (Rodrigues)."""
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _random_subset(xyz: np.ndarray, n_max: int, rng: np.random.Generator) -> np.ndarray:
    if len(xyz) <= n_max:
        return xyz
    return xyz[np.sort(rng.choice(len(xyz), n_max, replace=False))]


def icp_refine(source_xyz: np.ndarray, target_xyz: np.ndarray, max_corr_m: float = 3.0,
               voxel_m: float = 1.0, max_iter: int = 60, max_source: int = 200_000,
               max_target: int = 500_000, seed: int = 0) -> tuple[np.ndarray, float, float]:
    """Rigid point-to-plane ICP of a source cloud onto a target cloud, from the identity.

    Each iteration pairs every source point with its nearest target point within max_corr_m
    and solves the linearised point-to-plane least squares (6 unknowns: a rotation vector and a
    translation) exactly; it stops when fitness and inlier RMSE change by less than 1e-9.

    Args:
        source_xyz: (n, 3) points to move; target_xyz: (m, 3) reference points (same CRS/frame).
        max_corr_m: maximum correspondence distance (metres).
        voxel_m: voxel size for downsampling both clouds (metres; 0 = none). Target normals are
            estimated within 3 voxels (at least 1.5 m), from at most 30 neighbours.
        max_source, max_target: after downsampling, at most this many points are kept (a seeded
            random subset): six parameters need far fewer, and ICP's cost grows with both.
    Returns:
        T: (4, 4) rigid map, x_target ~ T [x_source, 1], in the input coordinates.
        fitness: fraction of (downsampled) source points with a correspondence.
        inlier_rmse: RMS distance of those correspondences (metres).
    """
    src = np.asarray(source_xyz, dtype=np.float64).reshape(-1, 3)
    tgt = np.asarray(target_xyz, dtype=np.float64).reshape(-1, 3)
    if len(src) < 10 or len(tgt) < 10:
        raise ReconstructionError(f"ICP needs >= 10 points per cloud, got {len(src)} and {len(tgt)}")
    c = np.concatenate([src, tgt]).mean(axis=0)
    rng = np.random.default_rng(seed)
    ps = _random_subset(voxel_downsample(src - c, voxel_m), max_source, rng)
    pt = _random_subset(voxel_downsample(tgt - c, voxel_m), max_target, rng)
    tree = cKDTree(pt)
    normals = estimate_normals(pt, tree, radius=max(3.0 * voxel_m, 1.5))
    R, t = np.eye(3), np.zeros(3)

    def pair(R, t):
        p = ps @ R.T + t
        d, j = tree.query(p, distance_upper_bound=max_corr_m, workers=-1)
        ok = np.isfinite(d)
        fit = float(ok.mean())
        rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else 0.0
        return p[ok], j[ok], fit, rmse

    p, j, fit, rmse = pair(R, t)
    for _ in range(max_iter):
        if len(p) < 6:
            break
        n = normals[j]
        r = np.einsum("ij,ij->i", p - pt[j], n)
        J = np.hstack([np.cross(p, n), n])                   # d r / d (w, t) at the identity
        x = np.linalg.lstsq(J.T @ J, -J.T @ r, rcond=None)[0]
        dR = _rotation(x[:3])
        R, t = dR @ R, dR @ t + x[3:]
        p, j, fit_new, rmse_new = pair(R, t)
        converged = abs(fit_new - fit) < 1e-9 and abs(rmse_new - rmse) < 1e-9
        fit, rmse = fit_new, rmse_new
        if converged:
            break
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t + c - R @ c
    return T, fit, rmse


def rigid_summary(T: np.ndarray) -> dict[str, float]:
    """Translation norm (m) and rotation angle (degrees) of a rigid (4, 4) map."""
    cos = np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return {"rotation_deg": float(np.degrees(np.arccos(cos))),
            "translation_m": float(np.linalg.norm(T[:3, 3]))}


def align_groups(clouds: dict[int, np.ndarray], cfg: DsmConfig, reference: int | None = None
                 ) -> tuple[dict[int, np.ndarray], dict[str, Any]]:
    """Rigid ICP of every upgraded group onto a reference group (default: the largest cloud
    given; callers that pass samples name the group with the largest full cloud).

    A group whose ICP fitness is below cfg.icp_min_fitness (too little overlap), or whose ICP
    fails, keeps its GCP-based position (the identity) and the report says why.

    Args:
        clouds: group -> (n_g, 3) points of the upgraded group (samples suffice), one frame.
    Returns:
        {group: T (4, 4)} with x_reference ~ T [x_group, 1], and the report: reference_group,
        and per other group fitness, inlier_rmse_m, applied, reason, translation_m,
        rotation_deg, T.
    """
    groups = [g for g in sorted(clouds) if len(clouds[g])]
    if not groups:
        raise ReconstructionError("no upgraded group has a cloud")
    ref = max(groups, key=lambda g: len(clouds[g])) if reference is None else reference
    if ref not in groups:
        raise ValueError(f"reference group {ref} has no cloud")
    Ts = {g: np.eye(4) for g in groups}
    report: dict[str, Any] = {"reference_group": ref, "icp": {}}
    for g in groups:
        if g == ref:
            continue
        if len(clouds[g]) < 100:
            report["icp"][str(g)] = {"fitness": 0.0, "inlier_rmse_m": None, "applied": False,
                                     "reason": f"only {len(clouds[g])} points: kept the GCP-based position"}
            continue
        try:
            T, fit, rmse = icp_refine(clouds[g], clouds[ref], max_corr_m=cfg.icp_max_corr_m,
                                      voxel_m=cfg.icp_voxel_m, max_iter=cfg.icp_max_iter,
                                      max_source=cfg.icp_max_source, max_target=cfg.icp_max_target)
        except ReconstructionError as exc:
            report["icp"][str(g)] = {"fitness": 0.0, "inlier_rmse_m": None, "applied": False,
                                     "reason": str(exc)}
            continue
        ok = fit >= cfg.icp_min_fitness
        summ = rigid_summary(T)
        report["icp"][str(g)] = {
            "fitness": fit, "inlier_rmse_m": rmse, "applied": ok, "translation_m": T[:3, 3].tolist(),
            "T": T.tolist(), "rotation_deg": summ["rotation_deg"], "shift_norm_m": summ["translation_m"],
            "reason": None if ok else (f"ICP fitness {fit:.2f} < {cfg.icp_min_fitness}: kept the "
                                       "GCP-based position (too little overlap?)")}
        if ok:
            Ts[g] = T
    return Ts, report

"""Rigid fusion of upgraded date groups by ICP (open3d, point-to-plane).

ICP is rigid: it cannot upgrade a group. Every date group is upgraded to Euclidean by its own
>= 4 GCPs (upgrade.py); ICP only refines the alignment of the upgraded groups to a reference
group, starting from the identity (the GCP-based upgrade is the initial guess).

Coordinates may be large (UTM, ECEF): every cloud is moved to a local frame (a common centroid
subtracted, float64) before open3d sees it, and the centroid is folded back into T.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .errors import ReconstructionError


def _o3d_cloud(xyz: np.ndarray, voxel_m: float):
    """open3d point cloud of (n, 3) float64 local coordinates, voxel-downsampled if voxel_m > 0."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(xyz, np.float64)))
    return pc.voxel_down_sample(voxel_m) if voxel_m > 0 else pc


def _random_subset(pc, n_max: int, rng: np.random.Generator):
    n = len(pc.points)
    if n <= n_max:
        return pc
    return pc.select_by_index(np.sort(rng.choice(n, n_max, replace=False)).tolist())


def _translation(t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


def icp_refine(source_xyz: np.ndarray, target_xyz: np.ndarray, max_corr_m: float = 3.0,
               voxel_m: float = 1.0, max_iter: int = 60, max_source: int = 200_000,
               max_target: int = 500_000, seed: int = 0) -> tuple[np.ndarray, float, float]:
    """Rigid point-to-plane ICP of a source cloud onto a target cloud, from the identity.

    Args:
        source_xyz: (n, 3) points to move; target_xyz: (m, 3) reference points (same CRS/frame).
        max_corr_m: maximum correspondence distance (metres).
        voxel_m: voxel size for downsampling both clouds (metres; 0 = none). Target normals are
            estimated within 3 voxels (at least 1.5 m).
        max_source, max_target: after downsampling, at most this many points are kept (a seeded
            random subset): six parameters need far fewer, and ICP's cost grows with both.
    Returns:
        T: (4, 4) rigid map, x_target ~ T [x_source, 1], in the input coordinates.
        fitness: fraction of (downsampled) source points with a correspondence.
        inlier_rmse: RMS distance of those correspondences (metres).
    """
    import open3d as o3d

    src = np.asarray(source_xyz, dtype=np.float64).reshape(-1, 3)
    tgt = np.asarray(target_xyz, dtype=np.float64).reshape(-1, 3)
    if len(src) < 10 or len(tgt) < 10:
        raise ReconstructionError(f"ICP needs >= 10 points per cloud, got {len(src)} and {len(tgt)}")
    c = np.concatenate([src, tgt]).mean(axis=0)
    ps, pt = _o3d_cloud(src - c, voxel_m), _o3d_cloud(tgt - c, voxel_m)
    rng = np.random.default_rng(seed)
    ps, pt = _random_subset(ps, max_source, rng), _random_subset(pt, max_target, rng)
    radius = max(3.0 * voxel_m, 1.5)
    pt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    reg = o3d.pipelines.registration
    result = reg.registration_icp(
        ps, pt, max_corr_m, np.eye(4), reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9,
                                   max_iteration=max_iter))
    T = _translation(c) @ np.asarray(result.transformation) @ _translation(-c)
    return T, float(result.fitness), float(result.inlier_rmse)


def rigid_summary(T: np.ndarray) -> dict[str, float]:
    """Translation norm (m) and rotation angle (degrees) of a rigid (4, 4) map."""
    cos = np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return {"rotation_deg": float(np.degrees(np.arccos(cos))),
            "translation_m": float(np.linalg.norm(T[:3, 3]))}


def apply_rigid(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """(n, 3) -> (n, 3) under a (4, 4) map."""
    return np.asarray(xyz, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def fuse_groups(clouds: list[tuple[np.ndarray, np.ndarray | None]], reference: int = 0, *,
                max_corr_m: float = 3.0, voxel_m: float = 1.0, min_fitness: float = 0.3
                ) -> tuple[np.ndarray, np.ndarray | None, list[dict[str, Any]]]:
    """Align each upgraded group rigidly to the reference group by ICP and merge them.

    A group whose ICP fitness is below `min_fitness` keeps its GCP-based position (identity)
    and the report says so.

    Args:
        clouds: one (xyz (n_i, 3), colors (n_i, 3) uint8 or None) per group, same frame/CRS.
        reference: index of the group the others are aligned to.
    Returns:
        merged xyz (sum n_i, 3) float64, merged colors (uint8, grey where a group had none;
        None if no group had colours), and one report dict per group: group, n_points,
        reference, T, fitness, inlier_rmse_m, rotation_deg, translation_m, accepted, reason.
    """
    if not clouds:
        raise ReconstructionError("no groups to fuse")
    if not 0 <= reference < len(clouds):
        raise ValueError(f"reference {reference} out of range for {len(clouds)} groups")
    ref_xyz = np.asarray(clouds[reference][0], dtype=np.float64)
    out_xyz, report = [], []
    for i, (xyz, _) in enumerate(clouds):
        xyz = np.asarray(xyz, dtype=np.float64)
        row: dict[str, Any] = {"group": i, "n_points": len(xyz), "reference": i == reference}
        if i == reference:
            T = np.eye(4)
            row.update(fitness=1.0, inlier_rmse_m=0.0, accepted=True, reason="reference group")
        else:
            T, row = _align_one(xyz, ref_xyz, row, max_corr_m, voxel_m, min_fitness)
        row.update(T=T.tolist(), **rigid_summary(T))
        out_xyz.append(apply_rigid(T, xyz))
        report.append(row)
    return np.concatenate(out_xyz), _merge_colors(clouds), report


def _align_one(xyz, ref_xyz, row, max_corr_m, voxel_m, min_fitness) -> tuple[np.ndarray, dict]:
    """ICP one group onto the reference; identity (with the reason) if it fails or fits poorly."""
    try:
        T, fit, rmse = icp_refine(xyz, ref_xyz, max_corr_m, voxel_m)
    except ReconstructionError as e:
        row.update(fitness=0.0, inlier_rmse_m=None, accepted=False, reason=str(e))
        return np.eye(4), row
    row.update(fitness=fit, inlier_rmse_m=rmse)
    if fit < min_fitness:
        row.update(accepted=False, reason=f"ICP fitness {fit:.2f} < {min_fitness}: kept the "
                                          "GCP-based position (too little overlap?)")
        return np.eye(4), row
    row.update(accepted=True, reason=None)
    return T, row


def _merge_colors(clouds) -> np.ndarray | None:
    """Concatenate per-group colours; grey (128) for a group without colours."""
    if all(c is None for _, c in clouds):
        return None
    parts = [np.full((len(x), 3), 128, np.uint8) if c is None
             else np.asarray(c, np.uint8).reshape(-1, 3) for x, c in clouds]
    return np.concatenate(parts)

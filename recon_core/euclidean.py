"""Euclidean products: per-group upgrade, fusion of groups, Euclidean cloud and DSM.

All groups share one local ENU frame (at the control GCPs' centroid). Each group is upgraded by
its own H_A (ICP is rigid and cannot upgrade a group); several groups are then refined onto the
largest one by ICP and merged. Heights written to the DSM are ellipsoidal h from geodetic
conversion of ENU, not ENU up.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .config import Config
from .dsm import DsmAccumulator, Grid, PlyWriter, fill_small_holes, open_ply, ply_fields, write_dsm
from .errors import ReconstructionError
from .geodesy import LocalFrame
from .georef import enu_to_output, frame_for, output_epsg, upgrade_group
from .io_utils import write_json
from .site import Site


def estimate_gsd(model, H: np.ndarray) -> float:
    """Median ground sample distance (m/px) of the registered tile cameras, via H_A."""
    Ainv = np.linalg.inv(H[:3, :3])
    gsd = []
    for t in np.flatnonzero(model.registered):
        J = model.cams[t][:, :3] @ Ainv          # pixels per metre along E, N, U
        det = abs(np.linalg.det(J[:, :2]))
        if det > 0:
            gsd.append(1.0 / np.sqrt(det))
    if not gsd:
        raise ReconstructionError("cannot estimate the GSD: no registered camera")
    return float(np.median(gsd))


def upgrade_groups(site: Site, models: dict, cfg: Config, out: Path) -> tuple[dict, LocalFrame, dict]:
    """Fit H_A for every group; returns ({g: H}, frame, report). Groups that fail are reported."""
    if not site.gcps:
        raise ReconstructionError(f"{site.root / 'gcps.geojson'}: no GCP; the Euclidean upgrade needs "
                                  ">= 4 control GCPs observed in >= 2 images of each group")
    frame = frame_for(site.gcps)
    Hs, report = {}, {"frame": frame.to_dict(), "groups": {}}
    for g, model in sorted(models.items()):
        try:
            res, _, aff = upgrade_group(model, site.gcps, frame, ransac_thresh_m=cfg.upgrade.ransac_thresh_m,
                                        seed=cfg.seed)
        except ReconstructionError as exc:
            report["groups"][str(g)] = {"error": f"group {g}: {exc}"}
            continue
        Hs[g] = res.H
        d = res.to_dict()
        d["gcp_affine"] = {k: {"xyz": None if a.xyz is None else a.xyz.tolist(), "n_images": a.n_images,
                               "reproj_rms_px": a.reproj_rms_px, "source": a.source} for k, a in aff.items()}
        d["gsd_m"] = estimate_gsd(model, res.H)
        report["groups"][str(g)] = d
        write_json(out / "upgrade" / f"group_{g}.json", d)
    if not Hs:
        raise ReconstructionError("; ".join(v["error"] for v in report["groups"].values()))
    write_json(out / "upgrade" / "frame.json", frame.to_dict())
    return Hs, frame, report


def load_upgrade(out: Path) -> tuple[dict, LocalFrame] | None:
    f = out / "upgrade" / "frame.json"
    if not f.exists():
        return None
    fr = json.loads(f.read_text())
    frame = LocalFrame(fr["lon0"], fr["lat0"], fr["h0"])
    Hs = {}
    for p in sorted((out / "upgrade").glob("group_*.json")):
        Hs[int(p.stem.split("_")[1])] = np.array(json.loads(p.read_text())["H"])
    return Hs, frame


class PointSource:
    """A group's affine cloud, read by slices: a memory-mapped PLY on disk, or arrays."""

    def __init__(self, xyz: np.ndarray | None = None, gray: np.ndarray | None = None,
                 ply: Path | None = None):
        self._rec = open_ply(ply) if ply is not None else None
        self._xyz, self._gray = xyz, gray

    def __len__(self) -> int:
        return len(self._rec) if self._rec is not None else len(self._xyz)

    def read(self, a: int, b: int, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(xyz (k, 3) float64, grey (k,) uint8) of points a, a + step, ... < b."""
        if self._rec is None:
            return np.asarray(self._xyz[a:b:step], np.float64), np.asarray(self._gray[a:b:step], np.uint8)
        xyz, rgb, _ = ply_fields(self._rec[a:b:step])
        return xyz, (rgb[:, 0] if rgb is not None else np.full(len(xyz), 128, np.uint8))

    def sample(self, max_n: int) -> np.ndarray:
        """At most max_n points spread evenly through the cloud (every k-th)."""
        return self.read(0, len(self), max(1, -(-len(self) // max_n)))[0]


ICP_SAMPLE = 3_000_000        # points per group given to ICP and to the grid extent
CHUNK = 4_000_000             # points per chunk when streaming clouds into the DSM
SPILL_ABOVE = 20_000_000      # DSM accumulation goes to disk above this many points


def _to_enu(H: np.ndarray, xyz: np.ndarray, T: np.ndarray | None = None) -> np.ndarray:
    enu = xyz @ H[:3, :3].T + H[:3, 3]
    return enu if T is None else enu @ T[:3, :3].T + T[:3, 3]


def fuse_transforms(sources: dict, Hs: dict, cfg: Config) -> tuple[dict, dict, dict]:
    """Per group: the ICP refinement T onto the largest group (identity for it), computed on
    evenly spread samples of the upgraded clouds. Returns ({g: T}, {g: sample ENU after T}, report)."""
    from .fusion import icp_refine

    groups = [g for g in sorted(Hs) if g in sources and len(sources[g])]
    if not groups:
        raise ReconstructionError("no upgraded group has a cloud")
    ref = max(groups, key=lambda g: len(sources[g]))
    samples = {g: _to_enu(Hs[g], sources[g].sample(ICP_SAMPLE)) for g in groups}
    report = {"reference_group": ref, "icp": {}}
    Ts = {g: np.eye(4) for g in groups}
    for g in groups:
        if g == ref or len(samples[g]) < 100:
            continue
        T, fitness, rmse = icp_refine(samples[g], samples[ref], max_corr_m=cfg.dsm.icp_max_corr_m)
        ok = fitness >= 0.3
        report["icp"][str(g)] = {"fitness": fitness, "inlier_rmse_m": rmse, "applied": ok,
                                 "translation_m": T[:3, 3].tolist()}
        if ok:
            Ts[g] = T
            samples[g] = samples[g] @ T[:3, :3].T + T[:3, 3]
    return Ts, samples, report


def output_grid(site: Site, xyh: np.ndarray, epsg: int, res: float) -> Grid:
    """site.json's bounds when given (in the output CRS), else the cloud's robust extent."""
    if site.hints.get("bounds") and int(site.hints.get("crs_epsg", epsg)) == epsg:
        return Grid.from_site_json({**site.hints, "resolution_m": res, "crs_epsg": epsg},
                                   site.root / "site.json")
    lo, hi = np.percentile(xyh[:, :2], [0.1, 99.9], axis=0)
    return Grid.from_points(np.stack([lo, hi]), res, epsg, margin=2 * res)


def make_dsm(site: Site, sources: dict, Hs: dict, frame: LocalFrame, gsd: float, cfg: Config,
             out: Path, bus=None) -> dict:
    """Write cloud.ply (Euclidean, output CRS) and dsm.tif; return the summary.

    Streams: each group's cloud is read by chunks (upgrade, ICP refinement, conversion to the
    output CRS), appended to cloud.ply and filed into the DSM accumulator, which reduces one
    block of grid rows at a time; memory does not grow with the number of points.
    """
    Ts, samples, fusion = fuse_transforms(sources, Hs, cfg)
    epsg = output_epsg(site.hints, frame)
    res = float(cfg.dsm.resolution_m or site.hints.get("resolution_m") or max(0.5, round(gsd * 2) / 2))
    grid = output_grid(site, enu_to_output(np.concatenate(list(samples.values())), frame, epsg), epsg, res)
    total = sum(len(sources[g]) for g in Ts)
    acc = DsmAccumulator(grid, stat=cfg.dsm.stat, spill_dir=out if total > SPILL_ABOVE else None)
    done = 0
    try:
        with PlyWriter(out / "cloud.ply") as w:
            for g in sorted(Ts):
                src = sources[g]
                for a in range(0, len(src), CHUNK):
                    xyz, gray = src.read(a, min(a + CHUNK, len(src)))
                    xyh = enu_to_output(_to_enu(Hs[g], xyz, Ts[g]), frame, epsg)
                    acc.add(xyh)
                    w.append(xyh, gray[:, None])
                    done += len(xyz)
                    if bus is not None:
                        bus.progress("dsm", done, total, f"group {g}")
        H, count = acc.finish()
    finally:
        acc.close()
    raw_valid = float(np.isfinite(H).mean())
    if cfg.dsm.fill_holes_px > 0:
        H = fill_small_holes(H, max_hole_px=cfg.dsm.fill_holes_px)
    write_dsm(out / "dsm.tif", H, grid)
    return {"crs_epsg": epsg, "resolution_m": res, "width": grid.width, "height": grid.height,
            "points": int(total), "points_in_grid": int(count.sum()), "valid_fraction_raw": raw_valid,
            "valid_fraction": float(np.isfinite(H).mean()), "stat": cfg.dsm.stat, "fusion": fusion,
            "gsd_m": gsd}

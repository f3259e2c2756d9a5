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
from .dsm import Grid, fill_small_holes, rasterize, write_dsm, write_ply
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


def euclidean_cloud(clouds: dict, Hs: dict, cfg: Config) -> tuple[np.ndarray, np.ndarray, dict]:
    """Upgrade each group's cloud to ENU, refine groups onto the largest by ICP, merge."""
    from .fusion import icp_refine

    enu = {g: clouds[g][0] @ Hs[g][:3, :3].T + Hs[g][:3, 3] for g in Hs if g in clouds}
    if not enu:
        raise ReconstructionError("no upgraded group has a cloud")
    ref = max(enu, key=lambda g: len(enu[g]))
    report = {"reference_group": ref, "icp": {}}
    for g in enu:
        if g == ref or len(enu[g]) < 100:
            continue
        T, fitness, rmse = icp_refine(enu[g], enu[ref], max_corr_m=cfg.dsm.icp_max_corr_m)
        ok = fitness >= 0.3
        report["icp"][str(g)] = {"fitness": fitness, "inlier_rmse_m": rmse, "applied": ok,
                                 "translation_m": T[:3, 3].tolist()}
        if ok:
            enu[g] = enu[g] @ T[:3, :3].T + T[:3, 3]
    xyz = np.concatenate([enu[g] for g in sorted(enu)])
    gray = np.concatenate([clouds[g][1] for g in sorted(enu)])
    return xyz, gray, report


def output_grid(site: Site, xyh: np.ndarray, epsg: int, res: float) -> Grid:
    """site.json's bounds when given (in the output CRS), else the cloud's robust extent."""
    if site.hints.get("bounds") and int(site.hints.get("crs_epsg", epsg)) == epsg:
        return Grid.from_site_json({**site.hints, "resolution_m": res, "crs_epsg": epsg},
                                   site.root / "site.json")
    lo, hi = np.percentile(xyh[:, :2], [0.1, 99.9], axis=0)
    return Grid.from_points(np.stack([lo, hi]), res, epsg, margin=2 * res)


def make_dsm(site: Site, clouds: dict, Hs: dict, frame: LocalFrame, gsd: float, cfg: Config,
             out: Path) -> dict:
    """Write cloud.ply (Euclidean, output CRS) and dsm.tif; return the summary."""
    xyz_enu, gray, fusion = euclidean_cloud(clouds, Hs, cfg)
    epsg = output_epsg(site.hints, frame)
    xyh = enu_to_output(xyz_enu, frame, epsg)
    write_ply(out / "cloud.ply", xyh, np.repeat(gray[:, None], 3, 1))
    res = float(cfg.dsm.resolution_m or site.hints.get("resolution_m") or max(0.5, round(gsd * 2) / 2))
    grid = output_grid(site, xyh, epsg, res)
    H, count = rasterize(xyh, grid, stat=cfg.dsm.stat)
    raw_valid = float(np.isfinite(H).mean())
    if cfg.dsm.fill_holes_px > 0:
        H = fill_small_holes(H, max_hole_px=cfg.dsm.fill_holes_px)
    write_dsm(out / "dsm.tif", H, grid)
    return {"crs_epsg": epsg, "resolution_m": res, "width": grid.width, "height": grid.height,
            "points": int(len(xyh)), "valid_fraction_raw": raw_valid,
            "valid_fraction": float(np.isfinite(H).mean()), "stat": cfg.dsm.stat, "fusion": fusion,
            "gsd_m": gsd}

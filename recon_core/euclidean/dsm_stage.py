"""The fusion + DSM stage: upgraded groups refined onto one another by ICP, one Euclidean cloud
and the DSM.

All groups share one local ENU frame (at the control GCPs' centroid). Each group is upgraded by
its own H_A (ICP is rigid and cannot upgrade a group); the groups are then refined onto the
largest one by ICP and merged. Heights written to the DSM are ellipsoidal h from geodetic
conversion of ENU, not ENU up.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon_core.config import Config
from recon_core.errors import ReconstructionError
from recon_core.euclidean.dsm import DsmAccumulator, fill_small_holes
from recon_core.euclidean.fusion import align_groups
from recon_core.euclidean.georef import enu_to_output, output_epsg
from recon_core.events import EventBus
from recon_core.geometry.affine import apply_affine_3d
from recon_core.geometry.geodesy import LocalFrame
from recon_core.io.layout import OutLayout
from recon_core.io.models import PointSource
from recon_core.io.ply import PlyWriter
from recon_core.io.raster import Grid, write_dsm
from recon_core.io.site import Site


def output_grid(site: Site, xyh: np.ndarray, epsg: int, res: float) -> Grid:
    """site.json's bounds when given (in the output CRS), else the cloud's robust extent."""
    if site.hints.get("bounds") and int(site.hints.get("crs_epsg", epsg)) == epsg:
        return Grid.from_site_json({**site.hints, "resolution_m": res, "crs_epsg": epsg},
                                   site.root / "site.json")
    lo, hi = np.percentile(xyh[:, :2], [0.1, 99.9], axis=0)
    return Grid.from_points(np.stack([lo, hi]), res, epsg, margin=2 * res)


def make_dsm(site: Site, sources: dict[int, PointSource], Hs: dict, frame: LocalFrame, gsd: float,
             cfg: Config, out: OutLayout, bus: EventBus | None = None) -> dict:
    """Write cloud.ply (Euclidean, output CRS) and dsm.tif; return the summary.

    Streams: ICP and the grid extent use evenly spread samples; then each group's cloud is read
    by chunks (upgrade, ICP refinement, conversion to the output CRS), appended to cloud.ply and
    filed into the DSM accumulator, which reduces one block of grid rows at a time; memory does
    not grow with the number of points.
    """
    c = cfg.dsm
    groups = [g for g in sorted(Hs) if g in sources and len(sources[g])]
    if not groups:
        raise ReconstructionError("no upgraded group has a cloud")
    samples = {g: apply_affine_3d(Hs[g], sources[g].sample(c.icp_sample_points)) for g in groups}
    Ts, fusion = align_groups(samples, c, reference=max(groups, key=lambda g: len(sources[g])))
    epsg = output_epsg(site.hints, frame)
    res = float(c.resolution_m or site.hints.get("resolution_m") or max(0.5, round(gsd * 2) / 2))
    extent = np.concatenate([apply_affine_3d(Ts[g], samples[g]) for g in groups])
    grid = output_grid(site, enu_to_output(extent, frame, epsg), epsg, res)
    total = sum(len(sources[g]) for g in groups)
    acc = DsmAccumulator(grid, stat=c.stat, spill_dir=out.root if total > c.spill_above_points else None)
    done = 0
    try:
        with PlyWriter(out.cloud) as w:
            for g in groups:
                src = sources[g]
                for a in range(0, len(src), c.chunk_points):
                    xyz, gray = src.read(a, min(a + c.chunk_points, len(src)))
                    xyh = enu_to_output(apply_affine_3d(Ts[g], apply_affine_3d(Hs[g], xyz)), frame, epsg)
                    acc.add(xyh)
                    w.append(xyh, gray[:, None])
                    done += len(xyz)
                    if bus is not None:
                        bus.progress("dsm", done, total, f"group {g}")
        H, count = acc.finish()
    finally:
        acc.close()
    raw_valid = float(np.isfinite(H).mean())
    if c.fill_holes_px > 0:
        H = fill_small_holes(H, max_hole_px=c.fill_holes_px)
    write_dsm(out.dsm, H, grid)
    return {"crs_epsg": epsg, "resolution_m": res, "width": grid.width, "height": grid.height,
            "points": int(total), "points_in_grid": int(count.sum()), "valid_fraction_raw": raw_valid,
            "valid_fraction": float(np.isfinite(H).mean()), "stat": c.stat, "fusion": fusion,
            "gsd_m": gsd}


def point_sources(state, bus: EventBus) -> dict[int, PointSource]:
    """Each upgraded group's dense cloud (on disk), or its sparse points when it has none."""
    sources = {}
    for g in state.upgrade[0]:
        path: Path | None = state.dense.get(g)
        src = PointSource(ply=path) if path is not None else None
        if src is not None and len(src):
            sources[g] = src
        elif g in state.models:
            m = state.models[g]
            ids = m.point_ids()
            sources[g] = PointSource(m.X[ids], m.gray[ids])
            bus.message(f"group {g}: no dense cloud, the DSM uses the sparse points", "warning", g)
    return sources


def run(state, bus: EventBus) -> dict:
    if state.upgrade is None:
        raise ReconstructionError("the DSM needs the upgrade stage")
    Hs, frame = state.upgrade
    ups = state.report.get("stages", {}).get("upgrade", {}).get("groups", {})
    gsd = min((v["gsd_m"] for v in ups.values() if "gsd_m" in v), default=0.5)
    return make_dsm(state.site, point_sources(state, bus), Hs, frame, gsd, state.cfg, state.layout, bus)


def load(state) -> None:
    pass

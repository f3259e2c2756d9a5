"""The fusion + DSM stage: upgraded groups refined onto one another by ICP, one Euclidean cloud
and the DSM.

All groups share one local ENU frame (at the control GCPs' centroid). Each group is upgraded by
its own H_A (ICP is rigid and cannot upgrade a group); the groups are then refined onto the
largest one by ICP and merged. Heights written to the DSM are ellipsoidal h from geodetic
conversion of ENU, not ENU up.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, cast

import numpy as np

from recon_core.config import Config
from recon_core.errors import ReconstructionError
from recon_core.euclidean.dsm import DsmAccumulator, fill_small_holes
from recon_core.euclidean.fusion import align_groups
from recon_core.euclidean.georef import enu_to_output, output_epsg
from recon_core.events import EventBus
from recon_core.geometry import affine
from recon_core.geometry.affine import apply_affine_3d
from recon_core.geometry.enu_map import EnuMap
from recon_core.geometry.geodesy import LocalFrame
from recon_core.io.las import write_las
from recon_core.io.layout import OutLayout
from recon_core.io.models import PointSource
from recon_core.io.ply import PlyWriter
from recon_core.io.raster import Grid, write_dsm, write_geotiff
from recon_core.io.site import Site, default_resolution

if TYPE_CHECKING:
    from recon_core.context import RunState


def output_grid(site: Site, xyh: np.ndarray, epsg: int, res: float) -> Grid:
    """site.json's bounds when given (in the output CRS), else the cloud's robust extent."""
    if site.hints.get("bounds") and int(site.hints.get("crs_epsg", epsg)) == epsg:
        return Grid.from_site_json({**site.hints, "resolution_m": res, "crs_epsg": epsg},
                                   site.root / "site.json")
    lo, hi = np.percentile(xyh[:, :2], [0.1, 99.9], axis=0)
    return Grid.from_points(np.stack([lo, hi]), res, epsg, margin=2 * res)


def make_dsm(site: Site, sources: dict[int, PointSource], maps: dict, frame: LocalFrame, gsd: float,
             cfg: Config, out: OutLayout, bus: EventBus | None = None,
             quality: dict[int, float] | None = None, geometry: dict[int, float] | None = None) -> dict:
    """Write cloud.ply (Euclidean, output CRS), dsm.tif and, with several groups, each group's
    own DSM; return the summary.

    Streams: ICP and the grid extent use evenly spread samples; then each group's cloud is read
    by chunks (upgrade, ICP refinement, conversion to the output CRS), appended to cloud.ply and
    filed into that group's DSM accumulator, which reduces one block of grid rows at a time;
    memory does not grow with the number of points. Nor with the grid: each group's DSM, the
    fused one and their filled copies are memory-mapped files in a work folder of OUT (removed
    at the end), fused, filled and written to GeoTIFF by strips of rows.

    Fusion of several groups (`fuse_groups`): each group's DSM without the cells only a weak
    pair's two-view points reach (dense `weak` marks); groups ranked by `quality` (their check
    points' vertical RMSE) and their noise: with `geometry` (group_geometry), one matching
    precision fitted to the groups' disagreement times each group's metres per pixel, else a
    per-group split of the disagreement (noise_from_pairs); ties by their number of precise
    cells; the best group is the reference, the others are brought
    onto it by a smooth correction and fill its holes, and where they agree within
    fusion_agree_sigmas the cell is their inverse-variance weighted mean. Each group's own DSM
    (written to dsm_groups/) keeps its weak-pair cells.
    """
    c = cfg.dsm
    maps = {g: m if isinstance(m, EnuMap) else EnuMap(np.asarray(m, np.float64)) for g, m in maps.items()}
    groups = [g for g in sorted(maps) if g in sources and len(sources[g])]
    if not groups:
        raise ReconstructionError("no upgraded group has a cloud")
    Ts, fusion, epsg, res, grid = _align_and_lay_out(site, sources, maps, frame, gsd, groups, c)
    total = sum(len(sources[g]) for g in groups)
    work = _GridWork(grid, out.root)

    def step(what: str) -> None:      # the grid's later steps take minutes on a large grid: said
        if bus is not None:
            bus.progress("dsm", total, total, f"{what} ({grid.width} x {grid.height} cells)")
    try:
        in_grid = _grid_points(sources, groups, Ts, maps, frame, epsg, grid, c, out, work, total, bus, step)
        step("comparing and fusing the date groups" if len(groups) > 1 else "counting the cells")
        fused = _fuse(work, groups, c, res, quality, geometry)
        raw_valid = count_rows(fused.H, np.isfinite, work.strip) / fused.H.size
        filled_buf = work.file("filled", np.float32)

        def filled(D: np.ndarray) -> np.ndarray:
            return fill_small_holes(D, max_hole_px=c.fill_holes_px, out=filled_buf, block_rows=work.strip) \
                if c.fill_holes_px > 0 else D

        step("filling small holes")
        H = filled(fused.H)
        valid = count_rows(H, np.isfinite, work.strip) / H.size
        agreement, groups_report = _write_products(H, filled, fused, work, grid, groups, sources, epsg, c, out,
                                                   quality, geometry, step)
    finally:
        work.close()
    return {"crs_epsg": epsg, "resolution_m": res, "width": grid.width, "height": grid.height,
            "points": int(total), "points_in_grid": int(in_grid), "valid_fraction_raw": raw_valid,
            "valid_fraction": valid, "stat": c.stat, "fusion": fusion,
            "fusion_rule": _fusion_rule(c, fused, groups), "group_order": fused.order, "groups": groups_report,
            "gsd_m": gsd, "agreement": agreement, "noise_model": _noise_model(fused, groups)}


def _align_and_lay_out(site: Site, sources: dict[int, PointSource], maps: dict[int, EnuMap], frame: LocalFrame,
                       gsd: float, groups: list[int], c) -> tuple[dict, dict, int, float, Grid]:
    """The groups' ICP refinements onto one another (none for one joint upgrade), the output
    CRS and resolution, and the grid over their evenly spread samples: (Ts, fusion report,
    epsg, res, grid)."""
    samples = {g: maps[g](sources[g].sample(c.icp_sample_points)) for g in groups}
    if len(groups) > 1 and all(maps[g].same(maps[groups[0]]) for g in groups):
        # one joint reconstruction upgraded by one H_A: the groups already share a frame, and
        # ICP between seasons would only move them by what differs (vegetation, shadows)
        Ts = {g: np.eye(4) for g in groups}
        fusion = {"reference_group": groups[0], "joint": True,
                  "icp": {str(g): {"applied": False, "reason": "one joint reconstruction and one "
                                   "upgrade: the groups share a frame"} for g in groups[1:]}}
    else:
        Ts, fusion = align_groups(samples, c, reference=max(groups, key=lambda g: len(sources[g])))
    epsg = output_epsg(site.hints, frame)
    res = float(c.resolution_m or site.hints.get("resolution_m") or default_resolution(gsd))
    extent = np.concatenate([apply_affine_3d(Ts[g], samples[g]) for g in groups])
    return Ts, fusion, epsg, res, output_grid(site, enu_to_output(extent, frame, epsg), epsg, res)


class _GridWork:
    """Every full-grid array of the DSM stage lives on disk (np.memmap in a work folder of OUT,
    removed at the end) and is read by strips of `strip` rows: memory holds strips, whatever the
    site's size."""

    def __init__(self, grid: Grid, root: Path):
        self.grid = grid
        self.dir = tempfile.TemporaryDirectory(prefix=".dsm_work_", dir=root)
        self.strip = max(64, min(1024, STRIP_CELLS // grid.width))      # rows per strip
        self.raw: dict[int, np.ndarray] = {}
        self.weak: dict[int, np.ndarray] = {}
        self.arrays: list[np.ndarray] = []

    def file(self, name: str, dtype) -> np.ndarray:
        path = Path(self.dir.name) / f"{name}.npy"
        arr = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=self.grid.shape)
        reserve_disk(path)
        self.arrays.append(arr)
        return arr

    def close(self) -> None:
        # let go of the memmaps (also those a traceback would keep) before removing their files
        self.raw.clear()
        self.weak.clear()
        self.arrays.clear()
        self.dir.cleanup()


def _grid_points(sources: dict[int, PointSource], groups: list[int], Ts: dict, maps: dict[int, EnuMap],
                 frame: LocalFrame, epsg: int, grid: Grid, c, out: OutLayout, work: _GridWork, total: int,
                 bus: EventBus | None, step) -> int:
    """Stream each group's cloud by chunks (upgrade, ICP refinement, output CRS) into cloud.ply and
    its DSM accumulator, then each group's reduced grid and weak-pair marks onto disk (work.raw,
    work.weak); returns the points that fell in the grid."""
    spill = out.root if total > c.spill_above_points else None
    accs = {g: DsmAccumulator(grid, stat=c.stat, spill_dir=spill) for g in groups}
    done = 0
    try:
        with PlyWriter(out.cloud, comments=(f"frame EPSG:{epsg} x y in metres, z height above "
                                            "the WGS84 ellipsoid in metres; date groups fused",)) as w:
            for g in groups:
                src = sources[g]
                for a in range(0, len(src), c.chunk_points):
                    b = min(a + c.chunk_points, len(src))
                    xyz, gray = src.read(a, b)
                    xyh = enu_to_output(apply_affine_3d(Ts[g], maps[g](xyz)), frame, epsg)
                    accs[g].add(xyh, src.tier(a, b))
                    w.append(xyh, gray[:, None])
                    done += len(xyz)
                    if bus is not None:
                        bus.progress("dsm", done, total, f"group {g}")
        in_grid = sum(a.n_points for a in accs.values())
        step("gridding the points")
        for g in groups:
            work.raw[g], work.weak[g] = work.file(f"raw_{g}", np.float32), work.file(f"weak_{g}", bool)
            for r0, r1, Hb, _, fb in accs[g].blocks():
                work.raw[g][r0:r1], work.weak[g][r0:r1] = Hb, fb
    finally:
        for acc in accs.values():
            acc.close()
    return in_grid


@dataclass
class _Fused:
    """The fused grid H (one group: its own), which group each cell came from (several groups),
    the groups' agreement, their order, noise, coverage and pairwise disagreement."""

    H: np.ndarray
    source: np.ndarray | None
    agree: np.ndarray | None
    order: list[int]
    noise: dict
    match_px: float | None
    coverage: dict[int, int]
    pairs: list
    block: int


def _fuse(work: _GridWork, groups: list[int], c, res: float, quality: dict[int, float] | None,
          geometry: dict[int, float] | None) -> _Fused:
    """Rank the groups and fuse their grids (fuse_groups); one group is its own DSM."""
    raw, weak, strip, shape = work.raw, work.weak, work.strip, work.grid.shape

    def precise_rows(g):     # without the cells only a weak pair's two-view points reach
        return lambda r0, r1: np.where(weak[g][r0:r1], np.float32(np.nan), raw[g][r0:r1])

    def weak_rows(g):
        return lambda r0, r1: np.where(weak[g][r0:r1], raw[g][r0:r1], np.float32(np.nan))

    precise = {g: RowView(shape, precise_rows(g), strip) for g in groups}
    block = int(round(c.fusion_correction_m / res)) if c.fusion_correction_m > 0 else 0
    pairs = pair_disagreement(precise, block)         # [] for one group
    noise, match_px = noise_from_pairs(groups, pairs, geometry)
    coverage = {g: count_rows(precise[g], np.isfinite, strip) for g in groups}
    order = rank_groups(groups, quality or {}, coverage, noise)
    if len(groups) == 1:
        return _Fused(raw[groups[0]], None, None, order, noise, match_px, coverage, pairs, block)
    agree = work.file("agree", np.float32)
    # every group's precise cells first; a weak pair's cells only where none has any
    fill = [RowView(shape, weak_rows(g), strip) for g in order] if c.fuse_weak_pair_cells else []
    H, source = fuse_groups([precise[g] for g in order] + fill, correct_block=block,
                            sigmas=[noise[g] for g in order] + [None] * len(fill),
                            agree_sigmas=c.fusion_agree_sigmas, fill_agreeing=c.fusion_fill_agreeing,
                            out=work.file("fused", np.float32),
                            source_out=work.file("source", np.int16), block_rows=strip,
                            agree_out=agree)
    return _Fused(H, source, agree, order, noise, match_px, coverage, pairs, block)


def _write_products(H: np.ndarray, filled, fused: _Fused, work: _GridWork, grid: Grid, groups: list[int],
                    sources: dict[int, PointSource], epsg: int, c, out: OutLayout,
                    quality: dict[int, float] | None, geometry: dict[int, float] | None, step) -> tuple:
    """dsm.tif, dsm_agreement.tif, cloud.laz and each group's own DSM (removing a previous run's
    that would not match); returns (the agreement summary, each group's report)."""
    strip = work.strip
    step("writing dsm.tif")
    write_dsm(out.dsm, H, grid)
    agreement = agreement_layer(fused.agree, H, strip) if fused.agree is not None else None
    if agreement is not None:
        assert fused.agree is not None           # the agreement layer is made of it
        write_geotiff(out.dsm_agreement, fused.agree, grid.transform, grid.crs, resampling="nearest",
                      description="date groups agreeing on the height of dsm.tif (0: a weak pair's "
                                  "two-view points or a filled small hole)")
    elif out.dsm_agreement.exists():              # a previous run's: it would not match
        out.dsm_agreement.unlink()
    if c.laz:
        step("writing cloud.laz")
        write_las(out.cloud, out.cloud_laz, epsg)
    elif out.cloud_laz.exists():                 # a previous run's: it would not match
        out.cloud_laz.unlink()
    groups_report = {}
    for g in out.group_dsms():                   # a previous run's, of groups not fused now
        if len(groups) == 1 or g not in groups:
            out.group_dsm(g).unlink()
    if len(groups) > 1:
        n_cells = grid.width * grid.height
        for k, g in enumerate(fused.order):
            step(f"writing group {g}'s own DSM")
            write_dsm(out.group_dsm(g), filled(work.raw[g]), grid)
            groups_report[str(g)] = {"rank": k, "quality_check_rmse_U_m": (quality or {}).get(g),
                                     "noise_m": fused.noise[g],
                                     "geometry_m_per_px": (geometry or {}).get(g),
                                     "points": int(len(sources[g])),
                                     "valid_fraction_raw": count_rows(work.raw[g], np.isfinite, strip) / n_cells,
                                     "precise_fraction": fused.coverage[g] / n_cells,
                                     "fused_cells_from_it": count_rows(fused.source, lambda v: v == k, strip) / n_cells,
                                     "fused_cells_from_its_weak_pair":
                                         count_rows(fused.source, lambda v: v == k + len(fused.order), strip) / n_cells}
    return agreement, groups_report


def _fusion_rule(c, fused: _Fused, groups: list[int]) -> str:
    """The fusion rule in words, as the report says it."""
    if len(groups) == 1:
        return "one group"
    return ("per cell, the best-ranked group with a precise value (ranked by the "
            "expected height error: check-point vertical RMSE and the DSM's noise, "
            + ("its geometry times one matching precision fitted to the groups' "
               "disagreement" if fused.match_px is not None else
               "the groups' disagreement split between them") +
            "; ties: the group with the most precise cells first)" +
            (f"; lower-ranked groups brought onto the fused surface by a smooth "
             f"correction ({c.fusion_correction_m:g} m blocks)" if fused.block else "") +
            (f"; where groups agree within {c.fusion_agree_sigmas:g} sigma, their "
             "inverse-variance weighted mean" if c.fusion_agree_sigmas > 0 else "") +
            (f"; a hole of the better groups filled only where {c.fusion_fill_agreeing} "
             "groups agree" if c.fusion_fill_agreeing > 1 and
             sum(fused.noise[g] is not None for g in groups) >= 2 else "") +
            ("; cells only a weak pair's two-view points reach, last"
             if c.fuse_weak_pair_cells else "; cells only a weak pair's two-view "
             "points reach are left out (they stay in each group's own DSM)"))


def _noise_model(fused: _Fused, groups: list[int]) -> dict | None:
    if len(groups) == 1:
        return None
    return {"matching_precision_px": fused.match_px,
            "rule": ("each group's geometry (metres per pixel of all its views) times one "
                     "matching precision fitted to the groups' disagreement") if fused.match_px is not None
                    else "the groups' disagreement split between them (three-cornered hat)",
            "pairs": [{"groups": [a, b], "disagreement_nmad_m": float(np.sqrt(v))} for a, b, v in fused.pairs]}


def agreement_layer(agree: np.ndarray, H: np.ndarray, block_rows: int = 1024) -> dict | None:
    """Complete fuse_groups' agreement counts (in place, by strips) for the final DSM H: 0 where
    H got a height after the fusion (a small hole filled), NaN where it has none. Returns the
    share of H's cells per count ({"0": f0, "1": f1, ...}, the layer's summary), or None when
    no cell has a count (no agreement test ran: no layer)."""
    counts: dict[int, int] = {}
    n_valid, step = 0, max(1, int(block_rows))
    for r0 in range(0, H.shape[0], step):
        r1 = min(H.shape[0], r0 + step)
        a = np.array(agree[r0:r1], dtype=np.float32)
        h = np.isfinite(np.asarray(H[r0:r1]))
        a[h & ~np.isfinite(a)] = 0.0
        a[~h] = np.nan
        agree[r0:r1] = a
        v = a[h].astype(np.int64)
        n_valid += len(v)
        for k, c in zip(*np.unique(v, return_counts=True)):
            counts[int(k)] = counts.get(int(k), 0) + int(c)
    if not any(k > 0 for k in counts):
        return None
    return {"file": "dsm_agreement.tif",
            "meaning": "per cell of dsm.tif, the number of date groups whose precise DSM agrees with its "
                       "height (within dsm.fusion_agree_sigmas); 0: a weak pair's two-view points or a filled "
                       "small hole",
            "fraction_of_valid_cells": {str(k): c / max(n_valid, 1) for k, c in sorted(counts.items())}}


def reserve_disk(path: Path) -> None:
    """Allocate a (sparse) file's blocks now: a full disk is then an OSError here, not a SIGBUS
    when a page of its memory map is first written."""
    if hasattr(os, "posix_fallocate"):
        with open(path, "r+b") as f:
            os.posix_fallocate(f.fileno(), 0, os.fstat(f.fileno()).st_size)


STRIP_CELLS = 8_000_000      # cells per strip of rows when fusing and filling grids on disk


def count_rows(D, test, block_rows: int = 1024) -> int:
    """How many cells of a (possibly disk-backed) grid pass `test`, read by strips."""
    return int(sum(int(np.count_nonzero(test(np.asarray(D[r0:r0 + block_rows]))))
                   for r0 in range(0, D.shape[0], block_rows)))


def rank_groups(groups: list[int], quality: dict[int, float], size: dict[int, int],
                noise: dict[int, float | None] | None = None) -> list[int]:
    """Best first, by the expected height error of each group's DSM: sqrt(q^2 + s^2) with q its
    check points' vertical RMSE (georeferencing) and s its noise (group_noise); a group without
    q after those with one; ties and the rest by `size` (its precise cells), largest first."""
    noise = noise or {}

    def key(g):
        q, s = quality.get(g), noise.get(g)
        s = float(s) if s is not None and np.isfinite(s) else 0.0
        if q is not None and np.isfinite(q):
            return (0, float(np.hypot(q, s)), -size[g])
        return (1, s, -size[g])
    return sorted(groups, key=key)


def group_geometry(models: dict, maps: dict) -> dict[int, float]:
    """Each group's height precision from its acquisition geometry alone: metres per pixel of
    matching error (affine.views_spread) of all its images' views together, in the upgraded
    (metric) frame. One view per image: the median linear part of its registered tiles'
    cameras, mapped by the group's H_A (its bend warps, smooth and small, left aside). A group
    of one view, or whose views do not fix a point, is left out."""
    out = {}
    for g, m in models.items():
        if g not in maps:
            continue
        M = maps[g]
        try:
            Hi = np.linalg.inv(affine.as_4x4(M.H if isinstance(M, EnuMap) else M))
            per: dict[str, list] = {}
            for t in np.flatnonzero(m.registered):
                per.setdefault(m.tiles[t].image, []).append((np.asarray(m.cams[t]) @ Hi)[:2, :3])
            if len(per) < 2:
                continue
            spread = affine.views_spread([np.median(np.stack(v), 0) for v in per.values()])
        except (np.linalg.LinAlgError, ValueError):      # a degenerate map or cameras: no geometry
            continue
        if np.isfinite(spread):
            out[int(g)] = spread
    return out


def pair_disagreement(dsms: Mapping[int, np.ndarray | RowView], correct_block: int = 0, min_overlap: int = 2000,
                      max_cells: int = 4_000_000) -> list[tuple[int, int, float]]:
    """(g_a, g_b, v) for each pair of DSMs sharing >= min_overlap cells: v = (1.4826 MAD of
    D_b - D_a)^2 after the smooth relative correction (fuse_groups' step 1), the variance of
    their disagreement. Grids above max_cells are decimated evenly first."""
    keys = sorted(dsms)
    step = max(1, int(np.ceil(np.sqrt(next(iter(dsms.values())).size / max_cells)))) if dsms else 1
    small = {g: dsms[g][::step, ::step] for g in keys}
    block = max(1, correct_block // step) if correct_block > 0 else 0
    out = []
    for a in range(len(keys)):
        for b in range(a + 1, len(keys)):
            A, B = small[keys[a]], small[keys[b]]
            if block:
                B = B - relative_correction(B, A, block, min_overlap)
            both = np.isfinite(A) & np.isfinite(B)
            if int(both.sum()) < min_overlap:
                continue
            d = (B - A)[both].astype(np.float64)
            out.append((int(keys[a]), int(keys[b]), float((1.4826 * np.median(np.abs(d - np.median(d)))) ** 2)))
    return out


def noise_from_pairs(keys: list[int], pairs: list[tuple[int, int, float]],
                     geometry: dict[int, float] | None = None) -> tuple[dict[int, float | None], float | None]:
    """Each group's DSM height noise (metres) from the pairs' disagreement (pair_disagreement).
    Returns ({group: noise or None}, the matching precision in pixels or None).

    With every overlapping group's geometry (group_geometry, metres per pixel): one matching
    precision k (pixels) for all, the same sensor and matcher, fitted to v_ab = k^2 (a_a^2 +
    a_b^2) as the ratio of sums (least squares weighted by 1 / (a_a^2 + a_b^2)); each group's
    noise is k a_g, also for a group that overlaps none. When any overlapping group lacks a
    geometry, all fall back to the split below (the report's noise_model says which). This is the default: a per-group split of the disagreement (below) assumes the
    groups' errors independent, and they are not (shared occlusions, edges and relief lost
    by every matcher: correlation 0.5-0.6 between wide3's groups); a group whose errors lie
    between two others' then agrees best with both and is taken for the most precise.

    Without geometry, the split (a three-cornered hat): v_ab = s_a^2 + s_b^2; three or more
    groups: the s^2 by least squares over the pairs (floored at a tenth of the mean); two
    groups share v / 2 each; a group that overlaps none gets None.
    """
    out: dict[int, float | None] = {g: None for g in keys}
    if not pairs:
        return out, None
    geo = geometry or {}
    seen = sorted({g for a, b, _ in pairs for g in (a, b)})
    if all(g in geo and np.isfinite(geo[g]) and geo[g] > 0 for g in seen):
        k2 = sum(v for _, _, v in pairs) / sum(geo[a] ** 2 + geo[b] ** 2 for a, b, _ in pairs)
        k = float(np.sqrt(k2))
        for g in keys:
            if g in geo and np.isfinite(geo[g]) and geo[g] > 0:
                out[g] = k * float(geo[g])
        return out, k
    col = {g: i for i, g in enumerate(seen)}
    M = np.zeros((len(pairs), len(seen)))
    for r, (a, b, _) in enumerate(pairs):
        M[r, [col[a], col[b]]] = 1.0
    v = np.array([p[2] for p in pairs])
    if len(pairs) >= 3 and np.linalg.matrix_rank(M) == len(seen):
        s2 = np.linalg.lstsq(M, v, rcond=None)[0]
        s2 = np.maximum(s2, 0.1 * float(v.mean()) / 2)
    else:                                   # pairs alone: each shares its pairs' mean equally
        s2 = (M * v[:, None]).sum(0) / M.sum(0) / 2
    for g in seen:
        out[g] = float(np.sqrt(s2[col[g]]))
    return out, None


def group_noise(dsms: dict[int, np.ndarray], correct_block: int = 0, min_overlap: int = 2000,
                max_cells: int = 4_000_000, geometry: dict[int, float] | None = None
                ) -> dict[int, float | None]:
    """Each DSM's height noise (metres) from how the groups disagree with one another
    (pair_disagreement, then noise_from_pairs: with `geometry`, one matching precision scaled
    by each group's geometry; without, a per-group split)."""
    keys = [int(g) for g in sorted(dsms)]
    return noise_from_pairs(keys, pair_disagreement(dsms, correct_block, min_overlap, max_cells),
                            geometry)[0]


def fuse_groups(dsms: list, correct_block: int = 0, min_overlap: int = 2000,
                sigmas: list[float | None] | None = None, agree_sigmas: float = 2.5,
                out: np.ndarray | None = None, source_out: np.ndarray | None = None,
                block_rows: int = 1024, fill_agreeing: int = 1,
                agree_out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fuse per-group DSMs given best first. Returns (H, index of the DSM each cell's reference
    value came from, -1 where none has one).

    1. The reference surface: per cell, the first DSM (in the given order) with a value. With
       `correct_block` > 0 (cells), a lower-ranked DSM is first brought onto the fused surface
       where they overlap: the difference's median per block of correct_block x correct_block
       cells, spread to blocks without overlap from the nearest ones and smoothed, is subtracted
       before it fills holes. A smooth bend of a worse group (ICP is rigid) then no longer shows
       where it fills in; its own detail stays. Needs `min_overlap` common cells, else no
       correction.
    2. With `sigmas` (each DSM's noise, metres; None: that DSM only fills): where several
       (corrected) DSMs agree with the reference within agree_sigmas * sqrt(s_ref^2 + s_k^2),
       the cell is their inverse-variance weighted mean: independent matchings of the same
       ground average their noise down; a DSM that disagrees (a shadow, a moved car, a
       mismatch) is left out of that cell.
    3. With `fill_agreeing` > 1 (and step 2's sigmas): a cell filled by a lower-ranked DSM with
       a noise (not the reference's, not a noiseless fill such as a weak pair's) is kept only
       where at least that many DSMs with a noise, the filling one included, agree there; the
       others are left empty (-1 in the source). Cells only one group sees are mostly the hard
       ones (occlusions, building edges): measured on wide3, 1.1-1.8 m median error.
    With `agree_out` (float32, the grid's shape, may be disk-backed): per cell of H, how many
    DSMs with a noise agree there in step 2 (the reference's own included: >= 1; 0 where the
    value is a noiseless fill's, such as a weak pair's), NaN where H has none; all NaN when
    step 2 does not run (no agreement test).

    Works by strips of about `block_rows` rows (a multiple of correct_block): the DSMs (taken as
    float32) may be disk-backed (np.memmap, or RowView), and so may `out` (float32) and
    `source_out` (int16); memory holds a few strips and the coarse correction grids, whatever
    the grid's size. The result does not depend on the strips.
    """
    h, w = shape = tuple(dsms[0].shape)
    step = max(1, int(block_rows))          # strips of whole correction blocks
    step = max(correct_block, step // correct_block * correct_block) if correct_block > 0 else step
    spans = [(r0, min(h, r0 + step)) for r0 in range(0, h, step)]
    H = out if out is not None else np.empty(shape, np.float32)
    source = source_out if source_out is not None else np.empty(shape, np.int16)
    for r0, r1 in spans:
        H[r0:r1] = np.nan
        source[r0:r1] = -1
        if agree_out is not None:
            agree_out[r0:r1] = np.nan
    coarse: list[np.ndarray | None] = [None] * len(dsms)

    def corrected(k: int, r0: int, r1: int) -> np.ndarray:
        D = np.asarray(dsms[k][r0:r1], dtype=np.float32)
        ck = coarse[k]
        if ck is not None:
            D = (D - correction_rows(ck, correct_block, r0, r1, w)).astype(np.float32)
        return D

    for k in range(len(dsms)):
        if k > 0 and correct_block > 0:
            coarse[k] = correction_surface(dsms[k], H, correct_block, min_overlap, block_rows=step)
        for r0, r1 in spans:
            D, Hb, sb = corrected(k, r0, r1), H[r0:r1], source[r0:r1]
            take = np.isnan(Hb) & np.isfinite(D)
            Hb[take] = D[take]
            sb[take] = k
    sig = [None if s is None or not np.isfinite(s) or s <= 0 else float(s) for s in (sigmas or [])]
    if agree_sigmas <= 0 or len(sig) != len(dsms) or sum(s is not None for s in sig) < 2:
        return H, source
    for r0, r1 in spans:
        Hb, sb = H[r0:r1], np.asarray(source[r0:r1])
        n_agree = _average_agreeing(Hb, sb, sig, lambda k: corrected(k, r0, r1), agree_sigmas)
        if fill_agreeing > 1:
            noisy_fill = np.zeros(Hb.shape, bool)
            for k, s in enumerate(sig):
                if k > 0 and s is not None:
                    noisy_fill |= sb == k
            drop = noisy_fill & (n_agree < fill_agreeing)
            Hb[drop] = np.nan
            source[r0:r1][drop] = -1
        if agree_out is not None:
            agree_out[r0:r1] = np.where(np.isfinite(Hb), n_agree, np.nan)
    return H, source


def _average_agreeing(Hb: np.ndarray, sb: np.ndarray, sig: list, corrected, agree_sigmas: float) -> np.ndarray:
    """fuse_groups' step 2 on one strip: where DSMs with a noise agree with the reference within
    agree_sigmas of their combined noise, the cell (Hb, in place) becomes their inverse-variance
    weighted mean; returns how many agree per cell. corrected(k): DSM k's strip, corrected."""
    # each cell's reference noise: that of the DSM its value came from
    s_ref = np.full(Hb.shape, np.nan, np.float32)
    for k, s in enumerate(sig):
        s_ref[sb == k] = np.nan if s is None else s
    num = np.zeros(Hb.shape, np.float32)
    den = np.zeros(Hb.shape, np.float32)
    n_agree = np.zeros(Hb.shape, np.int16)
    for k, s in enumerate(sig):
        if s is None:
            continue
        D = corrected(k)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(D) & (np.abs(D - Hb) <= agree_sigmas * np.sqrt(s_ref ** 2 + s * s))
        wk = 1.0 / (s * s)
        num[ok] += wk * D[ok]
        den[ok] += wk
        n_agree[ok] += 1
    avg = den > 0
    Hb[avg] = num[avg] / den[avg]
    return n_agree


def correction_surface(D, ref, block: int, min_overlap: int = 2000,
                       block_rows: int | None = None) -> np.ndarray | None:
    """The coarse grid (one value per block x block cells, float32) of the smooth difference
    D - ref: per-block medians where >= 5 % of the block's cells overlap, nearest-block
    extrapolation, a Gaussian of one block. None when they share fewer than min_overlap cells.
    Read by strips of block_rows rows (rounded to whole blocks; None: all at once)."""
    from scipy import ndimage

    h, w = D.shape
    nb_r, nb_c = -(-h // block), -(-w // block)
    step = h if not block_rows else max(block, int(block_rows) // block * block)
    coarse = np.full(nb_r * nb_c, np.nan)
    need = max(8, block * block // 20)             # >= 5 % of the block's cells overlap
    n_both = 0
    for r0 in range(0, h, step):
        Db = np.asarray(D[r0:r0 + step])
        Rb = np.asarray(ref[r0:r0 + step])
        both = np.isfinite(Db) & np.isfinite(Rb)
        r, c = np.nonzero(both)
        n_both += len(r)
        key = (r0 // block + r // block) * nb_c + (c // block)
        diff = (Db[r, c] - Rb[r, c]).astype(np.float64)
        order = np.argsort(key, kind="stable")
        key, diff = key[order], diff[order]
        cuts = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True])
        for a, b in zip(cuts[:-1], cuts[1:]):
            if b - a >= need:
                coarse[key[a]] = np.median(diff[a:b])
    if n_both < min_overlap:
        return None
    coarse = coarse.reshape(nb_r, nb_c)
    have = np.isfinite(coarse)
    if not have.any():
        return None
    idx = cast(np.ndarray, ndimage.distance_transform_edt(~have, return_distances=False, return_indices=True))
    coarse = coarse[idx[0], idx[1]]
    return ndimage.gaussian_filter(coarse, 1.0, mode="nearest").astype(np.float32)


def _bilinear_taps(n_out: int, start: int, stop: int, block: int, n_src: int):
    """For output cells start:stop of an up-sampling by `block` of n_src coarse cells (cell
    centres aligned, as cv2.resize's INTER_LINEAR): the two source cells and the weight of the
    second, computed from each cell's index in the whole grid (not in a piece of it)."""
    f = (np.arange(start, stop, dtype=np.float64) + 0.5) / block - 0.5
    i0 = np.floor(f).astype(np.int64)
    t = f - i0
    i1 = np.clip(i0 + 1, 0, n_src - 1)
    t = np.where(i0 < 0, 0.0, np.where(i0 >= n_src - 1, 0.0, t))
    i0 = np.clip(i0, 0, n_src - 1)
    return i0, i1, t


def correction_rows(coarse: np.ndarray, block: int, r0: int, r1: int, width: int) -> np.ndarray:
    """Rows r0:r1 (and the first `width` columns) of the bilinear up-sampling by `block` of a
    coarse correction grid. Each value depends only on its own row and column in the whole
    grid, so any split into strips gives the same surface bit for bit. float32."""
    nb_r, nb_c = coarse.shape
    ri0, ri1, rt = _bilinear_taps(nb_r * block, r0, r1, block, nb_r)
    ci0, ci1, ct = _bilinear_taps(nb_c * block, 0, width, block, nb_c)
    C = coarse.astype(np.float64)
    rows = C[ri0] * (1.0 - rt)[:, None] + C[ri1] * rt[:, None]            # (r1 - r0, nb_c)
    return (rows[:, ci0] * (1.0 - ct) + rows[:, ci1] * ct).astype(np.float32)


def relative_correction(D: np.ndarray, ref: np.ndarray, block: int, min_overlap: int = 2000) -> np.ndarray:
    """A smooth surface of the difference D - ref (full grid, float32; zeros when they share
    fewer than min_overlap cells): correction_surface up-sampled."""
    coarse = correction_surface(D, ref, block, min_overlap)
    if coarse is None:
        return np.zeros(D.shape, np.float32)
    return correction_rows(coarse, block, 0, D.shape[0], D.shape[1])


class RowView:
    """A (height, width) float32 grid computed strip by strip: `rows(r0, r1)` gives rows r0:r1.
    Indexing supports row slices and (row slice, column slice), as fuse_groups and group_noise
    use them, so a masked or combined DSM need not exist in memory as a whole."""

    def __init__(self, shape: tuple[int, int], rows, block_rows: int = 1024):
        self.shape, self.rows, self.block_rows = tuple(shape), rows, max(1, int(block_rows))

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]

    def __getitem__(self, key) -> np.ndarray:
        rs, cs = key if isinstance(key, tuple) else (key, slice(None))
        start, stop, step = rs.indices(self.shape[0])
        if step == 1:
            return self.rows(start, max(start, stop))[:, cs]
        want = np.arange(start, stop, step)
        if not len(want):
            return self.rows(0, 0)[:, cs]
        per = max(1, self.block_rows // step)             # wanted rows per strip read
        parts = []
        for a in range(0, len(want), per):
            sel = want[a:a + per]
            parts.append(self.rows(int(sel[0]), int(sel[-1]) + 1)[sel - sel[0]][:, cs])
        return np.concatenate(parts)


def point_sources(state, bus: EventBus) -> dict[int, PointSource]:
    """Each upgraded group's dense cloud (on disk), or its sparse points when it has none."""
    sources = {}
    for g in state.upgrade.maps:
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


def group_quality(upgrade_report: dict) -> dict[int, float]:
    """Each upgraded group's check-point vertical RMSE (leave-one-out when it has no check
    point), from the upgrade stage's report; groups with neither are left out."""
    out = {}
    for g, r in (upgrade_report.get("groups") or {}).items():
        st = r.get("stats") or {}
        for name in ("check", "loo"):
            figs = st.get(name) or {}
            v = figs.get("rmse_U_m")
            if figs.get("n") and v is not None and np.isfinite(v):
                out[int(g)] = float(v)
                break
    return out


def run(state: RunState, bus: EventBus) -> dict:
    if state.upgrade is None:
        raise ReconstructionError("the DSM needs the upgrade stage")
    maps, frame = state.upgrade
    up = state.report.get("stages", {}).get("upgrade", {})
    ups = up.get("groups", {})
    gsd = min((v["gsd_m"] for v in ups.values() if "gsd_m" in v), default=0.5)
    return make_dsm(state.site, point_sources(state, bus), maps, frame, gsd, state.cfg, state.layout, bus,
                    quality=group_quality(up), geometry=dense_geometry(state, maps))


def dense_geometry(state, maps: dict) -> dict[int, float]:
    """group_geometry of the groups whose DSM comes from their dense cloud: a group that fell
    back to its sparse points is not the same matcher, and would bias the shared precision."""
    return {g: a for g, a in group_geometry(state.models, maps).items() if state.dense.get(g) is not None}


def load(state) -> None:
    pass

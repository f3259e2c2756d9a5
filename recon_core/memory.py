"""How much memory each stage will need, estimated before any compute, and the refusal of a run
that cannot fit.

A stage that allocates by grid or by image is estimated from what the pre-flight knows: the
images' sizes, the DSM grid (site.json's bounds and resolution, else the images' footprints, else
their size), the ground truth's grid, the configuration (dense workers, the MGM volume cap,
chunk sizes). The figures are anonymous memory (what the machine must have: the clouds and the
DSM stage's grids are memory-mapped files the kernel can drop), of the run's process and its
dense workers. The coefficients are measured (bench/bench_memory.py prints the estimate against
the measured peak per stage; docs/benchmarks.md has the figures).

`check_memory` refuses, before any compute, a run whose largest stage would need more than the
machine has available, naming the stage and what to change.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from recon_core.errors import InputError

MB = 1 << 20
# Measured (bench/bench_memory.py on `tiny` and `demo`, DSM grids of 1.9e5 to 1.2e8 cells,
# ground truths of 1.9e5 to 7.4e7 cells, 2026-11-28):
BASE_MB = 180.0              # the run's process: the interpreter, numpy, GDAL, OpenCV, numba's kernels
SPARSE_BASE_MB = 110.0       # ... before the sparse stage has loaded its own libraries
SPARSE_MB_PER_MPX = 12.0     # keypoints, matches, tracks and the adjustment per Mpx of the group's images
SPARSE_BLOCK_BYTES = 40.0    # per pixel of a detection block (float window, 8-bit copy, SIFT's pyramid)
DENSE_WORKER_BASE_MB = 150.0  # a dense worker's own interpreter and libraries
DENSE_TILE_BYTES = 60.0      # per pixel of a tile pair's windows (images, rectified pairs, disparities)
MGM_VOLUME_BYTES = 768.0     # per tile pixel: MGM's 3 cost volumes over about 128 disparities, 2 bytes
POINTS_PER_PIXEL = 0.5       # dense points per pixel of a date group's images
DSM_POINT_BYTES = 140.0      # per point of a chunk streamed into the grid (coordinates, cells, sorting)
DSM_STRIP_BYTES = 12.5       # per cell of a strip of rows (fusion, filling), for each date group
EVAL_FIXED_MB = 340.0        # the evaluation's alignment search (batches of shifts) and maps
EVAL_GT_BYTES = 30.0         # per ground-truth cell (the grids, the resampled DSMs, errors, masks)
EVAL_DSM_BYTES = 12.0        # per cell of the DSM as the evaluation reads it (averaged down)
STRIP_CELLS = 8_000_000      # the DSM stage's strips (recon_core.euclidean.dsm_stage.STRIP_CELLS)
HEADROOM = 0.9               # a stage may use this share of the memory available
OFF_VARIABLE = "AEREC_MEMORY_CHECK"   # set to "off": the run is not refused for its estimate


@dataclass
class StageMemory:
    stage: str
    mb: float
    what: str                # what drives it, in words


def available_mb() -> float | None:
    """MemAvailable (Linux), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def dsm_cells(site, cfg) -> tuple[float, str]:
    """The DSM grid's cells as the pre-flight can know them, and how it knows."""
    res = cfg.dsm.resolution_m or site.hints.get("resolution_m")
    b = site.hints.get("bounds")
    if b and res:
        return (b[2] - b[0]) * (b[3] - b[1]) / res ** 2, "site.json's bounds and resolution"
    from recon_core.io.footprints import image_footprints

    foot = image_footprints(site)
    res = res or 0.5
    if foot:
        from recon_core.geometry.geodesy import LocalFrame

        ll = np.concatenate([f for _, f in foot])
        en = LocalFrame(float(ll[:, 0].mean()), float(ll[:, 1].mean())).geodetic_to_enu(
            np.c_[ll, np.zeros(len(ll))])
        area = float(np.ptp(en[:, 0]) * np.ptp(en[:, 1]))
        return area / res ** 2, "the images' footprints"
    px = max(im.width * im.height for im in site.images)
    return px * (0.5 / res) ** 2, "the largest image at 0.5 m"


def gt_cells(site) -> float:
    if site.gt_dsm is None:
        return 0.0
    import rasterio

    from recon_core.evaluation.evaluate import MAX_EVAL_CELLS

    with rasterio.open(site.gt_dsm) as ds:
        return float(min(ds.width * ds.height, MAX_EVAL_CELLS))


def estimate(site, cfg) -> list[StageMemory]:
    """Each stage's estimated peak (anonymous memory, MB)."""
    from recon_core.model.grouping import group_by_date

    groups = group_by_date(site.images, cfg.grouping.max_gap_days, cfg.grouping.max_span_days)
    group_px = max(sum(im.width * im.height for im in g.images) for g in groups)
    mpx = group_px / 1e6
    block = min(cfg.features.detect_block, max(max(im.width, im.height) for im in site.images))
    sparse_own = SPARSE_MB_PER_MPX * mpx + SPARSE_BLOCK_BYTES * block ** 2 / MB
    sparse = SPARSE_BASE_MB + sparse_own
    workers = max(1, cfg.dense.workers or _cores())
    d = cfg.tiling.tile_size
    volume = min(cfg.mgm.max_volume_mb, MGM_VOLUME_BYTES * d * d / MB) if cfg.dense.matcher == "mgm" else 0.0
    per_worker = DENSE_WORKER_BASE_MB + DENSE_TILE_BYTES * (2 * d) ** 2 / MB + volume
    dense = BASE_MB + workers * per_worker
    cells, how = dsm_cells(site, cfg)
    width = np.sqrt(cells)
    points = POINTS_PER_PIXEL * group_px
    # the run's process keeps what the sparse stage built (its models) through the later stages
    kept = BASE_MB + sparse_own
    dsm = (kept + DSM_POINT_BYTES * min(points, cfg.dsm.chunk_points) / MB
           + DSM_STRIP_BYTES * min(cells, STRIP_CELLS) * max(1, len(groups)) / MB)
    out = [StageMemory("sparse", sparse, f"{mpx:.0f} Mpx in the largest date group"),
           StageMemory("dense", dense, f"{workers} worker(s), tiles of {d} px"
                       + (f", MGM volumes of {volume:.0f} MB" if volume else "")),
           StageMemory("dsm", dsm, f"a grid of {cells:.3g} cells (from {how}), read by strips, "
                                   f"about {points:.2g} points a group")]
    g = gt_cells(site)
    if g:
        import rasterio

        from recon_core.evaluation.evaluate import read_factor

        res = cfg.dsm.resolution_m or site.hints.get("resolution_m") or 0.5
        with rasterio.open(site.gt_dsm) as ds:
            gt_res = float(ds.transform.a)
        f = read_factor(int(width), int(width), res, finer_than=gt_res)
        read = cells / f ** 2
        out.append(StageMemory("eval", kept + EVAL_FIXED_MB + EVAL_GT_BYTES * g / MB + EVAL_DSM_BYTES * read / MB,
                               f"a ground truth of {g:.3g} cells, the DSM read as {read:.3g}"))
    return out


def _cores() -> int:
    import os

    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def check_memory(site, cfg, stages, where=None) -> list[StageMemory]:
    """Refuse (InputError) a run whose `stages` (the names the run will compute) would need more
    memory than the machine has available; returns the estimates."""
    est = estimate(site, cfg)
    have = available_mb()
    if have is None or os.environ.get(OFF_VARIABLE, "").lower() in ("off", "0", "no"):
        return est
    for e in est:
        if e.stage not in stages or (e.stage == "dense" and cfg.dense.scheduler):
            continue                   # resumed, or the dense work runs on the Dask workers
        if e.mb > HEADROOM * have:
            hint = {"dense": "fewer dense workers (--workers) or a smaller mgm.max_volume_mb",
                    "dsm": "a coarser resolution_m or smaller bounds in site.json",
                    "eval": "a coarser resolution_m in site.json, or a smaller ground truth",
                    "sparse": "smaller images (a VRT window of the part to reconstruct)"}[e.stage]
            place = where if where is not None or e.stage not in ("dsm", "eval") else (
                site.root / "site.json" if (site.root / "site.json").exists() else None)
            raise InputError(place, f"the {e.stage} stage would need about {e.mb / 1024:.1f} GB ({e.what}); "
                                    f"this machine has {have / 1024:.1f} GB available: {hint} (to try anyway: "
                                    f"{OFF_VARIABLE}=off)")
    return est

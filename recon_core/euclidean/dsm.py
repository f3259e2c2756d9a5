"""Rasterising Euclidean clouds into a DSM grid (recon_core.io.raster.Grid) and filling small holes.

Cell statistic (`rasterize(stat=...)`): the default is the **median** of the heights falling in a
cell. It is unbiased where a cell straddles a roof edge (the cell takes the height of the larger
part, as a ground-truth DSM sampled at the cell centre does) and rejects isolated outliers on
both sides. "upper_median" (the 75th percentile) keeps roof edges sharper when walls and ground
points outnumber roof points near an edge (at the cost of fattening buildings by part of a cell)
and still rejects isolated high outliers; "max" is the lidar-style first-return statistic and
is outlier-sensitive; "mean" and "min" are there for comparisons.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Iterator, cast

import numpy as np

from recon_core.io.raster import Grid

STATS = {"median": 0.5, "upper_median": 0.75, "max": None, "min": None, "mean": None}


# --------------------------------------------------------------------------------------------
# Rasterisation
# --------------------------------------------------------------------------------------------
def _reduce_sorted(lin: np.ndarray, h: np.ndarray,
                   stat: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-cell statistic of heights.

    Args:
        lin: (n,) linear cell indices; h: (n,) float64 heights.
        stat: one of STATS.
    Returns:
        cells (k,) unique cell indices, values (k,) float64, counts (k,) int64.
    """
    order = np.lexsort((h, lin))                         # by cell, then by height
    lin, h = lin[order], h[order]
    start = np.flatnonzero(np.r_[True, lin[1:] != lin[:-1]])
    counts = np.diff(np.r_[start, len(lin)])
    cells = lin[start]
    if stat == "max":
        return cells, h[start + counts - 1], counts
    if stat == "min":
        return cells, h[start], counts
    if stat == "mean":
        return cells, np.add.reduceat(h, start) / counts, counts
    pos = STATS[stat] * (counts - 1)                     # linear interpolation, as np.percentile
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, counts - 1)
    frac = pos - lo
    return cells, h[start + lo] + frac * (h[start + hi] - h[start + lo]), counts


def _check_stat(stat: str) -> None:
    if stat not in STATS:
        raise ValueError(f"unknown cell statistic {stat!r}; choose one of {sorted(STATS)}")


def rasterize(xyz: np.ndarray, grid: Grid, *, stat: str = "median") -> tuple[np.ndarray, np.ndarray]:
    """Rasterise a cloud into a DSM in one pass.

    Args:
        xyz: (n, 3) points (x, y, h) in the grid's CRS; non-finite points are ignored.
        grid: the output grid; points outside it are ignored.
        stat: cell statistic (default "median"; see the module docstring).
    Returns:
        H: (height, width) float32, NaN where no point fell; count: (height, width) int32.
    """
    _check_stat(stat)
    xyz = np.asarray(xyz)
    row, col, h = _points_in_grid(xyz, grid)
    H = np.full(grid.shape, np.nan, dtype=np.float32)
    count = np.zeros(grid.shape, dtype=np.int32)
    if len(h):
        cells, vals, counts = _reduce_sorted(row * grid.width + col, h, stat)
        H.flat[cells] = vals
        count.flat[cells] = counts
    return H, count


def _points_in_grid(xyz: np.ndarray, grid: Grid,
                    extra: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """(row, col, h) of the finite points of (n, 3) xyz that fall inside the grid, and `extra`'s
    values of those points when given."""
    if xyz.ndim != 2 or xyz.shape[1] < 3:
        raise ValueError(f"expected (n, 3) points, got shape {xyz.shape}")
    row, col = grid.cell_of(xyz[:, 0], xyz[:, 1])
    h = xyz[:, 2].astype(np.float64)
    keep = grid.contains(row, col) & np.isfinite(h)
    if extra is None:
        return row[keep], col[keep], h[keep]
    return row[keep], col[keep], h[keep], np.asarray(extra)[keep]


class DsmAccumulator:
    """Streaming rasteriser: feed chunks of points, get the same DSM as `rasterize`.

    Each point is reduced to (cell index within its block, height) and filed under its block of
    `block_rows` grid rows, so the caller can drop each chunk after `add`. With `spill_dir` the
    per-block values go to files on disk (12 bytes per point) instead of memory. `finish` then
    reduces one block at a time with the same code as `rasterize`, so results are identical.

    Tiers: points added with tier 1 (fallbacks: a weak pair's two-view points) count only in
    cells where no tier-0 point falls; there the cell takes the statistic of its tier-1 points.
    """

    def __init__(self, grid: Grid, *, stat: str = "median", block_rows: int = 512,
                 spill_dir: str | Path | None = None):
        _check_stat(stat)
        self.grid, self.stat, self.block_rows = grid, stat, max(1, int(block_rows))
        self.n_blocks = math.ceil(grid.height / self.block_rows)
        self.n_points = 0
        self._mem: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
        self._tmp = None
        self._idx_dtype = "<i4" if 2 * self.block_rows * grid.width < 2**31 else "<i8"
        if spill_dir is not None:
            self._tmp = tempfile.TemporaryDirectory(prefix="dsm_blocks_", dir=spill_dir)

    def add(self, xyz: np.ndarray, tier: np.ndarray | None = None) -> None:
        """File a chunk of (n, 3) points (x, y, h in the grid's CRS) under their blocks; `tier`
        (n,) 0 or 1 per point (None: all 0)."""
        xyz = np.asarray(xyz)
        row, col, h, t = _points_in_grid(xyz, self.grid, np.zeros(len(xyz), np.int64)
                                         if tier is None else np.asarray(tier, np.int64))
        if not len(h):
            return
        self.n_points += len(h)
        block = row // self.block_rows
        # two slots per cell, tier 0 then tier 1
        local = 2 * ((row - block * self.block_rows) * self.grid.width + col).astype(np.int64) + t
        order = np.argsort(block, kind="stable")
        block, local, h = block[order], local[order], h[order]
        cuts = np.flatnonzero(np.r_[True, block[1:] != block[:-1], True])
        for a, b in zip(cuts[:-1], cuts[1:]):
            self._store(int(block[a]), local[a:b], h[a:b])

    def _store(self, b: int, local: np.ndarray, h: np.ndarray) -> None:
        if self._tmp is None:
            self._mem.setdefault(b, []).append((local.copy(), h.copy()))
            return
        base = Path(self._tmp.name) / f"b{b:06d}"
        with open(f"{base}.idx", "ab") as f:
            local.astype(self._idx_dtype).tofile(f)
        with open(f"{base}.h", "ab") as f:
            h.astype("<f8").tofile(f)

    def _load(self, b: int) -> tuple[np.ndarray, np.ndarray] | None:
        if self._tmp is None:
            parts = self._mem.pop(b, None)
            if not parts:
                return None
            return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        base = Path(self._tmp.name) / f"b{b:06d}"
        if not os.path.exists(f"{base}.h"):
            return None
        return (np.fromfile(f"{base}.idx", dtype=self._idx_dtype).astype(np.int64),
                np.fromfile(f"{base}.h", dtype="<f8"))

    def blocks(self) -> Iterator[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]]:
        """Reduce one block of grid rows at a time: yields (r0, r1, H, count, fallback) for rows
        r0:r1 (H float32 NaN-empty, count int32, fallback bool: the cells whose value came from
        tier 1), every block in order, then removes the spilled files. Memory: one block."""
        try:
            for b in range(self.n_blocks):
                r0 = b * self.block_rows
                r1 = min(r0 + self.block_rows, self.grid.height)
                shape = (r1 - r0, self.grid.width)
                H = np.full(shape, np.nan, dtype=np.float32)
                count = np.zeros(shape, dtype=np.int32)
                fallback = np.zeros(shape, dtype=bool)
                data = self._load(b)
                if data is not None:
                    slots, vals, counts = _reduce_sorted(data[0], data[1], self.stat)
                    cells = slots >> 1
                    first = np.r_[True, cells[1:] != cells[:-1]]     # tier 0 where a cell has both
                    cells, vals, counts, tier1 = cells[first], vals[first], counts[first], (slots[first] & 1) > 0
                    fallback.flat[cells[tier1]] = True
                    H.flat[cells] = vals
                    count.flat[cells] = counts
                yield r0, r1, H, count, fallback
        finally:
            self.close()

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """Reduce every block. Returns H (height, width) float32 NaN-empty, count int32;
        `fallback` (height, width) bool then marks the cells whose value came from tier 1."""
        self.fallback = np.zeros(self.grid.shape, bool)
        H = np.full(self.grid.shape, np.nan, dtype=np.float32)
        count = np.zeros(self.grid.shape, dtype=np.int32)
        for r0, r1, Hb, cb, fb in self.blocks():
            H[r0:r1], count[r0:r1], self.fallback[r0:r1] = Hb, cb, fb
        return H, count

    def close(self) -> None:
        """Remove spilled block files."""
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None
        self._mem.clear()


# --------------------------------------------------------------------------------------------
# Hole filling
# --------------------------------------------------------------------------------------------
def fill_small_holes(H: np.ndarray, max_hole_px: int = 3, min_support: float = 0.5,
                     window: int = 5, out: np.ndarray | None = None,
                     block_rows: int = 1024) -> np.ndarray:
    """Fill only small NaN holes; big voids stay NaN.

    A NaN cell is a candidate when its connected NaN region (4-connectivity) has at most
    (2 max_hole_px + 1)^2 cells. A candidate is filled with the median of the valid cells of its
    `window` x `window` neighbourhood when at least `min_support` of that window is valid. This
    is iterated at most `max_hole_px` times (holes close from their rim inwards).

    Works by blocks of `block_rows` rows, each read with a margin of rows above and below, so H
    and `out` may be disk-backed arrays (np.memmap) of any size: memory holds one block. The
    result does not depend on the blocks: a small region that meets the block's own rows lies
    inside the margin; a region cut by the margin's edge is taken as large, which can only be
    wrong for one lying farther than window // 2 * max_hole_px rows from the block's rows, out
    of reach of their filling. `out` must not be H (later blocks read rows of H around them).

    Args:
        H: (height, width) float array, NaN = empty.
        out: where to write the result (same shape, float32); None: a new array.
    Returns:
        The filled float32 array (`out` when given).
    """
    from scipy import ndimage

    if out is None:
        out = np.empty(H.shape, np.float32)
    elif np.shares_memory(out, H):
        raise ValueError("fill_small_holes: `out` must not share memory with H")
    h, block_rows = H.shape[0], max(1, int(block_rows))
    limit = (2 * max_hole_px + 1) ** 2
    r = window // 2
    iters = max(1, int(max_hole_px))
    margin = limit + 2 * r * iters + 1
    offs = np.array([(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)])
    for r0 in range(0, h, block_rows):
        r1 = min(r0 + block_rows, h)
        a, b = max(0, r0 - margin), min(h, r1 + margin)
        win = np.array(H[a:b], dtype=np.float32, copy=True)
        nan = np.isnan(win)
        if nan.any() and not nan.all():
            lab, n = cast("tuple[np.ndarray, int]", ndimage.label(nan))     # (labels, count): no output given
            sizes = np.bincount(lab.ravel(), minlength=n + 1)
            small = sizes <= limit
            small[0] = False
            # a region touching a cut edge of the window may go on beyond it: not small
            if a > 0:
                small[lab[0]] = False
            if b < h:
                small[lab[-1]] = False
            cand = small[lab]
            for _ in range(iters):
                rows, cols = np.nonzero(cand & np.isnan(win))
                if not len(rows):
                    break
                pad = np.pad(win, r, constant_values=np.nan)
                vals = pad[rows[:, None] + r + offs[:, 0], cols[:, None] + r + offs[:, 1]]   # (k, w*w)
                ok = np.isfinite(vals).sum(axis=1) >= min_support * len(offs)
                if not ok.any():
                    break
                win[rows[ok], cols[ok]] = np.nanmedian(vals[ok], axis=1)
        out[r0:r1] = win[r0 - a:r1 - a]
    return out

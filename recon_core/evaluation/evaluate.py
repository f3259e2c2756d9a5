"""DSM evaluation against a ground-truth DSM, as JHU/APL's align3d (IARPA MVS3DM) does it.

1. The GT grid is the reference: the DSM is resampled onto it (bilinear, NaN nodata).
2. Alignment: the DSM's valid cells (a fixed random sample, seed 0) are treated as points
   (x, y, z). For a candidate horizontal shift (dx, dy) the GT is interpolated (bilinear) at
   (x - dx, y - dy); the vertical offset is the median of the differences and the score the
   67th percentile of |difference - offset|. Candidates: a brute-force grid over
   +-max_shift_m in steps of one GT cell, then two finer grids around the best (1/4 and 1/20 of
   a cell).
   - Moving DSM points (instead of resampling the DSM for every candidate) leaves the DSM's
     voids out of the alignment without a void-filled copy, and does not smooth the DSM's noise
     by different amounts at different fractional shifts (bilinear resampling at a half-cell
     offset halves the noise, which would pull the search towards half cells).
   - Both surfaces are low-passed for the alignment only (NaN-aware Gaussian, sigma = the
     coarser of the two cell sizes): a raster only knows an edge to within a cell, and
     interpolating sharp rasters favours shifts that put DSM cells on GT nodes (a bias of up to
     0.3 cell measured on synthetic scenes, < 0.1 cell after the low-pass).
3. Scoring: the unfilled, unsmoothed DSM is resampled onto the GT grid displaced by (dx, dy),
   dz is the median difference, and the result is scored over every valid GT cell: missing DSM
   cells count as failures for completeness.

Sign convention: `alignment` = {dx_m, dy_m, dz_m} is the DSM's displacement relative to the GT
(east, north, up, metres): DSM(x, y) ~ GT(x - dx, y - dy) + dz. For a product geo-referenced by
GCPs this is its absolute accuracy. Errors are DSM minus GT.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any, cast

import numpy as np
import rasterio
import rasterio.errors
from rasterio.transform import Affine
from rasterio.warp import Resampling, reproject, transform_bounds
from rasterio.warp import transform as warp_transform

from recon_core.errors import AerecError, InputError
from recon_core.evaluation import colormap as cm
from recon_core.io.files import write_json
from recon_core.io.raster import write_geotiff

THRESH_M = 1.0          # completeness threshold on |error|
NMAD_K = 1.4826         # NMAD = 1.4826 x median |e - median e|: the normal's sigma


# --------------------------------------------------------------------------------------------
# Reading and checks
# --------------------------------------------------------------------------------------------
class Raster:
    """A single-band raster in memory: values (h, w) float32 with NaN nodata, transform, crs."""

    def __init__(self, path: str | Path, values: np.ndarray, transform: Affine, crs: Any, factor: int = 1):
        self.path, self.values, self.transform, self.crs = Path(path), values, transform, crs
        self.factor = factor              # read averaged by this much (read_factor)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        h, w = self.values.shape
        xs = [self.transform.c, self.transform.c + w * self.transform.a]
        ys = [self.transform.f, self.transform.f + h * self.transform.e]
        return min(xs), min(ys), max(xs), max(ys)


def read_factor(width: int, height: int, cell: float, finer_than: float | None = None,
                max_cells: float | None = None) -> int:
    """The decimation a raster is read with: a cell finer than half of `finer_than` (the ground
    truth's) is averaged down to about that (the evaluation samples the DSM at the GT's cells:
    a 0.01 m DSM read whole filled 21 GB), and a raster over `max_cells` down to that many."""
    f = 1
    if finer_than is not None and cell > 0 and cell < finer_than / 2.0:
        f = int(finer_than / (2.0 * cell))
    if max_cells is not None and width * height / f ** 2 > max_cells:
        f = int(np.ceil(np.sqrt(width * height / max_cells)))
    return max(1, f)


MAX_EVAL_CELLS = 4e8     # a ground truth read averaged down to this many cells (1.6 GB a grid)


def read_raster(path: str | Path, what: str, finer_than: float | None = None,
                max_cells: float | None = None, resampling: Resampling = Resampling.average) -> Raster:
    """Read band 1 as float32 with NaN for nodata and non-finite values; refuse no CRS or
    rotation. With `finer_than` / `max_cells`, read averaged down (read_factor); `factor` on
    the result says by how much."""
    try:
        src = rasterio.open(path)
    except rasterio.errors.RasterioIOError as e:
        raise InputError(path, f"cannot read the {what}: {e}") from None
    with src:
        if src.crs is None:
            raise InputError(path, f"the {what} has no CRS; it must be geo-referenced in a "
                                   "projected CRS (metres)")
        t = src.transform
        if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
            raise InputError(path, f"the {what} must be a north-up grid, transform {tuple(t)[:6]}")
        f = read_factor(src.width, src.height, float(t.a), finer_than, max_cells)
        try:
            if f == 1:
                vals = src.read(1, masked=True).astype(np.float32).filled(np.nan)
            else:
                shape = (max(1, src.height // f), max(1, src.width // f))
                vals = src.read(1, masked=True, out_shape=shape,
                                resampling=resampling).astype(np.float32).filled(np.nan)
                t = t * Affine.scale(src.width / shape[1], src.height / shape[0])
        except rasterio.errors.RasterioIOError as e:
            raise InputError(path, f"cannot read the {what}'s pixels (a truncated or damaged file?): "
                                   f"{e.__cause__ or e}") from None
        vals[~np.isfinite(vals)] = np.nan
        return Raster(path, vals, t, src.crs, f)


def _check_dsm(dsm: Raster, gt: Raster) -> None:
    """Refuse a DSM whose CRS cannot be brought to the GT's or which does not overlap the GT."""
    try:
        b = transform_bounds(dsm.crs, gt.crs, *dsm.bounds) if dsm.crs != gt.crs else dsm.bounds
        if not all(map(math.isfinite, b)):
            raise ValueError("non-finite bounds")
    except Exception as e:  # pyproj / GDAL raise various types
        raise InputError(dsm.path, f"its CRS ({dsm.crs}) cannot be reprojected to the ground "
                                   f"truth's ({gt.crs}): {e}") from None
    g = gt.bounds
    if b[0] >= g[2] or b[2] <= g[0] or b[1] >= g[3] or b[3] <= g[1]:
        raise InputError(dsm.path, f"does not overlap the ground truth {gt.path.name}: DSM "
                                   f"bounds {_fmt_b(b)} vs GT bounds {_fmt_b(g)} (in {gt.crs})")


def _fmt_b(b) -> str:
    return "[" + ", ".join(f"{v:.1f}" for v in b) + "]"


def resample_onto(dsm: Raster, gt: Raster, dx: float = 0.0, dy: float = 0.0,
                  resampling: Resampling = Resampling.bilinear) -> np.ndarray:
    """DSM values at the GT cell centres displaced by (dx, dy) (GT CRS metres); bilinear (or
    `resampling`, e.g. nearest for a class layer), NaN out.

    Returns (h, w) float32 on the GT grid: out[i] = DSM(centre_i + (dx, dy)).
    """
    out = np.full(gt.values.shape, np.nan, dtype=np.float32)
    reproject(source=dsm.values, destination=out, src_transform=dsm.transform, src_crs=dsm.crs,
              src_nodata=np.nan, dst_transform=Affine.translation(dx, dy) @ gt.transform,
              dst_crs=gt.crs, dst_nodata=np.nan, resampling=resampling)
    return out


# --------------------------------------------------------------------------------------------
# Alignment
# --------------------------------------------------------------------------------------------
def nan_gaussian(v: np.ndarray, sigma_rc: tuple[float, float]) -> np.ndarray:
    """NaN-aware Gaussian low-pass of (h, w) values (sigma in pixels per axis); NaN stays NaN."""
    from scipy import ndimage

    m = np.isfinite(v)
    num = ndimage.gaussian_filter(np.where(m, v, 0.0).astype(np.float64), sigma_rc, mode="nearest")
    den = ndimage.gaussian_filter(m.astype(np.float64), sigma_rc, mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        np.divide(num, den, out=num)              # in place: one grid of float64 less at peak
    del den
    num[~m] = np.nan
    return num


def _blur_at(v: np.ndarray, rows: np.ndarray, cols: np.ndarray,
             sigma_rc: tuple[float, float]) -> np.ndarray:
    """NaN-aware Gaussian low-pass of (h, w) values evaluated at (n,) cells only. Returns (n,)."""
    kr, kc = (max(1, int(math.ceil(3 * s))) for s in sigma_rc)
    dr, dc = np.meshgrid(np.arange(-kr, kr + 1), np.arange(-kc, kc + 1), indexing="ij")
    w = np.exp(-0.5 * ((dr / max(sigma_rc[0], 1e-6)) ** 2 + (dc / max(sigma_rc[1], 1e-6)) ** 2))
    r = rows[:, None] + dr.ravel()[None]
    c = cols[:, None] + dc.ravel()[None]
    inside = (r >= 0) & (r < v.shape[0]) & (c >= 0) & (c < v.shape[1])
    vals = v[np.clip(r, 0, v.shape[0] - 1), np.clip(c, 0, v.shape[1] - 1)].astype(np.float64)
    ok = inside & np.isfinite(vals)
    wk = np.where(ok, w.ravel()[None], 0.0)
    return np.sum(np.where(ok, vals, 0.0) * wk, axis=1) / np.sum(wk, axis=1)


def _cell_size_m(r: Raster, crs: Any) -> tuple[float, float]:
    """(row, col) cell size of raster r measured in the units of `crs` (metres for the GT)."""
    t = r.transform
    if r.crs == crs:
        return -t.e, t.a
    cx, cy = t.c + 0.5 * r.values.shape[1] * t.a, t.f + 0.5 * r.values.shape[0] * t.e
    x, y = cast("tuple[list[float], list[float]]",          # (xs, ys): no zs given
                warp_transform(r.crs, crs, [cx, cx + t.a, cx], [cy, cy, cy + t.e]))
    return float(np.hypot(x[2] - x[0], y[2] - y[0])), float(np.hypot(x[1] - x[0], y[1] - y[0]))


def _dsm_points(dsm: Raster, gt: Raster, n_max: int, seed: int, sigma_m: float) -> np.ndarray:
    """Up to n_max random valid DSM cell centres (x, y, z) in the GT CRS, z low-passed with a
    Gaussian of sigma_m metres. (n, 3) float64."""
    rows, cols = np.nonzero(np.isfinite(dsm.values))
    rng = np.random.default_rng(seed)
    if len(rows) > n_max:
        pick = np.sort(rng.choice(len(rows), n_max, replace=False))
        rows, cols = rows[pick], cols[pick]
    t = dsm.transform
    x = t.c + (cols + 0.5) * t.a
    y = t.f + (rows + 0.5) * t.e
    if dsm.crs != gt.crs:
        x, y = map(np.asarray, warp_transform(dsm.crs, gt.crs, x, y))
    cell = _cell_size_m(dsm, gt.crs)
    z = _blur_at(dsm.values, rows, cols, (sigma_m / cell[0], sigma_m / cell[1]))
    return np.column_stack([x, y, z])


class _ShiftScorer:
    """Scores candidate shifts of DSM points against the bilinearly interpolated GT.

    G: (h, w) GT values (NaN nodata) on the grid `transform` (north-up).
    """

    def __init__(self, pts: np.ndarray, G: np.ndarray, transform: Affine, max_shift_m: float):
        t = transform
        self.ax, self.ay = t.a, -t.e
        self.pad = int(math.ceil(max_shift_m / min(self.ax, self.ay))) + 3
        self.G = np.pad(G.astype(np.float64, copy=False), self.pad, constant_values=np.nan)
        self.cf = (pts[:, 0] - t.c) / self.ax - 0.5 + self.pad     # GT pixel coords (centres)
        self.rf = (t.f - pts[:, 1]) / self.ay - 0.5 + self.pad
        self.z = pts[:, 2]
        self._keep_fully_covered(max_shift_m)

    def _keep_fully_covered(self, max_shift_m: float) -> None:
        """Keep points whose GT neighbourhood is valid for every candidate (same set for all)."""
        from scipy import ndimage

        k = int(math.ceil(max_shift_m / min(self.ax, self.ay))) + 2
        ok = ndimage.minimum_filter(np.isfinite(self.G).astype(np.uint8), size=2 * k + 1,
                                    mode="constant", cval=0)
        r = np.clip(np.floor(self.rf).astype(np.int64), 0, self.G.shape[0] - 1)
        c = np.clip(np.floor(self.cf).astype(np.int64), 0, self.G.shape[1] - 1)
        inside = ((self.rf >= 0) & (self.cf >= 0) & (self.rf < self.G.shape[0] - 1)
                  & (self.cf < self.G.shape[1] - 1) & np.isfinite(self.z))
        full = inside & (ok[r, c] == 1)
        self.nan_aware = full.sum() < 500
        if self.nan_aware:                      # small overlap: score each shift on what it sees
            full = inside & np.isfinite(self.G[r, c])
        self.cf, self.rf, self.z = self.cf[full], self.rf[full], self.z[full]

    @property
    def n(self) -> int:
        return len(self.z)

    def _gt_at(self, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """GT bilinear at every point shifted by -(dx, dy): (B, n)."""
        cf = self.cf[None] - dx[:, None] / self.ax
        rf = self.rf[None] + dy[:, None] / self.ay
        hi_r, hi_c = self.G.shape[0] - 2, self.G.shape[1] - 2
        r0 = np.clip(np.floor(rf).astype(np.int64), 0, hi_r)
        c0 = np.clip(np.floor(cf).astype(np.int64), 0, hi_c)
        fr, fc = rf - r0, cf - c0
        G = self.G
        return ((G[r0, c0] * (1 - fc) + G[r0, c0 + 1] * fc) * (1 - fr)
                + (G[r0 + 1, c0] * (1 - fc) + G[r0 + 1, c0 + 1] * fc) * fr)

    def score(self, dx: np.ndarray, dy: np.ndarray, batch_elems: int = 4_000_000
              ) -> tuple[np.ndarray, np.ndarray]:
        """(score, dz) for each candidate (B,): 67th percentile of |d - median d|, median d."""
        dx, dy = np.atleast_1d(dx).astype(float), np.atleast_1d(dy).astype(float)
        scores, offs = np.empty(len(dx)), np.empty(len(dx))
        step = max(1, batch_elems // max(1, self.n))
        for a in range(0, len(dx), step):
            d = self.z[None] - self._gt_at(dx[a:a + step], dy[a:a + step])
            if self.nan_aware:
                off = np.nanmedian(d, axis=1)
                s = np.nanpercentile(np.abs(d - off[:, None]), 67, axis=1)
                s[np.isfinite(d).sum(axis=1) < 50] = np.inf
            else:
                off = np.median(d, axis=1)
                s = np.percentile(np.abs(d - off[:, None]), 67, axis=1)
            scores[a:a + step], offs[a:a + step] = s, off
        return scores, offs


def _grid_candidates(cx: float, cy: float, half_x: float, half_y: float, sx: float,
                     sy: float) -> tuple[np.ndarray, np.ndarray]:
    """Shifts on a grid centred at (cx, cy), nearest to the centre first (ties -> smaller shift)."""
    kx, ky = int(round(half_x / sx)), int(round(half_y / sy))
    X, Y = np.meshgrid(cx + np.arange(-kx, kx + 1) * sx, cy + np.arange(-ky, ky + 1) * sy)
    X, Y = X.ravel(), Y.ravel()
    order = np.argsort(np.hypot(X, Y), kind="stable")
    return X[order], Y[order]


MAX_SHIFT_M = 2000.0   # the largest misregistration `aerec eval --max-shift` searches (the padded grid grows with it)
COARSE_SHIFTS = 80     # the alignment's first search: at most this many steps across +-max_shift


def align(dsm: Raster, gt: Raster, max_shift_m: float = 10.0, step_m: float | None = None,
          n_samples: int = 30_000, seed: int = 0) -> dict[str, Any]:
    """Brute-force horizontal alignment with sub-cell refinement (see the module docstring).

    Returns {dx_m, dy_m, dz_m (sample median), score_p67_m (of the low-passed surfaces),
    n_samples, lowpass_sigma_m, step_x_m, step_y_m, max_shift_m, at_search_limit}.
    """
    gt_cell = _cell_size_m(gt, gt.crs)
    sigma_m = max(max(gt_cell), max(_cell_size_m(dsm, gt.crs)))
    G = nan_gaussian(gt.values, (sigma_m / gt_cell[0], sigma_m / gt_cell[1]))
    sc = _ShiftScorer(_dsm_points(dsm, gt, n_samples, seed, sigma_m), G, gt.transform,
                      max_shift_m)
    del G                                         # the scorer keeps its own padded copy
    if sc.n < 50:
        raise InputError(dsm.path, f"only {sc.n} DSM cells fall on valid ground truth: too "
                                   "little overlap to align")
    sx = step_m or gt.transform.a
    sy = step_m or -gt.transform.e
    best = (0.0, 0.0)
    # a fine ground truth (0.05 m cells: 160,000 shifts of one cell over +-10 m) is searched
    # coarse first, at most COARSE_SHIFTS a side, then refined down to 0.05 cell as always
    c = max(1.0, 2.0 * max_shift_m / (COARSE_SHIFTS * max(sx, sy)))
    passes = [(max_shift_m, c)]
    if c == 1.0:
        passes += [(1.0, 0.25), (0.25, 0.05)]
    else:
        half = c
        while half > 0.25:
            passes.append((half, half / 4.0))
            half /= 4.0
        passes.append((half, 0.05))
    for k, (half, frac) in enumerate(passes):
        hx, hy = (half, half) if k == 0 else (half * sx, half * sy)
        X, Y = _grid_candidates(*best, hx, hy, sx * frac, sy * frac)
        keep = (np.abs(X) <= max_shift_m + 1e-9) & (np.abs(Y) <= max_shift_m + 1e-9)
        s, off = sc.score(X[keep], Y[keep])
        i = int(np.argmin(s))
        best, best_s, best_off = (float(X[keep][i]), float(Y[keep][i])), float(s[i]), float(off[i])
    limit = max(abs(best[0]), abs(best[1])) >= max_shift_m - max(sx, sy)
    return {"dx_m": best[0], "dy_m": best[1], "dz_m": best_off, "score_p67_m": best_s,
            "n_samples": sc.n, "lowpass_sigma_m": sigma_m, "step_x_m": sx, "step_y_m": sy,
            "max_shift_m": max_shift_m,
            "at_search_limit": bool(limit)}


# --------------------------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------------------------
def height_metrics(err: np.ndarray, gt_valid: np.ndarray, thresh_m: float = THRESH_M) -> dict:
    """Figures of a signed error map (h, w) (NaN where the DSM is missing) over valid GT cells.

    completeness_pct = % of valid GT cells with |error| < thresh_m (missing cells fail);
    median_abs_err_m, rmse_m, mean_err_m, nmad_m (1.4826 median |e - median e|) over cells
    where both exist; coverage_pct = % of valid GT cells the DSM covers.
    """
    n_gt = int(gt_valid.sum())
    e = err[gt_valid & np.isfinite(err)].astype(np.float64)
    # one scratch array reused for every statistic (the medians partition it in place): two
    # copies of the compared cells at a time instead of four or five, the same figures
    a = np.abs(e)
    out = {"n_gt_cells": n_gt, "n_compared": int(e.size),
           "coverage_pct": 100.0 * e.size / n_gt if n_gt else 0.0,
           "completeness_pct": 100.0 * float(np.sum(a < thresh_m)) / n_gt if n_gt else 0.0,
           "threshold_m": thresh_m}
    if e.size == 0:
        return out | {k: None for k in ("median_abs_err_m", "rmse_m", "mean_err_m", "nmad_m")}
    med_abs = float(np.median(a, overwrite_input=True))
    a[:] = e
    med = float(np.median(a, overwrite_input=True))
    np.multiply(e, e, out=a)
    rmse = float(np.sqrt(np.mean(a)))
    np.subtract(e, med, out=a)
    np.abs(a, out=a)
    return out | {"median_abs_err_m": med_abs, "rmse_m": rmse, "mean_err_m": float(e.mean()),
                  "nmad_m": NMAD_K * float(np.median(a, overwrite_input=True))}


def evaluate_dsm(dsm_path: str | Path, gt_path: str | Path, out_dir: str | Path | None = None,
                 *, max_shift_m: float = 10.0, step_m: float | None = None,
                 thresh_m: float = THRESH_M, clip_m: float | None = 3.0,
                 n_samples: int = 30_000, seed: int = 0) -> dict[str, Any]:
    """Evaluate a DSM GeoTIFF against a ground-truth DSM GeoTIFF.

    Args:
        dsm_path, gt_path: single-band GeoTIFFs in projected CRSs (metres).
        out_dir: if given, write eval.json, height_error.tif, height_error.png, dsm_vs_gt.png.
        max_shift_m: half-size of the horizontal search (metres); step_m: its step (default one
            GT cell); thresh_m: completeness threshold; clip_m: colour range of the error map
            (None: 95th percentile of |error|).
    Returns:
        {"dsm", "gt", "alignment": {dx_m, dy_m, dz_m, ...}, "aligned": {...}, "unaligned": {...},
        "warnings": [...], "outputs": {...}} with the figures of `height_metrics`.
    Raises:
        InputError: naming the file: no CRS, unreadable or unreprojectable CRS, no overlap.
    """
    gt = read_raster(gt_path, "ground truth", max_cells=MAX_EVAL_CELLS)
    if not gt.crs.is_projected:
        raise InputError(gt_path, f"the ground truth must be in a projected CRS, got {gt.crs}")
    dsm = read_raster(dsm_path, "DSM", finer_than=gt.transform.a)
    _check_dsm(dsm, gt)
    gt_valid = np.isfinite(gt.values)
    raw = resample_onto(dsm, gt)
    if not np.any(np.isfinite(raw) & gt_valid):
        raise InputError(dsm_path, "has no valid heights over the valid ground-truth cells")
    al = align(dsm, gt, max_shift_m, step_m, n_samples, seed)
    shifted = resample_onto(dsm, gt, al["dx_m"], al["dy_m"])
    both = np.isfinite(shifted) & gt_valid
    al["dz_m"] = float(np.median(shifted[both] - gt.values[both]))
    err = (shifted - al["dz_m"]) - gt.values
    result = {"dsm": str(dsm_path), "gt": str(gt_path), "alignment": al,
              "aligned": height_metrics(err, gt_valid, thresh_m),
              "unaligned": height_metrics(raw - gt.values, gt_valid, thresh_m),
              "warnings": _warnings(al)}
    if dsm.factor > 1 or gt.factor > 1:
        result["read_averaged"] = {"dsm": dsm.factor, "gt": gt.factor}
        result["warnings"].append(
            (f"the DSM ({dsm.transform.a / dsm.factor:g} m cells) was read averaged by {dsm.factor} to about half "
             f"the ground truth's cells" if dsm.factor > 1 else "")
            + ("; " if dsm.factor > 1 and gt.factor > 1 else "")
            + (f"the ground truth was read averaged by {gt.factor} (more than {MAX_EVAL_CELLS:.0e} cells)"
               if gt.factor > 1 else ""))
    if out_dir is not None:
        result["outputs"] = write_outputs(Path(out_dir), result, err, shifted - al["dz_m"], gt,
                                          clip_m)
    return result


def same_cells(a_path: str | Path, a_align: dict, b_path: str | Path, b_align: dict,
               gt_path: str | Path, thresh_m: float = THRESH_M) -> dict[str, Any]:
    """Two DSMs scored on the same cells: those of the valid GT where both have a height, each
    with its own alignment (evaluate_dsm's "alignment"). Answers "is A better than B where
    both say something", which their own figures (each over its own cells) do not: a DSM that
    also covers the hard cells (occlusions, edges) has a larger median there.
    Returns {"cells": n, "cells_pct_of_gt", "a"/"b": {"median_abs_err_m", "within_pct"}} with
    within_pct the % of those cells within thresh_m."""
    gt = read_raster(gt_path, "ground truth", max_cells=MAX_EVAL_CELLS)
    both = np.isfinite(gt.values)
    errs = []
    for path, al in ((a_path, a_align), (b_path, b_align)):
        e = aligned_error(path, al, gt)
        both &= np.isfinite(e)
        errs.append(e)
    n = int(both.sum())
    out: dict[str, Any] = {"cells": n, "cells_pct_of_gt": 100.0 * n / max(int(np.isfinite(gt.values).sum()), 1),
                           "threshold_m": thresh_m}
    for key, e in zip(("a", "b"), errs):
        v = np.abs(e[both])
        out[key] = {"median_abs_err_m": float(np.median(v)) if n else None,
                    "within_pct": 100.0 * float(np.mean(v < thresh_m)) if n else None}
    return out


def aligned_error(path: str | Path, align: dict, gt: Raster) -> np.ndarray:
    """DSM - GT on the GT grid, the DSM shifted by its alignment (evaluate_dsm's "alignment":
    dx, dy, dz in metres); NaN where either has no height. float32."""
    e = resample_onto(read_raster(path, "DSM", finer_than=gt.transform.a), gt, align["dx_m"], align["dy_m"])
    e -= np.float32(align["dz_m"])
    e -= gt.values
    return e


def by_class(dsm_path: str | Path, align: dict, class_path: str | Path, gt_path: str | Path,
             thresh_m: float = THRESH_M) -> dict[str, Any]:
    """The DSM's errors (with its alignment) split by the integer classes of a layer on the
    DSM's grid (e.g. dsm_agreement.tif: how many date groups agree at each cell), sampled at the
    same shifted positions (nearest). Per class: its share of the GT's cells, the median
    absolute error and the % within thresh_m of its cells, and its share of the completeness
    (cells within thresh_m, in % of the GT's cells). Tells which cells of the DSM to trust."""
    gt = read_raster(gt_path, "ground truth", max_cells=MAX_EVAL_CELLS)
    n_gt = max(int(np.isfinite(gt.values).sum()), 1)
    e = aligned_error(dsm_path, align, gt)
    cls = resample_onto(read_raster(class_path, "class layer", finer_than=gt.transform.a, resampling=Resampling.nearest),
                        gt, align["dx_m"], align["dy_m"], Resampling.nearest)
    ok = np.isfinite(e) & np.isfinite(cls)
    v, c = np.abs(e[ok]), cls[ok].astype(np.int64)
    out: dict[str, Any] = {"threshold_m": thresh_m, "classes": {}}
    for k in np.unique(c):
        a = v[c == k]
        out["classes"][str(int(k))] = {"cells_pct_of_gt": 100.0 * len(a) / n_gt,
                                       "median_abs_err_m": float(np.median(a)),
                                       "within_pct": 100.0 * float(np.mean(a < thresh_m)),
                                       "completeness_share_pct": 100.0 * float(np.sum(a < thresh_m)) / n_gt}
    return out


def _warnings(al: dict) -> list[str]:
    if al["at_search_limit"]:
        return [f"the best shift ({al['dx_m']:.2f}, {al['dy_m']:.2f}) m lies at the edge of the "
                f"+-{al['max_shift_m']} m search: the true offset may be larger (--max-shift)"]
    return []


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------
def write_outputs(out: Path, result: dict, err: np.ndarray, dsm_aligned: np.ndarray,
                  gt: Raster, clip_m: float | None) -> dict[str, str]:
    """eval.json, height_error.tif, height_error.png and dsm_vs_gt.png in `out`."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {k: str(out / k) for k in ("eval.json", "height_error.tif", "height_error.png",
                                       "dsm_vs_gt.png")}
    write_geotiff(paths["height_error.tif"], err.astype(np.float32), gt.transform, gt.crs)
    cm.save_png(paths["height_error.png"], error_map_image(err, clip_m))
    cm.save_png(paths["dsm_vs_gt.png"], comparison_image(dsm_aligned, gt.values, gt.transform.a))
    write_json(paths["eval.json"], result | {"outputs": paths})
    return paths


def reduce_for_display(v: np.ndarray, max_side: int = 3200) -> tuple[np.ndarray, int]:
    """NaN-aware block mean by the smallest integer factor k that brings the longer side to
    <= max_side (k = 1: unchanged). Colouring and hill-shading then work on at most ~10 M cells
    whatever the DSM size (a 7000 x 7700 grid shaded at full size took over 5 GB). Returns (v, k)."""
    h, w = v.shape
    k = max(1, math.ceil(max(h, w) / max_side))
    if k == 1:
        return v, 1
    hh, ww = -(-h // k) * k, -(-w // k) * k
    pad = np.full((hh, ww), np.nan, np.float32)
    pad[:h, :w] = v
    blocks = pad.reshape(hh // k, k, ww // k, k)
    ok = np.isfinite(blocks)
    n = ok.sum(axis=(1, 3))
    tot = np.where(ok, blocks, 0.0).sum(axis=(1, 3), dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (tot / n).astype(np.float32)
    out[n == 0] = np.nan
    return out, k


def error_map_image(err: np.ndarray, clip_m: float | None = 3.0) -> np.ndarray:
    """Diverging colour map of signed errors (NaN grey) with a colour bar in metres. RGB uint8."""
    err, _ = reduce_for_display(err)
    fin = np.abs(err[np.isfinite(err)])
    clip = clip_m if clip_m else (float(np.percentile(fin, 95)) if fin.size else 1.0)
    clip = max(clip, 1e-3)
    img = cm.resize_for_display(cm.diverging(err, clip))
    img = cm.titled(img, f"DSM - GT after alignment (m), clipped at +-{clip:.2f} m")
    bar = cm.colorbar(img.shape[0], -clip, clip, lambda v: cm.diverging(v, clip))
    return cm.hstack([img, bar])


def comparison_image(dsm: np.ndarray, gt: np.ndarray, res: float) -> np.ndarray:
    """Side-by-side shaded relief of the aligned DSM and the GT, common height range. RGB uint8."""
    dsm, k = reduce_for_display(dsm)
    gt, _ = reduce_for_display(gt)
    res = res * k
    fin = gt[np.isfinite(gt)]
    lo, hi = (np.percentile(fin, [1, 99]) if fin.size else (0.0, 1.0))
    hi = hi if hi > lo else lo + 1.0
    a = cm.titled(cm.resize_for_display(cm.shaded(dsm, res, lo, hi)), "DSM (aligned)")
    b = cm.titled(cm.resize_for_display(cm.shaded(gt, res, lo, hi)), "ground truth")
    bar = cm.colorbar(a.shape[0], float(lo), float(hi), lambda v: cm.sequential(v, lo, hi))
    return cm.hstack([a, b, bar])


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------
def format_table(r: dict) -> str:
    """A short text table of the aligned and unaligned figures."""
    rows = [("median |error| (m)", "median_abs_err_m"), ("completeness, within 1 m (%)", "completeness_pct"),
            ("RMSE (m)", "rmse_m"), ("mean error (m)", "mean_err_m"), ("NMAD (m)", "nmad_m"),
            ("coverage (%)", "coverage_pct")]
    f = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    lines = [f"{'':22s}{'aligned':>12s}{'unaligned':>12s}"]
    lines += [f"{name:22s}{f(r['aligned'][k]):>12s}{f(r['unaligned'][k]):>12s}" for name, k in rows]
    a = r["alignment"]
    lines.append(f"alignment (DSM - GT): dx {a['dx_m']:+.2f} m, dy {a['dy_m']:+.2f} m, "
                 f"dz {a['dz_m']:+.2f} m")
    lines += [f"warning: {w}" for w in r.get("warnings", [])]
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of `aerec eval` (also `python -m recon_core.evaluation.evaluate`)."""
    p.add_argument("dsm", help="the DSM to score (GeoTIFF, projected CRS)")
    p.add_argument("gt", help="the ground-truth (or reference) DSM (GeoTIFF, projected CRS)")
    p.add_argument("--out", default=None, help="folder for eval.json, error maps and PNGs")
    p.add_argument("--max-shift", type=float, default=10.0, help="horizontal search, +- metres (default 10)")
    p.add_argument("--step", type=float, default=None, help="search step (default: one GT cell)")


def run_cli(a) -> int:
    """Evaluate and print the table; bad input raises InputError (one line, exit 2 upstream),
    and a --out folder this call made is removed again when nothing could be written into it."""
    if not (math.isfinite(a.max_shift) and 0 <= a.max_shift <= MAX_SHIFT_M):
        raise InputError(None, f"--max-shift {a.max_shift:g}: a number of metres from 0 to {MAX_SHIFT_M:g} "
                               "(a DSM off by more is of another place)")
    if a.step is not None and not (math.isfinite(a.step) and 0 < a.step <= MAX_SHIFT_M):
        raise InputError(None, f"--step {a.step:g}: a number of metres above 0 (and at most {MAX_SHIFT_M:g})")
    if a.out is not None and Path(a.out).exists() and not Path(a.out).is_dir():
        raise InputError(a.out, "--out must be a folder (it exists and is a file)")
    made = False
    if a.out is not None:
        from recon_core.io.files import writable_folder
        from recon_core.io.layout import OutLayout

        for parent in Path(a.out).resolve().parents:
            if OutLayout(parent).is_output():
                raise InputError(a.out, f"is inside the output folder {parent} of a run (whose eval/ "
                                        "it would overwrite): choose a folder outside it")
        made = not Path(a.out).exists()
        writable_folder(a.out)
    try:
        r = evaluate_dsm(a.dsm, a.gt, a.out, max_shift_m=a.max_shift, step_m=a.step)
    except BaseException:
        if made and a.out is not None and not any(Path(a.out).iterdir()):
            Path(a.out).rmdir()
        raise
    print(format_table(r))
    if a.out:
        print(f"wrote {a.out}/eval.json, height_error.tif, height_error.png, dsm_vs_gt.png")
    return 0


def main(argv: list[str] | None = None) -> int:
    """`python -m recon_core.evaluation.evaluate DSM GT [--out DIR] [--max-shift M] [--step M]`."""
    p = argparse.ArgumentParser(prog="aerec eval", description="Evaluate a DSM against a "
                                "ground-truth DSM (align3d-style alignment and metrics).")
    add_arguments(p)
    try:
        return run_cli(p.parse_args(argv))
    except AerecError as e:
        print(f"aerec eval: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""The vertical bend the views cannot see, held by a coarse reference DEM.

Three views of one date over 10 km leave quadratic warps of the structure that move no pixel
once every image's pushbroom model re-fits (recon_core.bend.observability); 4 GCPs fix an
affine map, not a bend: on the `wide` site the heights away from 4 GCPs were off by 28 m RMS
(docs: research-notes.md, "One date over 10 km: what 4 GCPs leave").
Nine or more control GCPs can hold it (recon_core.bend.gcp); so can a global DEM that every site has (SRTM, Copernicus GLO-30, a national DEM), the way other
satellite pipelines lean on one (s2p and CARS for their height range, ASP for its initial
heights): its cells of 30 m know no building and are metres off each, but over kilometres they
know the shape of the ground.

How: each sparse point's height in the Euclidean frame against the DEM's at its (E, N); the
median of those differences in cells of `cell_m`; a polynomial surface in (E, N) fitted to the
cells' medians, robustly (Huber, scale from the median absolute deviation), of degree 2 (or 3:
`upgrade.reference_dem_degree`, for a DEM whose errors do not reach over kilometres). The fit's constant
and tilt are left free and thrown away: they hold the DEM's datum (geoid or ellipsoid), bias and
tilt, which the GCPs fix better. Its dome or saddle becomes the vertical displacement D of the
group's map X -> Y + D(Y) (EnuWarp, U only), and H_A is refitted by the upgrade's own fit
(RANSAC, the cameras' metric constraint) on the control GCPs' surveyed positions less D
(repeated until H_A stops moving the structure). The horizontal warps are left as they are: a
DEM does not see them.

What it assumes: the DEM's errors over the site are not a dome or a saddle themselves (a DEM's
long-wave error over 10 km is a metre or less); the heights compared are of the same surface
(a DEM of buildings and trees, not a bare-earth DTM, is the better reference for a city; the
median over a cell's points lets a few roofs pass).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from recon_core.bend.result import BendFit
from recon_core.errors import InputError
from recon_core.geometry.affine import apply_affine_3d, as_4x4
from recon_core.geometry.enu_map import EnuWarp, monomial_degree, monomials, n_monomials

if TYPE_CHECKING:
    from affine import Affine


CELL_M = 150.0            # cells of the comparison (each holds ~ 25 sparse points on `wide`)
MIN_POINTS_PER_CELL = 5   # a cell's median needs this many points
MIN_CELLS = 50            # the surface needs this many cells
MIN_SPAN = 0.6            # ... spanning this share of the site along E and along N
MAX_BEND_SIGMA_M = 1.0   # ... and must tell the bend at the site's edge to this standard error,
MIN_BEND_SNR = 10.0      # or to this fraction of its size (a bend of tens of metres)
MAX_READ_PX = 6000        # a DEM window larger than this on a side is read decimated


@dataclass
class ReferenceDem:
    """A georeferenced raster of heights (band 1), read by window where it is sampled."""

    path: Path
    crs: object
    transform: Affine
    width: int
    height: int
    nodata: float | None

    def cell_m(self, lat: float) -> float:
        """The raster's cell size in metres (the larger side) at latitude lat."""
        a, e = abs(self.transform.a), abs(self.transform.e)
        if getattr(self.crs, "is_geographic", False):
            return float(max(a * 111_320.0 * np.cos(np.deg2rad(lat)), e * 111_320.0))
        return float(max(a, e))

    def heights(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """Bilinear heights at (lon, lat) (degrees, WGS84); NaN outside the raster or on nodata."""
        import rasterio
        import rasterio.enums
        from pyproj import Transformer
        from rasterio.windows import Window
        from scipy import ndimage

        lon, lat = np.asarray(lon, np.float64), np.asarray(lat, np.float64)
        out = np.full(lon.shape, np.nan)
        if lon.size == 0:
            return out
        x, y = Transformer.from_crs("EPSG:4326", self.crs, always_xy=True).transform(lon, lat)
        inv = ~self.transform
        x, y = np.asarray(x), np.asarray(y)
        col, row = inv.a * x + inv.b * y + inv.c, inv.d * x + inv.e * y + inv.f
        ok = (np.isfinite(col) & np.isfinite(row) & (col >= 0) & (col <= self.width)
              & (row >= 0) & (row <= self.height))                  # on the raster
        if not ok.any():
            return out
        span = max(np.ptp(col[ok]), np.ptp(row[ok])) + 4
        step = max(1, int(np.ceil(span / MAX_READ_PX)))     # a large DEM is read decimated
        pad = 2 * step                    # the outermost read pixels' centres beyond every point
        c0 = int(max(np.floor(col[ok].min()) - pad, 0))
        r0 = int(max(np.floor(row[ok].min()) - pad, 0))
        c1 = int(min(np.ceil(col[ok].max()) + pad, self.width))
        r1 = int(min(np.ceil(row[ok].max()) + pad, self.height))
        if c1 <= c0 or r1 <= r0:
            return out
        w, h = c1 - c0, r1 - r0
        with rasterio.open(self.path) as src:
            z = src.read(1, window=Window(c0, r0, w, h), out_shape=(int(np.ceil(h / step)), int(np.ceil(w / step))),  # pyright: ignore[reportCallIssue]
                         masked=True, resampling=rasterio.enums.Resampling.average if step > 1
                         else rasterio.enums.Resampling.nearest)
        z = np.ma.filled(z.astype(np.float64), np.nan)
        if self.nodata is not None and np.isfinite(self.nodata):
            z[z == self.nodata] = np.nan
        sy, sx = h / z.shape[0], w / z.shape[1]          # source pixels per read pixel
        # read pixel i covers source pixels [i s, (i + 1) s): its centre is at (i + 0.5) s
        rr = (row - r0) / sy - 0.5
        cc = (col - c0) / sx - 0.5
        # NaN within half a read pixel of the raster's edge (no neighbour to interpolate with)
        vals = ndimage.map_coordinates(z, [rr[ok], cc[ok]], order=1, mode="constant", cval=np.nan)
        out[ok] = vals
        return out


def open_reference_dem(path: str | Path, option: str = "upgrade.reference_dem") -> ReferenceDem:
    """The reference DEM at `path`, checked: a raster GDAL reads, with a CRS and a finite value
    somewhere. Raises InputError (one line naming the file and `option`, where it came from)."""
    import rasterio
    from rasterio.errors import RasterioIOError

    p = Path(path).expanduser()
    try:
        kind = "a folder" if p.is_dir() else None if p.is_file() else "no such file"
    except OSError as exc:                         # a name too long
        kind = exc.strerror or str(exc)
    if kind:
        raise InputError(p, f"{option}: {kind}" + (", not a DEM file" if kind == "a folder" else ""))
    try:
        with rasterio.open(p) as src:
            if src.crs is None:
                raise InputError(p, f"{option} has no CRS: a reference DEM must be georeferenced "
                                    "(SRTM and Copernicus DEM tiles are EPSG:4326)")
            if src.count < 1:
                raise InputError(p, f"{option} has no band")
            try:
                from pyproj import Transformer

                Transformer.from_crs("EPSG:4326", src.crs, always_xy=True).transform(0.0, 0.0)
            except Exception as exc:      # pyproj's CRSError / ProjError, or what GDAL's CRS gives it
                raise InputError(p, f"{option}'s CRS cannot be reached from WGS84 ({exc})") from None
            return ReferenceDem(p, src.crs, src.transform, src.width, src.height, src.nodata)
    except RasterioIOError as exc:
        raise InputError(p, f"{option} is not a raster GDAL can read ({str(exc).splitlines()[0]})") from None


def has_heights(dem: ReferenceDem, max_side: int = 1024) -> bool:
    """Does the DEM hold a finite, non-nodata height anywhere (read decimated)?"""
    import rasterio

    f = max(1, int(np.ceil(max(dem.width, dem.height) / max_side)))
    with rasterio.open(dem.path) as src:
        z = src.read(1, out_shape=(max(1, dem.height // f), max(1, dem.width // f))).astype(np.float64)
    ok = np.isfinite(z)
    if dem.nodata is not None:
        ok &= z != dem.nodata
    return bool(ok.any())


def check_covers(dem: ReferenceDem, llh: np.ndarray) -> None:
    """Refuse a DEM that has no height at any of the points llh (n, 3) (the control GCPs):
    InputError naming the DEM file."""
    llh = np.asarray(llh, np.float64).reshape(-1, 3)
    if len(llh) == 0:
        return
    h = dem.heights(llh[:, 0], llh[:, 1])
    if not np.isfinite(h).any():
        raise InputError(dem.path, f"upgrade.reference_dem has no height at any of the {len(llh)} control GCPs: "
                                   "it does not cover the site (or is all nodata there)")


def bend_kind(degree: int) -> str:
    """The bend's name for a surface of this degree (the report's note, the viewer)."""
    return {2: "quadratic", 3: "cubic"}.get(int(degree), f"degree {degree}")


def _columns(e: np.ndarray, n: np.ndarray, degree: int) -> np.ndarray:
    """1, e, n and the monomials of degree 2 to `degree` (EnuWarp's order)."""
    return np.concatenate([np.stack([np.ones_like(e), e, n], 1), monomials(e, n, degree)], 1)


def _huber_fit(A: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least squares of A x = y with Huber weights (threshold 1.5 x the residuals' MAD scale).
    Returns (x, the final weights (square roots), the scale)."""
    w = np.ones(len(y))
    for _ in range(20):
        sol = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)[0]
        res = y - A @ sol
        scale = max(1.4826 * float(np.median(np.abs(res))), 1e-6)
        w_new = np.sqrt(np.minimum(1.0, 1.5 * scale / np.maximum(np.abs(res), 1e-12)))
        if np.allclose(w_new, w, atol=1e-4):
            break
        w = w_new
    return sol, w, scale


def _cell_medians(E: np.ndarray, N: np.ndarray, r: np.ndarray, cell_m: float):
    """The median of r per cell of cell_m metres holding MIN_POINTS_PER_CELL points or more:
    (those cells' indices, their medians, their points' mean E and N)."""
    key = np.stack([np.floor(E / cell_m), np.floor(N / cell_m)], 1).astype(np.int64)
    _, cell, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    cell = cell.ravel()
    order = np.argsort(cell, kind="stable")
    bounds = np.r_[0, np.cumsum(cnt)]
    rs, es, ns = r[order], E[order], N[order]
    full = np.flatnonzero(cnt >= MIN_POINTS_PER_CELL)
    med = np.array([np.median(rs[bounds[i]:bounds[i + 1]]) for i in full])
    cE = np.add.reduceat(es, bounds[:-1])[full] / cnt[full]
    cN = np.add.reduceat(ns, bounds[:-1])[full] / cnt[full]
    return full, med, cE, cN


def _bootstrap_blocks(cE: np.ndarray, cN: np.ndarray, block_m: float) -> list[np.ndarray]:
    """The block bootstrap's blocks: the cells in each square of block_m metres."""
    _, blk = np.unique(np.floor(np.stack([cE, cN], 1) / block_m).astype(np.int64), axis=0, return_inverse=True)
    blk = blk.ravel()
    return [np.flatnonzero(blk == b) for b in range(int(blk.max()) + 1)]


def _bootstrap_sigma(A: np.ndarray, w: np.ndarray, med: np.ndarray, Q: np.ndarray, draws_idx: list) -> float:
    """The bend's standard error over the grid Q: a block bootstrap of the weighted fit (the
    Huber weights of the final fit kept), the largest over the grid."""
    Aw, mw = A * w[:, None], med * w
    draws = [Q @ np.linalg.lstsq(Aw[idx], mw[idx], rcond=None)[0][3:] for idx in draws_idx]
    return float(np.max(np.std(np.array(draws), axis=0)))


def fit_surface(E: np.ndarray, N: np.ndarray, r: np.ndarray, centre: np.ndarray, half: float,
                cell_m: float | None = None, seed: int = 0, gate: bool = True,
                degree: int = 2) -> tuple[np.ndarray | None, dict]:
    """The polynomial surface c0 + c1 e + c2 n + (monomials of degree 2 to `degree`) (e, n = (E,
    N - centre) / half) through the medians of r (DEM minus structure height; NaN where the DEM
    has none) in cells of cell_m (default: CELL_M, or a twentieth of a smaller site). Returns
    (the coefficients of the monomials of degree 2 to D in metres at e, n = +-1, EnuWarp's
    order; summary), or (None, summary with the reason).

    Its standard error (`bend_sigma_m`, the largest over the site's rectangle) is a block
    bootstrap over blocks of ~1 km (a fifth of the site when smaller): a DEM's errors are
    correlated over several cells, which a formula for independent cells would not see. With
    `gate`, a bend known no better than MAX_BEND_SIGMA_M and a MIN_BEND_SNR-th of its size is
    refused; a cubic that fails it falls back to the quadratic (`degrees_refused`). Over a wide
    site the gate seldom refuses a cubic: a cubic that fits a DEM's kilometre-scale errors also
    makes the surface larger, and the gate is relative to that size (on `wide` a cubic with a
    standard error of 6 m at the edge passed): the fallback catches a DEM that tells nothing,
    not one whose errors look like a cubic.

    The degree is the user's (upgrade.reference_dem_degree), not the data's: the structure's
    cubic bend and a DEM's error over kilometres look the same in this comparison. On `wide`,
    block cross-validation and a bootstrap estimate of each degree's risk preferred the cubic
    as much for a DEM whose errors are correlated over 1 km (where it is worse) as for one with
    errors over 300 m (where it is better) (docs: research-notes.md, "The vertical bend from a reference DEM")."""
    fin = np.isfinite(E) & np.isfinite(N)
    E, N, r = E[fin], N[fin], r[fin]
    if len(E) == 0:
        return None, {"points": 0, "reason": "no structure point"}
    extent = np.array([np.ptp(E), np.ptp(N)])
    cell_m = float(cell_m or min(CELL_M, max(extent.min(), 1.0) / 20.0))
    ok = np.isfinite(r)
    E, N, r = E[ok], N[ok], r[ok]
    info: dict = {"points": int(len(r)), "cell_m": cell_m}
    if len(r) == 0:
        return None, {**info, "reason": "the reference DEM has no height under the structure"}
    full, med, cE, cN = _cell_medians(E, N, r, cell_m)
    ce, cn = (cE - centre[0]) / half, (cN - centre[1]) / half
    info["cells"] = int(len(full))
    if len(full) < MIN_CELLS:
        return None, {**info, "reason": f"{len(full)} cells of {cell_m:.0f} m with >= {MIN_POINTS_PER_CELL} points "
                                        f"under the DEM, {MIN_CELLS} needed"}
    # the share of the structure's extent the cells span, along E and along N
    span = float(min(np.ptp(cE) / max(extent[0] - cell_m, cell_m), np.ptp(cN) / max(extent[1] - cell_m, cell_m)))
    info["span"] = span
    if span < MIN_SPAN:
        return None, {**info, "reason": f"the DEM covers {span:.0%} of the site along one axis, "
                                        f"{MIN_SPAN:.0%} needed to fit its bend"}
    block_m = min(1000.0, extent.min() / 5.0)
    members = _bootstrap_blocks(cE, cN, block_m)
    nb = len(members)
    info["degree_asked"] = degree = max(2, int(degree))
    # each degree up to the one asked that has 4 cells per unknown (a cubic that fails the gate
    # falls back to the quadratic)
    fits = {d: _huber_fit(_columns(ce, cn, d), med) for d in range(2, degree + 1)
            if len(full) >= 4 * (3 + n_monomials(d))}
    degree = max(fits)
    # the bend over the site's rectangle (the cells' bounding box)
    ge, gn = (v.ravel() for v in np.meshgrid(np.linspace(ce.min(), ce.max(), 11), np.linspace(cn.min(), cn.max(), 11)))
    rng = np.random.default_rng(seed)
    draws_idx = [np.concatenate([members[b] for b in rng.integers(0, nb, nb)]) for _ in range(200)]
    while True:
        sol, w, scale = fits[degree]
        Q = monomials(ge, gn, degree)
        surf = Q @ sol[3:]
        sigma = _bootstrap_sigma(_columns(ce, cn, degree), w, med, Q, draws_idx)
        passes = sigma <= max(MAX_BEND_SIGMA_M, float(np.ptp(surf)) / MIN_BEND_SNR)
        if passes or not gate or degree == 2:
            break
        info.setdefault("degrees_refused", []).append({"degree": degree, "bend_sigma_m": sigma})
        degree -= 1
    info.update(degree=degree, cell_scale_m=scale, offset_m=float(sol[0]), tilt_m=[float(sol[1]), float(sol[2])],
                bend_coef_m=[float(v) for v in sol[3:]], bend_range_m=float(np.ptp(surf)),
                bend_sigma_m=sigma, bootstrap_blocks=nb, block_m=float(block_m))
    if gate and not passes:
        return None, {**info, "reason": f"the DEM tells its bend of {info['bend_range_m']:.2f} m to {sigma:.2f} m at "
                                        f"the site's edge (a block bootstrap; its cells scatter by {scale:.2f} m "
                                        f"about the surface): more than {MAX_BEND_SIGMA_M:g} m and a "
                                        f"{MIN_BEND_SNR:g}th of the bend"}
    return sol[3:], info


def fit_dem_bend(H: np.ndarray, X_points: np.ndarray, frame, dem: ReferenceDem, centre: npt.ArrayLike, half: float,
                 refit, cell_m: float | None = None, iters: int = 6, seed: int = 0, degree: int = 2
                 ) -> BendFit[EnuWarp]:
    """The vertical bend of the structure X_points (n, 3, in the frame H maps) against the DEM.

    refit(warp) -> H: the upgrade's own fit of H_A on the control GCPs, their surveyed positions
    less the warp (the warp moves heights by a function of E and N alone, so Y + warp(Y) = X_enu
    is Y = X_enu - warp(X_enu)); it may raise (e.g. ReconstructionError). The warp is refitted
    on the structure the new H gives, until H stops moving it. `degree`: the surface's (2 or 3,
    fit_surface); a cubic the final structure's DEM comparison does not tell is redone as a
    quadratic. Returns a BendFit: the EnuWarp, the summary and H (4, 4), or no warp and the
    summary with the reason."""
    centre = np.asarray(centre, np.float64)
    sample = X_points[np.random.default_rng(seed).choice(len(X_points), min(len(X_points), 5000), replace=False)]

    def surface(H4: np.ndarray, gate: bool):
        Y = apply_affine_3d(H4, X_points)
        llh = frame.enu_to_geodetic(Y)
        return fit_surface(Y[:, 0], Y[:, 1], dem.heights(llh[:, 0], llh[:, 1]) - llh[:, 2], centre, half,
                           cell_m, seed, gate=gate, degree=degree)

    Hn, warp, info = as_4x4(H), None, {}
    for it in range(iters):
        # refused or not on the structure H_A gives once it stops moving (the first H_A, fitted
        # to GCPs on the bent structure, scales its heights wrongly: the cells scatter more)
        coef, info = surface(Hn, gate=False)
        if coef is None:
            return BendFit(None, {**info, "applied": False})
        warp = EnuWarp(centre, float(half), np.r_[np.zeros(2 * len(coef)), coef])
        H_new = as_4x4(refit(warp))
        moved = float(np.abs(apply_affine_3d(H_new, sample) - apply_affine_3d(Hn, sample)).max())
        Hn = H_new
        info.update(rounds=it + 1, last_move_m=moved)
        if moved < 0.01:
            break
    coef, final = surface(Hn, gate=True)
    if degree > 2 and (final.get("degrees_refused") or (coef is not None and final["degree"] < info["degree"])):
        # the degree the rounds applied is not told well enough on the final structure: again, lower
        again = fit_dem_bend(H, X_points, frame, dem, centre, half, refit, cell_m, iters, seed,
                             min(final.get("degree", 2), degree - 1))
        return BendFit(again.warp, {**again.summary, "degree_asked": degree,
                                    "degrees_refused": final.get("degrees_refused", [])
                                    + again.summary.get("degrees_refused", [])}, again.H)
    if coef is None:
        return BendFit(None, {**final, "applied": False, "rounds": info["rounds"]})
    g = np.linspace(-1.0, 1.0, 11)
    ge, gn = (v.ravel() for v in np.meshgrid(g, g))

    def surf(c: list) -> np.ndarray:
        return monomials(ge, gn, monomial_degree(len(c))) @ np.asarray(c)

    info.update(applied=True, final_change_m=float(np.abs(surf(final["bend_coef_m"]) - surf(info["bend_coef_m"])).max()),
                bend_sigma_m=final["bend_sigma_m"], cell_scale_m=final["cell_scale_m"])
    return BendFit(warp, info, Hn)


"""The vertical bend the views cannot see, held by a coarse reference DEM.

Three views of one date over 10 km leave quadratic warps of the structure that move no pixel
once every image's pushbroom model re-fits (upgrade_stage.bend_observability); 4 GCPs fix an
affine map, not a bend: on the `wide` site the heights away from 4 GCPs were off by 28 m RMS
(README, "Synthetic `wide`"). Nine or more control GCPs can hold it (recon_core.euclidean.gcp_bend);
so can a global DEM that every site has (SRTM, Copernicus GLO-30, a national DEM), the way other
satellite pipelines lean on one (s2p and CARS for their height range, ASP for its initial
heights): its cells of 30 m know no building and are metres off each, but over kilometres they
know the shape of the ground.

How: each sparse point's height in the Euclidean frame against the DEM's at its (E, N); the
median of those differences in cells of `cell_m`; a quadratic surface in (E, N) fitted to the
cells' medians, robustly (Huber, scale from the median absolute deviation). The fit's constant
and tilt are left free and thrown away: they hold the DEM's datum (geoid or ellipsoid), bias and
tilt, which the GCPs fix better. Its dome or saddle becomes the vertical displacement D of the
group's map X -> Y + D(Y) (EnuWarp, U only), and the affine correction of H_A is refitted on the
control GCPs with it (repeated, since D is evaluated at the corrected positions). The
horizontal warps are left as they are: a DEM does not see them.

What it assumes: the DEM's errors over the site are not a dome or a saddle themselves (a DEM's
long-wave error over 10 km is a metre or less); the heights compared are of the same surface
(a DEM of buildings and trees, not a bare-earth DTM, is the better reference for a city; the
median over a cell's points lets a few roofs pass).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon_core.errors import InputError
from recon_core.geometry.affine import apply_affine_3d, fit_affine_3d
from recon_core.geometry.enu_map import EnuWarp

CELL_M = 150.0            # cells of the comparison (each holds ~ 25 sparse points on `wide`)
MIN_POINTS_PER_CELL = 5   # a cell's median needs this many points
MIN_CELLS = 50            # the quadratic needs this many cells
MIN_SPAN = 0.6            # ... spanning this share of the site along E and along N
MAX_BEND_SIGMA_M = 1.0   # ... and must tell the bend at the site's edge to this standard error
MAX_READ_PX = 6000        # a DEM window larger than this on a side is read decimated


@dataclass
class ReferenceDem:
    """A georeferenced raster of heights (band 1), read by window where it is sampled."""

    path: Path
    crs: object
    transform: object
    width: int
    height: int
    nodata: float | None

    def heights(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """Bilinear heights at (lon, lat) (degrees, WGS84); NaN outside the raster or on nodata."""
        import rasterio
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
        ok = np.isfinite(col) & np.isfinite(row)
        if not ok.any():
            return out
        c0 = int(max(np.floor(col[ok].min()) - 2, 0))
        r0 = int(max(np.floor(row[ok].min()) - 2, 0))
        c1 = int(min(np.ceil(col[ok].max()) + 2, self.width))
        r1 = int(min(np.ceil(row[ok].max()) + 2, self.height))
        if c1 <= c0 or r1 <= r0:
            return out
        w, h = c1 - c0, r1 - r0
        step = max(1, int(np.ceil(max(w, h) / MAX_READ_PX)))
        with rasterio.open(self.path) as src:
            z = src.read(1, window=Window(c0, r0, w, h), out_shape=(int(np.ceil(h / step)), int(np.ceil(w / step))),
                         masked=True, resampling=rasterio.enums.Resampling.average if step > 1
                         else rasterio.enums.Resampling.nearest)
        z = np.ma.filled(z.astype(np.float64), np.nan)
        if self.nodata is not None and np.isfinite(self.nodata):
            z[z == self.nodata] = np.nan
        sy, sx = h / z.shape[0], w / z.shape[1]          # source pixels per read pixel
        # read pixel i covers source pixels [i s, (i + 1) s): its centre is at (i + 0.5) s
        rr = (row - r0) / sy - 0.5
        cc = (col - c0) / sx - 0.5
        vals = ndimage.map_coordinates(z, [rr[ok], cc[ok]], order=1, mode="constant", cval=np.nan)
        out[ok] = vals
        return out


def open_reference_dem(path: str | Path) -> ReferenceDem:
    """The reference DEM at `path`, checked: a raster GDAL reads, with a CRS and a finite value
    somewhere. Raises InputError (one line naming the file)."""
    import rasterio
    from rasterio.errors import RasterioIOError

    p = Path(path).expanduser()
    if not p.is_file():
        raise InputError(p, "upgrade.reference_dem: no such file")
    try:
        with rasterio.open(p) as src:
            if src.crs is None:
                raise InputError(p, "upgrade.reference_dem has no CRS: a reference DEM must be georeferenced "
                                    "(SRTM and Copernicus DEM tiles are EPSG:4326)")
            if src.count < 1:
                raise InputError(p, "upgrade.reference_dem has no band")
            return ReferenceDem(p, src.crs, src.transform, src.width, src.height, src.nodata)
    except RasterioIOError as exc:
        raise InputError(p, f"upgrade.reference_dem is not a raster GDAL can read ({str(exc).splitlines()[0]})") from None


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


def _quadratic_columns(e: np.ndarray, n: np.ndarray) -> np.ndarray:
    return np.stack([np.ones_like(e), e, n, e * e, e * n, n * n], 1)


def fit_surface(E: np.ndarray, N: np.ndarray, r: np.ndarray, centre: np.ndarray, half: float,
                cell_m: float = CELL_M) -> tuple[np.ndarray | None, dict]:
    """The quadratic surface c0 + c1 e + c2 n + a e^2 + b e n + c n^2 (e, n = (E, N - centre) /
    half) through the medians of r (DEM minus structure height) in cells of cell_m. Returns
    ((a, b, c) in metres at e, n = +-1, summary), or (None, summary with the reason)."""
    ok = np.isfinite(r) & np.isfinite(E) & np.isfinite(N)
    E, N, r = E[ok], N[ok], r[ok]
    info: dict = {"points": int(len(r)), "cell_m": float(cell_m)}
    if len(r) == 0:
        return None, {**info, "reason": "the reference DEM has no height under the structure"}
    key = np.stack([np.floor(E / cell_m), np.floor(N / cell_m)], 1).astype(np.int64)
    _, cell, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    cell = cell.ravel()
    order = np.argsort(cell, kind="stable")
    bounds = np.r_[0, np.cumsum(cnt)]
    rs, es, ns = r[order], E[order], N[order]
    full = np.flatnonzero(cnt >= MIN_POINTS_PER_CELL)
    med = np.array([np.median(rs[bounds[i]:bounds[i + 1]]) for i in full])
    ce = (np.add.reduceat(es, bounds[:-1])[full] / cnt[full] - centre[0]) / half
    cn = (np.add.reduceat(ns, bounds[:-1])[full] / cnt[full] - centre[1]) / half
    info["cells"] = int(len(full))
    if len(full) < MIN_CELLS:
        return None, {**info, "reason": f"{len(full)} cells of {cell_m:g} m with >= {MIN_POINTS_PER_CELL} points "
                                        f"under the DEM, {MIN_CELLS} needed"}
    span = min(np.ptp(ce), np.ptp(cn)) / 2.0
    info["span"] = float(span)
    if span < MIN_SPAN:
        return None, {**info, "reason": f"the DEM covers {span:.0%} of the site along one axis, "
                                        f"{MIN_SPAN:.0%} needed to fit its bend"}
    A = _quadratic_columns(ce, cn)
    w = np.ones(len(med))
    for _ in range(20):
        sol = np.linalg.lstsq(A * w[:, None], med * w, rcond=None)[0]
        res = med - A @ sol
        scale = max(1.4826 * float(np.median(np.abs(res))), 1e-6)
        w_new = np.sqrt(np.minimum(1.0, 1.5 * scale / np.maximum(np.abs(res), 1e-12)))   # Huber
        if np.allclose(w_new, w, atol=1e-4):
            break
        w = w_new
    # the surface's standard error at the site's edge, as if the cells were independent (a
    # DEM's errors are correlated over a few cells: a lower bound)
    cov = scale ** 2 * np.linalg.pinv((A * w[:, None]).T @ (A * w[:, None]))
    g = np.linspace(-1.0, 1.0, 11)
    ge, gn = (v.ravel() for v in np.meshgrid(g, g))
    Q = _quadratic_columns(ge, gn)[:, 3:]
    surf = Q @ sol[3:]
    info.update(cell_scale_m=scale, offset_m=float(sol[0]), tilt_m=[float(sol[1]), float(sol[2])],
                bend_coef_m=[float(v) for v in sol[3:]], bend_range_m=float(np.ptp(surf)),
                bend_sigma_m=float(np.sqrt(np.max(np.einsum("ij,jk,ik->i", Q, cov[3:, 3:], Q)))))
    if info["bend_sigma_m"] > MAX_BEND_SIGMA_M:
        return None, {**info, "reason": f"the DEM tells the bend to {info['bend_sigma_m']:.2f} m at the site's "
                                        f"edge (its cells scatter by {scale:.2f} m about the surface), more "
                                        f"than {MAX_BEND_SIGMA_M:g} m"}
    return sol[3:], info


def fit_dem_bend(H: np.ndarray, X_points: np.ndarray, frame, dem: ReferenceDem, X_aff: np.ndarray,
                 X_enu: np.ndarray, centre: np.ndarray, half: float, cell_m: float | None = None,
                 iters: int = 4):
    """The vertical bend of the structure X_points (n, 3, the frame H maps) against the DEM,
    with the affine correction of H refitted on the control GCPs (affine positions X_aff,
    surveyed ENU X_enu, (k, 3), k >= 4) each round. Returns (new H (4, 4), EnuWarp, summary) or
    (None, None, summary with the reason)."""
    cell_m = cell_m or CELL_M
    Hn = np.eye(4)
    Hn[:3] = np.asarray(H, np.float64)[:3]
    warp, info = None, {}
    centre = np.asarray(centre, np.float64)
    for it in range(iters):
        Y = apply_affine_3d(Hn, X_points)
        llh = frame.enu_to_geodetic(Y)
        r = dem.heights(llh[:, 0], llh[:, 1]) - llh[:, 2]
        coef, info = fit_surface(Y[:, 0], Y[:, 1], r, centre, half, cell_m)
        if coef is None:
            return None, None, {**info, "applied": False}
        warp = EnuWarp(centre, float(half), np.r_[np.zeros(6), coef])
        Yc = apply_affine_3d(Hn, X_aff)
        C = np.eye(4)
        C[:3] = fit_affine_3d(Yc + warp(Yc), X_enu)
        Hn = C @ Hn
        info["rounds"] = it + 1
        info["last_correction_m"] = float(np.abs(apply_affine_3d(C, Yc) - Yc).max())
        if info["last_correction_m"] < 1e-3:
            break
    Yc = apply_affine_3d(Hn, X_aff)
    info.update(applied=True, control_rms_m=float(np.sqrt(np.mean(np.sum((Yc + warp(Yc) - X_enu) ** 2, 1)))))
    return Hn, warp, info

"""A simulated coarse reference DEM of a synthetic site (what SRTM or Copernicus GLO-30 would be).

From the site's ground-truth DSM: block means of `cell_m` (a radar DEM's cell sees a roof and the
street beside it as one height), resampled to a geographic grid of 1 arc-second (EPSG:4326, as
SRTM and Copernicus tiles come), with errors of the kind such a DEM has: a constant datum offset
(a geoid, or a bias), a tilt across the site, and spatially correlated noise of `noise_m` with a
correlation length of `corr_m`. For benchmarks and tests: the pipeline reads it as it would read
a real DEM (recon_core.bend.dem), never the truth it was made from.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def simulate_reference_dem(gt_dsm: str | Path, out: str | Path, *, cell_m: float = 30.0, noise_m: float = 2.0,
                           corr_m: float = 300.0, offset_m: float = 20.0, tilt: float = 2e-4,
                           longwave_m: float = 0.0, longwave_km: float = 20.0, percentile: float | None = None,
                           arcsec: float = 1.0, seed: int = 0) -> Path:
    """Write the DEM (float32 GeoTIFF, nodata NaN) to `out` and return its path.

    Harder DEMs for a sensitivity study: `percentile` takes that percentile of each block
    instead of its mean (10: nearly bare earth, a DTM that knows no building; 90: the roofs);
    `longwave_m` adds a wave of that amplitude and of wavelength `longwave_km` in a random
    direction (a DEM's long-wave error, which a dome can take after)."""
    import rasterio
    from rasterio.transform import array_bounds
    from rasterio.warp import Resampling, calculate_default_transform, reproject
    from scipy import ndimage

    with rasterio.open(gt_dsm) as src:
        z = src.read(1, masked=True).astype(np.float64).filled(np.nan)
        tr, crs = src.transform, src.crs
        res = abs(tr.a)
    b = max(1, int(round(cell_m / res)))
    h, w = (z.shape[0] // b) * b, (z.shape[1] // b) * b
    blocks = z[:h, :w].reshape(h // b, b, w // b, b)
    valid = np.isfinite(blocks).sum(axis=(1, 3))
    if percentile is None:
        zb = np.where(valid > 0, np.nansum(blocks, axis=(1, 3)) / np.maximum(valid, 1), np.nan)
    else:
        flat = blocks.transpose(0, 2, 1, 3).reshape(h // b, w // b, b * b)
        zb = np.where(valid > 0, np.nanpercentile(np.where(valid[..., None] > 0, flat, 0.0), percentile, axis=2),
                      np.nan)
    rng = np.random.default_rng(seed)
    noise = ndimage.gaussian_filter(rng.standard_normal(zb.shape), max(corr_m / (b * res) / 2.0, 0.5))
    noise *= noise_m / max(float(noise.std()), 1e-12)
    ii, jj = np.mgrid[0:zb.shape[0], 0:zb.shape[1]]
    zb = zb + noise + offset_m + tilt * b * res * (jj - ii)
    if longwave_m:
        a = rng.uniform(0.0, 2.0 * np.pi, 2)
        along = (np.cos(a[0]) * jj - np.sin(a[0]) * ii) * b * res
        zb = zb + longwave_m * np.sin(2.0 * np.pi * along / (longwave_km * 1e3) + a[1])
    trb = tr @ rasterio.Affine.scale(b)
    bounds = array_bounds(zb.shape[0], zb.shape[1], trb)
    dst_tr, dw, dh = calculate_default_transform(crs, "EPSG:4326", zb.shape[1], zb.shape[0], *bounds,
                                                 resolution=arcsec / 3600.0)
    dem = np.full((dh, dw), np.nan, np.float32)
    reproject(zb.astype(np.float32), dem, src_transform=trb, src_crs=crs, dst_transform=dst_tr,
              dst_crs="EPSG:4326", resampling=Resampling.bilinear, src_nodata=np.nan, dst_nodata=np.nan)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.tif")
    with rasterio.open(tmp, "w", driver="GTiff", width=dw, height=dh, count=1, dtype="float32", crs="EPSG:4326",
                       transform=dst_tr, nodata=np.nan) as dst:
        dst.write(dem, 1)
    tmp.replace(out)
    return out

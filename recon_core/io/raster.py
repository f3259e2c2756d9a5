"""GeoTIFF rasters: the DSM grid and reading/writing single-band float32 GeoTIFFs (COG).

Grid convention: north-up, square cells of side `res` metres; cell (row 0, col 0) has its
top-left corner at (xmin, ymax); cell (r, c) covers x in [xmin + c res, xmin + (c+1) res) and
y in (ymax - (r+1) res, ymax - r res]. Its centre is at (xmin + (c + 0.5) res, ymax - (r + 0.5) res).
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.shutil import copy as rio_copy
from rasterio.transform import Affine
from rasterio.windows import Window

from recon_core.errors import InputError
from recon_core.io.files import atomic_path


# --------------------------------------------------------------------------------------------
# Grid
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Grid:
    """A north-up raster grid in a projected CRS (see the module docstring for conventions)."""

    crs_epsg: int
    xmin: float
    ymax: float
    res: float
    width: int
    height: int

    @property
    def transform(self) -> Affine:
        """rasterio Affine: pixel (col, row) corner -> (x, y)."""
        return Affine(self.res, 0.0, self.xmin, 0.0, -self.res, self.ymax)

    @property
    def crs(self) -> CRS:
        return CRS.from_epsg(self.crs_epsg)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax)."""
        return (self.xmin, self.ymax - self.height * self.res,
                self.xmin + self.width * self.res, self.ymax)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    def cell_of(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) int64 arrays of the cells containing (x, y); may lie outside the grid."""
        col = np.floor((np.asarray(x, dtype=np.float64) - self.xmin) / self.res).astype(np.int64)
        row = np.floor((self.ymax - np.asarray(y, dtype=np.float64)) / self.res).astype(np.int64)
        return row, col

    def contains(self, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """Bool mask of (row, col) inside the grid."""
        return (row >= 0) & (row < self.height) & (col >= 0) & (col < self.width)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates X, Y, each (height, width) float64."""
        xs = self.xmin + (np.arange(self.width) + 0.5) * self.res
        ys = self.ymax - (np.arange(self.height) + 0.5) * self.res
        return np.meshgrid(xs, ys)

    def to_dict(self) -> dict[str, Any]:
        return {"crs_epsg": self.crs_epsg, "xmin": self.xmin, "ymax": self.ymax, "res": self.res,
                "width": self.width, "height": self.height, "bounds": list(self.bounds)}

    @classmethod
    def from_bounds(cls, bounds: tuple[float, float, float, float], res: float,
                    crs_epsg: int) -> "Grid":
        """Grid covering (xmin, ymin, xmax, ymax) with cells of `res` starting at (xmin, ymax)."""
        xmin, ymin, xmax, ymax = map(float, bounds)
        if not (res > 0 and xmax > xmin and ymax > ymin):
            raise ValueError(f"bad grid bounds {bounds} or resolution {res}")
        width = max(1, math.ceil((xmax - xmin) / res - 1e-9))
        height = max(1, math.ceil((ymax - ymin) / res - 1e-9))
        return cls(int(crs_epsg), xmin, ymax, float(res), width, height)

    @classmethod
    def from_site_json(cls, d: dict[str, Any], path: str | Path = "site.json") -> "Grid":
        """Grid from site.json hints {"crs_epsg", "resolution_m", "bounds": [xmin, ymin, xmax, ymax]}."""
        missing = [k for k in ("crs_epsg", "resolution_m", "bounds") if d.get(k) is None]
        if missing:
            raise InputError(path, f"cannot build the DSM grid: missing {', '.join(missing)}")
        b = d["bounds"]
        if len(b) != 4 or not (b[2] > b[0] and b[3] > b[1]) or not d["resolution_m"] > 0:
            raise InputError(path, f"bad bounds {b} or resolution_m {d['resolution_m']}")
        return cls.from_bounds(tuple(b), float(d["resolution_m"]), int(d["crs_epsg"]))

    @classmethod
    def from_points(cls, xy: np.ndarray, res: float, crs_epsg: int,
                    margin: float = 0.0) -> "Grid":
        """Smallest grid snapped to multiples of `res` holding all points plus a margin.

        xy: (n, 2) or (n, 3) coordinates in the grid's CRS.
        """
        xy = np.asarray(xy, dtype=np.float64)
        if len(xy) == 0:
            raise ValueError("no points to build a grid from")
        lo = xy[:, :2].min(axis=0) - margin
        hi = xy[:, :2].max(axis=0) + margin
        xmin = math.floor(lo[0] / res) * res
        ymax = math.ceil(hi[1] / res) * res
        xmin -= res if xmin > lo[0] else 0.0             # guard against rounding
        ymax += res if ymax < hi[1] else 0.0
        width = int(math.floor((hi[0] - xmin) / res)) + 1
        height = int(math.floor((ymax - lo[1]) / res)) + 1
        return cls(int(crs_epsg), float(xmin), float(ymax), float(res), width, height)


# --------------------------------------------------------------------------------------------
# GeoTIFF
# --------------------------------------------------------------------------------------------
def _has_cog_driver() -> bool:
    with rasterio.Env() as env:
        return "COG" in env.drivers()


GDAL_CACHE_MB = 256        # GDAL's block cache while writing (its default: 5 % of the RAM)


def write_geotiff(path: str | Path, arr: np.ndarray, transform: Affine, crs: Any,
                  *, resampling: str = "average", tags: dict[str, str] | None = None,
                  description: str | None = None, units: str | None = None,
                  block_rows: int = 1024) -> Path:
    """Write a single-band float32 raster (NaN nodata) as a Cloud-Optimized GeoTIFF, atomically.

    256 x 256 tiles, DEFLATE with the floating-point predictor, internal overviews. `arr` may be
    disk-backed (np.memmap): it is read `block_rows` rows at a time into a tiled GTiff, which
    GDAL's COG driver then copies with its overviews (GDAL's cache capped at GDAL_CACHE_MB), so
    memory does not grow with the raster.
    Without the COG driver the tiled GTiff gets overviews built after writing and is the result.
    `tags` (dataset metadata), `description` and `units` (of the band) are written when given.
    """
    path = Path(path)
    if not isinstance(arr, np.ndarray):
        arr = np.asarray(arr, dtype=np.float32)
    if arr.ndim != 2:
        raise ValueError(f"expected a 2D array, got shape {arr.shape}")
    cog = _has_cog_driver()
    with atomic_path(path) as tmp, rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB):
        plain = tmp
        if cog:             # named like the atomic temporaries: an interrupted run's is swept
            fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tif", dir=path.parent)
            os.close(fd)
            plain = Path(name)
        try:
            _write_gtiff_tiled(plain, arr, dict(count=1, dtype="float32", width=arr.shape[1],
                                                height=arr.shape[0], crs=crs, transform=transform,
                                                nodata=np.nan),
                               None if cog else resampling, tags, description, units, block_rows)
            if cog:
                rio_copy(plain, tmp, driver="COG", BLOCKSIZE=256, COMPRESS="DEFLATE",
                         PREDICTOR="FLOATING_POINT", OVERVIEWS="AUTO", BIGTIFF="IF_SAFER",
                         OVERVIEW_RESAMPLING=resampling.upper())
        finally:
            if cog and plain.exists():
                plain.unlink()
    return path


def _describe(dst, tags, description, units) -> None:
    if tags:
        dst.update_tags(**tags)
    if description:
        dst.set_band_description(1, description)
    if units:
        dst.units = (units,)


def _write_gtiff_tiled(tmp: Path, arr: np.ndarray, profile: dict, resampling: str | None,
                       tags=None, description=None, units=None, block_rows: int = 1024) -> None:
    """A tiled DEFLATE GTiff written by strips of rows; internal overviews when `resampling`."""
    step = max(256, block_rows // 256 * 256)
    with rasterio.open(tmp, "w", driver="GTiff", tiled=True, blockxsize=256, blockysize=256,
                       compress="deflate", predictor=3, BIGTIFF="IF_SAFER", **profile) as dst:
        for r0 in range(0, arr.shape[0], step):
            r1 = min(r0 + step, arr.shape[0])
            dst.write(np.asarray(arr[r0:r1], dtype=np.float32), 1,
                      window=Window(0, r0, arr.shape[1], r1 - r0))  # pyright: ignore[reportCallIssue]
        _describe(dst, tags, description, units)
        factors, f = [], 2
        while resampling and max(arr.shape) / f >= 256:
            factors.append(f)
            f *= 2
        if factors and resampling:
            dst.build_overviews(factors, Resampling[resampling])


def write_dsm(path: str | Path, H: np.ndarray, grid: Grid) -> Path:
    """Write a DSM (height, width) float32, NaN nodata, in the grid's CRS (see write_geotiff)."""
    if H.shape != grid.shape:
        raise ValueError(f"DSM shape {H.shape} does not match the grid {grid.shape}")
    return write_geotiff(path, H, grid.transform, grid.crs, tags=DSM_TAGS,
                         description="height above the WGS84 ellipsoid", units="metre")


# GDAL metadata of every DSM this project writes: the vertical reference (docs: site-format.md; heights
# are ellipsoidal), so that tools do not take them for orthometric (geoid) heights.
DSM_TAGS = {"AREA_OR_POINT": "Area", "VERTICAL_DATUM": "WGS84 ellipsoid (EPSG:4979 heights)",
            "VERTICAL_UNITS": "metre", "PRODUCER": "AE-Rec"}


def read_dsm(path: str | Path) -> tuple[np.ndarray, Grid]:
    """Read a single-band DSM: (H (height, width) float32 with NaN nodata, its Grid).

    Raises:
        InputError: no CRS, no EPSG code, rotated or non-square pixels.
    """
    with rasterio.open(path) as src:
        if src.crs is None:
            raise InputError(path, "has no CRS; a DSM must be geo-referenced in a projected CRS")
        epsg = src.crs.to_epsg()
        t = src.transform
        if epsg is None:
            raise InputError(path, f"its CRS has no EPSG code ({src.crs.to_string()[:60]})")
        if t.b != 0 or t.d != 0 or t.e >= 0 or not math.isclose(t.a, -t.e, rel_tol=1e-9):
            raise InputError(path, f"needs a north-up grid with square cells, got {tuple(t)[:6]}")
        H = src.read(1, masked=True).astype(np.float32).filled(np.nan)
        grid = Grid(int(epsg), float(t.c), float(t.f), float(t.a), src.width, src.height)
    return H, grid

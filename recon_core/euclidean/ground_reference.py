"""A GCP's ground position from a reference orthoimage and DEM of the site, for a user without a
survey: the point clicked on the orthoimage gives its easting and northing (the orthoimage's
georeferencing), the DEM its height there (bilinear).

Any georeferenced raster serves as the orthoimage (a national orthophoto, a WMS export saved as
GeoTIFF); any georeferenced height raster as the DEM (recon_core.bend.dem.ReferenceDem).
Heights are taken as the DEM gives them and stored as ellipsoidal: a DEM on the geoid (SRTM,
Copernicus DEM: EGM96 / EGM2008) puts every GCP, and so the whole product, off by the geoid's
undulation there (tens of metres, about constant over a site); convert it first.

Pixels follow the project's convention: (col, row) with pixel centres at whole numbers.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from recon_core.errors import InputError
from recon_core.model.images import ImageInfo

if TYPE_CHECKING:
    from affine import Affine

    from recon_core.bend.dem import ReferenceDem

ORTHO_NAME = "reference orthoimage"


@dataclass
class GroundReference:
    """The orthoimage (as an image the viewer can show) and, if given, the DEM."""

    ortho: ImageInfo              # named "reference orthoimage: <file>"
    crs: object
    transform: Affine
    dem: ReferenceDem | None = None

    @cached_property
    def _to_wgs84(self):
        from pyproj import Transformer

        return Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)

    @cached_property
    def _from_wgs84(self):
        from pyproj import Transformer

        return Transformer.from_crs("EPSG:4326", self.crs, always_xy=True)

    def lonlat_at(self, col: float, row: float) -> tuple[float, float]:
        """(lon, lat) of the orthoimage's pixel (col, row)."""
        a = self.transform
        x, y = col + 0.5, row + 0.5                      # GDAL's pixel corners
        e, n = a.a * x + a.b * y + a.c, a.d * x + a.e * y + a.f
        lon, lat = self._to_wgs84.transform(e, n)
        return float(lon), float(lat)

    def pixel_of(self, lon: npt.ArrayLike, lat: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """(col, row) in the orthoimage of points (lon, lat): where GCPs' ground positions lie."""
        e, n = self._from_wgs84.transform(np.asarray(lon, np.float64), np.asarray(lat, np.float64))
        inv = ~self.transform
        e, n = np.asarray(e), np.asarray(n)
        return inv.a * e + inv.b * n + inv.c - 0.5, inv.d * e + inv.e * n + inv.f - 0.5

    def ground_at(self, col: float, row: float) -> tuple[float, float, float | None]:
        """(lon, lat, h) of the orthoimage's pixel; h None without a DEM or where it has none."""
        lon, lat = self.lonlat_at(col, row)
        if self.dem is None:
            return lon, lat, None
        h = float(self.dem.heights(np.array([lon]), np.array([lat]))[0])
        return lon, lat, (h if np.isfinite(h) else None)


    def height_spread(self, lon: float, lat: float, radius_m: float = 1.0) -> float | None:
        """The DEM's range (max - min, m) over the spot and 8 points radius_m around it: large on a
        wall or a roof's edge, where the height of a spot a few centimetres off is another one."""
        if self.dem is None:
            return None
        a = np.deg2rad(np.arange(8) * 45.0)
        dlat = radius_m / 111_320.0
        dlon = dlat / max(np.cos(np.deg2rad(lat)), 1e-6)
        h = self.dem.heights(np.r_[lon, lon + dlon * np.cos(a)], np.r_[lat, lat + dlat * np.sin(a)])
        h = h[np.isfinite(h)]
        return float(np.ptp(h)) if len(h) > 1 else None


    def height_doubt(self, lon: float, lat: float) -> "HeightDoubt | None":
        """How far the DEM's height at a spot can be trusted: its range within 1 m and within
        DOUBT_CELLS of its cells around it (a 5 m DEM smooths a roof into its surroundings: a roof
        corner gets a height between the roof's and the ground's, and only the wider ring shows
        the change). None without a DEM or where it has no height."""
        if self.dem is None:
            return None
        cell = self.dem.cell_m(lat)
        radius = max(1.0, DOUBT_CELLS * cell)
        spread = [x for x in (self.height_spread(lon, lat, 1.0), self.height_spread(lon, lat, radius))
                  if x is not None]
        return None if not spread else HeightDoubt(max(spread), radius, cell)


@dataclass(frozen=True)
class HeightDoubt:
    """The DEM's change around a spot: spread_m (max - min) within radius_m (DOUBT_CELLS of its cells of
    cell_m metres)."""

    spread_m: float
    radius_m: float
    cell_m: float

    @property
    def flat(self) -> bool:
        return self.spread_m <= EDGE_SPREAD_M

    @property
    def sigma_m(self) -> float:
        """The height's standard deviation when taken from the DEM there: anywhere in its range."""
        return max(self.spread_m / 2.0, EDGE_SPREAD_M / 2.0)


EDGE_SPREAD_M = 1.0   # a DEM changing more than this around the spot: its height is uncertain
# ... within this many of its cells (and 1 m). A 5 m DEM averaged from bench_operator's city, 6000
# random spots: 0.75 flags 99 % of the heights more than 0.5 m off (99 % of the others within
# 0.6 m) and 49 % of spots on flat ground; 1.5 flagged 100 % and 79 %, 0.5 96 % and 35 %
DOUBT_CELLS = 0.75


def open_ground_reference(ortho: str | Path, dem: str | Path | None = None) -> GroundReference:
    """The orthoimage (and DEM) checked before use: readable rasters GDAL knows, georeferenced
    (a CRS reachable from WGS84 and a geotransform). Raises InputError (one line naming the file)."""
    import rasterio
    from pyproj import Transformer
    from rasterio.errors import RasterioIOError

    from recon_core.bend.dem import open_reference_dem
    from recon_core.io.site import open_image

    p = Path(ortho).expanduser()
    if not p.is_file():
        raise InputError(p, "--reference-ortho: " + ("a folder, not an image" if p.is_dir() else "no such file"))
    try:
        with rasterio.open(p) as src:
            crs, transform = src.crs, src.transform
    except RasterioIOError as exc:
        raise InputError(p, f"--reference-ortho is not a raster GDAL can read ({str(exc).splitlines()[0]})") from None
    if crs is None or transform.is_identity:
        raise InputError(p, "--reference-ortho is not georeferenced (no CRS or no geotransform): an "
                            "orthoimage must say where its pixels are")
    try:
        Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(transform.c, transform.f)
    except Exception as exc:              # pyproj's CRSError / ProjError
        raise InputError(p, f"--reference-ortho's CRS cannot be turned into WGS84 ({exc})") from None
    info = open_image(p)                  # its pixels readable, a band count and type the viewer shows
    info.name = f"{ORTHO_NAME}: {p.name}"
    ref = GroundReference(info, crs, transform)
    if dem is not None:
        ref.dem = open_reference_dem(dem, option="--reference-dem")
    return ref


# -- where the site is, and reference files that must cover it ---------------------------------
MAX_REFERENCE_GAP_M = 10_000.0    # a reference file farther than this from every point of the
                                  # site is of another place (a footprint's own error is metres)


def site_lonlat(site, gcps=None) -> np.ndarray | None:
    """(n, 2) lon, lat of what says where a site is: its enabled GCPs, its images' footprints
    (from their RPCs, for this check only), the corners of site.json's bounds; None without any."""
    from recon_core.geometry.geodesy import projected_to_geodetic
    from recon_core.io.footprints import image_footprints

    pts = [np.array([[g.lon, g.lat] for g in (site.gcps if gcps is None else gcps) if g.enabled]).reshape(-1, 2)]
    pts += [ll for _, ll in image_footprints(site)]
    b, epsg = site.hints.get("bounds"), site.hints.get("crs_epsg")
    if b and epsg:
        xy = np.array([[b[0], b[1], 0.0], [b[2], b[1], 0.0], [b[2], b[3], 0.0], [b[0], b[3], 0.0]])
        pts.append(projected_to_geodetic(xy, int(epsg))[:, :2])
    pts = np.concatenate(pts) if pts else np.zeros((0, 2))
    return pts if len(pts) else None


def _raster_lonlat_box(path: Path, crs, transform, width: int, height: int) -> np.ndarray:
    """(4, 2) lon, lat of a raster's corners."""
    from pyproj import Transformer

    t = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    a, b, c, d, e, f = transform[:6]           # the affine's coefficients (no operator that
                                               # changes meaning across affine's versions)
    corners = [(a * x + b * y + c, d * x + e * y + f)
               for x, y in ((0, 0), (width, 0), (width, height), (0, height))]
    return np.array([t.transform(x, y) for x, y in corners], np.float64)


def gap_m(points: np.ndarray, box: np.ndarray) -> float:
    """Metres from the nearest of `points` (n, 2 lon, lat) to the lon-lat box of `box` (k, 2)."""
    from recon_core.geometry.geodesy import LocalFrame

    f = LocalFrame(float(np.mean(box[:, 0])), float(np.mean(box[:, 1])))
    b = f.geodetic_to_enu(np.c_[box, np.zeros(len(box))])[:, :2]
    q = f.geodetic_to_enu(np.c_[points, np.zeros(len(points))])[:, :2]
    gap = np.maximum(np.maximum(b.min(0) - q, q - b.max(0)), 0.0)
    return float(np.min(np.hypot(gap[:, 0], gap[:, 1])))


def check_reference_files(site, gcps=None, *, ortho: "GroundReference | None" = None, dem=None,
                          dem_option: str = "--reference-dem") -> None:
    """The reference files of a site, whichever command reads them (`aerec run --reference-dem`,
    `aerec view --reference-ortho / --reference-dem`): a DEM must have heights (not all nodata)
    and have them where the site is; an orthoimage must lie where the site is. InputError naming
    the file otherwise. Where nothing says where the site is (no GCP, no RPC, no site.json), only
    the DEM's heights are checked."""
    from recon_core.bend.dem import has_heights

    if dem is not None and not has_heights(dem):
        raise InputError(dem.path, f"{dem_option} has no height anywhere (every value is nodata or not finite)")
    pts = site_lonlat(site, gcps)
    if pts is None:
        return
    if dem is not None:
        lo, hi = pts.min(axis=0), pts.max(axis=0)          # and inside the site, not only its corners
        gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 9), np.linspace(lo[1], hi[1], 9))
        grid = np.c_[gx.ravel(), gy.ravel()]
        h = dem.heights(np.r_[pts[:, 0], grid[:, 0]], np.r_[pts[:, 1], grid[:, 1]])
        if not np.isfinite(h).any():
            d = gap_m(pts, _raster_lonlat_box(dem.path, dem.crs, dem.transform, dem.width, dem.height))
            raise InputError(dem.path, f"{dem_option} has no height where the site is: "
                                       + (f"it lies {d / 1000:,.0f} km from it" if d > 0 else
                                          "it is all nodata there"))
    if ortho is not None:
        d = gap_m(pts, _raster_lonlat_box(Path(ortho.ortho.path), ortho.crs, ortho.transform,
                                          ortho.ortho.width, ortho.ortho.height))
        if d > MAX_REFERENCE_GAP_M:
            raise InputError(ortho.ortho.path, f"--reference-ortho lies {d / 1000:,.0f} km from the site (its GCPs, "
                                               "its images' footprints or site.json's bounds): another place")

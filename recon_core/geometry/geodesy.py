"""WGS84 geodetic <-> ECEF <-> local ENU <-> UTM conversions.

Geodetic coordinates are (lon, lat, h): degrees, degrees, ellipsoidal metres (EPSG:4979).
ECEF is EPSG:4978 in metres. ENU is the local tangent frame at an origin given in geodetic
coordinates. All functions take and return float64 arrays of shape (..., 3) unless stated.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from pyproj import CRS, Transformer

WGS84_A = 6378137.0                 # the WGS84 ellipsoid: semi-major axis (m), flattening
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


@lru_cache(maxsize=64)
def _transformer(src: str, dst: str) -> Transformer:
    return Transformer.from_crs(CRS.from_user_input(src), CRS.from_user_input(dst), always_xy=True)


def geodetic_to_ecef(llh: np.ndarray) -> np.ndarray:
    """(lon, lat, h) -> ECEF (x, y, z), closed form."""
    llh = np.asarray(llh, dtype=np.float64)
    lon, lat, h = np.radians(llh[..., 0]), np.radians(llh[..., 1]), llh[..., 2]
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    x = (n + h) * np.cos(lat) * np.cos(lon)
    y = (n + h) * np.cos(lat) * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * np.sin(lat)
    return np.stack([x, y, z], axis=-1)


def ecef_to_geodetic(xyz: np.ndarray) -> np.ndarray:
    """ECEF -> (lon, lat, h) by pyproj (exact to well below a millimetre)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    t = _transformer("EPSG:4978", "EPSG:4979")
    lon, lat, h = t.transform(xyz[..., 0], xyz[..., 1], xyz[..., 2])
    return np.stack([lon, lat, h], axis=-1)


def enu_rotation(lon0: float, lat0: float) -> np.ndarray:
    """3x3 rotation whose rows are the E, N, U unit vectors at (lon0, lat0), in ECEF."""
    lo, la = np.radians(lon0), np.radians(lat0)
    return np.array([
        [-np.sin(lo), np.cos(lo), 0.0],
        [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
        [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)],
    ])


class LocalFrame:
    """A local ENU frame at a geodetic origin; converts to and from geodetic, ECEF and UTM."""

    def __init__(self, lon0: float, lat0: float, h0: float = 0.0):
        self.origin_llh = np.array([lon0, lat0, h0], dtype=np.float64)
        self.origin_ecef = geodetic_to_ecef(self.origin_llh)
        self.R = enu_rotation(lon0, lat0)

    def ecef_to_enu(self, xyz: np.ndarray) -> np.ndarray:
        return (np.asarray(xyz, dtype=np.float64) - self.origin_ecef) @ self.R.T

    def enu_to_ecef(self, enu: np.ndarray) -> np.ndarray:
        return np.asarray(enu, dtype=np.float64) @ self.R + self.origin_ecef

    def geodetic_to_enu(self, llh: np.ndarray) -> np.ndarray:
        return self.ecef_to_enu(geodetic_to_ecef(llh))

    def enu_to_geodetic(self, enu: np.ndarray) -> np.ndarray:
        return ecef_to_geodetic(self.enu_to_ecef(enu))

    def to_dict(self) -> dict:
        return {"lon0": float(self.origin_llh[0]), "lat0": float(self.origin_llh[1]),
                "h0": float(self.origin_llh[2])}


def utm_epsg_for(lon: float, lat: float) -> int:
    """EPSG code of the WGS84 UTM zone containing (lon, lat)."""
    zone = int(np.floor((lon + 180.0) / 6.0)) % 60 + 1
    return (32600 if lat >= 0 else 32700) + zone


def geodetic_to_projected(llh: np.ndarray, epsg: int) -> np.ndarray:
    """(lon, lat, h) -> (x, y, h) in a projected 2D CRS; h passes through unchanged."""
    llh = np.asarray(llh, dtype=np.float64)
    x, y = _transformer("EPSG:4326", f"EPSG:{epsg}").transform(llh[..., 0], llh[..., 1])
    return np.stack([x, y, llh[..., 2]], axis=-1)


def projected_to_geodetic(xyh: np.ndarray, epsg: int) -> np.ndarray:
    """(x, y, h) in a projected 2D CRS -> (lon, lat, h)."""
    xyh = np.asarray(xyh, dtype=np.float64)
    lon, lat = _transformer(f"EPSG:{epsg}", "EPSG:4326").transform(xyh[..., 0], xyh[..., 1])
    return np.stack([lon, lat, xyh[..., 2]], axis=-1)

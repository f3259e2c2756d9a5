"""Rational polynomial camera models (RPC00B): projection, localisation, GDAL/rasterio round
trip. AE-Rec's reconstruction never reads an RPC; benchmarks, evaluations and `aerec site init`
(for a product's footprint) do.

Conventions: ground (lon, lat, h) in degrees and ellipsoidal metres (EPSG:4979); image (col,
row) = (sample, line), centre of the top-left pixel at (0, 0), as RPC00B and the site format
(GDAL's RPC transformer, in corner coordinates, reports col + 0.5, row + 0.5); the 20 RPC00B
monomials of L, P, H (normalised lon, lat, h) in the standard's order.
"""

from __future__ import annotations

from dataclasses import dataclass

from typing import Any

import numpy as np

N_COEF = 20       # the RPC00B cubic polynomial's coefficients (per numerator and denominator)


def monomials(L: np.ndarray, P: np.ndarray, H: np.ndarray) -> np.ndarray:
    """RPC00B monomials of normalised coordinates: (n,) x 3 -> (n, 20)."""
    one = np.ones_like(L)
    return np.stack([one, L, P, H, L * P, L * H, P * H, L * L, P * P, H * H,
                     P * L * H, L ** 3, L * P * P, L * H * H, L * L * P, P ** 3, P * H * H,
                     L * L * H, P * P * H, H ** 3], axis=-1)


@dataclass
class RPCModel:
    """An RPC00B model: normalisation offsets/scales and four 20-coefficient polynomials."""

    line_off: float
    samp_off: float
    lat_off: float
    long_off: float
    height_off: float
    line_scale: float
    samp_scale: float
    lat_scale: float
    long_scale: float
    height_scale: float
    line_num: np.ndarray
    line_den: np.ndarray
    samp_num: np.ndarray
    samp_den: np.ndarray
    err_bias: float = -1.0
    err_rand: float = -1.0

    # ---- projection
    def _norm(self, llh: np.ndarray) -> np.ndarray:
        llh = np.atleast_2d(np.asarray(llh, dtype=np.float64))
        return monomials((llh[:, 0] - self.long_off) / self.long_scale,
                         (llh[:, 1] - self.lat_off) / self.lat_scale,
                         (llh[:, 2] - self.height_off) / self.height_scale)

    def project(self, llh: np.ndarray) -> np.ndarray:
        """(n, 3) lon, lat, h -> (n, 2) col, row (pixel centre convention)."""
        m = self._norm(llh)
        row = self.line_off + self.line_scale * (m @ self.line_num) / (m @ self.line_den)
        col = self.samp_off + self.samp_scale * (m @ self.samp_num) / (m @ self.samp_den)
        return np.stack([col, row], axis=-1)

    def localize(self, colrow: np.ndarray, h: np.ndarray | float, n_iter: int = 20,
                 tol_px: float = 1e-6) -> np.ndarray:
        """Inverse projection: (n, 2) col, row at heights h -> (n, 3) lon, lat, h (Newton)."""
        colrow = np.atleast_2d(np.asarray(colrow, dtype=np.float64))
        n = colrow.shape[0]
        hh = np.broadcast_to(np.asarray(h, dtype=np.float64), (n,)).copy()
        lon = np.full(n, self.long_off)
        lat = np.full(n, self.lat_off)
        dlon = 1e-6 * self.long_scale
        dlat = 1e-6 * self.lat_scale
        for _ in range(n_iter):
            p0 = self.project(np.stack([lon, lat, hh], -1))
            p1 = self.project(np.stack([lon + dlon, lat, hh], -1))
            p2 = self.project(np.stack([lon, lat + dlat, hh], -1))
            J = np.stack([(p1 - p0) / dlon, (p2 - p0) / dlat], axis=-1)   # (n, 2, 2)
            r = colrow - p0
            d = np.linalg.solve(J, r[..., None])[..., 0]
            lon += d[:, 0]
            lat += d[:, 1]
            if np.max(np.abs(r)) < tol_px:
                break
        return np.stack([lon, lat, hh], axis=-1)

    # ---- serialisation
    def to_dict(self) -> dict:
        d: dict[str, Any] = {k: float(getattr(self, k)) for k in (
            "line_off", "samp_off", "lat_off", "long_off", "height_off", "line_scale",
            "samp_scale", "lat_scale", "long_scale", "height_scale", "err_bias", "err_rand")}
        for k in ("line_num", "line_den", "samp_num", "samp_den"):
            d[k] = [float(v) for v in getattr(self, k)]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RPCModel":
        kw: dict[str, Any] = {k: float(d[k]) for k in (
            "line_off", "samp_off", "lat_off", "long_off", "height_off", "line_scale",
            "samp_scale", "lat_scale", "long_scale", "height_scale")}
        for k in ("line_num", "line_den", "samp_num", "samp_den"):
            kw[k] = np.asarray(d[k], dtype=np.float64)
        return cls(err_bias=float(d.get("err_bias", -1.0)), err_rand=float(d.get("err_rand", -1.0)),
                   **kw)

    def to_rasterio(self):
        """rasterio.rpc.RPC for writing into GDAL's RPC metadata domain."""
        from rasterio.rpc import RPC

        # (as a keyword dict: rasterio's RPC is an untyped attrs class, whose fields a checker
        # cannot see)
        kw: dict[str, Any] = dict(height_off=self.height_off, height_scale=self.height_scale,
                                  lat_off=self.lat_off, lat_scale=self.lat_scale,
                                  line_den_coeff=[float(v) for v in self.line_den],
                                  line_num_coeff=[float(v) for v in self.line_num],
                                  line_off=self.line_off, line_scale=self.line_scale,
                                  long_off=self.long_off, long_scale=self.long_scale,
                                  samp_den_coeff=[float(v) for v in self.samp_den],
                                  samp_num_coeff=[float(v) for v in self.samp_num],
                                  samp_off=self.samp_off, samp_scale=self.samp_scale,
                                  err_bias=self.err_bias, err_rand=self.err_rand)
        return RPC(**kw)

    @classmethod
    def from_rasterio(cls, rpcs) -> "RPCModel":
        """From a rasterio.rpc.RPC (e.g. ``dataset.rpcs``)."""
        return cls(line_off=float(rpcs.line_off), samp_off=float(rpcs.samp_off),
                   lat_off=float(rpcs.lat_off), long_off=float(rpcs.long_off),
                   height_off=float(rpcs.height_off), line_scale=float(rpcs.line_scale),
                   samp_scale=float(rpcs.samp_scale), lat_scale=float(rpcs.lat_scale),
                   long_scale=float(rpcs.long_scale), height_scale=float(rpcs.height_scale),
                   line_num=np.asarray(rpcs.line_num_coeff, dtype=np.float64),
                   line_den=np.asarray(rpcs.line_den_coeff, dtype=np.float64),
                   samp_num=np.asarray(rpcs.samp_num_coeff, dtype=np.float64),
                   samp_den=np.asarray(rpcs.samp_den_coeff, dtype=np.float64),
                   err_bias=float(rpcs.err_bias if rpcs.err_bias is not None else -1.0),
                   err_rand=float(rpcs.err_rand if rpcs.err_rand is not None else -1.0))

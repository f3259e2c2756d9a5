"""Rational polynomial camera models (RPC00B): fitting, projection, GDAL/rasterio round trip.

Conventions
-----------
* Ground coordinates are (lon, lat, h): degrees, degrees, ellipsoidal metres (EPSG:4979).
* Image coordinates are (col, row) = (sample, line) with the centre of the top-left pixel at
  (0, 0), the convention of the RPC00B standard and of the site format. (GDAL's RPC
  transformer, in pixel/line *corner* coordinates, therefore reports col + 0.5, row + 0.5.)
* Normalised variables: L = (lon - LONG_OFF) / LONG_SCALE, P = (lat - LAT_OFF) / LAT_SCALE,
  H = (h - HEIGHT_OFF) / HEIGHT_SCALE; row = LINE_OFF + LINE_SCALE * Num_L / Den_L and
  col = SAMP_OFF + SAMP_SCALE * Num_S / Den_S, with the 20 RPC00B monomials in the order
  1, L, P, H, LP, LH, PH, L^2, P^2, H^2, PLH, L^3, LP^2, LH^2, L^2P, P^3, PH^2, L^2H, P^2H, H^3.

Fitting (:func:`fit_rpc`) is the usual terrain-independent scheme: project a 3D grid of ground
points (several height layers) with the physical camera, then solve the linearised problem
``Num - y Den = 0`` (Den's constant term fixed to 1) by linear least squares on normalised
variables with a light Tikhonov term, re-weighting by 1/Den a few times so that the weighted
linear residual equals the true image residual. :func:`rpc_residuals` measures the fit on an
independent, staggered check grid.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from recon_core.geometry.rpc import N_COEF, RPCModel, monomials  # noqa: F401 (re-exported)


# ----------------------------------------------------------------------------------------
def ground_grid(bounds: tuple[float, float, float, float, float, float], n_xy: int, n_h: int,
                stagger: bool = False) -> np.ndarray:
    """Regular 3D grid (n_xy x n_xy x n_h, 3) of (lon, lat, h) over
    bounds = (lon_min, lon_max, lat_min, lat_max, h_min, h_max); `stagger` shifts every axis
    by half a step (cells' centres), giving a check grid disjoint from the fit grid."""
    lo0, lo1, la0, la1, h0, h1 = bounds

    def axis(a, b, n):
        if stagger:
            step = (b - a) / n
            return a + step * (np.arange(n) + 0.5)
        return np.linspace(a, b, n)

    L, P, H = np.meshgrid(axis(lo0, lo1, n_xy), axis(la0, la1, n_xy), axis(h0, h1, n_h),
                          indexing="ij")
    return np.stack([L.ravel(), P.ravel(), H.ravel()], axis=-1)


def _fit_ratio(M: np.ndarray, y: np.ndarray, reg: float, n_iter: int) -> tuple[np.ndarray, np.ndarray]:
    """Fit y ~ (M @ num) / (M @ den), den[0] = 1, by reweighted linear least squares."""
    w = np.ones(len(y))
    num = den = None
    for _ in range(n_iter):
        A = np.hstack([M, -y[:, None] * M[:, 1:]]) * w[:, None]
        b = y * w
        AtA = A.T @ A
        lam = reg * np.trace(AtA) / AtA.shape[0]
        x = np.linalg.solve(AtA + lam * np.eye(AtA.shape[0]), A.T @ b)
        num = x[:N_COEF]
        den = np.concatenate([[1.0], x[N_COEF:]])
        B = M @ den
        w = 1.0 / np.maximum(np.abs(B), 1e-6)
    assert num is not None and den is not None   # n_iter >= 1
    return num, den


def fit_rpc(project_fn: Callable[[np.ndarray], np.ndarray],
            bounds: tuple[float, float, float, float, float, float],
            image_size: tuple[int, int] | None = None, n_xy: int = 21, n_h: int = 7,
            reg: float = 1e-7, n_iter: int = 3) -> RPCModel:
    """Fit an RPC00B model to a camera.

    project_fn: (n, 3) lon, lat, h -> (n, 2) col, row (pixel-centre convention).
    bounds: (lon_min, lon_max, lat_min, lat_max, h_min, h_max) of the ground volume to fit
        (the image footprint over the scene's height range).
    image_size: (width, height) for the image normalisation (else from the projections).
    n_xy, n_h: grid points per horizontal axis and height layers.
    reg: Tikhonov weight relative to the mean diagonal of the normal matrix.
    """
    X = ground_grid(bounds, n_xy, n_h)
    uv = np.asarray(project_fn(X), dtype=np.float64)
    ok = np.all(np.isfinite(uv), axis=1)
    X, uv = X[ok], uv[ok]
    lo0, lo1, la0, la1, h0, h1 = bounds
    if image_size is not None:
        w, h = image_size
        samp_off, line_off = (w - 1) / 2.0, (h - 1) / 2.0
        samp_scale, line_scale = w / 2.0, h / 2.0
    else:
        samp_off = 0.5 * (uv[:, 0].min() + uv[:, 0].max())
        line_off = 0.5 * (uv[:, 1].min() + uv[:, 1].max())
        samp_scale = max(0.5 * (uv[:, 0].max() - uv[:, 0].min()), 1.0)
        line_scale = max(0.5 * (uv[:, 1].max() - uv[:, 1].min()), 1.0)
    model = RPCModel(line_off=line_off, samp_off=samp_off,
                     lat_off=0.5 * (la0 + la1), long_off=0.5 * (lo0 + lo1),
                     height_off=0.5 * (h0 + h1), line_scale=line_scale, samp_scale=samp_scale,
                     lat_scale=max(0.5 * (la1 - la0), 1e-9),
                     long_scale=max(0.5 * (lo1 - lo0), 1e-9),
                     height_scale=max(0.5 * (h1 - h0), 1.0),
                     line_num=np.zeros(N_COEF), line_den=np.zeros(N_COEF),
                     samp_num=np.zeros(N_COEF), samp_den=np.zeros(N_COEF))
    M = model._norm(X)
    model.line_num, model.line_den = _fit_ratio(M, (uv[:, 1] - line_off) / line_scale, reg, n_iter)
    model.samp_num, model.samp_den = _fit_ratio(M, (uv[:, 0] - samp_off) / samp_scale, reg, n_iter)
    return model


def rpc_residuals(model: RPCModel, project_fn: Callable[[np.ndarray], np.ndarray],
                  bounds: tuple[float, float, float, float, float, float],
                  image_size: tuple[int, int] | None = None, n_xy: int = 30,
                  n_h: int = 6) -> dict:
    """RPC vs camera on a staggered check grid (disjoint from the fit grid).

    Only points projecting inside the image (when image_size is given) are scored.
    Returns {"max_px", "rms_px", "n_check"} (Euclidean pixel distance).
    """
    X = ground_grid(bounds, n_xy, n_h, stagger=True)
    uv = np.asarray(project_fn(X), dtype=np.float64)
    ok = np.all(np.isfinite(uv), axis=1)
    if image_size is not None:
        w, h = image_size
        ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)
    d = np.linalg.norm(model.project(X[ok]) - uv[ok], axis=1)
    return {"max_px": float(d.max()), "rms_px": float(np.sqrt(np.mean(d ** 2))),
            "n_check": int(ok.sum())}

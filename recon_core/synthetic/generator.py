"""Synthetic satellite sites: a procedural city rendered by true pushbroom cameras.

:func:`generate_site` writes a complete site folder in the project's site format
(docs: site-format.md) and returns the truth (:class:`SynthTruth`)::

    SITE/
      images/img_XX.tif    uint16 11-bit panchromatic, tiled GeoTIFF, TIFFTAG_DATETIME (UTC),
                           RPC00B fitted to the physical camera in GDAL's RPC domain
                           ((0, 0) = centre of the top-left pixel)
      images/img_XX.json   {"acquired": "YYYY-MM-DDTHH:MM:SSZ", "view": {"incidence_deg", "azimuth_deg"}}
      gcps.geojson         12-20 GCPs (EPSG:4979 lon, lat, ellipsoidal h), observations =
                           true projection + 0.3 px noise in the images where visible;
                           4 "role": "control" (largest tetrahedron), the others "check"
      gt_dsm.tif           float32 DSM, site UTM zone, 0.5 m, ellipsoidal heights, nodata -9999
                           outside the area seen by >= 2 images of one date group
      site.json            name, crs_epsg, resolution_m = 0.5, bounds of that area
      truth/               TRUTH FOR TESTS AND EVALUATION ONLY: the pipeline never reads it
        cameras.json       the physical pushbroom cameras (:meth:`PushbroomCamera.to_dict`),
                           reload with :func:`load_truth_cameras`
        scene.json         the scene model parameters (reload with :func:`load_truth_scene`)
        images.json        per image: date group, acquisition time, sun and view angles
        rpc_fit.json       RPC fit residuals (max, RMS px) on an independent 3D check grid
        gcps_truth.json    GCPs with noise-free projections and scene-local coordinates

Scene: :class:`recon_core.synthetic.generator.scene_model.SceneModel` (h = H(E, N) over UTM easting/northing,
evaluated analytically by numba kernels). Cameras: :class:`PushbroomCamera`, a linear array on
a circular ~620-700 km orbit in ECEF (Earth rotation included) with agile steering: the
boresight of line ``row`` aims at a ground target moving one GSD per line along the scan
azimuth, plus smooth attitude drift and small jitter. Rendering casts ss x ss rays per pixel
into the height field (occlusions, cast shadows, Lambert + sky light), applies a Gaussian PSF,
shot and read noise, and quantises to 0..2047.

Everything is deterministic for a (preset, seed): same bytes.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np

from recon_core.geometry.geodesy import (
    WGS84_A,
    WGS84_E2,
    LocalFrame,
    enu_rotation,
    geodetic_to_ecef,
    geodetic_to_projected,
)
from recon_core.io.files import atomic_path, write_json
from recon_core.synthetic import scene_model as sm
from recon_core.synthetic.rpc import RPCModel, fit_rpc, rpc_residuals
from recon_core.synthetic.scene_model import SceneModel

GM = 3.986004418e14          # m^3 / s^2
OMEGA_EARTH = 7.2921150e-5   # rad / s
SSO_INCLINATION = 97.8       # degrees
NODATA = -9999.0

Progress = Callable[[str, int, int], None]

# ----------------------------------------------------------------------------------------
# Presets


@dataclass(frozen=True)
class SynthPreset:
    """Parameters of a synthetic site.

    groups: number of images in each date group (dates in a group < 15 days apart).
    group_months: acquisition month of each group (groups months apart).
    image_size: nominal (width, height) in pixels; each image varies by +-size_jitter.
    first_image_size: optional exact size of image 0 (e.g. the large preset's 8192 px).
    gsd: ground sample distance at the scene (m); the IFOV of each image is set for it.
    off_nadir: (min, max) off-nadir angle (deg) at the satellite.
    bh: (min, max) base-to-height ratio required between the images of a group.
    supersample: ss (ss x ss rays per pixel). psf_sigma: Gaussian PSF sigma (px).
    altitude: (min, max) orbit altitude (m).
    accel_cell, accel_sample: cell size and sampling step (m) of the max-height acceleration
        grid (finer sampling = tighter bounds = faster rendering, slower set-up).
    n_gcps: number of GCPs. block_rows: rows rendered per block.
    drift: scale of the attitude drift (1 = a few microradians over a 0.8 s acquisition).
    bow_px, distortion_px: a focal plane that is not one straight, undistorted line (0: it is).
    scene: overrides of the procedural scene (scene_model.scene_params: park, open, tall, terrain).
    """

    name: str
    groups: tuple[int, ...]
    group_months: tuple[int, ...]
    image_size: tuple[int, int]
    size_jitter: float = 0.06
    first_image_size: tuple[int, int] | None = None
    gsd: float = 0.5
    off_nadir: tuple[float, float] = (5.0, 30.0)
    bh: tuple[float, float] = (0.1, 0.6)
    supersample: int = 2
    psf_sigma: float = 0.45
    altitude: tuple[float, float] = (620e3, 690e3)
    accel_cell: float = 1.0
    accel_sample: float = 0.25
    n_gcps: int = 16
    block_rows: int = 128
    drift: float = 1.0
    year: int = 2021
    scene: tuple[tuple[str, float], ...] = ()   # scene_model.scene_params overrides
    bow_px: float = 0.0           # focal plane (PushbroomCamera): each image's line bowed by
    distortion_px: float = 0.0    # 0.5-1 times this many rows at its ends, its across-track
                                  # distortion 0.5-1 times this many columns (either sign)

    @property
    def n_images(self) -> int:
        return int(sum(self.groups))


PRESETS: dict[str, SynthPreset] = {
    "tiny": SynthPreset(name="tiny", groups=(3,), group_months=(4,), image_size=(400, 400),
                        n_gcps=12, block_rows=64),
    # two date groups of 2 small images: the smallest site that exercises fusion (ICP)
    "tiny2": SynthPreset(name="tiny2", groups=(2, 2), group_months=(4, 9), image_size=(400, 400),
                         n_gcps=12, block_rows=64),
    "demo": SynthPreset(name="demo", groups=(3, 3), group_months=(3, 8),
                        image_size=(2000, 2000), n_gcps=16),
    # sensors as real ones are, and as an independent simulator makes them (omaha_3dates): a
    # bowed, distorted focal plane and an attitude drift of pixels; `tiny2`'s and `demo`'s layouts
    "tiny2fp": SynthPreset(name="tiny2fp", groups=(2, 2), group_months=(4, 9), image_size=(400, 400),
                           n_gcps=12, block_rows=64, bow_px=1.0, distortion_px=3.0, drift=10.0),
    "demofp": SynthPreset(name="demofp", groups=(3, 3), group_months=(3, 8), image_size=(2000, 2000),
                          n_gcps=16, bow_px=1.0, distortion_px=3.0, drift=10.0),
    # the viewer's first demo: `demo`'s layout on 1200 px images rendered with one ray per
    # pixel (11x fewer rays): generated in seconds, first points within a minute
    # the demo shipped in assets/ (a few MB): `demo`'s layout on 800 px images, one ray per pixel
    "mini": SynthPreset(name="mini", groups=(3, 3), group_months=(3, 8), image_size=(800, 800),
                        supersample=1, n_gcps=12),
    # `mini` with sensors as real ones are (the focal plane and drift of `demofp`): the small
    # site of the upgrade's tests with 6 views
    "minifp": SynthPreset(name="minifp", groups=(3, 3), group_months=(3, 8), image_size=(800, 800),
                          supersample=1, n_gcps=12, bow_px=1.0, distortion_px=3.0, drift=10.0),
    "quick": SynthPreset(name="quick", groups=(3, 3), group_months=(3, 8),
                         image_size=(1200, 1200), supersample=1, n_gcps=16),
    # a flat suburb of ~2.5 km seen by 3 views (one pair with a small angle): low buildings,
    # many parks and open flat blocks, gentle terrain; most tiles see nearly coplanar ground
    "flat": SynthPreset(name="flat", groups=(3,), group_months=(5,), image_size=(5000, 5000),
                        size_jitter=0.04, supersample=1, accel_cell=2.0, accel_sample=0.5,
                        bh=(0.08, 0.45), n_gcps=20, block_rows=256,
                        scene=(("park", 0.3), ("open", 0.35), ("tall", 0.15), ("terrain", 0.5))),
    # `flat` with sensors as real ones are (`demofp`'s focal plane and drift, which over a
    # 5000-row scan reach pixels): the one-date bend of real sensors over kilometres
    "flatfp": SynthPreset(name="flatfp", groups=(3,), group_months=(5,), image_size=(5000, 5000),
                          size_jitter=0.04, supersample=1, accel_cell=2.0, accel_sample=0.5,
                          bh=(0.08, 0.45), n_gcps=20, block_rows=256,
                          scene=(("park", 0.3), ("open", 0.35), ("tall", 0.15), ("terrain", 0.5)),
                          bow_px=1.0, distortion_px=3.0, drift=10.0),
    "large": SynthPreset(name="large", groups=(3, 3, 3), group_months=(2, 6, 10),
                         image_size=(6000, 6000), size_jitter=0.1,
                         first_image_size=(8192, 8192), supersample=1, accel_cell=2.0,
                         accel_sample=0.5,
                         n_gcps=20, block_rows=256),
    # a 10 km site: one date of 3 images of ~10,000 px at 1 m GSD (the extent of a real scene
    # with a quarter of its pixels at 0.5 m); the scale issue's end-to-end reference
    "wide": SynthPreset(name="wide", groups=(3,), group_months=(5,), image_size=(10000, 10000),
                        size_jitter=0.04, gsd=1.0, supersample=1, accel_cell=2.0,
                        accel_sample=0.5, n_gcps=24, block_rows=256),
    # the same 10 km extent over three dates of 3 images (large's layout at wide's size): what
    # the dates' different views do to the bend of one date, end to end
    "wide3": SynthPreset(name="wide3", groups=(3, 3, 3), group_months=(2, 6, 10),
                         image_size=(10000, 10000), size_jitter=0.04, gsd=1.0, supersample=1,
                         accel_cell=2.0, accel_sample=0.5, n_gcps=24, block_rows=256),
}

# ----------------------------------------------------------------------------------------
# Geodesy helpers (vectorised, fast)


def ecef_to_llh_fast(X: np.ndarray) -> np.ndarray:
    """ECEF (..., 3) -> (lon, lat, h) (..., 3) by Bowring's formula (< 0.1 mm near the Earth)."""
    X = np.asarray(X, dtype=np.float64)
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    a = WGS84_A
    e2 = WGS84_E2
    b = a * math.sqrt(1.0 - e2)
    ep2 = e2 / (1.0 - e2)
    p = np.hypot(x, y)
    th = np.arctan2(z * a, p * b)
    lat = np.arctan2(z + ep2 * b * np.sin(th) ** 3, p - e2 * a * np.cos(th) ** 3)
    sl, cl = np.sin(lat), np.cos(lat)
    h = p * cl + z * sl - a * np.sqrt(1.0 - e2 * sl * sl)
    return np.stack([np.degrees(np.arctan2(y, x)), np.degrees(lat), h], axis=-1)


def _normal_ecef(llh: np.ndarray) -> np.ndarray:
    """Ellipsoid normal (up) unit vectors at (..., 3) geodetic points."""
    lon, lat = np.radians(llh[..., 0]), np.radians(llh[..., 1])
    return np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], -1)


def intersect_height(origin: np.ndarray, direction: np.ndarray, h: np.ndarray | float,
                     n_iter: int = 12, tol: float = 1e-6) -> np.ndarray:
    """Points where rays O + s d (..., 3), unit d, reach ellipsoidal height h: (..., 3) ECEF."""
    O = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    O, d = np.broadcast_arrays(O, d)
    h = np.broadcast_to(np.asarray(h, dtype=np.float64), O.shape[:-1])
    llh = ecef_to_llh_fast(O)
    up = _normal_ecef(llh)
    s = (llh[..., 2] - h) / np.maximum(-np.sum(d * up, -1), 1e-3)
    for _ in range(n_iter):
        X = O + s[..., None] * d
        llh = ecef_to_llh_fast(X)
        dh = llh[..., 2] - h
        rate = np.sum(d * _normal_ecef(llh), -1)
        s = s - dh / np.minimum(rate, -1e-3)
        if np.max(np.abs(dh)) < tol:
            break
    return O + s[..., None] * d


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) from rotation vectors (n, 3)."""
    th = np.linalg.norm(w, axis=-1)
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th ** 2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th ** 2 / 24.0, (1.0 - np.cos(ths)) / ths ** 2)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _publish(path: Path) -> None:
    """Give an atomically written file the usual permissions (mkstemp creates it 0600)."""
    import os

    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


def _write_json(path: Path, obj) -> None:
    write_json(path, obj)
    _publish(path)


# ----------------------------------------------------------------------------------------
# Pushbroom camera


def _secant_rows(f, X: np.ndarray, r0: np.ndarray, tol: float, max_iter: int):
    """Solve f(X, row)[0] = 0 for each point's row by secant from r0 and r0 + 1; f also returns
    each point's column. A point stops once its step is below tol (round-off would make its
    secant wander). Returns (columns, rows)."""
    r0 = np.array(r0, dtype=np.float64)
    r1 = r0 + 1.0
    (f0, _), (f1, c1) = f(X, r0), f(X, r1)
    act = np.ones(len(X), bool)
    for _ in range(max_iter):
        den = f1[act] - f0[act]
        ok = np.abs(den) > 0
        step = np.where(ok, f1[act] * (r1[act] - r0[act]) / np.where(ok, den, 1.0), 0.0)
        r0[act], f0[act] = r1[act], f1[act]
        r1[act] = r1[act] - step
        f1[act], c1[act] = f(X[act], r1[act])
        act[act] = np.abs(step) > tol
        if not act.any():
            break
    return c1, r1


@dataclass
class PushbroomCamera:
    """Physical camera of one image: a linear array on a circular orbit with agile steering.

    Time of row r (continuous, pixel centres at integers): tau = (r - r_mid) * line_period
    seconds from the image's mid time ``t_mid``; r_mid = (height - 1) / 2.

    * Satellite position (ECEF, m): circular orbit of radius ``orbit_radius`` through ``s0``
      with in-plane unit velocity ``v0`` at tau = 0, angular rate sqrt(GM / R^3), seen from the
      Earth-fixed frame (rotated by -omega_E tau about z).
    * Steering: the boresight of row r aims at ``target0 + (r - r_mid) * gsd_row * scan_dir``
      (ECEF), a ground target moving one GSD per line along the scan direction.
    * Camera frame: z = boresight, y = scan direction orthogonalised against z, x = y cross z
      (columns to the right, rows forward in time: the image is not mirrored), then rotated by
      the attitude perturbation exp([w(tau)]x) (camera frame), w = drift polynomial
      sum_n drift[:, n] tau^n plus jitter sinusoids (axis, amplitude rad, frequency Hz, phase).
    * Column c looks along R(tau) @ normalize([(c - c0) * ifov, 0, 1]), c0 = (width - 1) / 2,
      for a straight, undistorted line array. A real focal plane is neither (``bow_px``,
      ``distortion_px``, both 0 by default): with n = (c - c0) / c0 the detector of column c
      sits at [(c - c0 + distortion_px * n^3) * ifov, bow_px * n^2 * ifov, 1] (across-track
      distortion, cubic, and a bowed line, its ends bow_px rows off its centre).
    """

    name: str
    width: int
    height: int
    t_mid: str
    line_period: float
    ifov: float
    orbit_radius: float
    s0: np.ndarray
    v0: np.ndarray
    target0: np.ndarray
    scan_dir: np.ndarray
    gsd_row: float
    drift: np.ndarray = field(default_factory=lambda: np.zeros((3, 4)))
    jitter: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    earth_rate: float = OMEGA_EARTH
    bow_px: float = 0.0
    distortion_px: float = 0.0

    def __post_init__(self):
        for k in ("s0", "v0", "target0", "scan_dir"):
            setattr(self, k, np.asarray(getattr(self, k), dtype=np.float64))
        self.drift = np.asarray(self.drift, dtype=np.float64).reshape(3, -1)
        self.jitter = np.asarray(self.jitter, dtype=np.float64).reshape(-1, 4)

    # ---- geometry of time
    @property
    def r_mid(self) -> float:
        return (self.height - 1) / 2.0

    @property
    def c0(self) -> float:
        return (self.width - 1) / 2.0

    @property
    def orbit_rate(self) -> float:
        return math.sqrt(GM / self.orbit_radius ** 3)

    def tau(self, rows: np.ndarray) -> np.ndarray:
        """Seconds from the image mid time for (continuous) rows."""
        return (np.asarray(rows, dtype=np.float64) - self.r_mid) * self.line_period

    def position(self, tau: np.ndarray) -> np.ndarray:
        """Satellite ECEF position (n, 3) at times tau (n,)."""
        tau = np.asarray(tau, dtype=np.float64)
        a = self.orbit_rate * tau
        S = self.orbit_radius * (np.cos(a)[..., None] * _unit(self.s0) + np.sin(a)[..., None] * self.v0)
        e = -self.earth_rate * tau
        ce, se = np.cos(e), np.sin(e)
        return np.stack([ce * S[..., 0] - se * S[..., 1], se * S[..., 0] + ce * S[..., 1],
                         S[..., 2]], axis=-1)

    def perturbation(self, tau: np.ndarray) -> np.ndarray:
        """Attitude perturbation rotation vectors (n, 3) (camera frame, rad)."""
        tau = np.asarray(tau, dtype=np.float64)
        powers = np.stack([tau ** k for k in range(self.drift.shape[1])], axis=-1)
        w = powers @ self.drift.T
        for axis, amp, freq, phase in self.jitter:
            w[..., int(axis)] += amp * np.sin(2 * np.pi * freq * tau + phase)
        return w

    def rotation(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(S (n, 3) ECEF position, R (n, 3, 3) camera-to-ECEF, columns x, y, z) for rows (n,)."""
        rows = np.asarray(rows, dtype=np.float64)
        tau = self.tau(rows)
        S = self.position(tau)
        G = self.target0 + ((rows - self.r_mid) * self.gsd_row)[..., None] * self.scan_dir
        z = _unit(G - S)
        y = _unit(self.scan_dir - np.sum(self.scan_dir * z, -1, keepdims=True) * z)
        x = np.cross(y, z)
        R = np.stack([x, y, z], axis=-1) @ _rodrigues(self.perturbation(tau))
        return S, R

    def _cam(self, X: np.ndarray, rows: np.ndarray) -> np.ndarray:
        S, R = self.rotation(rows)
        return np.einsum("nji,nj->ni", R, X - S)

    @property
    def straight(self) -> bool:
        return self.bow_px == 0.0 and self.distortion_px == 0.0

    def detector(self, cols: np.ndarray) -> np.ndarray:
        """(n, 3) the focal-plane direction [x, y, 1] of columns cols (n,) (class docstring)."""
        cols = np.asarray(cols, dtype=np.float64)
        n = (cols - self.c0) / max(self.c0, 1.0)
        return np.stack([(cols - self.c0 + self.distortion_px * n ** 3) * self.ifov,
                         self.bow_px * n ** 2 * self.ifov, np.ones_like(cols)], axis=-1)

    def _column_of(self, x: np.ndarray) -> np.ndarray:
        """The column whose detector has focal-plane x (n,) (Newton on the cubic)."""
        c = self.c0 + x / self.ifov
        for _ in range(8):
            n = (c - self.c0) / max(self.c0, 1.0)
            f = c - self.c0 + self.distortion_px * n ** 3 - x / self.ifov
            c = c - f / (1.0 + 3.0 * self.distortion_px * n ** 2 / max(self.c0, 1.0))
        return c

    # ---- projection and rays
    def project_ecef(self, X: np.ndarray, tol: float = 1e-9, max_iter: int = 30) -> np.ndarray:
        """ECEF points (n, 3) -> (n, 2) (col, row): the row where the point crosses the line
        array, by secant (camera y / z = 0); on a bowed, distorted line (class docstring), from
        that solution, the row where it crosses the detector of the column it is seen at,
        y / z = bow(col(x / z))."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))

        def straight(Xa, r):
            q = self._cam(Xa, r)
            return q[:, 1] / q[:, 2], self.c0 + (q[:, 0] / q[:, 2]) / self.ifov

        def bowed(Xa, r):
            q = self._cam(Xa, r)
            c = self._column_of(q[:, 0] / q[:, 2])
            return q[:, 1] / q[:, 2] - self.detector(c)[:, 1], c

        r0 = self.r_mid + ((X - self.target0) @ self.scan_dir) / self.gsd_row
        col, row = _secant_rows(straight, X, r0, tol, max_iter)
        if not self.straight:
            col, row = _secant_rows(bowed, X, row, tol, max_iter)
        return np.stack([col, row], axis=-1)

    def project(self, llh: np.ndarray) -> np.ndarray:
        """(n, 3) lon, lat, ellipsoidal h -> (n, 2) col, row (pixel-centre convention)."""
        return self.project_ecef(geodetic_to_ecef(np.atleast_2d(np.asarray(llh, dtype=np.float64))))

    def ray(self, colrow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 2) col, row -> (origin (n, 3) ECEF, unit direction (n, 3) ECEF)."""
        colrow = np.atleast_2d(np.asarray(colrow, dtype=np.float64))
        S, R = self.rotation(colrow[:, 1])
        d = _unit(self.detector(colrow[:, 0]))
        return S, np.einsum("nij,nj->ni", R, d)

    def rays_grid(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays of a (rows x cols) grid: origins (m, 3), directions (m, k, 3)."""
        S, R = self.rotation(np.asarray(rows, dtype=np.float64))
        cols = np.asarray(cols, dtype=np.float64)
        d = _unit(self.detector(cols))
        return S, np.einsum("mij,kj->mki", R, d)

    def localize(self, colrow: np.ndarray, h: np.ndarray | float) -> np.ndarray:
        """(n, 2) col, row at ellipsoidal heights h -> (n, 3) lon, lat, h."""
        O, d = self.ray(colrow)
        return ecef_to_llh_fast(intersect_height(O, d, h))

    def footprint(self, h: float, n_side: int = 16) -> np.ndarray:
        """Image border localized at height h: (4 n_side, 3) lon, lat, h, clockwise from (0, 0)."""
        w, hh = self.width - 1, self.height - 1
        t = np.linspace(0, 1, n_side, endpoint=False)
        cr = np.concatenate([np.stack([t * w, 0 * t], -1), np.stack([w + 0 * t, t * hh], -1),
                             np.stack([(1 - t) * w, hh + 0 * t], -1),
                             np.stack([0 * t, (1 - t) * hh], -1)])
        return self.localize(cr, h)

    def off_nadir_deg(self) -> float:
        """Angle between the mid-time boresight and the geocentric nadir (degrees)."""
        S, R = self.rotation(np.array([self.r_mid]))
        return float(np.degrees(np.arccos(np.clip(-R[0, :, 2] @ _unit(S[0]), -1, 1))))

    def centre_view(self, h: float) -> dict:
        """The viewing direction at the image centre, as a vendor's metadata states it (the site
        format's sidecar member "view"): the centre pixel's line of sight where it meets the
        height h, incidence from that point's vertical and azimuth of the direction to the
        satellite, clockwise from north (degrees, to 0.001 as vendors give them)."""
        centre = np.array([[(self.width - 1) / 2.0, (self.height - 1) / 2.0]])
        O, d = self.ray(centre)
        llh = ecef_to_llh_fast(intersect_height(O, d, h))[0]
        v = enu_rotation(llh[0], llh[1]) @ -d[0]
        return {"incidence_deg": round(float(np.degrees(np.arccos(np.clip(v[2], -1, 1)))), 3),
                "azimuth_deg": round(float(np.degrees(np.arctan2(v[0], v[1])) % 360.0), 3)}

    def view_angles(self, llh: np.ndarray) -> tuple[float, float]:
        """(zenith, azimuth) in degrees of the satellite seen from a ground point at mid time."""
        llh = np.asarray(llh, dtype=np.float64)
        X = geodetic_to_ecef(llh)
        S = self.position(np.array([0.0]))[0]
        v = enu_rotation(llh[0], llh[1]) @ _unit(S - X)
        return float(np.degrees(np.arccos(v[2]))), float(np.degrees(np.arctan2(v[0], v[1])) % 360)

    # ---- serialisation
    def to_dict(self) -> dict:
        d = {}
        for k, v in asdict(self).items():
            d[k] = v.tolist() if isinstance(v, np.ndarray) else v
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "PushbroomCamera":
        return cls(**d)


# ----------------------------------------------------------------------------------------
# Sun and season


def solar_position(when: datetime, lon: float, lat: float) -> tuple[float, float]:
    """(elevation, azimuth) of the sun in degrees (azimuth clockwise from north); NOAA formulas."""
    when = when.astimezone(timezone.utc)
    doy = when.timetuple().tm_yday
    hours = when.hour + when.minute / 60 + when.second / 3600
    g = 2 * math.pi / 365 * (doy - 1 + (hours - 12) / 24)
    decl = (0.006918 - 0.399912 * math.cos(g) + 0.070257 * math.sin(g) - 0.006758 * math.cos(2 * g)
            + 0.000907 * math.sin(2 * g) - 0.002697 * math.cos(3 * g) + 0.00148 * math.sin(3 * g))
    eqt = 229.18 * (0.000075 + 0.001868 * math.cos(g) - 0.032077 * math.sin(g)
                    - 0.014615 * math.cos(2 * g) - 0.040849 * math.sin(2 * g))
    tst = hours * 60 + eqt + 4 * lon
    ha = math.radians(tst / 4 - 180)
    phi = math.radians(lat)
    cz = math.sin(phi) * math.sin(decl) + math.cos(phi) * math.cos(decl) * math.cos(ha)
    el = 90 - math.degrees(math.acos(max(-1.0, min(1.0, cz))))
    az = math.degrees(math.atan2(-math.sin(ha) * math.cos(decl),
                                 math.sin(decl) * math.cos(phi) - math.cos(decl) * math.sin(phi) * math.cos(ha)))
    return el, az % 360


def equation_of_time_min(when: datetime) -> float:
    doy = when.timetuple().tm_yday
    g = 2 * math.pi / 365 * (doy - 1)
    return 229.18 * (0.000075 + 0.001868 * math.cos(g) - 0.032077 * math.sin(g)
                     - 0.014615 * math.cos(2 * g) - 0.040849 * math.sin(2 * g))


def greenness(when: datetime, lat: float) -> float:
    """Vegetation greenness in [0, 1] from the day of year (peak mid-July in the north)."""
    doy = when.timetuple().tm_yday
    peak = 196 if lat >= 0 else 15
    return 0.5 + 0.5 * math.cos(2 * math.pi * (doy - peak) / 365.25)


# ----------------------------------------------------------------------------------------
# Sites: locations, acquisitions, cameras

# (name, lon, lat, ellipsoidal base height)
LOCATIONS = (("nile-delta", 30.0, 31.2, 32.0), ("atlanta", -84.39, 33.75, 290.0),
             ("buenos-aires", -58.44, -34.61, 40.0), ("paris", 2.35, 48.86, 85.0))


@dataclass
class Acquisition:
    """Design of one image: date, view geometry and size."""

    name: str
    group: int
    when: datetime
    off_nadir: float      # degrees at the satellite
    view_az: float        # azimuth of the satellite seen from the scene (deg)
    scan_az: float        # azimuth of the scan direction (deg)
    size: tuple[int, int]
    altitude: float
    speed_ratio: float    # scan speed on the ground / satellite ground speed
    target_offset: tuple[float, float]   # scene-local (m)


def _zenith_from_off_nadir(theta_deg: float, altitude: float, r_ground: float = 6.37e6) -> float:
    return math.degrees(math.asin(min(1.0, (r_ground + altitude) / r_ground * math.sin(math.radians(theta_deg)))))


def _bh(z1, a1, z2, a2) -> float:
    p1 = math.tan(math.radians(z1)) * np.array([math.sin(math.radians(a1)), math.cos(math.radians(a1))])
    p2 = math.tan(math.radians(z2)) * np.array([math.sin(math.radians(a2)), math.cos(math.radians(a2))])
    return float(np.linalg.norm(p1 - p2))


def _draw_group_views(rng: np.random.Generator, n: int, preset: SynthPreset, alts):
    """Off-nadir angles and view azimuths for n images with pairwise B/H in preset.bh."""
    lo, hi = preset.bh
    best = None
    for _ in range(20000):
        th = rng.uniform(*preset.off_nadir, n)
        az = rng.uniform(0, 360, n)
        z = [_zenith_from_off_nadir(t, a) for t, a in zip(th, alts)]
        bhs = [_bh(z[i], az[i], z[j], az[j]) for i in range(n) for j in range(i + 1, n)]
        if all(lo <= b <= hi for b in bhs):
            return th, az
        score = sum(max(0, lo - b) + max(0, b - hi) for b in bhs)
        if best is None or score < best[0]:
            best = (score, th, az)
    assert best is not None                  # tries > 0
    return best[1], best[2]


def design_acquisitions(preset: SynthPreset, seed: int, lat: float, lon: float) -> list[Acquisition]:
    """Dates, view geometry, sizes of every image of a preset (deterministic in seed)."""
    rng = np.random.default_rng([int(seed), 7002])
    acqs = []
    idx = 0
    for g, (n, month) in enumerate(zip(preset.groups, preset.group_months)):
        day0 = datetime(preset.year, month, 1 + int(rng.integers(0, 12)), tzinfo=timezone.utc)
        offs = np.sort(rng.choice(np.arange(1, 14), size=n - 1, replace=False)) if n > 1 else []
        days = [0] + [int(o) for o in offs]
        alts = rng.uniform(*preset.altitude, n)
        th, vaz = _draw_group_views(rng, n, preset, alts)
        # scan azimuths: near the descending ground track, tens of degrees apart
        heading = 180.0 - math.degrees(math.asin(max(-1, min(1, math.cos(math.radians(SSO_INCLINATION))
                                                                / math.cos(math.radians(lat))))))
        for _ in range(1000):
            deltas = rng.uniform(-50, 50, n)
            if n < 2 or min(abs(a - b) for i, a in enumerate(deltas) for b in deltas[i + 1:]) > 12:
                break
        for k in range(n):
            date = day0 + timedelta(days=days[k])
            eqt = equation_of_time_min(date)
            hours = 10.5 + rng.uniform(-0.3, 0.3) - lon / 15.0 - eqt / 60.0
            when = date + timedelta(hours=hours)
            when = when.replace(microsecond=0)
            if idx == 0 and preset.first_image_size is not None:
                size = preset.first_image_size
            else:
                jit = rng.uniform(1 - preset.size_jitter, 1 + preset.size_jitter, 2)
                size = (int(round(preset.image_size[0] * jit[0] / 2)) * 2,
                        int(round(preset.image_size[1] * jit[1] / 2)) * 2)
            foot = preset.gsd * min(size)
            off_e, off_n = (float(v) for v in rng.uniform(-0.04, 0.04, 2) * foot)
            off = (off_e, off_n)
            acqs.append(Acquisition(name=f"img_{idx:02d}.tif", group=g, when=when,
                                    off_nadir=float(th[k]), view_az=float(vaz[k]),
                                    scan_az=float((heading + deltas[k]) % 360), size=size,
                                    altitude=float(alts[k]),
                                    speed_ratio=float(rng.uniform(0.55, 0.95)),
                                    target_offset=off))
            idx += 1
    return acqs


def make_camera(acq: Acquisition, scene: SceneModel, preset: SynthPreset,
                rng: np.random.Generator) -> PushbroomCamera:
    """Build the pushbroom camera of one acquisition (see :class:`PushbroomCamera`)."""
    tx, ty = acq.target_offset
    llh_t = scene.local_to_llh(np.array([tx, ty, scene.h0]))
    G0 = geodetic_to_ecef(llh_t)
    Renu = enu_rotation(llh_t[0], llh_t[1])
    E, N, U = Renu
    rt = float(np.linalg.norm(G0))
    rs = rt - scene.h0 + acq.altitude
    # satellite position from off-nadir angle (at the satellite) and view azimuth
    sin_th = math.sin(math.radians(acq.off_nadir))
    cos_e = min(1.0, rs / rt * sin_th)
    el = math.acos(cos_e)
    az = math.radians(acq.view_az)
    u = math.sin(az) * cos_e * E + math.cos(az) * cos_e * N + math.sin(el) * U
    gu = float(G0 @ u)
    rho = -gu + math.sqrt(gu * gu - rt * rt + rs * rs)
    S0 = G0 + rho * u
    # orbit velocity: sun-synchronous-like descending heading at the sub-satellite point
    up_s = _unit(S0)
    e_s = _unit(np.cross([0.0, 0.0, 1.0], up_s))
    n_s = np.cross(up_s, e_s)
    lat_s = math.asin(up_s[2])
    psi = math.pi - math.asin(max(-1.0, min(1.0, math.cos(math.radians(SSO_INCLINATION)) / math.cos(lat_s))))
    v0 = math.cos(psi) * n_s + math.sin(psi) * e_s
    omega = math.sqrt(GM / rs ** 3)
    # scan direction and ifov giving the GSD across the line at the target
    b = math.radians(acq.scan_az)
    scan = math.sin(b) * E + math.cos(b) * N
    z0 = _unit(G0 - S0)
    y0 = _unit(scan - (scan @ z0) * z0)
    x0 = np.cross(y0, z0)
    dPda = rho * (x0 - z0 * (x0 @ U) / (z0 @ U))
    ifov = preset.gsd / float(np.linalg.norm(dPda))
    v_ground = omega * rt
    line_period = preset.gsd / (v_ground * acq.speed_ratio)
    # attitude: drift polynomial (rad / s^n) and jitter well below the RPC tolerance
    dscale = preset.drift * 1e-6
    drift = np.zeros((3, 4))
    drift[:, 0] = rng.normal(0, 2.0, 3) * dscale
    drift[:, 1] = rng.normal(0, 3.0, 3) * dscale
    drift[:, 2] = rng.choice([-1, 1], 3) * rng.uniform(8.0, 16.0, 3) * dscale
    drift[:, 3] = rng.choice([-1, 1], 3) * rng.uniform(10.0, 25.0, 3) * dscale
    jitter = []
    for axis in range(3):
        for _ in range(2):
            jitter.append([axis, 0.004 * ifov * rng.uniform(0.5, 1.0), rng.uniform(30, 120),
                           rng.uniform(0, 2 * np.pi)])
    h = acq.size[1]
    t_mid = acq.when
    fp = {}
    if preset.bow_px or preset.distortion_px:
        # its own stream: the other draws, and every preset without a focal plane, unchanged
        frng = np.random.default_rng([int(acq.when.timestamp()), int(acq.off_nadir * 1000), 5011])
        fp = {k: float(v * frng.uniform(0.5, 1.0) * frng.choice([-1.0, 1.0]))
              for k, v in (("bow_px", preset.bow_px), ("distortion_px", preset.distortion_px))}
    return PushbroomCamera(name=acq.name, width=acq.size[0], height=h,
                           t_mid=t_mid.strftime("%Y-%m-%dT%H:%M:%SZ"), line_period=line_period,
                           ifov=ifov, orbit_radius=rs, s0=S0, v0=v0, target0=G0,
                           scan_dir=scan, gsd_row=preset.gsd, drift=drift,
                           jitter=np.array(jitter), **fp)


def design_cameras(preset: str | SynthPreset = "tiny", seed: int = 0
                   ) -> tuple[SceneModel, dict[str, PushbroomCamera]]:
    """The scene and the physical cameras generate_site would use, without rendering."""
    P = PRESETS[preset] if isinstance(preset, str) else preset
    loc = LOCATIONS[int(seed) % len(LOCATIONS)]
    scene = SceneModel.create(seed, loc[1], loc[2], loc[3], dict(P.scene))
    acqs = design_acquisitions(P, seed, scene.lat0, scene.lon0)
    rng_cam = np.random.default_rng([int(seed), 7004])
    return scene, {a.name: make_camera(a, scene, P, rng_cam) for a in acqs}


# ----------------------------------------------------------------------------------------
# Truth container and loaders


@dataclass
class SynthTruth:
    """What generate_site produced: scene, cameras, GCP truth, fit figures and timings."""

    site_dir: Path
    preset: SynthPreset
    seed: int
    scene: SceneModel
    cameras: dict[str, PushbroomCamera]
    rpcs: dict[str, RPCModel]
    images: dict[str, dict]
    gcps: list[dict]
    rpc_fit: dict
    bounds: tuple[float, float, float, float]
    timings: dict


def load_truth_cameras(site_dir: str | Path) -> dict[str, PushbroomCamera]:
    """Physical cameras of a generated site: image file name -> PushbroomCamera."""
    d = json.loads((Path(site_dir) / "truth" / "cameras.json").read_text())
    return {k: PushbroomCamera.from_dict(v) for k, v in d["cameras"].items()}


def load_truth_scene(site_dir: str | Path) -> SceneModel:
    """Scene model of a generated site (call ``build_accel`` before casting rays)."""
    d = json.loads((Path(site_dir) / "truth" / "scene.json").read_text())
    return SceneModel.from_dict(d["scene"])


# ----------------------------------------------------------------------------------------
# Footprints, coverage, rendering


def _local_xy(scene: SceneModel, llh: np.ndarray) -> np.ndarray:
    return scene.llh_to_local(llh)[..., :2]


def ray_segments(cam: PushbroomCamera, scene: SceneModel, colrow: np.ndarray,
                 h_top: float, h_bot: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact scene-local (x, y, h) of the rays of pixels (n, 2) at h_top and h_bot: (n, 3) x 2."""
    O, d = cam.ray(colrow)
    top = scene.llh_to_local(ecef_to_llh_fast(intersect_height(O, d, h_top)))
    bot = scene.llh_to_local(ecef_to_llh_fast(intersect_height(O, d, h_bot)))
    return top, bot


def cast_pixels(cam: PushbroomCamera, scene: SceneModel, colrow: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """First surface hit of the exact rays of pixels (n, 2): (scene-local (n, 3), status (n,))."""
    hmin, hmax = scene.height_bounds()
    top, bot = ray_segments(cam, scene, colrow, hmax + 0.05, hmin - 0.5)
    return scene.cast_local(top, bot)


NODE_STEP = 16


def _node_cols(width: int, halo: int) -> np.ndarray:
    c0 = -halo - 1.0
    n = int(math.ceil((width + 2 * halo + 2) / NODE_STEP)) + 2
    return c0 + NODE_STEP * np.arange(n)


def block_segments(cam: PushbroomCamera, scene: SceneModel, rows: np.ndarray,
                   node_cols: np.ndarray, h_top: float, h_bot: float):
    """top, bot (m, k, 3) scene-local ray points of sub-rows (m,) x node columns (k,)."""
    O, D = cam.rays_grid(rows, node_cols)
    Ob = np.broadcast_to(O[:, None, :], D.shape)
    top = scene.llh_to_local(ecef_to_llh_fast(intersect_height(Ob, D, h_top)))
    bot = scene.llh_to_local(ecef_to_llh_fast(intersect_height(Ob, D, h_bot)))
    return np.ascontiguousarray(top), np.ascontiguousarray(bot)


def _shade_vector(scene: SceneModel, when: datetime, h_top: float) -> tuple[np.ndarray, dict]:
    el, az = solar_position(when, scene.lon0, scene.lat0)
    # grid azimuth of true north (meridian convergence)
    p = geodetic_to_projected(np.array([[scene.lon0, scene.lat0, 0.0],
                                        [scene.lon0, scene.lat0 + 1e-3, 0.0]]), scene.epsg)
    gamma = math.atan2(p[1, 0] - p[0, 0], p[1, 1] - p[0, 1])
    ag = math.radians(az) + gamma
    ce = math.cos(math.radians(el))
    S = np.zeros(sm.N_SHADE)
    S[sm.S_SUNX], S[sm.S_SUNY], S[sm.S_SUNZ] = ce * math.sin(ag), ce * math.cos(ag), math.sin(math.radians(el))
    S[sm.S_SKY] = 0.2
    S[sm.S_DIFF] = 1.0
    S[sm.S_VEG] = greenness(when, scene.lat0)
    S[sm.S_ZTOP] = h_top
    return S, {"sun_elevation": el, "sun_azimuth": az, "greenness": S[sm.S_VEG]}


def warm_render_kernel() -> tuple:
    """Compile the render kernel into numba's cache with the argument types render_image passes,
    on no rows and without building a scene (whose own kernels another process is compiling):
    a first `aerec view` runs this beside generate_site, so the render's compile (~10 s) is off
    the critical path. Returns the stand-in context (a test checks its types are a scene's)."""
    f8 = np.float64
    ctx = (np.zeros(1, f8), np.zeros((1, 1), f8), np.zeros((1, 1), f8), np.zeros((1, 1, 1), f8),
           np.zeros((1, 1, 1), f8), np.zeros((1, 1, 1), f8), np.zeros(1, np.int64), 0)
    empty = np.zeros((0, 2, 3))
    sm.render_rows(empty, empty, 0.0, 1.0, -3.0, 4, 1, ctx, np.zeros((2, 2), np.float32),
                   0.0, 0.0, 1.0, np.zeros(sm.N_SHADE))
    return ctx


def render_image(cam: PushbroomCamera, scene: SceneModel, preset: SynthPreset, shade: np.ndarray,
                 seed: int, index: int, out_path: Path, rpc: RPCModel, datetime_tag: str,
                 progress: Progress | None = None) -> None:
    """Render one image by blocks of rows and write it (by window) as a tiled uint16 GeoTIFF."""
    import cv2
    import rasterio
    from rasterio.windows import Window

    ss = preset.supersample
    W, Hh = cam.width, cam.height
    halo = 3
    ncols = W + 2 * halo
    nodes = _node_cols(W, halo)
    hmin, hmax = scene.height_bounds()
    h_top, h_bot = hmax + 0.05, hmin - 0.5
    acc = scene.accel
    assert acc is not None               # built above (build_accel)
    el = math.degrees(math.asin(shade[sm.S_SUNZ]))
    gain = 2300.0 / (0.35 + 0.65 * math.sin(math.radians(el)))
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    profile: dict[str, Any] = dict(driver="GTiff", width=W, height=Hh, count=1, dtype="uint16", tiled=True,
                   blockxsize=256, blockysize=256, compress="deflate", predictor=2,
                   rpcs=rpc.to_rasterio())
    with atomic_path(out_path) as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.update_tags(TIFFTAG_DATETIME=datetime_tag)
            for r0 in range(0, Hh, preset.block_rows):
                r1 = min(Hh, r0 + preset.block_rows)
                rows = np.arange(r0 - halo, r1 + halo, dtype=np.float64)
                subrows = (rows[:, None] + sub[None, :]).ravel()
                top, bot = block_segments(cam, scene, subrows, nodes, h_top, h_bot)
                rad = sm.render_rows(top, bot, float(nodes[0]), float(NODE_STEP), float(-halo),
                                     ncols, ss, scene.ctx, acc.cellmax, acc.x0, acc.y0, acc.cs,
                                     shade)
                if preset.psf_sigma > 0:
                    rad = cv2.GaussianBlur(rad, (0, 0), preset.psf_sigma,
                                           borderType=cv2.BORDER_REFLECT)
                rad = rad[halo:halo + (r1 - r0), halo:halo + W].astype(np.float64)
                dn = 30.0 + gain * rad
                rng = np.random.default_rng([int(seed), 7003, index, r0])
                sigma = np.sqrt(0.12 * np.maximum(dn, 0) + 2.0 ** 2)
                dn = dn + sigma * rng.standard_normal(dn.shape)
                img = np.clip(np.rint(dn), 0, 2047).astype(np.uint16)
                dst.write(img, 1, window=Window(0, r0, W, r1 - r0))  # pyright: ignore[reportCallIssue]
                if progress is not None:
                    progress(f"render {cam.name}", r1, Hh)
    _publish(out_path)


# ----------------------------------------------------------------------------------------
# Affine approximation error


def affine_error_vs_tile_size(camera: PushbroomCamera, scene: SceneModel,
                              sizes=(500, 1000, 2000), n_grid: int = 7, n_h: int = 4,
                              max_tiles: int = 64) -> dict:
    """Error of the best 2x4 affine camera fitted to the true projection, per tile size.

    For each size s (and "full" = the whole image), tiles of s x s pixels cover the image
    (stride s, the last tile shifted to end at the border); ground points are the tile's
    n_grid x n_grid pixel grid localized at n_h heights spanning the scene, in the scene's local
    ENU frame; the affine camera [col, row] = A [E, N, U, 1] is fitted by least squares.
    Returns {s: {"max_px", "mean_max_px", "rms_px", "n_tiles"}} (max over tiles, mean of the
    per-tile maxima, RMS over all points); s = "full" for the whole image.
    """
    hmin, hmax = scene.height_bounds()
    heights = np.linspace(hmin, hmax, n_h)
    frame = LocalFrame(scene.lon0, scene.lat0, scene.h0)
    out = {}
    W, H = camera.width, camera.height
    for s in list(sizes) + ["full"]:
        sw = W if s == "full" else min(int(s), W)
        sh = H if s == "full" else min(int(s), H)
        xs = _tile_starts(W, sw)
        ys = _tile_starts(H, sh)
        tiles = [(x, y) for y in ys for x in xs]
        if len(tiles) > max_tiles:
            pick = np.linspace(0, len(tiles) - 1, max_tiles).round().astype(int)
            tiles = [tiles[i] for i in pick]
        g = np.linspace(0, 1, n_grid)
        gc, gr = np.meshgrid(g, g)
        pts = []
        for (x, y) in tiles:
            cr = np.stack([x + gc.ravel() * (sw - 1), y + gr.ravel() * (sh - 1)], -1)
            pts.append(np.repeat(cr[None], n_h, 0).reshape(-1, 2))
        cr_all = np.concatenate(pts)
        hh = np.tile(np.repeat(heights, n_grid * n_grid), len(tiles))
        enu = frame.geodetic_to_enu(camera.localize(cr_all, hh))
        per = n_grid * n_grid * n_h
        maxes, sq = [], []
        for t in range(len(tiles)):
            X = enu[t * per:(t + 1) * per]
            uv = cr_all[t * per:(t + 1) * per]
            A = np.hstack([X - X.mean(0), np.ones((per, 1))])
            coef, *_ = np.linalg.lstsq(A, uv, rcond=None)
            r = np.linalg.norm(A @ coef - uv, axis=1)
            maxes.append(float(r.max()))
            sq.append(r ** 2)
        out[s] = {"max_px": max(maxes), "mean_max_px": float(np.mean(maxes)),
                  "rms_px": float(np.sqrt(np.mean(np.concatenate(sq)))), "n_tiles": len(tiles),
                  "tile_px": [sw, sh]}
    return out


def _tile_starts(n: int, s: int) -> list[int]:
    if s >= n:
        return [0]
    starts = list(range(0, n - s + 1, s))
    if starts[-1] + s < n:
        starts.append(n - s)
    return starts


# ----------------------------------------------------------------------------------------
# GCPs


def _uv_to_xy(scene: SceneModel, u, v):
    c, s = scene.P[sm.I_COS], scene.P[sm.I_SIN]
    u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
    return c * u - s * v, s * u + c * v


def gcp_candidates(scene: SceneModel, xy_bounds: tuple[float, float, float, float]
                   ) -> list[dict]:
    """Distinctive points in a scene-local rectangle: building eave/parapet corners (roof)
    and sidewalk corners at intersections (ground). Each {"kind", "x", "y", "h"}."""
    P, salt = scene.P, scene.salt
    x0, y0, x1, y1 = xy_bounds
    c, s = P[sm.I_COS], P[sm.I_SIN]
    corners = np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]])
    us = c * corners[:, 0] + s * corners[:, 1]
    vs = -s * corners[:, 0] + c * corners[:, 1]
    i0 = int(math.floor(us.min() / P[sm.I_PU])) - 1
    i1 = int(math.floor(us.max() / P[sm.I_PU])) + 1
    j0 = int(math.floor(vs.min() / P[sm.I_PV])) - 1
    j1 = int(math.floor(vs.max() / P[sm.I_PV])) + 1
    sw = P[sm.I_SW]
    out = []
    for i in range(i0, i1 + 1):
        U0, w0 = sm._line(i, P[sm.I_PU], P[sm.I_JU], salt, 0)
        U1, w1 = sm._line(i + 1, P[sm.I_PU], P[sm.I_JU], salt, 0)
        a0, a1 = U0 + 0.5 * w0, U1 - 0.5 * w1
        for j in range(j0, j1 + 1):
            V0, z0 = sm._line(j, P[sm.I_PV], P[sm.I_JV], salt, 1)
            V1, z1 = sm._line(j + 1, P[sm.I_PV], P[sm.I_JV], salt, 1)
            b0, b1 = V0 + 0.5 * z0, V1 - 0.5 * z1
            # sidewalk corners (ground)
            e = 0.3
            for (u, v) in ((a0 + e, b0 + e), (a1 - e, b0 + e), (a0 + e, b1 - e), (a1 - e, b1 - e)):
                out.append({"kind": "ground", "u": u, "v": v})
            bt, _, _ = sm._block_type(i, j, P, salt)
            if bt != sm.B_BUILT:
                continue
            for k in range(2):
                ok, u0, u1, v0, v1 = sm._building_rect(i, j, k, a0 + sw, a1 - sw, b0 + sw,
                                                       b1 - sw, salt)
                if not ok:
                    break
                e = 0.25
                for (u, v) in ((u0 + e, v0 + e), (u1 - e, v0 + e), (u0 + e, v1 - e), (u1 - e, v1 - e)):
                    out.append({"kind": "roof", "u": u, "v": v})
    if not out:
        return []
    u = np.array([o["u"] for o in out])
    v = np.array([o["v"] for o in out])
    x, y = _uv_to_xy(scene, u, v)
    ev = scene.evaluate(x, y)
    res = []
    for k, o in enumerate(out):
        if not (x0 <= x[k] <= x1 and y0 <= y[k] <= y1):
            continue
        mat = int(ev["material"][k])
        if o["kind"] == "roof" and mat not in (sm.M_ROOF, sm.M_PARAPET):
            continue                     # covered by a tree crown
        if o["kind"] == "ground" and mat != sm.M_SIDEWALK:
            continue
        res.append({"kind": o["kind"], "x": float(x[k]), "y": float(y[k]), "h": float(ev["h"][k])})
    return res


def _visible(cams: dict[str, PushbroomCamera], scene: SceneModel, pts_local: np.ndarray,
             margin: float = 3.0, tol: float = 0.15) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per image: (visible flags (n,), true projections (n, 2)) of scene-local points (n, 3)."""
    llh = scene.local_to_llh(pts_local)
    out = {}
    for name, cam in cams.items():
        uv = cam.project(llh)
        inside = ((uv[:, 0] >= margin) & (uv[:, 0] <= cam.width - 1 - margin)
                  & (uv[:, 1] >= margin) & (uv[:, 1] <= cam.height - 1 - margin))
        vis = np.zeros(len(pts_local), bool)
        if inside.any():
            hits, st = cast_pixels(cam, scene, uv[inside])
            vis[inside] = (st > 0) & (np.linalg.norm(hits - pts_local[inside], axis=1) < tol)
        out[name] = (vis, uv)
    return out


def select_gcps(cands: list[dict], visibility: dict, groups: dict[str, int], n_gcps: int,
                rng: np.random.Generator) -> list[int]:
    """Indices of GCPs: visible in >= 2 images of every group, farthest-point sampled in
    (x, y, 4 h), alternating roof and ground points."""
    n = len(cands)
    ok = np.ones(n, bool)
    for g in set(groups.values()):
        cnt = sum(visibility[name][0].astype(int) for name, gg in groups.items() if gg == g)
        ok &= cnt >= 2
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return []
    X = np.array([[cands[k]["x"], cands[k]["y"], 4.0 * cands[k]["h"]] for k in idx])
    kinds = np.array([cands[k]["kind"] for k in idx])
    chosen = [int(np.argmin(np.linalg.norm(X[:, :2] - X[:, :2].mean(0), axis=1)))]
    dmin = np.linalg.norm(X - X[chosen[0]], axis=1)
    while len(chosen) < min(n_gcps, len(idx)):
        want = "roof" if len(chosen) % 2 == 1 else "ground"
        d = dmin.copy()
        d[chosen] = -1
        if (kinds == want).any() and d[kinds == want].max() > 0:
            d[kinds != want] = -1
        k = int(np.argmax(d))
        if d[k] <= 0:
            break
        chosen.append(k)
        dmin = np.minimum(dmin, np.linalg.norm(X - X[k], axis=1))
    return [int(idx[k]) for k in chosen]


def control_quadruple(xyh: np.ndarray, height_weight: float = 4.0) -> set[int]:
    """The 4 GCPs (indices) spanning the largest tetrahedron in (x, y, w h): well spread in plan
    and off one plane, as the method's 4 control points; the others become check points."""
    from itertools import combinations

    P = xyh * [1.0, 1.0, height_weight]
    quads = np.array(list(combinations(range(len(P)), 4)))
    E = P[quads[:, 1:]] - P[quads[:, :1]]
    vol = np.abs(np.linalg.det(E))
    return set(int(i) for i in quads[int(np.argmax(vol))])


# ----------------------------------------------------------------------------------------
# Site generation


class _Mask:
    """Validity mask on a grid of `cov` metres (a multiple of the DSM resolution) whose top-left
    corner is the DSM's; `block(r0, r1, nx, res)` gives DSM rows r0..r1 at resolution res."""

    def __init__(self, m: np.ndarray, cov: float):
        self.m, self.cov = m, cov

    @property
    def shape_m(self) -> tuple[float, float]:
        return self.m.shape[0] * self.cov, self.m.shape[1] * self.cov

    def block(self, r0: int, r1: int, nx: int, res: float) -> np.ndarray:
        f = int(round(self.cov / res))
        rr = np.minimum(np.arange(r0, r1) // f, self.m.shape[0] - 1)
        cc = np.minimum(np.arange(nx) // f, self.m.shape[1] - 1)
        return self.m[np.ix_(rr, cc)]


def _coverage(scene: SceneModel, cams: dict[str, PushbroomCamera], groups: dict[str, int],
              h_ground: float, res: float) -> tuple[tuple[float, float, float, float], _Mask]:
    """UTM bounds (multiples of res) and mask of the cells seen by >= 2 images of one date
    group (image footprints at the ground height). The mask is computed at res, or at 2 m when
    the site is large (> 4000 cells a side) to keep memory bounded."""
    import cv2

    polys = {name: scene.llh_to_local(cam.footprint(h_ground))[:, :2] for name, cam in cams.items()}
    allp = np.concatenate(list(polys.values()))
    ext = max(np.ptp(allp[:, 0]), np.ptp(allp[:, 1]))
    res_dsm = res
    res = res if ext / res <= 4000 else max(res, 2.0)
    x0 = math.floor((allp[:, 0].min() + scene.E0) / res) * res
    x1 = math.ceil((allp[:, 0].max() + scene.E0) / res) * res
    y0 = math.floor((allp[:, 1].min() + scene.N0) / res) * res
    y1 = math.ceil((allp[:, 1].max() + scene.N0) / res) * res
    nx, ny = int(round((x1 - x0) / res)), int(round((y1 - y0) / res))
    valid = np.zeros((ny, nx), bool)
    for g in set(groups.values()):
        cnt = np.zeros((ny, nx), np.uint8)
        for name, p in polys.items():
            if groups[name] != g:
                continue
            m = np.zeros((ny, nx), np.uint8)
            px = (p[:, 0] + scene.E0 - x0) / res - 0.5
            py = (y1 - (p[:, 1] + scene.N0)) / res - 0.5
            pts = np.round(np.stack([px, py], -1) * 16).astype(np.int32)
            cv2.fillPoly(m, [pts], 1, lineType=cv2.LINE_8, shift=4)
            cnt += m
        valid |= cnt >= 2
    rr = np.flatnonzero(valid.any(1))
    cc = np.flatnonzero(valid.any(0))
    bounds = (x0 + cc[0] * res, y1 - (rr[-1] + 1) * res, x0 + (cc[-1] + 1) * res, y1 - rr[0] * res)
    assert abs(res / res_dsm - round(res / res_dsm)) < 1e-9
    return bounds, _Mask(valid[rr[0]:rr[-1] + 1, cc[0]:cc[-1] + 1], res)


def _write_gt_dsm(path: Path, scene: SceneModel, bounds, valid: "_Mask", res: float,
                  progress: Progress | None) -> None:
    import rasterio
    from affine import Affine
    from rasterio.crs import CRS
    from rasterio.windows import Window

    xmin, ymin, xmax, ymax = bounds
    nx = int(round((xmax - xmin) / res))
    ny = int(round((ymax - ymin) / res))
    profile: dict[str, Any] = dict(driver="GTiff", width=nx, height=ny, count=1, dtype="float32",
                   crs=CRS.from_epsg(scene.epsg), transform=Affine(res, 0.0, xmin, 0.0, -res, ymax),
                   nodata=NODATA, tiled=True, blockxsize=256, blockysize=256, compress="deflate",
                   predictor=3)
    step = 512
    with atomic_path(path) as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            for r0 in range(0, ny, step):
                r1 = min(ny, r0 + step)
                dsm, _ = scene.gt_dsm((xmin, ymax - r1 * res, xmax, ymax - r0 * res), res)
                dsm[~valid.block(r0, r1, nx, res)] = NODATA
                dst.write(dsm, 1, window=Window(0, r0, nx, r1 - r0))  # pyright: ignore[reportCallIssue]
                if progress is not None:
                    progress("gt_dsm", r1, ny)
    _publish(path)


def render_ortho(site: str | Path, out_path: str | Path, preset: str | SynthPreset = "tiny",
                 seed: int = 0, supersample: int = 2) -> Path:
    """A true orthoimage of a generated site (`preset`, `seed`: those it was generated with): its
    scene seen from straight above (occlusions and shadows as the images render them, sunlit as
    on the site's first acquisition, no noise), on the ground-truth DSM's grid and CRS, uint16.
    The reference orthoimage a user would take from a national orthophoto, for tests and
    bench_operator; the truth DSM beside it serves as a (lidar-like) reference DEM."""
    import rasterio

    site, out_path = Path(site), Path(out_path)
    P = PRESETS[preset] if isinstance(preset, str) else preset
    scene, _ = design_cameras(P, seed)
    when = design_acquisitions(P, seed, scene.lat0, scene.lon0)[0].when
    with rasterio.open(site / "gt_dsm.tif") as g:
        tf, crs, W, H = g.transform, g.crs, g.width, g.height
    res = tf.a
    x0, y1 = tf.c - scene.E0, tf.f - scene.N0                   # scene-local left and top edges
    m = 200.0                                                   # shadows come from beyond the edge
    scene.build_accel(x0 - m, y1 - H * res - m, x0 + W * res + m, y1 + m, P.accel_cell, P.accel_sample)
    hmin, hmax = scene.height_bounds()
    shade, _ = _shade_vector(scene, when, hmax + 0.05)
    el = math.degrees(math.asin(shade[sm.S_SUNZ]))
    gain = 2300.0 / (0.35 + 0.65 * math.sin(math.radians(el)))
    nodes = _node_cols(W, 0)
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    acc = scene.accel
    assert acc is not None               # built above (build_accel)
    out = np.empty((H, W), np.uint16)
    for r0 in range(0, H, 256):
        r1 = min(H, r0 + 256)
        rows = (np.arange(r0, r1, dtype=np.float64)[:, None] + sub[None, :]).ravel()
        y = y1 - (rows + 0.5) * res
        x = x0 + (nodes + 0.5) * res
        top = np.empty((len(rows), len(nodes), 3))
        top[:, :, 0], top[:, :, 1], top[:, :, 2] = x[None, :], y[:, None], hmax + 0.05
        bot = top.copy()
        bot[:, :, 2] = hmin - 0.5
        rad = sm.render_rows(np.ascontiguousarray(top), np.ascontiguousarray(bot), float(nodes[0]),
                             float(NODE_STEP), 0.0, W, supersample, scene.ctx, acc.cellmax, acc.x0,
                             acc.y0, acc.cs, shade)
        out[r0:r1] = np.clip(np.rint(30.0 + gain * rad), 0, 2047).astype(np.uint16)
    profile: dict[str, Any] = dict(driver="GTiff", width=W, height=H, count=1, dtype="uint16", crs=crs, transform=tf,
                   tiled=True, blockxsize=256, blockysize=256, compress="deflate", predictor=2)
    with atomic_path(out_path) as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(out, 1)
    return out_path


def generate_site(out_dir: str | Path, preset: str | SynthPreset = "tiny", seed: int = 0,
                  progress: Progress | None = None,
                  before_render: Callable[[], None] | None = None) -> SynthTruth:
    """Generate a synthetic site folder (see the module docstring) and return its truth.

    before_render() is called once the scene is built, before the first image is rendered (the
    viewer's first run waits there for the render kernel another process compiles).

    progress(stage, done, total) is called as stages advance (stages: "cameras", "accel",
    "rpc", "render img_XX.tif", "gt_dsm", "gcps").
    """
    pr = progress or (lambda stage, done, total: None)
    P = PRESETS[preset] if isinstance(preset, str) else preset
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    loc = LOCATIONS[int(seed) % len(LOCATIONS)]
    scene, cams = design_cameras(P, seed)
    acqs = design_acquisitions(P, seed, scene.lat0, scene.lon0)
    pr("cameras", len(cams), len(cams))
    groups = {a.name: a.group for a in acqs}

    # acceleration grid over everything any ray can traverse
    hlo, hhi = scene.height_bounds()
    pts = np.concatenate([_local_xy(scene, cam.footprint(h, 8)) for cam in cams.values()
                          for h in (hlo - 1.0, hhi + 1.0)])
    m = 20.0
    x0, y0 = pts.min(0) - m
    x1, y1 = pts.max(0) + m
    scene.build_accel(float(x0), float(y0), float(x1), float(y1), P.accel_cell,
                      P.accel_sample, progress=lambda d, t: pr("accel", d, t))
    hmin, hmax = scene.height_bounds()
    timings["scene"] = time.perf_counter() - t0

    # RPCs
    t1 = time.perf_counter()
    rpcs, fit = {}, {}
    for k, (name, cam) in enumerate(cams.items()):
        foot = np.concatenate([cam.footprint(h, 12) for h in (hmin - 5.0, hmax + 5.0)])
        b = (foot[:, 0].min(), foot[:, 0].max(), foot[:, 1].min(), foot[:, 1].max(),
             hmin - 5.0, hmax + 5.0)
        rpcs[name] = fit_rpc(cam.project, b, image_size=(cam.width, cam.height))
        fit[name] = rpc_residuals(rpcs[name], cam.project, b, image_size=(cam.width, cam.height))
        pr("rpc", k + 1, len(cams))
    rpc_fit = {"images": fit, "max_px": max(f["max_px"] for f in fit.values()),
               "rms_px": float(np.sqrt(np.mean([f["rms_px"] ** 2 for f in fit.values()]))),
               "check_grid": "30 x 30 x 6 staggered (cell centres of the 21 x 21 x 7 fit grid), "
                             "points projecting inside the image"}
    timings["rpc"] = time.perf_counter() - t1

    # images
    if before_render is not None:
        before_render()
    t2 = time.perf_counter()
    images = {}
    for k, (a, (name, cam)) in enumerate(zip(acqs, cams.items())):
        shade, sun = _shade_vector(scene, a.when, hmax + 0.05)
        render_image(cam, scene, P, shade, seed, k, out / "images" / name, rpcs[name],
                     a.when.strftime("%Y:%m:%d %H:%M:%S"), progress=pr)
        _write_json(out / "images" / (Path(name).stem + ".json"),
                   {"acquired": a.when.strftime("%Y-%m-%dT%H:%M:%SZ"), "view": cam.centre_view(scene.h0)})
        zen, vaz = cam.view_angles(np.array([scene.lon0, scene.lat0, scene.h0]))
        images[name] = {"group": a.group, "acquired": a.when.strftime("%Y-%m-%dT%H:%M:%SZ"),
                        "width": cam.width, "height": cam.height,
                        "off_nadir_deg": cam.off_nadir_deg(), "view_zenith_deg": zen,
                        "view_azimuth_deg": vaz, "scan_azimuth_deg": a.scan_az,
                        "line_period_s": cam.line_period, "ifov_urad": cam.ifov * 1e6,
                        "altitude_m": a.altitude, **sun}
    timings["render"] = time.perf_counter() - t2

    # B/H per pair in each group
    names = list(cams)
    bh = {}
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            if groups[names[i]] == groups[names[j]]:
                a, b = images[names[i]], images[names[j]]
                bh[f"{names[i]}/{names[j]}"] = _bh(a["view_zenith_deg"], a["view_azimuth_deg"],
                                                   b["view_zenith_deg"], b["view_azimuth_deg"])

    # GT DSM and site.json
    t3 = time.perf_counter()
    res = max(0.5, P.gsd)    # the GT DSM's cell: 0.5 m, or the GSD of a coarser site
    bounds, valid = _coverage(scene, cams, groups, scene.h0, res)
    _write_gt_dsm(out / "gt_dsm.tif", scene, bounds, valid, res, pr)
    _write_json(out / "site.json", {"name": f"synth-{P.name}-{seed}", "crs_epsg": scene.epsg,
                                   "resolution_m": res, "bounds": [float(v) for v in bounds]})
    timings["gt_dsm"] = time.perf_counter() - t3

    # GCPs
    t4 = time.perf_counter()
    xyb = (bounds[0] - scene.E0, bounds[1] - scene.N0, bounds[2] - scene.E0, bounds[3] - scene.N0)
    cands = gcp_candidates(scene, xyb)
    pts_local = np.array([[c["x"], c["y"], c["h"]] for c in cands]).reshape(-1, 3)
    vis = _visible(cams, scene, pts_local)
    rng_g = np.random.default_rng([int(seed), 7005])
    chosen = select_gcps(cands, vis, groups, P.n_gcps, rng_g)
    llh = scene.local_to_llh(pts_local[chosen]) if chosen else np.zeros((0, 3))
    control = control_quadruple(pts_local[chosen]) if len(chosen) >= 4 else set(range(len(chosen)))
    gcps, features = [], []
    for n_, k in enumerate(chosen):
        gid = f"GCP-{n_ + 1:02d}"
        role = "control" if n_ in control else "check"
        true_obs, obs = {}, {}
        for name in names:
            v, uv = vis[name]
            if v[k]:
                true_obs[name] = [float(uv[k, 0]), float(uv[k, 1])]
                noisy = uv[k] + rng_g.normal(0.0, 0.3, 2)
                obs[name] = [round(float(noisy[0]), 3), round(float(noisy[1]), 3)]
        lon, lat, h = (float(v) for v in llh[n_])
        gcps.append({"id": gid, "role": role, "kind": cands[k]["kind"], "llh": [lon, lat, h],
                     "local": [cands[k]["x"], cands[k]["y"], cands[k]["h"]],
                     "observations": obs, "true_observations": true_obs})
        features.append({"type": "Feature",
                         "geometry": {"type": "Point",
                                      "coordinates": [round(lon, 9), round(lat, 9), round(h, 4)]},
                         "properties": {"id": gid, "role": role, "observations": obs}})
        pr("gcps", n_ + 1, len(chosen))
    _write_json(out / "gcps.geojson", {"type": "FeatureCollection", "features": features})
    timings["gcps"] = time.perf_counter() - t4
    timings["total"] = time.perf_counter() - t0

    # truth
    _write_json(out / "truth" / "cameras.json",
               {"note": "physical pushbroom cameras; truth for tests/evaluation only",
                "cameras": {k: c.to_dict() for k, c in cams.items()}})
    _write_json(out / "truth" / "scene.json",
               {"scene": scene.to_dict(), "location": loc[0], "preset": asdict(P), "seed": seed,
                "height_bounds": [hmin, hmax]})
    _write_json(out / "truth" / "images.json", {"images": images, "base_to_height": bh})
    _write_json(out / "truth" / "rpc_fit.json", rpc_fit)
    _write_json(out / "truth" / "gcps_truth.json", {"gcps": gcps, "noise_px": 0.3})

    return SynthTruth(site_dir=out, preset=P, seed=int(seed), scene=scene, cameras=cams,
                      rpcs=rpcs, images=images, gcps=gcps, rpc_fit=rpc_fit, bounds=bounds,
                      timings=timings)

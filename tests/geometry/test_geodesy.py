"""Geodesy against closed-form truths (WGS84 constants, ENU of known offsets, UTM zones)."""

from __future__ import annotations

import numpy as np

from recon_core.geometry.geodesy import (
    LocalFrame,
    ecef_to_geodetic,
    geodetic_to_ecef,
    geodetic_to_projected,
    projected_to_geodetic,
    utm_epsg_for,
)

A = 6378137.0
B = 6356752.314245


def test_ecef_of_known_points_and_round_trip():
    np.testing.assert_allclose(geodetic_to_ecef(np.array([0.0, 0.0, 0.0])), [A, 0, 0], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(np.array([90.0, 0.0, 100.0])), [0, A + 100, 0], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(np.array([0.0, 90.0, 0.0])), [0, 0, B], atol=1e-3)
    rng = np.random.default_rng(0)
    llh = np.column_stack([rng.uniform(-180, 180, 50), rng.uniform(-85, 85, 50), rng.uniform(-100, 9000, 50)])
    np.testing.assert_allclose(ecef_to_geodetic(geodetic_to_ecef(llh)), llh, atol=1e-7)


def test_enu_axes_and_earth_curvature():
    f = LocalFrame(30.0, 31.2, 50.0)
    np.testing.assert_allclose(f.geodetic_to_enu(np.array([[30.0, 31.2, 60.0]])), [[0, 0, 10]], atol=1e-6)
    e = f.geodetic_to_enu(np.array([[30.0, 31.2 + 1e-3, 50.0]]))[0]      # ~111 m north
    assert abs(e[0]) < 1e-6 and 110.0 < e[1] < 111.5
    far = f.geodetic_to_enu(np.array([[30.0 + 0.06, 31.2, 50.0]]))[0]   # ~5.7 km east
    assert np.isclose(far[2], -far[0] ** 2 / (2 * A), rtol=0.02)         # up drifts by d^2 / 2R
    rng = np.random.default_rng(1)
    enu = rng.uniform(-5000, 5000, (20, 3))
    np.testing.assert_allclose(f.geodetic_to_enu(f.enu_to_geodetic(enu)), enu, atol=1e-6)


def test_utm_zone_and_projection_round_trip():
    assert utm_epsg_for(30.0, 31.2) == 32636 and utm_epsg_for(55.5, -21.1) == 32740
    llh = np.array([[30.01, 31.21, 42.0], [30.2, 31.0, -5.0]])
    xyh = geodetic_to_projected(llh, 32636)
    assert np.allclose(xyh[:, 2], llh[:, 2]) and 100_000 < xyh[0, 0] < 900_000
    np.testing.assert_allclose(projected_to_geodetic(xyh, 32636), llh, atol=1e-9)

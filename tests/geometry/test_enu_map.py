"""The upgrade's whole map (recon_core.geometry.enu_map.EnuMap) undone: a local ENU position
back to the affine frame, with and without its warps."""

from __future__ import annotations

import numpy as np
import pytest

from recon_core.geometry.enu_map import BendWarp, EnuMap, EnuWarp, undo_displacement


def _site(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(H of an affine frame in pixels to ENU metres at 0.5 m per pixel, slightly skewed as an
    affine reconstruction is; affine points over a 4 x 4 km site with 300 m of relief)."""
    rng = np.random.default_rng(seed)
    A = 0.5 * (np.eye(3) + 0.05 * rng.normal(size=(3, 3)))
    H = np.vstack([np.hstack([A, rng.normal(0, 50, (3, 1))]), [0, 0, 0, 1]])
    Y = np.column_stack([rng.uniform(-2000, 2000, (500, 2)), rng.uniform(0, 300, 500)])
    X = np.linalg.solve(A, (Y - H[:3, 3]).T).T
    return H, X


def _metric_warp() -> BendWarp:
    """A metric bend step's warp of a few pixels over the frame (its size on the real sites)."""
    return BendWarp(np.zeros(3), np.eye(3) / 4000.0, np.eye(3)[:2], np.zeros(3),
                    np.array([1e-3, -6e-4, 8e-4, 5e-4, 2e-4, -1e-3, 3e-4, 0.0, -2e-4]))


def _gcp_warps() -> list[EnuWarp]:
    """A quadratic bend fitted to GCPs (metres at the edge) and a cubic one (a reference DEM's)."""
    quad = EnuWarp(np.array([100.0, -50.0]), 2000.0, np.array([0.3, -0.2, 0.1, 0.0, 0.2, 0.1, 1.5, -0.8, 1.2]))
    cubic = EnuWarp(np.array([0.0, 0.0]), 2000.0, np.concatenate([np.zeros(14), [0.8, -0.5, 0.3, 0.4, -0.6, 0.2, 0.5]]))
    return [quad, cubic]


@pytest.mark.parametrize("warps", ["none", "metric", "gcp", "cubic", "both"])
def test_the_inverse_round_trips_to_a_micrometre(warps):
    H, X = _site()
    w, g = {"none": (None, None), "metric": (_metric_warp(), None), "gcp": (None, _gcp_warps()[0]),
            "cubic": (None, _gcp_warps()[1]), "both": (_metric_warp(), _gcp_warps()[0])}[warps]
    m = EnuMap(H, w, g)
    if w is not None:                  # the warps are not negligible: the inverse must undo them
        assert np.abs(w(X)).max() > 1.0
    if g is not None:
        assert np.abs(g(m(X))).max() > 0.5
    Y = m(X)
    back = m.inverse(Y)
    np.testing.assert_allclose(m(back), Y, rtol=0, atol=1e-6)          # metres
    np.testing.assert_allclose(back, X, rtol=0, atol=2e-6)              # pixels of the frame (0.5 m)
    assert m.inverse(np.zeros((0, 3))).shape == (0, 3)


def test_undo_displacement_solves_x_plus_d_of_x():
    w = _metric_warp()
    _, X = _site(1)
    Z = X + w(X)
    np.testing.assert_allclose(undo_displacement(w, Z), X, rtol=0, atol=1e-9)


def test_undo_displacement_says_so_where_it_cannot():
    """Far outside the site a strong warp's fixed-point inverse does not converge: the point is
    NaN, never a wrong position, while points on the site still round-trip."""
    from recon_core.geometry.enu_map import EnuWarp, undo_displacement

    coef = np.zeros(9)
    coef[0] = 20.0                                # E += 20 e^2, e = E / 500: strong far out
    w = EnuWarp(np.zeros(2), 500.0, coef)
    Z = np.array([[100.0, 50.0, 0.0], [20000.0, 0.0, 0.0], [-20000.0, 0.0, 0.0]])
    X = undo_displacement(w, Z)
    assert np.allclose(X[0] + w(X[:1])[0], Z[0], atol=1e-6)
    assert np.isnan(X[1:]).all()

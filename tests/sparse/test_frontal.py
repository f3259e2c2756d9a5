"""The Cholesky factorisation by dense fronts (recon_core.sparse.frontal) against dense LAPACK:
on a grid of 8 x 8 blocks coupled to their neighbours, in the bundle adjustment's
nested-dissection order with its leaves and separators as fronts, and with arbitrary fronts."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import csc_matrix

from recon_core.sparse.bundle import _dissection_order
from recon_core.sparse.frontal import FrontalCholesky


def _grid_system(g: int, seed: int = 0):
    """A g x g grid of tiles, each with an 8 x 8 block coupled to its 8 neighbours: a random
    symmetric positive definite matrix with that block pattern; the block pattern (CSR of
    pairs a <= b) and the tiles' positions."""
    rng = np.random.default_rng(seed)
    ij = np.array([(i, j) for i in range(g) for j in range(g)], float)
    n = g * g
    pairs = sorted((a, b) for a in range(n) for b in range(a, n) if np.abs(ij[a] - ij[b]).max() <= 1)
    bptr = np.searchsorted([p[0] for p in pairs], np.arange(n + 1)).astype(np.int64)
    bcol = np.array([p[1] for p in pairs], np.int64)
    J = np.zeros((8 * n, 8 * n))
    for a, b in pairs:
        # a Gram-like coupling so that the whole matrix is positive definite
        B = rng.normal(size=(8, 8)) * (1.0 if a == b else 0.3)
        J[8 * a:8 * a + 8, 8 * b:8 * b + 8] += B
    A = J @ J.T + 8 * n * 1e-3 * np.eye(8 * n)
    # keep exactly the block pattern (J J^T reaches the neighbours' neighbours)
    mask = np.zeros((n, n), bool)
    for a, b in pairs:
        mask[a, b] = mask[b, a] = True
    A = A * np.kron(mask, np.ones((8, 8)))
    A += np.diag(np.abs(A).sum(1))                        # diagonally dominant: positive definite
    return A, bptr, bcol, ij


def test_fronts_on_the_dissection_solve_as_dense_cholesky():
    A, bptr, bcol, ij = _grid_system(12)
    order, sizes = _dissection_order(bptr, bcol, ij, leaf=4, chunks=True)
    assert sizes.sum() == len(order) == 144 and len(sizes) > 10
    P = (8 * order[:, None] + np.arange(8)).ravel()           # scalar unknowns in that order
    Ap = A[np.ix_(P, P)]
    starts = 8 * np.r_[0, np.cumsum(sizes)]
    f = FrontalCholesky(csc_matrix(Ap), starts)
    rng = np.random.default_rng(1)
    b = rng.normal(size=(len(P), 3))
    np.testing.assert_allclose(f.solve(b), np.linalg.solve(Ap, b), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(f.solve(b[:, 0]), np.linalg.solve(Ap, b[:, 0]), rtol=1e-9, atol=1e-12)
    # only the lower triangle is read
    low = FrontalCholesky(csc_matrix(np.tril(Ap)), starts)
    np.testing.assert_allclose(low.solve(b), f.solve(b), rtol=1e-12, atol=1e-14)
    # the dissection keeps the factor sparse: far fewer stored entries than a dense triangle
    n = len(P)
    assert f.nnz < 0.45 * n * (n + 1) / 2


@pytest.mark.parametrize("starts", [None, "ones", "uneven"])
def test_any_partition_into_fronts_gives_the_same_solution(starts):
    A, *_ = _grid_system(5, seed=3)
    n = len(A)
    rng = np.random.default_rng(2)
    if starts is None:
        s = np.array([0, n])                                  # one front: dense Cholesky
    elif starts == "ones":
        s = np.arange(n + 1)                                  # one unknown per front
    else:
        s = np.unique(np.r_[0, np.sort(rng.choice(np.arange(1, n), 17, replace=False)), n])
    b = rng.normal(size=n)
    # the natural order has fill: fronts padded by their children's boundaries
    f = FrontalCholesky(csc_matrix(A), s)
    np.testing.assert_allclose(f.solve(b), np.linalg.solve(A, b), rtol=1e-9, atol=1e-12)


def test_an_indefinite_matrix_is_refused():
    A, *_ = _grid_system(4)
    A[10, 10] = -5.0 * abs(A[10, 10])
    with pytest.raises(np.linalg.LinAlgError):
        FrontalCholesky(csc_matrix(A), np.array([0, 32, 64, 96, len(A)]))
    with pytest.raises(ValueError):
        FrontalCholesky(csc_matrix(A), np.array([0, 32, 32, len(A)]))

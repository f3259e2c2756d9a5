"""A sparse Cholesky factorisation by dense fronts on a nested-dissection order (multifrontal).

The bundle adjustment's reduced camera system is symmetric positive definite and, in the
nested-dissection order of the tiles by ground position (bundle._dissection_order), its
factor is block-structured: each leaf or separator of the dissection (a *chunk* of consecutive
unknowns) couples only to a set of later unknowns (its *boundary*). Factoring chunk by chunk,
each as one dense front [own | boundary] with LAPACK and BLAS-3 (the children's Schur
complements added in first), costs the dense kernels' speed instead of a general sparse LU's:
on a 7.5 km site seen by 9 images (23,476 unknowns, 15 % fill) SciPy's SuperLU, whose kernels
use no optimised BLAS, takes 24-27 s where this takes 9 s (docs: research-notes.md, "Bundle adjustment at scale";
bench/bench_ba_scale.py --solvers superlu sparse for 3 images).

Chunks may be any partition of the order into consecutive ranges: a chunk's boundary is the
union of its own columns' later rows and its children's boundaries (a superset of the exact
fill only where a chunk's columns differ; the padding is zeros in the dense front), and a
chunk's parent is the chunk that holds its boundary's first unknown.
"""

from __future__ import annotations

from contextlib import nullcontext

import numpy as np
import scipy.linalg
from scipy.linalg.blas import dsyrk as _syrk  # pyright: ignore[reportAttributeAccessIssue]
from scipy.linalg.blas import dtrsm as _trsm  # pyright: ignore[reportAttributeAccessIssue]
from scipy.sparse import csc_matrix
from threadpoolctl import ThreadpoolController

# OpenBLAS's threads cost more than they give on a small front or a triangular solve (measured:
# 100 right-hand sides on a 16,212-unknown system, 2.4 s with 2 threads, 0.26 s with 1): those
# run on one thread; fronts above BIG_FRONT flops (the separators of a wide site) on all.
BIG_FRONT = 2e8
_controller: ThreadpoolController | None = None


def _one_thread():
    global _controller
    if _controller is None:
        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")


class FrontalCholesky:
    """L L^T = A for a symmetric positive definite A (CSC; only its lower triangle is read) and
    chunk starts `starts` (m + 1 offsets, 0 ... n). Raises numpy.linalg.LinAlgError when a front
    is not positive definite. `solve(b)` for b of shape (n,) or (n, k); `nnz` counts the factor's
    stored entries (lower triangle, the fronts' padding included)."""

    def __init__(self, A: csc_matrix, starts: np.ndarray):
        A = A.tocsc()
        if not A.has_canonical_format:
            A = A.copy()
            A.sum_duplicates()
        n = A.shape[0]  # pyright: ignore[reportOptionalSubscript]
        starts = np.asarray(starts, dtype=np.int64)
        if starts[0] != 0 or starts[-1] != n or np.any(np.diff(starts) <= 0):
            raise ValueError("chunk starts must rise strictly from 0 to n")
        m = len(starts) - 1
        chunk_of = np.repeat(np.arange(m), np.diff(starts))
        self.n, self.starts = n, starts
        self.L11: list[np.ndarray] = []
        self.L21: list[np.ndarray] = []
        self.bnd: list[np.ndarray] = []
        pending: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
        nnz = 0
        indptr, indices, data = A.indptr, A.indices, A.data
        for k in range(m):
            s, e = int(starts[k]), int(starts[k + 1])
            o = e - s
            lo, hi = indptr[s], indptr[e]
            rows = indices[lo:hi]
            cols = np.repeat(np.arange(o), np.diff(indptr[s:e + 1]))
            vals = data[lo:hi]
            keep = rows >= s                      # earlier rows belong to earlier fronts
            rows, cols, vals = rows[keep], cols[keep], vals[keep]
            kids = pending.pop(k, [])
            parts = [rows[rows >= e]] + [b[b >= e] for _, b in kids]
            bnd = np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)
            front = np.concatenate([np.arange(s, e), bnd])
            F = np.zeros((len(front), len(front)))
            F[np.searchsorted(front, rows), cols] = vals           # the chunk's columns, lower part
            for U, b in kids:                                       # the children's updates
                p = np.searchsorted(front, b)
                F[np.ix_(p, p)] += U
            b = len(bnd)
            with (nullcontext() if o ** 3 / 3 + o * o * b + o * b * b > BIG_FRONT else _one_thread()):
                L11 = np.asfortranarray(scipy.linalg.cholesky(F[:o, :o], lower=True, check_finite=False))
                L21 = scipy.linalg.solve_triangular(L11, F[o:, :o].T, lower=True, check_finite=False).T
                if b:
                    # the children's updates only (the boundary's own entries of A come with its
                    # own chunks), minus L21 L21^T: lower triangles throughout (syrk: half a product)
                    U = _syrk(-1.0, L21, beta=1.0, c=F[o:, o:], lower=1, overwrite_c=1)
                    pending.setdefault(int(chunk_of[bnd[0]]), []).append((U, bnd))
            self.L11.append(L11)
            self.L21.append(np.ascontiguousarray(L21))
            self.bnd.append(bnd)
            nnz += o * (o + 1) // 2 + o * len(bnd)
        self.nnz = nnz

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x with A x = b, for b of shape (n,) or (n, k): the fronts' triangular pairs (BLAS
        trsm on each front's right-hand sides)."""
        with _one_thread():
            return self._solve(b)

    def _solve(self, b: np.ndarray) -> np.ndarray:
        y = np.array(b, dtype=np.float64, copy=True)
        vec = y.ndim == 1
        if vec:
            y = y[:, None]
        st = self.starts
        for k in range(len(self.L11)):                      # L y = b
            sl = slice(st[k], st[k + 1])
            y[sl] = _trsm(1.0, self.L11[k], np.asfortranarray(y[sl]), lower=1)
            if len(self.bnd[k]):
                y[self.bnd[k]] -= self.L21[k] @ y[sl]
        for k in range(len(self.L11) - 1, -1, -1):          # L^T x = y
            sl = slice(st[k], st[k + 1])
            if len(self.bnd[k]):
                y[sl] -= self.L21[k].T @ y[self.bnd[k]]
            y[sl] = _trsm(1.0, self.L11[k], np.asfortranarray(y[sl]), lower=1, trans_a=1)
        return y[:, 0] if vec else y

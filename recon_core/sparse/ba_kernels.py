"""Compiled assembly of the bundle adjustment's normal equations (numba: a per-point loop with
no library kernel; general sparse-matrix products spent most of the time of an iteration).

Parameters: the free entries of the free tile cameras (columns `cam_col[c, 0..7]`, -1 where an
entry is held) and the free points (slots `ps`, -1 for a held point). Observation k (camera c,
point p, weight w) has residual r = M_c X_p + t_c - x and h = [X_p, 1]:
  d r_row / d P_c[row, j] = h_j  (camera entry row * 4 + j),   d r / d X_p = M_c.
`assemble_blocks` builds U (one 8 x 8 block per camera), g_c, V (3 x 3 per point) and g_p;
`schur` forms the damped reduced system S dc = rhs as a dense matrix, `schur_blocks` as 8 x 8
blocks over the camera pairs that share points (`block_pattern`); `back_substitute` gives the
point steps. Observations are
visited point by point through `order` / `start` (a CSR of the observations of each point slot
that involve a free camera entry: the others add nothing to S, rhs or the point steps).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

_JIT: dict[str, Any] = dict(cache=True, nogil=True, fastmath=False)


@njit(**_JIT)
def _inv3(A):
    """Inverse of a symmetric positive 3 x 3 matrix (cofactors)."""
    a, b, c = A[0, 0], A[0, 1], A[0, 2]
    d, e, f = A[1, 1], A[1, 2], A[2, 2]
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    det = a * c00 + b * c01 + c * c02
    out = np.empty((3, 3))
    out[0, 0] = c00 / det
    out[0, 1] = c01 / det
    out[0, 2] = c02 / det
    out[1, 0] = out[0, 1]
    out[1, 1] = (a * f - c * c) / det
    out[1, 2] = (b * c - a * e) / det
    out[2, 0] = out[0, 2]
    out[2, 1] = out[1, 2]
    out[2, 2] = (a * d - b * b) / det
    return out


@njit(**_JIT)
def _max_run(start):
    """The largest number of observations of one point."""
    mmax = 0
    for p in range(start.shape[0] - 1):
        mmax = max(mmax, start[p + 1] - start[p])
    return mmax


@njit(**_JIT)
def _load_point(p, lam, V, Vinv, h, M, w, oc, cam_col, cc, order, start, G, Mq, hw, cols, cam):
    """Point p's damped V^-1 (stored in Vinv[p]) and, per observation q of it: G = M V^-1, M,
    w h, the camera's 8 columns and (when cc is given) its compact camera. Returns their
    number."""
    Vd = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            Vd[i, j] = V[p, i, j]
        Vd[i, i] = V[p, i, i] * (1.0 + lam) + 1e-12
    Vi = _inv3(Vd)
    Vinv[p] = Vi
    k0 = start[p]
    m = start[p + 1] - k0
    for q in range(m):
        k = order[k0 + q]
        if cc.shape[0]:
            cam[q] = cc[oc[k]]
        for e in range(8):
            cols[q, e] = cam_col[oc[k], e]
        for j in range(4):
            hw[q, j] = w[k] * h[k, j]
        for row in range(2):
            for i in range(3):
                Mq[q, row, i] = M[k, row, i]
                G[q, row, i] = M[k, row, 0] * Vi[0, i] + M[k, row, 1] * Vi[1, i] + M[k, row, 2] * Vi[2, i]
    return m


@njit(**_JIT)
def _add_point_rhs(rhs, p, m, g_p, G, hw, cols):
    """rhs += W_p V_p'^-1 g_p for point p's m observations (loaded by _load_point)."""
    for q1 in range(m):
        for row1 in range(2):
            gg = G[q1, row1, 0] * g_p[p, 0] + G[q1, row1, 1] * g_p[p, 1] + G[q1, row1, 2] * g_p[p, 2]
            for j1 in range(4):
                col1 = cols[q1, row1 * 4 + j1]
                if col1 >= 0:
                    rhs[col1] += hw[q1, j1] * gg


@njit(inline="always", **_JIT)
def _point_scratch(start):
    """Scratch for the observations of one point (as many as the longest track): G = M V^-1,
    M, w h, the camera's 8 columns, its compact camera, and the 8 x 8 block of one pair."""
    mmax = _max_run(start)
    return (np.empty((mmax, 2, 3)), np.empty((mmax, 2, 3)), np.empty((mmax, 4)),
            np.empty((mmax, 8), np.int64), np.empty(mmax, np.int64), np.empty((8, 8)))


@njit(inline="always", **_JIT)
def _next_point(pi, porder, lam, V, Vinv, h, M, w, oc, cam_col, cc, order, start, g_p, rhs,
                G, Mq, hw, cols, cam):
    """Load the pi-th point of the visiting order into the scratch and add its share of the
    right-hand side; returns its number of observations."""
    p = porder[pi]
    m = _load_point(p, lam, V, Vinv, h, M, w, oc, cam_col, cc, order, start, G, Mq, hw, cols, cam)
    _add_point_rhs(rhs, p, m, g_p, G, hw, cols)
    return m


@njit(inline="always", **_JIT)
def _pair_block(B, G, Mq, hw, q1, q2):
    """B[row1 * 4 + j1, row2 * 4 + j2] = w1 h1_j1 w2 h2_j2 (M1 V^-1 M2^T)[row1, row2]: the 8 x 8
    entry block of W V^-1 W^T for a pair of observations of one point (W_k[row*4 + j, i] =
    w h_j M[row, i]), every entry whether or not its camera column is free."""
    for row1 in range(2):
        for row2 in range(2):
            a = (G[q1, row1, 0] * Mq[q2, row2, 0] + G[q1, row1, 1] * Mq[q2, row2, 1]
                 + G[q1, row1, 2] * Mq[q2, row2, 2])
            for j1 in range(4):
                ah = a * hw[q1, j1]
                for j2 in range(4):
                    B[row1 * 4 + j1, row2 * 4 + j2] = ah * hw[q2, j2]


@njit(**_JIT)
def schur(U, g_c, V, g_p, lam, h, M, w, oc, cam_col, order, start, porder):
    """Damped reduced camera system: S = U' - sum_p W_p V_p'^-1 W_p^T, rhs = -(g_c - sum_p
    W_p V_p'^-1 g_p), with U', V' the diagonals scaled by (1 + lam) (+1e-12). Returns
    (S, rhs, Vinv (npt, 3, 3)). Points are visited in the order `porder`: points seen by the
    same cameras one after another keep the blocks of S they update in the cache."""
    nc = U.shape[0]
    npt = V.shape[0]
    S = U.copy()
    for i in range(nc):
        S[i, i] = S[i, i] * (1.0 + lam) + 1e-12
    rhs = -g_c.copy()
    Vinv = np.empty((npt, 3, 3))
    G, Mq, hw, cols, cam, B = _point_scratch(start)
    no_cc = np.empty(0, np.int64)
    for pi in range(npt):
        m = _next_point(pi, porder, lam, V, Vinv, h, M, w, oc, cam_col, no_cc, order, start,
                        g_p, rhs, G, Mq, hw, cols, cam)
        # S is symmetric: each unordered pair of observations once (q2 >= q1), filed in the
        # upper triangle, mirrored at the end
        for q1 in range(m):
            for q2 in range(q1, m):
                same = q1 == q2
                _pair_block(B, G, Mq, hw, q1, q2)
                for e1 in range(8):
                    col1 = cols[q1, e1]
                    if col1 < 0:
                        continue
                    for e2 in range(8):
                        col2 = cols[q2, e2]
                        if col2 < 0:
                            continue
                        if col1 < col2:
                            S[col1, col2] -= B[e1, e2]
                        elif col2 < col1:
                            if not same:
                                S[col2, col1] -= B[e1, e2]
                        elif same:
                            S[col1, col2] -= B[e1, e2]
                        else:                        # never in practice: one camera twice
                            S[col1, col2] -= 2.0 * B[e1, e2]
    for i in range(nc):
        for j in range(i + 1, nc):
            S[j, i] = S[i, j]
    return S, rhs, Vinv


@njit(**_JIT)
def back_substitute(dc, g_p, Vinv, h, M, w, oc, cam_col, order, start):
    """Point steps dp_p = -V_p'^-1 (g_p + W_p^T dc)."""
    npt = g_p.shape[0]
    dp = np.empty((npt, 3))
    b = np.empty(3)
    for p in range(npt):
        for i in range(3):
            b[i] = g_p[p, i]
        for q in range(start[p], start[p + 1]):
            k = order[q]
            for e in range(8):                  # the camera's entries: row e // 4, column e % 4
                col = cam_col[oc[k], e]
                if col >= 0:
                    whd = w[k] * h[k, e % 4] * dc[col]
                    for i in range(3):
                        b[i] += whd * M[k, e // 4, i]
        for i in range(3):
            dp[p, i] = -(Vinv[p, i, 0] * b[0] + Vinv[p, i, 1] * b[1] + Vinv[p, i, 2] * b[2])
    return dp


# -- block-sparse reduced system (large sites) --------------------------------------------------
# The dense S above is nc^2 numbers: 2.1 GB for a 10 x 10 km site's ~16,000 unknowns. Two tile
# cameras are coupled in S only when they see a common point, so S is stored as 8 x 8 blocks
# over the pairs of cameras that do (upper triangle, a camera with itself included), indexed
# by compact camera numbers `cc` (cameras with a free entry; -1 otherwise). Entries of held
# camera parameters stay 0 in the blocks and are dropped when the matrix is built.


@njit(**_JIT)
def assemble_blocks(h, M, r, w, oc, ps, cam_col, cc, ncc, nc, npt):
    """(Ub (ncc, 8, 8), g_c (nc,), V (npt, 3, 3), g_p (npt, 3)) of J^T W J and J^T W r, U (the
    camera x camera part) as one 8 x 8 block per compact camera: it couples only the entries of
    one camera (indexed 0..7 in its block; held entries stay 0)."""
    K = h.shape[0]
    Ub = np.zeros((ncc, 8, 8))
    g_c = np.zeros(nc)
    V = np.zeros((npt, 3, 3))
    g_p = np.zeros((npt, 3))
    for k in range(K):
        c = oc[k]
        wk = w[k]
        a_ = cc[c]
        for row in range(2):
            for a in range(4):
                ca = cam_col[c, row * 4 + a]
                if ca < 0:
                    continue
                wha = wk * h[k, a]
                g_c[ca] += wha * r[k, row]
                for b in range(4):
                    if cam_col[c, row * 4 + b] >= 0:
                        Ub[a_, row * 4 + a, row * 4 + b] += wha * h[k, b]
        p = ps[k]
        if p >= 0:
            for i in range(3):
                g_p[p, i] += wk * (M[k, 0, i] * r[k, 0] + M[k, 1, i] * r[k, 1])
                for j in range(3):
                    V[p, i, j] += wk * (M[k, 0, i] * M[k, 0, j] + M[k, 1, i] * M[k, 1, j])
    return Ub, g_c, V, g_p


@njit(**_JIT)
def block_pattern(oc, cc, ncc, order, start):
    """The block pairs (a <= b) of compact cameras that share a point among the observations
    `order` / `start`, every (a, a) included: CSR (bptr (ncc + 1), bcol) with sorted rows."""
    npt = start.shape[0] - 1
    # observations by camera: the points each compact camera sees
    cnt = np.zeros(ncc + 1, np.int64)
    for q in range(start[npt]):
        cnt[cc[oc[order[q]]] + 1] += 1
    cptr = np.cumsum(cnt)
    fill = cptr[:-1].copy()
    cpts = np.empty(start[npt], np.int64)
    for p in range(npt):
        for q in range(start[p], start[p + 1]):
            a = cc[oc[order[q]]]
            cpts[fill[a]] = p
            fill[a] += 1
    mark = np.full(ncc, -1, np.int64)
    # two passes: count, then fill
    bptr = np.zeros(ncc + 1, np.int64)
    none = np.empty(0, np.int64)
    for a in range(ncc):
        bptr[a + 1] = bptr[a] + _later_neighbours(a, cptr, cpts, start, order, oc, cc, mark, none, 1)
    bcol = np.empty(bptr[ncc], np.int64)
    mark[:] = -1
    for a in range(ncc):
        bcol[bptr[a]] = a
        _later_neighbours(a, cptr, cpts, start, order, oc, cc, mark, bcol, bptr[a] + 1)
        bcol[bptr[a]:bptr[a + 1]].sort()
    return bptr, bcol


@njit(**_JIT)
def _later_neighbours(a, cptr, cpts, start, order, oc, cc, mark, out, f):
    """The compact cameras b > a that share a point with camera a, each once (marked with a in
    `mark`): written to out[f], out[f + 1], ... unless `out` is empty; returns the end f."""
    mark[a] = a
    for i in range(cptr[a], cptr[a + 1]):
        p = cpts[i]
        for q in range(start[p], start[p + 1]):
            b = cc[oc[order[q]]]
            if b > a and mark[b] != a:
                mark[b] = a
                if out.shape[0]:
                    out[f] = b
                f += 1
    return f


@njit(**_JIT)
def _block_of(bptr, bcol, a, b):
    """Index of block (a, b), a <= b (binary search in row a)."""
    lo = bptr[a]
    hi = bptr[a + 1] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if bcol[mid] < b:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(**_JIT)
def schur_blocks(Ub, g_c, V, g_p, lam, diag, h, M, w, oc, cam_col, cc, order, start, porder, bptr, bcol):
    """As `schur`, into blocks: S (nb, 8, 8) with block (a, b) a <= b holding S[a entries, b
    entries]; Ub the undamped camera blocks, `diag` (ncc, 8) the diagonal the damping scales
    (Ub's plus any penalty's), so S_ii = Ub_ii + lam * diag_i + 1e-12 before the points."""
    ncc = Ub.shape[0]
    npt = V.shape[0]
    S = np.zeros((bcol.shape[0], 8, 8))
    for a in range(ncc):
        d = bptr[a]
        for i in range(8):
            for j in range(8):
                S[d, i, j] = Ub[a, i, j]
            S[d, i, i] += lam * diag[a, i] + 1e-12
    rhs = -g_c.copy()
    Vinv = np.empty((npt, 3, 3))
    G, Mq, hw, cols, cam, B = _point_scratch(start)
    for pi in range(npt):
        m = _next_point(pi, porder, lam, V, Vinv, h, M, w, oc, cam_col, cc, order, start,
                        g_p, rhs, G, Mq, hw, cols, cam)
        for q1 in range(m):
            for q2 in range(q1, m):
                a, b = cam[q1], cam[q2]
                swap = b < a
                blk = _block_of(bptr, bcol, b, a) if swap else _block_of(bptr, bcol, a, b)
                # the same camera twice through two observations (never in practice): both
                # orders of the pair land in the one diagonal block
                twice = a == b and q1 != q2
                _pair_block(B, G, Mq, hw, q1, q2)
                for e1 in range(8):
                    if cols[q1, e1] < 0:
                        continue
                    for e2 in range(8):
                        if cols[q2, e2] < 0:
                            continue
                        if swap:
                            S[blk, e2, e1] -= B[e1, e2]
                        else:
                            S[blk, e1, e2] -= B[e1, e2]
                            if twice:
                                S[blk, e2, e1] -= B[e1, e2]
    return S, rhs, Vinv

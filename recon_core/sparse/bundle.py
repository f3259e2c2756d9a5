"""Bundle adjustment of affine tile cameras and points: Levenberg-Marquardt with a Schur complement.

The residual of observation k (camera c, point p) is r_k = P_c [X_p; 1] - x_k: bilinear, so its
Jacobian is exact and cheap (d r / d P_c[row] = [X_p, 1] on that row, d r / d X_p = M_c). The
normal equations [[U, W], [W^T, V]] have a block-diagonal V (one 3 x 3 block per point): points
are eliminated (Schur complement S = U - W V^-1 W^T, a small dense system over the free camera
entries), the cameras solved by Cholesky, the points back-substituted. A Huber loss enters as
iteratively reweighted least squares. The 12-dof affine gauge is fixed by the caller through
`fixed` (GEOMETRY_NOTES, "Gauge").
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy.sparse import csr_matrix

from recon_core.geometry.affine import solve3x3


@dataclass
class BAResult:
    cams: np.ndarray
    X: np.ndarray
    cost_before: float        # robust cost 0.5 sum rho(|r|^2) at the start
    cost_after: float
    rms_px: float             # plain RMS of the residual norms at the end
    n_obs: int
    seconds: float
    iterations: int = 0


LOSSES = ("linear", "huber", "cauchy")     # BundleConfig.loss


def _robust(sq: np.ndarray, loss: str, delta: float) -> tuple[np.ndarray, np.ndarray]:
    """(rho(s), rho'(s)) for squared residual norms s."""
    if loss == "linear":
        return sq, np.ones_like(sq)
    if loss == "huber":
        r = np.sqrt(sq)
        big = r > delta
        rho = np.where(big, 2.0 * delta * r - delta ** 2, sq)
        w = np.where(big, delta / np.maximum(r, 1e-300), 1.0)
        return rho, w
    if loss == "cauchy":
        return delta ** 2 * np.log1p(sq / delta ** 2), 1.0 / (1.0 + sq / delta ** 2)
    raise ValueError(f"unknown loss {loss!r} (linear, huber, cauchy)")


def bundle_adjust(cams: np.ndarray, X: np.ndarray, obs_cam: np.ndarray, obs_pt: np.ndarray,
                  obs_xy: np.ndarray, free_cams: np.ndarray, free_pts: np.ndarray,
                  fixed: np.ndarray | None = None, *, loss: str = "huber", f_scale: float = 1.0,
                  max_nfev: int = 50, rel_tol: float = 1e-6, compiled: bool = True,
                  ties: list | None = None) -> BAResult:
    """Refine the cameras `free_cams` and points `free_pts` (index arrays).

    cams (T, 2, 4), X (N, 3), observations (K,) camera and point indices with (K, 2) pixels;
    `fixed` (T, 2, 4) bool marks camera entries held constant (the gauge). Observations whose
    camera and point are both held constant are left out. `max_nfev` caps the LM iterations;
    they stop when an iteration lowers the robust cost by less than `rel_tol` of it.
    `compiled`: assemble the normal equations with the compiled per-point kernels
    (recon_core.sparse.ba_kernels); False takes the scipy.sparse path (same steps, slower).
    `ties`: quadratic penalties on camera entries (recon_core.sparse.image_model.Tie), added to
    the cost and to the camera normal equations.
    """
    t0 = time.time()
    cams, X = cams.astype(np.float64).copy(), X.astype(np.float64).copy()
    T, N = len(cams), len(X)
    fixed = np.zeros((T, 2, 4), bool) if fixed is None else fixed
    cam_free = np.zeros(T, bool)
    cam_free[np.asarray(free_cams, dtype=np.int64)] = True
    pt_free = np.zeros(N, bool)
    pt_free[np.asarray(free_pts, dtype=np.int64)] = True
    use = cam_free[obs_cam] | pt_free[obs_pt]
    oc, op, ox = obs_cam[use], obs_pt[use], obs_xy[use]
    K = len(oc)
    if K == 0:
        return BAResult(cams, X, 0.0, 0.0, 0.0, 0, 0.0)

    # camera parameter columns (free entries of free cameras); point slots (free points)
    free_entries = (cam_free[:, None, None] & ~fixed).reshape(T, 8)
    cam_col = np.full((T, 8), -1, np.int64)
    nc = int(free_entries.sum())
    cam_col[free_entries] = np.arange(nc)
    fp = np.flatnonzero(pt_free)
    pslot = np.full(N, -1, np.int64)
    pslot[fp] = np.arange(len(fp))
    npt = len(fp)
    ps = pslot[op]                                   # (K,) point slot or -1
    has_p = ps >= 0

    def residuals(c, Xp):
        return np.einsum("kij,kj->ki", c[oc, :, :3], Xp[op]) + c[oc, :, 3] - ox

    ties = list(ties or [])
    flat_col = cam_col.reshape(-1)
    tie_cols = [flat_col[t.idx] for t in ties]

    def cost_of(r, c):
        rho, w = _robust(np.sum(r * r, axis=1), loss, f_scale)
        flat = c.reshape(-1)
        return 0.5 * float(rho.sum()) + sum(t.cost(flat) for t in ties), w

    def add_ties(U, g_c, c):
        flat = c.reshape(-1)
        for t, cc in zip(ties, tie_cols):
            m = cc >= 0
            if m.any():
                U[np.ix_(cc[m], cc[m])] += t.Q[np.ix_(m, m)]
                g_c[cc[m]] += (t.Q @ flat[t.idx])[m]

    r = residuals(cams, X)
    cost, w = cost_of(r, cams)
    cost0 = cost
    lam = 1e-3
    it = 0
    if compiled:
        from recon_core.sparse import ba_kernels as kern

        with_p = np.flatnonzero(has_p)
        order = with_p[np.argsort(ps[with_p], kind="stable")]
        # an observation in a held camera adds nothing to the reduced system (a local
        # adjustment's points are mostly seen by held cameras): left out of the per-point pass
        order = order[(cam_col >= 0).any(axis=1)[oc[order]]]
        start = np.searchsorted(ps[order], np.arange(npt + 1)).astype(np.int64)
        # points ordered by the cameras that see them (first, last), for the cache
        first = np.full(npt, T, np.int64)
        last = np.full(npt, T, np.int64)
        seen = np.flatnonzero(start[:-1] < start[1:])
        if len(seen):
            occ = oc[order].astype(np.int64)
            first[seen] = np.minimum.reduceat(occ, start[seen])
            last[seen] = np.maximum.reduceat(occ, start[seen])
        porder = np.lexsort((last, first)).astype(np.int64)
    for it in range(1, max_nfev + 1):
        h = np.concatenate([X[op], np.ones((K, 1))], axis=1)        # (K, 4)
        M = np.ascontiguousarray(cams[oc, :, :3])                     # (K, 2, 3)
        if compiled:
            U, g_c, V, g_p = kern.assemble(h, M, r, w, oc, ps, cam_col, nc, npt)
            add_ties(U, g_c, cams)

            def step(lam):
                S, rhs, Vinv = kern.schur(U, g_c, V, g_p, lam, h, M, w, oc, cam_col, order, start, porder)
                dc = _cholesky_solve(S, rhs)
                return dc, kern.back_substitute(dc, g_p, Vinv, h, M, w, oc, cam_col, order, start)
        else:
            step = _sparse_normal_equations(h, M, r, w, oc, cam_col, ps, has_p, nc, npt, K,
                                            lambda U, g: add_ties(U, g, cams))
        improved = False
        for _ in range(8):                                            # LM damping attempts
            dc, dp = step(lam)
            new_cams = cams.copy()
            flat = new_cams.reshape(T, 8)
            flat[free_entries] += dc[cam_col[free_entries]]
            new_X = X.copy()
            new_X[fp] += dp
            r_new = residuals(new_cams, new_X)
            cost_new, w_new = cost_of(r_new, new_cams)
            if np.isfinite(cost_new) and cost_new < cost:
                rel = (cost - cost_new) / max(cost, 1e-300)
                cams, X, r, cost, w = new_cams, new_X, r_new, cost_new, w_new
                lam = max(lam / 3.0, 1e-9)
                improved = True
                break
            lam *= 4.0
        if not improved or rel < rel_tol:   # relative decrease of the robust cost
            break
    rms = float(np.sqrt(np.mean(np.sum(r * r, axis=1))))
    return BAResult(cams, X, cost0, cost, rms, K, time.time() - t0, it)


def warm_compiled_kernels() -> None:
    """Compile the kernels of recon_core.sparse.ba_kernels into numba's cache (one LM iteration
    on 2 cameras x 8 points, with the argument types the SfM passes): a first `aerec view`
    does this in a second process while the demo renders."""
    rng = np.random.default_rng(0)
    X = rng.uniform(-1.0, 1.0, (8, 3))
    cams = np.stack([np.hstack([np.eye(2, 3) + rng.normal(0, 0.1, (2, 3)), [[5.0], [5.0]]])
                     for _ in range(2)])
    obs_cam = np.repeat(np.arange(2, dtype=np.int64), 8)
    obs_pt = np.tile(np.arange(8, dtype=np.int64), 2)
    xy = np.einsum("kij,kj->ki", cams[obs_cam, :, :3], X[obs_pt]) + cams[obs_cam, :, 3]
    fixed = np.zeros((2, 2, 4), bool)
    fixed[0] = True
    bundle_adjust(cams, X, obs_cam, obs_pt, xy, np.arange(2), np.arange(8), fixed, max_nfev=1)


SPARSE_SOLVE_MIN = 10000     # camera unknowns from which a sparse factorisation is tried
SPARSE_SOLVE_DENSITY = 0.25  # ... when at most this fraction of the reduced system is non-zero


def _cholesky_solve(S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve the reduced camera system S dc = rhs (S symmetric positive definite).

    S is already dense in memory, and LAPACK's dense Cholesky (one BLAS thread, as the core
    runs) beats SuperLU's sparse LU at the sizes met so far: `large`'s joint model, 617 tiles,
    4,924 unknowns, 10.5 % non-zero (two tile cameras are coupled only where they overlap),
    1.2 s against 1.9 s; with the per-image ties of the final adjustments (15.7 % non-zero,
    each image's tiles coupled together) 1.2 s against 5.2 s. The dense cost grows as n^3
    (~10 s at 10,000 unknowns) and the sparse one more slowly on a site's grid of tiles, so
    systems above SPARSE_SOLVE_MIN unknowns that are sparse enough go to SuperLU (COLAMD)."""
    if len(rhs) == 0:
        return np.zeros(0)
    if len(rhs) >= SPARSE_SOLVE_MIN and np.count_nonzero(S) <= SPARSE_SOLVE_DENSITY * S.size:
        from scipy.sparse import csc_matrix
        from scipy.sparse.linalg import splu

        try:
            dc = splu(csc_matrix(S), permc_spec="COLAMD", options={"SymmetricMode": True}).solve(rhs)
            if np.all(np.isfinite(dc)):
                return dc
        except RuntimeError:                  # singular: the dense path below decides
            pass
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), rhs)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(S, rhs, rcond=None)[0]


def _sparse_normal_equations(h, M, r, w, oc, cam_col, ps, has_p, nc, npt, K, extra=None):
    """The normal equations with numpy and scipy.sparse; returns step(lam) -> (dc, dp)."""
    # -- camera blocks: U (nc x nc), g_c; cross terms W (nc x 3 npt) as a sparse matrix
    cols0, cols1 = cam_col[oc, :4], cam_col[oc, 4:]               # (K, 4) each
    wh = w[:, None] * h
    rows_u, cols_u, vals_u = [], [], []
    for cols in (cols0, cols1):
        a = np.repeat(cols, 4, axis=1)
        b = np.tile(cols, (1, 4))
        v = (wh[:, :, None] * h[:, None, :]).reshape(K, 16)
        m = (a >= 0) & (b >= 0)
        rows_u.append(a[m]); cols_u.append(b[m]); vals_u.append(v[m])
    U = np.zeros((nc, nc))
    if nc:   # bincount on flat indices: np.add.at is ~20x slower on millions of entries
        flat_idx = np.concatenate(rows_u) * nc + np.concatenate(cols_u)
        U = np.bincount(flat_idx, np.concatenate(vals_u), minlength=nc * nc).reshape(nc, nc)
    g_c = np.zeros(nc)
    for row, cols in enumerate((cols0, cols1)):
        v = wh * r[:, row:row + 1]
        m = cols >= 0
        g_c += np.bincount(cols[m], v[m], minlength=nc)
    # W entries: d r_row / d P[row, j] * d r_row / d X_i = h_j * M[row, i]
    wr, wc, wv = [], [], []
    for row, cols in enumerate((cols0, cols1)):
        v = w[:, None, None] * h[:, :, None] * M[:, row, None, :]   # (K, 4, 3)
        a = np.repeat(cols[:, :, None], 3, axis=2)
        b = np.broadcast_to((3 * ps)[:, None, None] + np.arange(3)[None, None, :], (K, 4, 3))
        m = (a >= 0) & (b >= 0) & has_p[:, None, None]
        wr.append(a[m]); wc.append(b[m]); wv.append(v[m])
    Wm = csr_matrix((np.concatenate(wv), (np.concatenate(wr), np.concatenate(wc))), shape=(nc, 3 * npt))
    # -- point blocks: V_p (3 x 3), g_p
    MtM = np.einsum("kri,krj->kij", M, M) * w[:, None, None]
    V = np.zeros((npt, 3, 3))
    Mtr = np.einsum("kri,kr->ki", M, r) * w[:, None]
    g_p = np.zeros((npt, 3))
    if npt:
        for i in range(3):
            for j in range(3):
                V[:, i, j] = np.bincount(ps[has_p], MtM[has_p, i, j], minlength=npt)
            g_p[:, i] = np.bincount(ps[has_p], Mtr[has_p, i], minlength=npt)
    if extra is not None:
        extra(U, g_c)
    return lambda lam: _solve_step(U, g_c, Wm, V, g_p, lam)


def _solve_step(U, g_c, Wm, V, g_p, lam):
    """One damped Gauss-Newton step by the Schur complement on the points."""
    npt = len(V)
    Vd = V.copy()
    idx = np.arange(3)
    Vd[:, idx, idx] *= 1.0 + lam
    Vd[:, idx, idx] += 1e-12
    # V^-1 applied blockwise; as a sparse block-diagonal matrix for the Schur complement
    Vinv = np.stack([solve3x3(Vd, np.broadcast_to(np.eye(3)[k], (npt, 3))) for k in range(3)], axis=2) \
        if npt else np.zeros((0, 3, 3))
    nc = len(g_c)
    if nc:
        rows = (3 * np.arange(npt))[:, None, None] + idx[None, :, None]
        cols = (3 * np.arange(npt))[:, None, None] + idx[None, None, :]
        Vi = csr_matrix((Vinv.ravel(), (np.broadcast_to(rows, Vinv.shape).ravel(),
                                        np.broadcast_to(cols, Vinv.shape).ravel())), shape=(3 * npt, 3 * npt))
        WVi = Wm @ Vi
        S = U.copy()
        S[np.diag_indices(nc)] *= 1.0 + lam
        S[np.diag_indices(nc)] += 1e-12
        S -= (WVi @ Wm.T).toarray()
        rhs = -(g_c - WVi @ g_p.ravel())
        try:
            dc = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), rhs)
        except np.linalg.LinAlgError:
            dc = np.linalg.lstsq(S, rhs, rcond=None)[0]
        back = -(g_p.ravel() + Wm.T @ dc)
    else:
        dc = np.zeros(0)
        back = -g_p.ravel()
    dp = np.einsum("nij,nj->ni", Vinv, back.reshape(-1, 3)) if npt else np.zeros((0, 3))
    return dc, dp

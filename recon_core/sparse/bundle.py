"""Bundle adjustment of affine tile cameras and points: Levenberg-Marquardt with a Schur complement.

The residual of observation k (camera c, point p) is r_k = P_c [X_p; 1] - x_k: bilinear, so its
Jacobian is exact and cheap (d r / d P_c[row] = [X_p, 1] on that row, d r / d X_p = M_c). The
normal equations [[U, W], [W^T, V]] have a block-diagonal V (one 3 x 3 block per point): points
are eliminated (Schur complement S = U - W V^-1 W^T, a system over the free camera entries:
dense and solved by Cholesky for small models, 8 x 8 blocks over the camera pairs that share
points and factored by dense fronts on a nested dissection for large ones, `_BlockSystem`,
`frontal.FrontalCholesky`), the points back-substituted. A
Huber loss enters as
iteratively reweighted least squares. The 12-dof affine gauge is fixed by the caller through
`fixed`: exactly the 12 numbers of a canonical frame, no more (holding two whole
cameras would freeze the pair's epipolar geometry at its first estimate).
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
SOLVERS = ("auto", "dense", "sparse")      # BundleConfig.solver


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
                  ties: list | None = None, solver: str = "auto") -> BAResult:
    """Refine the cameras `free_cams` and points `free_pts` (index arrays).

    cams (T, 2, 4), X (N, 3), observations (K,) camera and point indices with (K, 2) pixels;
    `fixed` (T, 2, 4) bool marks camera entries held constant (the gauge). Observations whose
    camera and point are both held constant are left out. `max_nfev` caps the LM iterations;
    they stop when an iteration lowers the robust cost by less than `rel_tol` of it.
    `compiled`: assemble the normal equations with the compiled per-point kernels
    (recon_core.sparse.ba_kernels); False takes the scipy.sparse path (same steps, slower).
    `ties`: quadratic penalties on camera entries (recon_core.bend.image_model.Tie), added to
    the cost and to the camera normal equations.
    `solver`: "dense" (the reduced camera system as one dense matrix, Cholesky), "sparse" (as
    8 x 8 blocks over the pairs of cameras that share points, sparse LU; the ties as a low-rank
    term; needs `compiled`) or "auto" (sparse from SPARSE_SOLVE_MIN camera unknowns).
    """
    _check_solver(solver, compiled)
    t0 = time.time()
    cams, X = cams.astype(np.float64).copy(), X.astype(np.float64).copy()
    T, N = len(cams), len(X)
    u = _Unknowns.of(T, N, fixed, free_cams, free_pts, obs_cam, obs_pt, obs_xy)
    if u.K == 0:
        return BAResult(cams, X, 0.0, 0.0, 0.0, 0, 0.0)
    oc, op, K = u.oc, u.op, u.K
    free_entries, cam_col, nc, fp, npt, ps, has_p = u.free_entries, u.cam_col, u.nc, u.fp, u.npt, u.ps, u.has_p

    use_blocks = compiled and (solver == "sparse" or (solver == "auto" and nc >= SPARSE_SOLVE_MIN))
    obj = _Objective(u, list(ties or []), loss, f_scale, dense_ties=not use_blocks)
    residuals, cost_of, add_ties = obj.residuals, obj.cost, obj.add_ties

    r = residuals(cams, X)
    cost, w = cost_of(r, cams)
    cost0 = cost
    lam = 1e-3
    it = 0
    if compiled:
        from recon_core.sparse import ba_kernels as kern

        order, start, porder = _point_passes(oc, ps, has_p, cam_col, npt, T)
        cc, cams_cc = _compact_cameras(cam_col)
        if use_blocks:
            blocks = _BlockSystem(cam_col, oc, op, X, order, start, obj.ties, obj.tie_cols)
    for it in range(1, max_nfev + 1):
        h = np.concatenate([X[op], np.ones((K, 1))], axis=1)        # (K, 4)
        M = np.ascontiguousarray(cams[oc, :, :3])                     # (K, 2, 3)
        if use_blocks:
            step = blocks.stepper(cams, h, M, r, w, oc, ps, cam_col, nc, npt, order, start, porder)
        elif compiled:
            Ub, g_c, V, g_p = kern.assemble_blocks(h, M, r, w, oc, ps, cam_col, cc, len(cams_cc), nc, npt)
            U = _dense_from_blocks(Ub, cam_col[cams_cc], nc)
            add_ties(U, g_c, cams)

            def step(lam):
                S, rhs, Vinv = kern.schur(U, g_c, V, g_p, lam, h, M, w, oc, cam_col, order, start, porder)
                dc = _cholesky_solve(S, rhs)
                return dc, kern.back_substitute(dc, g_p, Vinv, h, M, w, oc, cam_col, order, start)
        else:
            step = _sparse_normal_equations(h, M, r, w, oc, cam_col, ps, has_p, nc, npt, K,
                                            lambda U, g: add_ties(U, g, cams))
        def apply(dc, dp):
            new_cams = cams.copy()
            new_cams.reshape(T, 8)[free_entries] += dc[cam_col[free_entries]]
            new_X = X.copy()
            new_X[fp] += dp
            r_new = residuals(new_cams, new_X)
            return (new_cams, new_X, r_new) + cost_of(r_new, new_cams)

        got, lam = _damped_step(step, apply, cost, lam)
        if got is None:
            break
        rel = (cost - got[3]) / max(cost, 1e-300)
        cams, X, r, cost, w = got
        if rel < rel_tol:                   # relative decrease of the robust cost
            break
    rms = float(np.sqrt(np.mean(np.sum(r * r, axis=1))))
    return BAResult(cams, X, cost0, cost, rms, K, time.time() - t0, it)


@dataclass
class _Unknowns:
    """The adjustment's unknowns: the observations it uses (oc, op, ox: K of them, those whose
    camera or point is free), the camera parameter columns (free entries of free cameras:
    cam_col (T, 8), -1 when held; nc of them) and the point slots (free points fp, npt of them;
    ps (K,) each observation's slot or -1)."""

    oc: np.ndarray
    op: np.ndarray
    ox: np.ndarray
    K: int
    free_entries: np.ndarray
    cam_col: np.ndarray
    nc: int
    fp: np.ndarray
    npt: int
    ps: np.ndarray
    has_p: np.ndarray

    @classmethod
    def of(cls, T: int, N: int, fixed, free_cams, free_pts, obs_cam, obs_pt, obs_xy) -> "_Unknowns":
        fixed = np.zeros((T, 2, 4), bool) if fixed is None else fixed
        cam_free = np.zeros(T, bool)
        cam_free[np.asarray(free_cams, dtype=np.int64)] = True
        pt_free = np.zeros(N, bool)
        pt_free[np.asarray(free_pts, dtype=np.int64)] = True
        use = cam_free[obs_cam] | pt_free[obs_pt]
        oc, op, ox = obs_cam[use], obs_pt[use], obs_xy[use]
        free_entries = (cam_free[:, None, None] & ~fixed).reshape(T, 8)
        cam_col = np.full((T, 8), -1, np.int64)
        nc = int(free_entries.sum())
        cam_col[free_entries] = np.arange(nc)
        fp = np.flatnonzero(pt_free)
        pslot = np.full(N, -1, np.int64)
        pslot[fp] = np.arange(len(fp))
        ps = pslot[op]
        return cls(oc, op, ox, len(oc), free_entries, cam_col, nc, fp, len(fp), ps, ps >= 0)


def _check_solver(solver: str, compiled: bool) -> None:
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r} (auto, dense, sparse)")
    if solver == "sparse" and not compiled:
        raise ValueError("the block-sparse system needs the compiled kernels (compiled=True)")


class _Objective:
    """The robust cost of the reprojection residuals plus the ties' quadratic penalties, and the
    ties' share of the camera normal equations (dense_ties: added to a dense system)."""

    def __init__(self, u: _Unknowns, ties: list, loss: str, f_scale: float, dense_ties: bool):
        self.u, self.ties, self.loss, self.f_scale = u, ties, loss, f_scale
        flat_col = u.cam_col.reshape(-1)
        self.tie_cols = [flat_col[t.idx] for t in ties]
        self.tie_q = [t.dense_q() for t in ties] if dense_ties else []

    def residuals(self, c: np.ndarray, Xp: np.ndarray) -> np.ndarray:
        u = self.u
        return np.einsum("kij,kj->ki", c[u.oc, :, :3], Xp[u.op]) + c[u.oc, :, 3] - u.ox

    def cost(self, r: np.ndarray, c: np.ndarray) -> tuple[float, np.ndarray]:
        rho, w = _robust(np.sum(r * r, axis=1), self.loss, self.f_scale)
        flat = c.reshape(-1)
        return 0.5 * float(rho.sum()) + sum(t.cost(flat) for t in self.ties), w

    def add_ties(self, U: np.ndarray, g_c: np.ndarray, c: np.ndarray) -> None:
        for q, cc in zip(self.tie_q, self.tie_cols):
            m = cc >= 0
            if m.any():
                U[np.ix_(cc[m], cc[m])] += q[np.ix_(m, m)]
        _add_tie_gradient(g_c, self.ties, self.tie_cols, c.reshape(-1))


def _point_passes(oc: np.ndarray, ps: np.ndarray, has_p: np.ndarray, cam_col: np.ndarray, npt: int,
                  T: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The compiled kernels' per-point pass: (the observations grouped by point, where each
    point's start, the points ordered by the cameras that see them)."""
    with_p = np.flatnonzero(has_p)
    order = with_p[np.argsort(ps[with_p], kind="stable")]
    # an observation in a held camera adds nothing to the reduced system (a local
    # adjustment's points are mostly seen by held cameras): left out of the per-point pass
    order = order[(cam_col >= 0).any(axis=1)[oc[order]]]  # pyright: ignore[reportIndexIssue]
    start = np.searchsorted(ps[order], np.arange(npt + 1)).astype(np.int64)
    # points ordered by the cameras that see them (first, last), for the cache
    first = np.full(npt, T, np.int64)
    last = np.full(npt, T, np.int64)
    seen = np.flatnonzero(start[:-1] < start[1:])
    if len(seen):
        occ = oc[order].astype(np.int64)
        first[seen] = np.minimum.reduceat(occ, start[seen])
        last[seen] = np.maximum.reduceat(occ, start[seen])
    return order, start, np.lexsort((last, first)).astype(np.int64)


def _damped_step(step, apply, cost: float, lam: float, attempts: int = 8):
    """One Levenberg-Marquardt iteration: solve with damping lam, keep the update if it lowers
    the robust cost, else damp more (x4) and try again, up to `attempts` times. Returns (the
    new (cams, X, r, cost, w), or None when no attempt improved; the damping to go on with)."""
    for _ in range(attempts):
        got = apply(*step(lam))
        if np.isfinite(got[3]) and got[3] < cost:
            return got, max(lam / 3.0, 1e-9)
        lam *= 4.0
    return None, lam


def warm_compiled_kernels() -> None:
    """Compile the kernels of recon_core.sparse.ba_kernels into numba's cache (one LM iteration
    on 2 cameras x 8 points, with the argument types the SfM passes): a first `aerec view`
    does this in a second process while the demo renders. Only the dense system's: the demo
    never reaches the block-sparse one (SPARSE_SOLVE_MIN), and compiling it too would take
    10 s more of CPU (cold cache) beside the demo's reconstruction on a 2-core machine; a site
    large enough to need it pays that once in a run of many minutes."""
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


# camera unknowns from which "auto" takes the block-sparse system. Measured (one thread): 588
# unknowns the same time; `large`'s group 0, 1,992 unknowns, 0.32 s against 0.37 s per
# iteration; its 9-image joint model, 4,924, 2.5 s against 2.7 s; a 5 x 5 km site, 4,044,
# 0.62 s against 1.47 s; 10 x 10 km, 16,212, 3.7 s against 59 s (bench/bench_ba_scale.py)
SPARSE_SOLVE_MIN = 1500
DENSE_FILL = 0.4             # ... whose factorisation turns dense when its factor fills more than this
DENSE_FACTOR_MAX = 16000     # ... and the dense matrix (8 bytes x this^2: 2 GB) is affordable


def _cholesky_solve(S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve the dense reduced camera system S dc = rhs (S symmetric positive definite)."""
    if len(rhs) == 0:
        return np.zeros(0)
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), rhs)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(S, rhs, rcond=None)[0]


class _BlockSystem:
    """The reduced camera system of a large site, block-sparse (the "sparse" solver).

    Memory and time. The dense S is nc^2 numbers and its Cholesky nc^3 / 3 flops: `large`'s
    joint model (4,924 unknowns) is 194 MB and ~1.1 s, a 10 x 10 km site's ~16,000 unknowns
    2.1 GB and ~40 s, a 20 x 20 km site's ~65,000 34 GB. Two tile cameras are coupled only when
    they share points (a tile, its neighbours in its image, and the tiles of the other images
    over the same ground: ~25 others), so S is kept as 8 x 8 blocks over those pairs, assembled
    by the compiled per-point pass (ba_kernels.schur_blocks), put in a nested-dissection order
    of the cameras by their ground position (`_dissection_order`) and factored by one dense
    front per leaf and separator of that dissection (frontal.FrontalCholesky). Figures:
    bench/bench_ba_scale.py, docs: research-notes.md, "Bundle adjustment at scale".

    The per-image ties. Their Q = blockdiag(DtD) - L L^T (image_model.Tie) would couple all
    tiles of an image: a dense block of (8 x tiles)^2. Its block-diagonal part goes into S's
    diagonal blocks; the low-rank part (the image model's eliminated parameters, <= 17 per
    image) is solved by the Woodbury identity: with A the sparse part,
    (A - L L^T)^-1 b = A^-1 b + A^-1 L (I - L^T A^-1 L)^-1 L^T A^-1 b, one factorisation of A and
    as many extra solves as model parameters. The steps are those of the dense system (a test
    checks both paths agree)."""

    def __init__(self, cam_col, oc, op, X, order, start, ties, tie_cols):
        from recon_core.sparse import ba_kernels as kern

        self.kern = kern
        self.cc, self.cams_cc = _compact_cameras(cam_col)
        ncc = len(self.cams_cc)
        self.bptr, self.bcol = kern.block_pattern(oc, self.cc, ncc, order, start)
        nb = len(self.bcol)
        brow = np.repeat(np.arange(ncc), np.diff(self.bptr))
        # every entry of every block with both parameters free, and the mirror of the
        # off-diagonal blocks' entries: a symmetric CSC built by one gather per iteration
        ca = cam_col[self.cams_cc[brow]]                       # (nb, 8) rows' columns
        cb = cam_col[self.cams_cc[self.bcol]]                  # (nb, 8)
        R = np.broadcast_to(ca[:, :, None], (nb, 8, 8))
        C = np.broadcast_to(cb[:, None, :], (nb, 8, 8))
        src = np.arange(nb * 64, dtype=np.int64).reshape(nb, 8, 8)
        ok = (R >= 0) & (C >= 0)
        off = (brow != self.bcol)[:, None, None] & ok
        rows = np.concatenate([R[ok], C[off]])
        cols = np.concatenate([C[ok], R[off]])
        srcs = np.concatenate([src[ok], src[off]])
        nc = int(cam_col.max()) + 1
        # the factorisation's order: nested dissection of the cameras by their ground position
        # (the matrix is built in that order; solves permute in and out)
        obs = np.flatnonzero(self.cc[oc] >= 0)
        corder, sizes = _dissection_order(self.bptr, self.bcol,
                                          _camera_positions(self.cc[oc[obs]], X[op[obs]], ncc), chunks=True)
        cols_cc = cam_col[self.cams_cc[corder]]
        self.perm = cols_cc[cols_cc >= 0]                      # new scalar index -> old
        # the dissection's leaves and separators as ranges of scalar unknowns (the fronts)
        per_cam = np.cumsum(np.r_[0, (cols_cc >= 0).sum(1)])
        self.starts = np.unique(per_cam[np.r_[0, np.cumsum(sizes)]])
        inv = np.empty(nc, np.int64)
        inv[self.perm] = np.arange(nc)
        rows, cols = inv[rows], inv[cols]
        perm = np.lexsort((rows, cols))
        self.src = srcs[perm]
        self.indices = rows[perm].astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(cols, minlength=nc))]).astype(np.int32)
        self.nc = nc
        # ties: block-diagonal part per compact camera, its diagonal, and the low-rank columns
        self.tie_blocks = np.zeros((ncc, 8, 8))
        self.tie_diag = np.zeros(nc)
        Ls = []
        for t, tc in zip(ties, tie_cols):
            tiles = t.idx[::8] // 8
            a = self.cc[tiles]
            free = tc.reshape(-1, 8) >= 0
            for coord in range(2):
                sl = slice(4 * coord, 4 * coord + 4)
                blk = t.DtD * (free[:, sl, None] & free[:, None, sl])
                for k in np.flatnonzero(a >= 0):
                    self.tie_blocks[a[k], sl, sl] += blk[k]
                L = t.L[coord]                                      # (n, 4, k)
                if L.shape[2] == 0:
                    continue
                Lc = np.zeros((nc, L.shape[2]))
                rr = tc.reshape(-1, 8)[:, sl]                        # (n, 4) columns or -1
                m = rr >= 0
                Lc[rr[m]] = L[m]
                Ls.append(Lc)
            m = tc >= 0
            self.tie_diag[tc[m]] += t.diag()[m]
        self.L = np.hstack(Ls) if Ls else np.zeros((nc, 0))
        self.L = self.L[self.perm]                             # in the factorisation's order
        self.ties, self.tie_cols = ties, tie_cols
        self.dense_factor: bool | None = None       # decided by the first factorisation

    def _factor(self, A):
        """A solve function for A (symmetric positive definite, CSC, in nested-dissection
        order). A Cholesky factorisation by dense fronts, one per leaf and separator of the
        dissection (frontal.FrontalCholesky: LAPACK and BLAS-3 on each front; SciPy's SuperLU,
        used before, took 2.6x as long on a 9-image 7.5 km system, 1.7x per LM iteration at
        20 km). When the factor comes out nearly dense (more than DENSE_FILL of n^2: many images over a small site) and the dense
        matrix is affordable, this adjustment's later factorisations are LAPACK's dense
        Cholesky of the whole matrix. The choice depends on the pattern only: runs stay
        deterministic."""
        from recon_core.sparse.frontal import FrontalCholesky

        n = A.shape[0]
        if self.dense_factor:
            # in Fortran order and factored in place: LAPACK would otherwise copy it (2x memory)
            cf = scipy.linalg.cho_factor(A.toarray(order="F"), overwrite_a=True, check_finite=False)
            return lambda b: scipy.linalg.cho_solve(cf, b)
        f = FrontalCholesky(A, self.starts)
        if self.dense_factor is None:
            self.dense_factor = n <= DENSE_FACTOR_MAX and 2 * f.nnz > DENSE_FILL * n * n
        return f.solve

    def stepper(self, cams, h, M, r, w, oc, ps, cam_col, nc, npt, order, start, porder):
        """step(lam) -> (dc, dp) for the current linearisation."""
        from scipy.sparse import csc_matrix

        kern = self.kern
        ncc = len(self.cams_cc)
        Ub, g_c, V, g_p = kern.assemble_blocks(h, M, r, w, oc, ps, cam_col, self.cc, ncc, nc, npt)
        _add_tie_gradient(g_c, self.ties, self.tie_cols, cams.reshape(-1))
        # the damping scales the diagonal of the whole camera system, ties included (as the
        # dense path, where Q is added to U before the Schur complement)
        cols = cam_col[self.cams_cc]                                    # (ncc, 8)
        diag = np.einsum("aii->ai", Ub).copy()
        diag[cols >= 0] += self.tie_diag[cols[cols >= 0]]
        Ub += self.tie_blocks
        L = self.L

        def step(lam):
            S, rhs, Vinv = kern.schur_blocks(Ub, g_c, V, g_p, lam, diag, h, M, w, oc, cam_col, self.cc,
                                             order, start, porder, self.bptr, self.bcol)
            A = csc_matrix((S.reshape(-1)[self.src], self.indices, self.indptr), shape=(nc, nc))
            b = rhs[self.perm]
            try:
                solve = self._factor(A)
                y = solve(b)
                if L.shape[1]:
                    Y = solve(L)
                    cf = scipy.linalg.lu_factor(np.eye(L.shape[1]) - L.T @ Y)

                    def full_solve(v):
                        x = solve(v)
                        return x + Y @ scipy.linalg.lu_solve(cf, L.T @ x)
                    y = full_solve(b)
                    # one step of iterative refinement: the image models' weakly determined
                    # modes make the system ill-conditioned, and Woodbury's sum loses digits
                    y += full_solve(b - (A @ y - L @ (L.T @ y)))
                dc = np.empty(nc)
                dc[self.perm] = y
            except (RuntimeError, np.linalg.LinAlgError):    # singular: LM damps harder
                dc = np.full(nc, np.nan)
            if not np.all(np.isfinite(dc)):
                return np.full(nc, np.nan), np.full((npt, 3), np.nan)
            return dc, kern.back_substitute(dc, g_p, Vinv, h, M, w, oc, cam_col, order, start)
        return step


def _add_tie_gradient(g_c: np.ndarray, ties: list, tie_cols: list, flat: np.ndarray) -> None:
    """g_c += each tie's gradient Q p on its free camera entries (tie_cols: their columns)."""
    for t, cc in zip(ties, tie_cols):
        m = cc >= 0
        if m.any():
            g_c[cc[m]] += t.grad(flat)[m]


def _compact_cameras(cam_col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cc (T,): each camera's number among those with a free entry, -1 for the others; those
    cameras (ncc,))."""
    has = (cam_col >= 0).any(axis=1)
    cc = np.full(len(cam_col), -1, np.int64)
    cc[has] = np.arange(int(has.sum()))
    return cc, np.flatnonzero(has)


def _dense_from_blocks(Ub: np.ndarray, cols: np.ndarray, nc: int) -> np.ndarray:
    """The dense (nc, nc) matrix of per-camera 8 x 8 blocks Ub, cols (ncc, 8) their columns (-1:
    held entry). Each entry belongs to one camera: a scatter, no sums."""
    U = np.zeros((nc, nc))
    ok = (cols[:, :, None] >= 0) & (cols[:, None, :] >= 0)
    R = np.broadcast_to(cols[:, :, None], Ub.shape)
    C = np.broadcast_to(cols[:, None, :], Ub.shape)
    U[R[ok], C[ok]] = Ub[ok]
    return U


def _camera_positions(cam: np.ndarray, Xo: np.ndarray, ncc: int) -> np.ndarray:
    """(ncc, 2) position of each compact camera: the mean of its observed points on the two
    principal axes of all of them (the affine frame's ground plane, whatever its gauge)."""
    if len(Xo) < 3:
        return np.zeros((ncc, 2))
    sub = Xo[:: max(1, len(Xo) // 200000)]
    c = sub.mean(0)
    axes = np.linalg.svd(sub - c, full_matrices=False)[2][:2]
    n = np.maximum(np.bincount(cam, minlength=ncc), 1)
    P = (Xo - c) @ axes.T
    return np.column_stack([np.bincount(cam, P[:, 0], minlength=ncc), np.bincount(cam, P[:, 1], minlength=ncc)]) / n[:, None]


def _dissection_order(bptr: np.ndarray, bcol: np.ndarray, pos: np.ndarray, leaf: int = 16,
                      chunks: bool = False):
    """A nested-dissection order of the cameras of a block pattern (CSR of pairs a <= b): split
    by the median of the longer extent of their positions, the cameras of one side coupled to
    the other side (the separator) last, each side recursively, down to `leaf` cameras. On a
    10 x 10 km site (bench/bench_ba_scale.py: 2,028 tiles, 16,212 unknowns) SuperLU then fills
    7 % and factors in 1.3 s (leaves of 256: 15 %, 4.6 s); with its own minimum-degree
    ordering of S + S^T 48 % and 61 s, more than the dense Cholesky (a tile is coupled to ~25
    others: its neighbours and the tiles of the other images over the same ground).
    With `chunks`, also the number of cameras of each leaf and separator, in order (the fronts
    of frontal.FrontalCholesky)."""
    from scipy.sparse import coo_matrix

    n = len(pos)
    brow = np.repeat(np.arange(n), np.diff(bptr))
    G = coo_matrix((np.ones(len(brow)), (brow, bcol)), shape=(n, n)).tocsr()
    G = (G + G.T).tocsr()
    out: list[np.ndarray] = []
    stack = [(np.arange(n), False)]
    while stack:                                   # (nodes, emit): emit a separator as is
        nodes, emit = stack.pop()
        if emit or len(nodes) <= leaf:
            out.append(nodes)
            continue
        p = pos[nodes]
        ax = int(np.argmax(p.max(0) - p.min(0)))
        left = p[:, ax] < np.median(p[:, ax])
        if left.all() or not left.any():
            out.append(nodes)
            continue
        in_right = np.zeros(n)
        in_right[nodes[~left]] = 1.0
        touches = (G[nodes[left]] @ in_right) > 0
        # pushed in reverse: the left part first, then the right, then the separator
        stack.append((nodes[left][touches], True))
        stack.append((nodes[~left], False))
        stack.append((nodes[left][~touches], False))
    order = np.concatenate(out) if out else np.zeros(0, np.int64)
    if chunks:
        return order, np.array([len(o) for o in out if len(o)], np.int64)
    return order


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

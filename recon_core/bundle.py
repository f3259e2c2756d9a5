"""Bundle adjustment of affine tile cameras and points, with an analytic sparse Jacobian.

The residual of observation k (camera c, point p) is P_c [X_p; 1] - x_k: bilinear in the
unknowns, so its Jacobian is exact and cheap: d r / d P_c[row] = [X_p, 1], d r / d X_p = M_c.
The 12-dof affine gauge is fixed by the caller through `fixed` (GEOMETRY_NOTES, "Gauge").
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix


@dataclass
class BAResult:
    cams: np.ndarray
    X: np.ndarray
    cost_before: float
    cost_after: float
    rms_px: float
    n_obs: int
    seconds: float


def bundle_adjust(cams: np.ndarray, X: np.ndarray, obs_cam: np.ndarray, obs_pt: np.ndarray,
                  obs_xy: np.ndarray, free_cams: np.ndarray, free_pts: np.ndarray,
                  fixed: np.ndarray | None = None, *, loss: str = "huber", f_scale: float = 1.0,
                  max_nfev: int = 50) -> BAResult:
    """Refine the cameras `free_cams` and points `free_pts` (index arrays).

    cams (T, 2, 4), X (N, 3), observations (K,) camera and point indices with (K, 2) pixels;
    `fixed` (T, 2, 4) bool marks camera entries held constant (the gauge). Observations whose
    camera and point are both held constant are left out.
    """
    t0 = time.time()
    cams, X = cams.copy(), X.copy()
    T, N = len(cams), len(X)
    fixed = np.zeros((T, 2, 4), bool) if fixed is None else fixed
    cam_free = np.zeros(T, bool)
    cam_free[free_cams] = True
    pt_free = np.zeros(N, bool)
    pt_free[free_pts] = True
    use = cam_free[obs_cam] | pt_free[obs_pt]
    oc, op, ox = obs_cam[use], obs_pt[use], obs_xy[use]
    if len(oc) == 0:
        return BAResult(cams, X, 0.0, 0.0, 0.0, 0, 0.0)

    # Parameter layout: free camera entries first, then free points (3 each).
    cam_param = np.full((T, 2, 4), -1, np.int64)
    free_entries = cam_free[:, None, None] & ~fixed
    n_cam_params = int(free_entries.sum())
    cam_param[free_entries] = np.arange(n_cam_params)
    pt_param = np.full(N, -1, np.int64)
    fp = np.flatnonzero(pt_free)
    pt_param[fp] = n_cam_params + 3 * np.arange(len(fp))
    n_params = n_cam_params + 3 * len(fp)

    x0 = np.concatenate([cams[free_entries], X[fp].ravel()])
    K = len(oc)
    rows, cols, kind = _jacobian_structure(oc, op, cam_param, pt_param, K)

    def unpack(p):
        c = cams.copy()
        c[free_entries] = p[:n_cam_params]
        Xp = X.copy()
        Xp[fp] = p[n_cam_params:].reshape(-1, 3)
        return c, Xp

    def residuals(p):
        c, Xp = unpack(p)
        pred = np.einsum("kij,kj->ki", c[oc, :, :3], Xp[op]) + c[oc, :, 3]
        return (pred - ox).ravel()

    def jac(p):
        c, Xp = unpack(p)
        vals = _jacobian_values(c, Xp, oc, op, kind)
        return coo_matrix((vals, (rows, cols)), shape=(2 * K, n_params)).tocsr()

    r0 = residuals(x0)
    res = least_squares(residuals, x0, jac=jac, method="trf", loss=loss, f_scale=f_scale,
                        max_nfev=max_nfev, x_scale="jac", tr_solver="lsmr", xtol=1e-10, ftol=1e-8)
    cams, X = unpack(res.x)
    r1 = res.fun.reshape(-1, 2)
    return BAResult(cams, X, float(0.5 * np.sum(r0 ** 2)), float(0.5 * np.sum(r1 ** 2)),
                    float(np.sqrt(np.mean(np.sum(r1 ** 2, axis=1)))), K, time.time() - t0)


def _jacobian_structure(oc, op, cam_param, pt_param, K):
    """Row/column indices of the non-zeros and, per entry, which value to put there."""
    rows, cols, kinds = [], [], []
    k = np.arange(K)
    for r in range(2):
        for j in range(4):          # d r_r / d P[r, j]: X_j (j < 3) or 1 (j == 3)
            col = cam_param[oc, r, j]
            m = col >= 0
            rows.append(2 * k[m] + r)
            cols.append(col[m])
            kinds.append(np.stack([k[m], np.full(m.sum(), r), np.full(m.sum(), j), np.zeros(m.sum(), int)], 1))
        for j in range(3):          # d r_r / d X_j = M[r, j]
            base = pt_param[op]
            m = base >= 0
            rows.append(2 * k[m] + r)
            cols.append(base[m] + j)
            kinds.append(np.stack([k[m], np.full(m.sum(), r), np.full(m.sum(), j), np.ones(m.sum(), int)], 1))
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(kinds)


def _jacobian_values(c, Xp, oc, op, kind):
    k, r, j, is_pt = kind.T
    Xh = np.concatenate([Xp[op], np.ones((len(op), 1))], axis=1)
    cam_vals = Xh[k, j]
    pt_vals = c[oc[k], r, np.minimum(j, 2)]
    return np.where(is_pt == 1, pt_vals, cam_vals)

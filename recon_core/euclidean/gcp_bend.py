"""The bend the views cannot see, fitted to control GCPs spread over the site.

Three views of one date leave up to six quadratic warps of the structure that move no pixel
once every image's pushbroom model re-fits (upgrade_stage.bend_observability: a warp of 1 m at
the site's edge moves them by < 1e-3 px). No adjustment finds them and 4 GCPs fix an affine map,
not a bend: on a 10 km site of one date the heights away from 4 central GCPs were off by 30 m
RMS (README, "A 10 km site of one date"). Control GCPs beyond the four can: this module fits,
on the control GCPs H_A used, an affine correction of H_A together with those invisible warps
(in the metric frame, as displacements of ENU positions), and keeps the fit only when it
predicts each control GCP left out better than H_A alone does (leave-one-out over the same
points, the same least squares). The warps the views see are left to the views.

The map of a group becomes X -> Y + D(Y), Y = H_A (X + metric warp(X)), D the fitted warp
(`EnuWarp`): recon_core.geometry.enu_map.EnuMap carries it to the DSM and the viewer.
"""

from __future__ import annotations

import numpy as np

from recon_core.geometry.enu_map import EnuWarp

# each fitted warp takes one unknown; the fit needs this many equations (3 per GCP) beyond its
# unknowns (12 of the affine correction + the warps) to be tried at all
MIN_REDUNDANCY = 6
# ... and the leave-one-out RMS with the warps must be below this fraction of the one without
MAX_LOO_RATIO = 0.9


def _design(Y: np.ndarray, warp: EnuWarp, basis: np.ndarray) -> np.ndarray:
    """(3 n, 12 + k) equations of an affine correction [M | t] of Y (n, 3) and k warps (basis
    rows (k, 9)), in E, N, U per GCP; the affine columns are centred and scaled like the warps."""
    n = len(Y)
    Yc = np.hstack([(Y - np.r_[warp.centre, Y[:, 2].mean()]) / warp.half, np.ones((n, 1))])
    mono = warp.mono(Y)
    k = len(basis)
    A = np.zeros((n, 3, 12 + k))
    for a in range(3):
        A[:, a, 4 * a:4 * a + 4] = Yc
        A[:, a, 12:] = mono @ basis[:, 3 * a:3 * a + 3].T
    return A.reshape(3 * n, 12 + k)


def _solve(Y: np.ndarray, Xe: np.ndarray, warp: EnuWarp, basis: np.ndarray) -> np.ndarray:
    """The correction and warp steps that take Y + warp(Y) onto Xe (least squares)."""
    A = _design(Y, warp, basis)
    return np.linalg.lstsq(A, (Xe - Y - warp(Y)).reshape(-1), rcond=None)[0]


def _loo(Y: np.ndarray, Xe: np.ndarray, warp: EnuWarp, basis: np.ndarray) -> np.ndarray:
    """(n, 3) residual of each point predicted by the fit on the others."""
    res = []
    for i in range(len(Y)):
        keep = np.arange(len(Y)) != i
        p = _solve(Y[keep], Xe[keep], warp, basis)
        pred = Y[i] + warp(Y[i:i + 1])[0] + (_design(Y[i:i + 1], warp, basis) @ p)
        res.append(pred - Xe[i])
    return np.array(res).reshape(-1, 3)


def _rms3(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def _compose(H: np.ndarray, p: np.ndarray, warp: EnuWarp, z0: float) -> np.ndarray:
    """H followed by the affine correction p[:12] (Y -> Y + M Yc + t, Yc centred and scaled as
    in _design)."""
    M = p[:12].reshape(3, 4)
    s = 1.0 / warp.half
    c = np.r_[warp.centre, z0]
    L = np.eye(4)
    L[:3, :3] += M[:, :3] * s
    L[:3, 3] += M[:, 3] - (M[:, :3] * s) @ c
    return L @ H


def fit_gcp_bend(H: np.ndarray, X_aff: np.ndarray, X_enu: np.ndarray, obs: dict,
                 invisible_px_per_m: float
                 ) -> tuple[np.ndarray | None, EnuWarp | None, dict, np.ndarray | None]:
    """Fit the warps the views cannot see to control GCPs (affine positions X_aff (n, 3) in the
    frame H maps, surveyed ENU X_enu (n, 3)), with an affine correction of H.

    obs: upgrade_stage.bend_observability of the model in the metric frame H gives, with its
    "basis" (the 9 warps, centre and scale). Returns (new H, warp, summary, leave-one-out
    residuals (n, 3) of the fit) when it applies, else (None, None, summary saying why, None)."""
    basis_rec = obs.get("basis") if obs else None
    if not basis_rec:
        return None, None, {"applied": False, "reason": "no view of the structure to tell the invisible warps"}, None
    s = np.asarray(obs["singular_px_per_m"])
    V = np.asarray(basis_rec["warps"], np.float64)[s < invisible_px_per_m]
    k, n = len(V), len(X_aff)
    info: dict = {"invisible_warps": int(k), "control_gcps": int(n),
                  "meaning": "the quadratic warps the views cannot see, fitted with an affine correction "
                             "of H_A to the control GCPs; kept only when each control GCP left out is "
                             "predicted better than by H_A alone"}
    if k == 0:
        return None, None, {**info, "applied": False, "reason": "the views see every quadratic warp"}, None
    need = int(np.ceil((12 + k + MIN_REDUNDANCY) / 3.0))
    info["control_gcps_needed"] = need
    if n < need:
        return None, None, {**info, "applied": False,
                            "reason": f"{n} control GCPs used, {need} needed to fit {k} invisible warps "
                                      f"with {MIN_REDUNDANCY} equations to spare"}, None
    warp = EnuWarp(np.asarray(basis_rec["centre_m"], np.float64), float(basis_rec["half_width_m"]),
                   np.zeros(9))
    Y = (np.c_[X_aff, np.ones(n)] @ H.T)[:, :3]
    loo_affine = _rms3(_loo(Y, X_enu, warp, V[:0]))
    loo_res = _loo(Y, X_enu, warp, V)
    loo_bend = _rms3(loo_res)
    info.update(loo_rms_affine_m=loo_affine, loo_rms_bend_m=loo_bend)
    if not loo_bend < MAX_LOO_RATIO * loo_affine:
        return None, None, {**info, "applied": False,
                            "reason": f"leave-one-out {loo_bend:.3f} m with the warps against {loo_affine:.3f} m "
                                      f"without: not below {MAX_LOO_RATIO:g} x"}, None
    # the warp is evaluated at the corrected positions: re-solved until the fit is the map
    Hn, z0 = H.copy(), float(Y[:, 2].mean())
    for _ in range(3):
        Yn = (np.c_[X_aff, np.ones(n)] @ Hn.T)[:, :3]
        p = _solve(Yn, X_enu, warp, V)
        Hn = _compose(Hn, p, warp, z0)
        warp = EnuWarp(warp.centre, warp.half, warp.coef + p[12:] @ V)
    Yf = (np.c_[X_aff, np.ones(n)] @ Hn.T)[:, :3]
    Yf = Yf + warp(Yf)
    g = np.linspace(-1.0, 1.0, 21)
    ge, gn = np.meshgrid(g, g)
    grid = np.c_[warp.centre[0] + warp.half * ge.ravel(), warp.centre[1] + warp.half * gn.ravel(),
                 np.zeros(ge.size)]
    d = warp(grid)
    info.update(applied=True, control_rms_m=float(np.sqrt(np.mean(np.sum((Yf - X_enu) ** 2, axis=1)))),
                warp_max_m=[float(v) for v in np.abs(d).max(axis=0)],
                warp_rms_m=[float(v) for v in np.sqrt(np.mean(d * d, axis=0))])
    return Hn, warp, info, loo_res


def rescore(res, H: np.ndarray, warp: EnuWarp, positions: dict, enu: dict, loo: dict, info: dict):
    """The UpgradeResult `res` with H and the warp: every GCP row with an affine position
    (positions: id -> (3,) in the frame H maps; enu: id -> surveyed (3,)) re-scored by the new
    map, the used control points' leave-one-out from the fit with the warps (loo: id -> (3,)),
    the statistics and degrees of freedom updated, and a note. A new object; res is unchanged."""
    from dataclasses import replace

    from recon_core.euclidean.upgrade import _attach_loo, accuracy_stats

    rows, groups = [], {"control": [], "check": []}
    for row in res.points:
        row = dict(row)
        x = positions.get(row["id"])
        if x is not None and row.get("dE") is not None:
            Y = (H @ np.r_[np.asarray(x, np.float64), 1.0])[:3]
            r = Y + warp(Y[None])[0] - np.asarray(enu[row["id"]], np.float64)
            row.update(dE=float(r[0]), dN=float(r[1]), dU=float(r[2]),
                       horizontal_m=float(np.hypot(r[0], r[1])), norm3d_m=float(np.linalg.norm(r)))
            if row["status"] == "used":
                groups["control"].append(r)
            elif row["status"] == "check":
                groups["check"].append(r)
        rows.append(row)
    ids = list(loo)
    _attach_loo(rows, ids, np.array([loo[i] for i in ids]).reshape(-1, 3))
    stats = {k: accuracy_stats(np.array(v).reshape(-1, 3)) for k, v in groups.items()}
    stats["loo"] = accuracy_stats(np.array([loo[i] for i in ids]).reshape(-1, 3))
    k = info["invisible_warps"]
    note = (f"{k} quadratic warps the views cannot see were fitted to the {len(ids)} control GCPs with an "
            f"affine correction of H_A (leave-one-out {info['loo_rms_bend_m']:.3f} m RMS against "
            f"{info['loo_rms_affine_m']:.3f} m for H_A alone); the residuals are of that map")
    return replace(res, H=H, points=rows, stats=stats, dof=3 * len(ids) - 12 - k,
                   notes=list(res.notes) + [note])

"""The bend the views cannot see, fitted to control GCPs spread over the site.

Three views of one date leave up to six quadratic warps of the structure that move no pixel
once every image's pushbroom model re-fits (recon_core.bend.observability: a warp of 1 m at
the site's edge moves them by < 1e-3 px). No adjustment finds them and 4 GCPs fix an affine map,
not a bend: on a 10 km site of one date the heights away from 4 central GCPs were off by 30 m
RMS (docs: research-notes.md, "One date over 10 km: what 4 GCPs leave"). Control GCPs beyond the four can: this module fits,
on the control GCPs H_A used, an affine correction of H_A together with those invisible warps
(in the metric frame, as displacements of ENU positions), and keeps the fit only when it
predicts each control GCP left out better than H_A alone does (leave-one-out over the same
points, the same least squares). The warps the views see are left to the views.

The map of a group becomes X -> Y + D(Y), Y = H_A (X + metric warp(X)), D the fitted warp
(`EnuWarp`): recon_core.geometry.enu_map.EnuMap carries it to the DSM and the viewer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon_core.bend.observability import BendView
from recon_core.bend.result import BendFit
from recon_core.geometry.affine import apply_affine_3d
from recon_core.geometry.enu_map import EnuWarp

# each fitted warp takes one unknown; the fit needs this many equations (3 per GCP) beyond its
# unknowns (12 of the affine correction + the warps) to be tried at all
MIN_REDUNDANCY = 6
# ... and the leave-one-out RMS with the warps must be below this fraction of the one without
MAX_LOO_RATIO = 0.9


def _design(Y: np.ndarray, warp: EnuWarp, basis: np.ndarray, z0: float) -> np.ndarray:
    """(3 n, 12 + k) equations of an affine correction [M | t] of Y (n, 3) and k warps (basis
    rows (k, 9)), in E, N, U per GCP; the affine columns are centred and scaled like the warps."""
    n = len(Y)
    Yc = np.hstack([(Y - np.r_[warp.centre, z0]) / warp.half, np.ones((n, 1))])
    mono = warp.mono(Y)
    k = len(basis)
    A = np.zeros((n, 3, 12 + k))
    for a in range(3):
        A[:, a, 4 * a:4 * a + 4] = Yc
        A[:, a, 12:] = mono @ basis[:, 3 * a:3 * a + 3].T
    return A.reshape(3 * n, 12 + k)


def _unknowns_per_gcp(V: np.ndarray) -> int:
    """The fewest GCPs that can fix an affine correction and the warps V (k, 9): the 12 + k
    unknowns over 3 equations each, and no fewer than each axis's own 4 + (its warps' rank)."""
    per_axis = max(4 + np.linalg.matrix_rank(V[:, 3 * a:3 * a + 3]) if len(V) else 4 for a in range(3))
    return int(max(np.ceil((12 + len(V)) / 3.0), per_axis))


def _needed(V: np.ndarray) -> int:
    """Control GCPs needed to fit V: the fewest that fix it, with MIN_REDUNDANCY equations to spare
    (and two GCPs to spare on the worst axis)."""
    return int(max(np.ceil((12 + len(V) + MIN_REDUNDANCY) / 3.0), _unknowns_per_gcp(V) + 2))


def _solve(Y: np.ndarray, Xe: np.ndarray, warp: EnuWarp, basis: np.ndarray, z0: float) -> np.ndarray:
    """The correction and warp steps that take Y + warp(Y) onto Xe (least squares)."""
    A = _design(Y, warp, basis, z0)
    return np.linalg.lstsq(A, (Xe - Y - warp(Y)).reshape(-1), rcond=None)[0]


def _predict(Y: np.ndarray, warp: EnuWarp, basis: np.ndarray, z0: float, p: np.ndarray) -> np.ndarray:
    """(n, 3) positions Y moved by the warp and by the correction and warp steps p."""
    return Y + warp(Y) + (_design(Y, warp, basis, z0) @ p).reshape(-1, 3)


def _loo(Y: np.ndarray, Xe: np.ndarray, warp: EnuWarp, basis: np.ndarray, z0: float) -> np.ndarray:
    """(n, 3) residual of each point predicted by the fit on the others."""
    res = []
    for i in range(len(Y)):
        keep = np.arange(len(Y)) != i
        p = _solve(Y[keep], Xe[keep], warp, basis, z0)
        res.append(_predict(Y[i:i + 1], warp, basis, z0, p)[0] - Xe[i])
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


def _consensus(Y: np.ndarray, Xe: np.ndarray, warp: EnuWarp, V: np.ndarray, thresh_m: float,
               rng: np.random.Generator, z0: float, iters: int = 2000) -> np.ndarray:
    """Inliers (n,) bool of the fit with the warps: MSAC over minimal samples (every sample
    when there are fewer than `iters`), refitted on the inliers until they stop changing."""
    from itertools import combinations
    from math import comb

    n, m = len(Y), _unknowns_per_gcp(V)
    if comb(n, m) <= iters:
        samples = [np.array(c) for c in combinations(range(n), m)]
    else:
        samples = [rng.choice(n, m, replace=False) for _ in range(iters)]
    best, best_cost = None, np.inf
    for sm in samples:
        r = np.linalg.norm(_predict(Y, warp, V, z0, _solve(Y[sm], Xe[sm], warp, V, z0)) - Xe, axis=1)
        cost = np.minimum(r, thresh_m).sum()
        if cost < best_cost:
            best, best_cost = r < thresh_m, cost
    assert best is not None                  # samples is not empty
    for _ in range(5):
        if best.sum() < m:
            break
        r = np.linalg.norm(_predict(Y, warp, V, z0, _solve(Y[best], Xe[best], warp, V, z0)) - Xe, axis=1)
        new = r < thresh_m
        if (new == best).all():
            break
        best = new
    return best


@dataclass(frozen=True)
class GcpBendFit(BendFit[EnuWarp]):
    """What `fit_gcp_bend` found. When it applies, besides the warp and the new H_A: the control
    GCPs it kept (inliers, (n,) bool) and their leave-one-out residuals ((inliers, 3), m)."""

    inliers: np.ndarray | None = None
    loo: np.ndarray | None = None


def fit_gcp_bend(H: np.ndarray, X_aff: np.ndarray, X_enu: np.ndarray, obs: BendView | None,
                 invisible_px_per_m: float, thresh_m: float = 2.0, seed: int = 0) -> GcpBendFit:
    """Fit the warps the views cannot see to control GCPs (affine positions X_aff (n, 3) in the
    frame H maps, surveyed ENU X_enu (n, 3): every usable control GCP, whether or not the
    affine fit of H kept it: a bend makes good GCPs disagree with any affine map), with an
    affine correction of H, robustly (GCPs off by more than thresh_m from the consensus left out).

    obs: what the model's views see of a bend, in the metric frame H gives (its 9 warps, centre
    and scale). Returns a GcpBendFit (its summary says why not, when it does not apply)."""
    if obs is None:
        return GcpBendFit(None, {"applied": False, "reason": "no view of the structure to tell the invisible warps"})
    s = np.asarray(obs.singular_px_per_m)
    W = np.asarray(obs.warps, np.float64)
    Vi = W[s < invisible_px_per_m]                  # the warps the views cannot see
    k, n = len(Vi), len(X_aff)
    info: dict = {"invisible_warps": k, "control_gcps": int(n),
                  "meaning": "quadratic warps of the structure fitted with an affine correction of H_A to "
                             "the control GCPs: the warps the views cannot see, or all nine (one date's "
                             "SfM also leaves the ones they see), whichever predicts each control GCP left "
                             "out best; kept only when that is better than an affine map alone"}
    if k == 0:
        return GcpBendFit(None, {**info, "applied": False, "reason": "the views see every quadratic warp"})
    need, need_all = _needed(Vi), _needed(W)
    info["control_gcps_needed"] = need
    if n < need:
        return GcpBendFit(None, {**info, "applied": False,
                            "reason": f"{n} usable control GCPs, {need} needed to fit {k} invisible warps "
                                      f"with {MIN_REDUNDANCY} equations to spare"})
    warp = EnuWarp(np.asarray(obs.centre_m, np.float64), float(obs.half_width_m),
                   np.zeros(9))
    Y = apply_affine_3d(H, X_aff)
    z0 = float(Y[:, 2].mean())       # one centre of the heights for every fit below
    # the consensus with the richest family the GCPs can fit (a bend makes good GCPs disagree
    # with a poorer one), then the family chosen by leave-one-out on its inliers
    rich = W if n >= need_all else Vi
    inl = _consensus(Y, X_enu, warp, rich, thresh_m, np.random.default_rng(seed), z0)
    info["inliers"] = int(inl.sum())
    if inl.sum() < need:
        return GcpBendFit(None, {**info, "applied": False,
                            "reason": f"only {int(inl.sum())} of {n} control GCPs agree within {thresh_m:g} m "
                                      f"with the warps, {need} needed"})
    families = {"invisible": Vi}
    if inl.sum() >= need_all:
        families["all"] = W
    loo_affine = _rms3(_loo(Y[inl], X_enu[inl], warp, W[:0], z0))
    loos = {name: _loo(Y[inl], X_enu[inl], warp, V, z0) for name, V in families.items()}
    rms = {name: _rms3(r) for name, r in loos.items()}
    best = min(rms, key=lambda name: rms[name])
    V, loo_res, loo_bend = families[best], loos[best], rms[best]
    info.update(loo_rms_affine_m=loo_affine, loo_rms_bend_m=loo_bend, family=best, warps_fitted=len(V),
                loo_rms_m={name: v for name, v in rms.items()})
    if not loo_bend < MAX_LOO_RATIO * loo_affine:
        return GcpBendFit(None, {**info, "applied": False,
                            "reason": f"leave-one-out {loo_bend:.3f} m with the warps against {loo_affine:.3f} m "
                                      f"without: not below {MAX_LOO_RATIO:g} x"})
    # the warp is evaluated at the corrected positions: re-solved until the fit is the map
    Hn = H.copy()
    Xa, Xe = X_aff[inl], X_enu[inl]
    for _ in range(3):
        p = _solve(apply_affine_3d(Hn, Xa), Xe, warp, V, z0)
        Hn = _compose(Hn, p, warp, z0)
        warp = EnuWarp(warp.centre, warp.half, warp.coef + p[12:] @ V)
    Yf = apply_affine_3d(Hn, Xa)
    Yf = Yf + warp(Yf)
    g = np.linspace(-1.0, 1.0, 21)
    ge, gn = np.meshgrid(g, g)
    grid = np.c_[warp.centre[0] + warp.half * ge.ravel(), warp.centre[1] + warp.half * gn.ravel(),
                 np.zeros(ge.size)]
    d = warp(grid)
    info.update(applied=True, control_rms_m=_rms3(Yf - Xe),
                warp_max_m=[float(v) for v in np.abs(d).max(axis=0)],
                warp_rms_m=[float(v) for v in np.sqrt(np.mean(d * d, axis=0))])
    return GcpBendFit(warp, info, Hn, inl, loo_res)

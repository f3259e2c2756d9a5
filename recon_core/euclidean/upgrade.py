"""Euclidean upgrade: one 3D affine map H_A from a group's affine frame to local ENU metres.

An affine reconstruction is defined up to a 3D affine map (12 degrees of freedom, Hartley &
Zisserman ch. 14). Given >= 4 non-coplanar ground control points (GCPs) with both an affine
position (triangulated in the group's frame) and a surveyed ENU position, H_A is the 4 x 4 map

    [E, N, U, 1]^T = H_A [x, y, z, 1]^T,   H_A[3] = [0, 0, 0, 1],

fitted by linear least squares (12 unknowns, 3 equations per point). Gross outliers (a bad click,
a wrong point) are rejected by RANSAC on minimal 4-point samples.

Residuals are always "fitted minus surveyed": dE = E(H_A x) - E_surveyed (metres), etc.

Conventions of the report (the photogrammetric ones):
- RMSE per axis over the points of a set: RMSE_E, RMSE_N, RMSE_U.
- RMSE_horizontal = sqrt((RMSE_E^2 + RMSE_N^2) / 2), the per-axis horizontal RMSE for which the
  circular-normal factor 2.146 holds: CE90 = 2.146 * RMSE_horizontal. The radial RMSE
  sqrt(RMSE_E^2 + RMSE_N^2) is reported too, labelled `rmse_radial_m`.
- LE90 = 1.645 * RMSE_U.
- Degrees of freedom of the fit: 3 N - 12 for N control points used. With N = 4 the control
  residuals are zero by construction: only check points and reprojection residuals tell.
- Leave-one-out (N >= 5): refit without each control point; its residual then is an honest
  prediction error.

The cameras' metric constraint (`upgrade.metric_prior_sigma_cos`, off by default: the true
cameras of an independent simulator are 2e-3 to 4e-3 off it, docs/research-notes.md): every image's
tile cameras have orthogonal rows in metres; one equation per image joins the GCPs' 3N in a
weighted least squares, which fixes the height scale and the shear of height into E and N that
nearly coplanar GCPs leave loose (then dof = 3N - 12 + images, and the control residuals are not
zero even at N = 4).

Conditioning (flat land is the normal case): the height scale of H_A is set by how far the GCPs
lie off their best-fit plane. Its relative error is about sigma / d_rms, where sigma is the
height uncertainty of a GCP's affine point (in metres) and d_rms the RMS distance of the GCPs
from their plane; on a structure of height h that is h * sigma / d_rms metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from itertools import combinations
from typing import Any

import numpy as np

from recon_core.errors import ReconstructionError
from recon_core.euclidean.conditioning import REFUSE_HEIGHT_ERROR_M, conditioning, flat_gcp_refusal  # noqa: F401
from recon_core.euclidean.conditioning import plane as _plane
from recon_core.euclidean.control import MIN_CONTROL_HELD, min_control, unusable_reason
from recon_core.euclidean.held import SIGMA_VIEW_DEG, ControlPoints, Covariance, fit_held, gcp_normal, looseness
from recon_core.euclidean.metric_prior import ImageRows, fit_with_metric_prior, gcp_only_cov, height_sigma, row_cosines
from recon_core.geometry.affine import apply_affine_3d, as_4x4, fit_affine_3d
from recon_core.geometry.enu_map import EnuWarp

CE90_FACTOR = 2.146   # CE90 = 2.146 x the horizontal RMSE per axis (circular normal, 90 %)
LE90_FACTOR = 1.645   # LE90 = 1.645 x the vertical RMSE (normal, two-sided 90 %)
# Relative smallest/largest singular value below which a point set is rank deficient
# ("exactly" collinear or coplanar, up to floating point).
RANK_TOL = 1e-9


# --------------------------------------------------------------------------------------------
# Inputs and basic fits
# --------------------------------------------------------------------------------------------
@dataclass
class GcpInput:
    """One ground control point as the upgrade sees it.

    Attributes:
        id: the GCP's identifier.
        role: "control" (enters the fit) or "check" (only scored).
        affine_xyz: (3,) position in the group's affine frame, or None when the point could not be
            triangulated in this group (observed in fewer than two of its images).
        enu: (3,) surveyed position in the local ENU frame (metres).
        sigma_m: a-priori accuracy of the surveyed position (metres), if known.
        reproj_rms_px: RMS reprojection residual of the GCP's image observations after
            triangulation (pixels), if known. It catches a bad click even when N = 4.
        enabled: False leaves the point out of the fit and the scores (listed as unusable, with
            the reason "disabled").
        affine_cov: (3, 3) covariance of affine_xyz from its image observations (affine units),
            if known (None: a point picked on the cloud, held.PICK_SIGMA_M per axis).
        sigma_h_m: the surveyed height's own accuracy (metres) when worse than sigma_m (a height
            read off a DEM where it changes): the fit held by the images' lines of sight weighs
            the GCP's height by it, and RANSAC forgives that much of its height residual.
    """

    id: str
    role: str
    affine_xyz: np.ndarray | None
    enu: np.ndarray
    sigma_m: float | None = None
    reproj_rms_px: float | None = None
    enabled: bool = True
    affine_cov: np.ndarray | None = None
    sigma_h_m: float | None = None


def singular_ratio(X: np.ndarray) -> float:
    """Smallest / largest singular value of the centred (n, 3) coordinates (0 if degenerate)."""
    X = np.asarray(X, dtype=np.float64)
    if len(X) < 3:
        return 0.0
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    return float(s[-1] / s[0]) if len(s) == 3 and s[0] > 0 else 0.0


def _rank(X: np.ndarray, tol: float = RANK_TOL) -> int:
    """Numerical rank of the centred (n, 3) coordinates (0 to 3)."""
    if len(X) < 2:
        return 0
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if s[0] <= 0:
        return 0
    return int(np.sum(s / s[0] > tol))


def fit_affine_upgrade(X_aff: np.ndarray, X_enu: np.ndarray) -> np.ndarray:
    """Least-squares 3D affine map from affine to ENU coordinates.

    Both point sets are normalised (centroid to origin, RMS norm sqrt(3)) before the 12-unknown
    linear solve, and the normalisation is undone afterwards.

    Args:
        X_aff: (n, 3) points in the affine frame, n >= 4, not coplanar.
        X_enu: (n, 3) the same points in ENU metres.
    Returns:
        H: (4, 4) with last row [0, 0, 0, 1] and X_enu ~ H [X_aff, 1].
    Raises:
        ReconstructionError: fewer than 4 points or the affine points are rank deficient.
    """
    X_aff = np.asarray(X_aff, dtype=np.float64)
    X_enu = np.asarray(X_enu, dtype=np.float64)
    if X_aff.shape != X_enu.shape or X_aff.ndim != 2 or X_aff.shape[1] != 3:
        raise ValueError(f"expected two (n, 3) arrays, got {X_aff.shape} and {X_enu.shape}")
    if len(X_aff) < 4:
        raise ReconstructionError(f"an affine upgrade needs >= 4 points, got {len(X_aff)}")
    if _rank(X_aff) < 3:
        raise ReconstructionError("the affine points are collinear or coplanar: H_A is undetermined")
    return as_4x4(fit_affine_3d(X_aff, X_enu))          # normalised linear least squares


# --------------------------------------------------------------------------------------------
# RANSAC
# --------------------------------------------------------------------------------------------
def _whitener(X: np.ndarray) -> np.ndarray:
    """(3, 3) W with (X - mean) W isotropic; makes degeneracy tests affine invariant."""
    C = np.cov((X - X.mean(axis=0)).T) + 1e-12 * np.eye(3)
    w, V = np.linalg.eigh(C)
    return V / np.sqrt(np.maximum(w, 1e-300))


def _sample_degenerate(Xa_w: np.ndarray, Xe_w: np.ndarray, min_ratio: float) -> bool:
    """True if a 4-point sample is nearly coplanar in either (whitened) space. (4, 3) inputs."""
    return singular_ratio(Xa_w) < min_ratio or singular_ratio(Xe_w) < min_ratio


def _samples(n: int, iters: int, rng: np.random.Generator) -> np.ndarray:
    """(k, 4) index samples: all C(n, 4) combinations when that is <= iters, else random ones."""
    n_comb = n * (n - 1) * (n - 2) * (n - 3) // 24
    if n_comb <= iters:
        return np.array(list(combinations(range(n), 4)), dtype=np.int64)
    keys = rng.random((iters, n))
    return np.argsort(keys, axis=1)[:, :4]


def fit_upgrade_ransac(X_aff: np.ndarray, X_enu: np.ndarray, thresh_m: float = 2.0,
                       iters: int = 1000, rng: np.random.Generator | None = None,
                       min_ratio: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC for H_A on minimal 4-point samples, then a least-squares refit on the inliers.

    A sample is degenerate when its centred coordinates are nearly coplanar in either space:
    smallest / largest singular value < `min_ratio`, measured after whitening each space by the
    covariance of the whole set (so the test does not depend on the arbitrary affine frame, and a
    flat-land GCP set is not rejected wholesale; the set's own flatness is `conditioning`'s job).
    Samples are scored by inlier count (3D residual < thresh_m), ties broken by the sum of
    truncated squared residuals (MSAC). When C(n, 4) <= iters every sample is tried.

    Args:
        X_aff: (n, 3) affine points; X_enu: (n, 3) ENU points (metres); n >= 4.
        thresh_m: inlier threshold on the 3D residual norm (metres).
        iters: maximum number of samples.
        rng: random generator (default: seeded 0, so runs are reproducible).
    Returns:
        H: (4, 4) refitted on the inliers; inliers: (n,) bool.
    Raises:
        ReconstructionError: every sample is degenerate or fewer than 4 inliers remain.
    """
    X_aff = np.asarray(X_aff, dtype=np.float64)
    X_enu = np.asarray(X_enu, dtype=np.float64)
    n = len(X_aff)
    if n < 4:
        raise ReconstructionError(f"RANSAC for H_A needs >= 4 points, got {n}")
    rng = np.random.default_rng(0) if rng is None else rng
    Xa_w = (X_aff - X_aff.mean(axis=0)) @ _whitener(X_aff)
    Xe_w = (X_enu - X_enu.mean(axis=0)) @ _whitener(X_enu)
    best: tuple[int, float] | None = None
    best_mask = None
    for idx in _samples(n, iters, rng):
        if _sample_degenerate(Xa_w[idx], Xe_w[idx], min_ratio):
            continue
        H = fit_affine_upgrade(X_aff[idx], X_enu[idx])
        r2 = np.sum((apply_affine_3d(H, X_aff) - X_enu) ** 2, axis=1)
        mask = r2 < thresh_m ** 2
        score = (int(mask.sum()), -float(np.minimum(r2, thresh_m ** 2).sum()))
        if best is None or score > best:
            best, best_mask = score, mask
    if best_mask is None:
        raise ReconstructionError("every 4-point sample of GCPs is degenerate (nearly coplanar)")
    return _refit_inliers(X_aff, X_enu, best_mask, thresh_m)


def _refit_inliers(X_aff: np.ndarray, X_enu: np.ndarray, mask: np.ndarray,
                   thresh_m: float, rounds: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Alternate LS refit and inlier re-selection until the inlier set is stable."""
    for _ in range(rounds):
        if mask.sum() < 4 or _rank(X_aff[mask]) < 3:
            raise ReconstructionError(
                f"only {int(mask.sum())} GCPs agree within {thresh_m} m (need >= 4, non-coplanar)")
        H = fit_affine_upgrade(X_aff[mask], X_enu[mask])
        new = np.linalg.norm(apply_affine_3d(H, X_aff) - X_enu, axis=1) < thresh_m
        if np.array_equal(new, mask) or new.sum() < 4:
            break
        mask = new
    return H, mask


# --------------------------------------------------------------------------------------------
# The full upgrade with its report
# --------------------------------------------------------------------------------------------
@dataclass
class UpgradeResult:
    """H_A with the report photogrammetrists expect (see the module docstring).

    Attributes:
        H: (4, 4) affine -> ENU map.
        points: one dict per GCP: id, role, status ("used" | "rejected" | "check" | "unusable"),
            reason, dE, dN, dU, horizontal_m, norm3d_m (None when no affine point),
            reproj_rms_px, sigma_m, and loo_dE/loo_dN/loo_dU/loo_norm3d_m for used points when
            N >= 5.
        stats: {"control": {...}, "check": {...}, "loo": {...}} with n, rmse_E_m, rmse_N_m,
            rmse_U_m, rmse_horizontal_m, rmse_radial_m, rmse_3d_m, ce90_m, le90_m.
        dof: 3 N - 12, plus one per image with the metric prior, two per image held by its line
            of sight.
        metric_prior: what the cameras' metric constraint did (None when off).
        views: what the images' lines of sight did (None when the fit had none).
        rejections: [{"id", "reason"}] RANSAC rejections and unusable GCPs.
        conditioning: dict of `conditioning`.
        notes: plain-words remarks (no redundancy, ...); warnings: things to act on.
    """

    H: np.ndarray
    points: list[dict[str, Any]]
    stats: dict[str, dict[str, Any]]
    dof: int
    n_control_used: int
    rejections: list[dict[str, str]]
    conditioning: dict[str, Any]
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    metric_prior: dict[str, Any] | None = None
    views: dict[str, Any] | None = None

    def apply(self, X_aff: np.ndarray) -> np.ndarray:
        """Affine-frame points (n, 3) -> ENU metres (n, 3)."""
        return apply_affine_3d(self.H, X_aff)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict for report.json."""
        return {
            "H": self.H.tolist(), "n_control_used": self.n_control_used, "dof": self.dof,
            "residual_convention": "fitted minus surveyed, metres, ENU axes",
            "rmse_horizontal_definition": "sqrt((RMSE_E^2 + RMSE_N^2) / 2); "
                                          "CE90 = 2.146 * that, LE90 = 1.645 * RMSE_U",
            "points": self.points, "stats": self.stats, "rejections": self.rejections,
            "conditioning": self.conditioning, "notes": self.notes, "warnings": self.warnings,
            "metric_prior": self.metric_prior, "views": self.views,
        }


def accuracy_stats(res: np.ndarray) -> dict[str, Any]:
    """RMSE per axis, CE90 and LE90 from residuals (n, 3) in ENU metres."""
    res = np.asarray(res, dtype=np.float64).reshape(-1, 3)
    if len(res) == 0:
        return {"n": 0}
    rmse = np.sqrt(np.mean(res ** 2, axis=0))
    rmse_h = float(np.sqrt((rmse[0] ** 2 + rmse[1] ** 2) / 2.0))
    return {"n": len(res), "rmse_E_m": float(rmse[0]), "rmse_N_m": float(rmse[1]),
            "rmse_U_m": float(rmse[2]), "rmse_horizontal_m": rmse_h,
            "rmse_radial_m": float(np.hypot(rmse[0], rmse[1])),
            "rmse_3d_m": float(np.sqrt(np.sum(rmse ** 2))),
            "ce90_m": CE90_FACTOR * rmse_h, "le90_m": LE90_FACTOR * float(rmse[2])}


def _usable(g: GcpInput) -> str | None:
    """Reason a GCP cannot be used, or None (recon_core.euclidean.control: the one rule)."""
    return unusable_reason(g.role, g.enabled, g.affine_xyz, g.enu)


def _check_rank(ids: list[str], X_enu: np.ndarray, X_aff: np.ndarray) -> None:
    """Raise if the control set is collinear or exactly coplanar in either space."""
    for name, X in (("surveyed (ENU)", X_enu), ("affine", X_aff)):
        r = _rank(X)
        if r < 3:
            shape = "all coincide" if r == 0 else ("are collinear" if r == 1 else
                                                  "are exactly coplanar")
            raise ReconstructionError(
                f"the {len(ids)} usable control GCPs ({', '.join(ids)}) {shape} in {name} "
                "coordinates: the system is rank deficient and H_A (in particular its height "
                "scale) is undetermined; add a GCP off their plane")


def _loo(X_aff: np.ndarray, X_enu: np.ndarray, fit=fit_affine_upgrade) -> np.ndarray:
    """Leave-one-out residuals (n, 3): refit (by `fit`) without point i, residual at i (NaN if
    degenerate)."""
    n = len(X_aff)
    out = np.full((n, 3), np.nan)
    for i in range(n):
        keep = np.arange(n) != i
        if _rank(X_aff[keep]) < 3 or _rank(X_enu[keep]) < 3:
            continue
        H = fit(X_aff[keep], X_enu[keep])
        out[i] = apply_affine_3d(H, X_aff[i:i + 1])[0] - X_enu[i]
    return out


def _combined_sigma(gcps: list[GcpInput], affine_height_sigma_m: float) -> float:
    """Affine-point height sigma combined in quadrature with the RMS of the GCPs' sigma_m."""
    s = [g.sigma_m for g in gcps if g.sigma_m is not None and np.isfinite(g.sigma_m)]
    extra = float(np.sqrt(np.mean(np.square(s)))) if s else 0.0
    return float(np.hypot(affine_height_sigma_m, extra))


# control GCPs whose width across their best line is under this share of their length are on
# one line: nothing fixes H_A across it (10 m off a 1 km road leaves metres across it)
LINE_RATIO = 0.01


def on_one_line(X: np.ndarray) -> bool:
    """Do the (n, 3) points lie within LINE_RATIO of their length of one line?"""
    if len(X) < 3:
        return True
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    return bool(s[0] <= 0 or s[1] < LINE_RATIO * s[0])


def _check_line(ids: list[str], X_enu: np.ndarray, X_aff: np.ndarray) -> None:
    """Raise if the control set is collinear (or coincident) in either space."""
    for name, X in (("surveyed (ENU)", X_enu), ("affine", X_aff)):
        r = _rank(X) if not on_one_line(X) else min(_rank(X), 1)
        if r < 2:
            raise ReconstructionError(
                f"the {len(ids)} usable control GCPs ({', '.join(ids)}) "
                f"{'all coincide' if r == 0 else 'are collinear'} in {name} coordinates: nothing fixes "
                "H_A across their line; add a GCP off it")


def control_points(gcps: list[GcpInput], idx: list[int]) -> ControlPoints:
    """The control GCPs idx as the weighted fit takes them (recon_core.euclidean.held)."""
    S = np.array([np.full((3, 3), np.nan) if gcps[i].affine_cov is None else np.asarray(gcps[i].affine_cov, float)
                  for i in idx]).reshape(-1, 3, 3)
    sig = np.array([g.sigma_m if g.sigma_m is not None and np.isfinite(g.sigma_m) else 0.0
                    for g in (gcps[i] for i in idx)], dtype=np.float64)
    sig_h = np.array([max(g.sigma_h_m, s) if g.sigma_h_m is not None and np.isfinite(g.sigma_h_m) else s
                      for g, s in zip((gcps[i] for i in idx), sig)], dtype=np.float64)
    return ControlPoints(np.array([gcps[i].affine_xyz for i in idx], np.float64).reshape(-1, 3),
                         np.array([gcps[i].enu for i in idx], np.float64).reshape(-1, 3), S, sig, sig_h)


@dataclass
class ImageHold:
    """The images' lines of sight as the fit of H_A uses them (recon_core.euclidean.sight)."""

    rays: list
    frame: Any = None                  # the site's LocalFrame (turns each image's vertical into it)
    sigma_view_deg: float = SIGMA_VIEW_DEG

    def fit(self, pts: ControlPoints, H0: np.ndarray | None = None):
        return fit_held(pts, self.rays, self.frame, self.sigma_view_deg, H0=H0)

    def refit(self, Xa: np.ndarray, Xe: np.ndarray) -> np.ndarray:
        """H from these points alone (no covariances: RANSAC samples)."""
        n = len(Xa)
        return fit_held(ControlPoints(Xa, Xe, np.full((n, 3, 3), np.nan), np.zeros(n)), self.rays,
                        self.frame, self.sigma_view_deg).H


VIEW_BLUNDER_DEG = 1.0   # an image's line of sight this far from the fit (10 sigmas of the
                         # prior) is a wrong "view" (elevation for incidence, a flipped azimuth)


def _screen_views(hold: ImageHold, pts: ControlPoints) -> tuple[ImageHold, list[tuple[str, float]]]:
    """The images whose stated viewing direction disagrees with the rest by more than
    VIEW_BLUNDER_DEG, left out one at a time while three or more remain: each time the one
    without which the others agree best (a wrong image pulls the fit off the right ones), if the
    others and the GCPs put it that far off. Returns (the hold without them, [(image, degrees
    off)]). Needs 3 control GCPs not on one line (else unchanged)."""
    dropped = []
    if len(hold.rays) == 2 and len(pts) >= 3 and _rank(pts.Xe) >= 2:
        fit = hold.fit(pts)                  # two that disagree: which one is wrong cannot be told
        if max(fit.view_residual_deg.values()) > VIEW_BLUNDER_DEG:
            return replace(hold, rays=[]), [(im, deg) for im, deg in fit.view_residual_deg.items()]
        return hold, []
    while len(hold.rays) >= 3 and len(pts) >= 3 and _rank(pts.Xe) >= 2:
        if max(hold.fit(pts).view_residual_deg.values()) <= VIEW_BLUNDER_DEG:
            break
        best = None
        for r in hold.rays:
            rest = replace(hold, rays=[q for q in hold.rays if q is not r])
            fit = rest.fit(pts)
            u = fit.H[:3, :3] @ r.d
            off = float(np.degrees(np.arccos(min(1.0, abs(float(u @ r.direction(hold.frame, fit.H)))
                                                 / np.linalg.norm(u)))))
            key = (max(fit.view_residual_deg.values()), -off)
            if best is None or key < best[0]:
                best = (key, r.image, off, rest)
        assert best is not None              # hold has rays
        _, im, off, rest = best
        if off <= VIEW_BLUNDER_DEG:
            break
        dropped.append((im, off))
        hold = rest
    if dropped and len(dropped) >= len(hold.rays):     # as many wrong as right: none can be trusted
        dropped += [(r.image, float("nan")) for r in hold.rays]
        hold = replace(hold, rays=[])
    return hold, dropped


def fit_held_ransac(Xa: np.ndarray, Xe: np.ndarray, hold: ImageHold, thresh_m: float, iters: int,
                    rng: np.random.Generator, min_ratio: float = 0.05,
                    slack_u: np.ndarray | None = None) -> np.ndarray:
    """RANSAC for H_A on 3-point samples, each held by the images' lines of sight: the inliers
    (n,) bool of the best consensus (inlier count, then truncated cost). A sample nearly on one
    line (second singular value below `min_ratio` of the first, whitened) is skipped. slack_u
    (n,): metres of each point's height residual forgiven (a height known that much worse)."""
    n = len(Xa)
    slack = np.zeros(n) if slack_u is None else np.asarray(slack_u, np.float64)

    def residual(H: np.ndarray) -> np.ndarray:
        r = apply_affine_3d(H, Xa) - Xe
        r[:, 2] = np.sign(r[:, 2]) * np.maximum(np.abs(r[:, 2]) - slack, 0.0)
        return r

    todo = (np.array(list(combinations(range(n), 3)), dtype=np.int64) if n * (n - 1) * (n - 2) // 6 <= iters
            else np.argsort(rng.random((iters, n)), axis=1)[:, :3])
    best, best_mask = None, None
    for idx in todo:
        # in plan: three points fix H_A's horizontal across their line only when they are off it
        # (whitened in 3D, a flat site's tiny heights would pass a line as a triangle)
        sv = np.linalg.svd(Xe[idx, :2] - Xe[idx, :2].mean(0), compute_uv=False)
        if sv[0] <= 0 or sv[1] / sv[0] < min_ratio:
            continue
        H = hold.refit(Xa[idx], Xe[idx])
        r2 = np.sum(residual(H) ** 2, axis=1)
        mask = r2 < thresh_m ** 2
        score = (int(mask.sum()), -float(np.minimum(r2, thresh_m ** 2).sum()))
        if best is None or score > best:
            best, best_mask = score, mask
    if best_mask is None:
        raise ReconstructionError("every 3-point sample of GCPs is degenerate (nearly collinear)")
    for _ in range(5):
        if best_mask.sum() < 3 or _rank(Xe[best_mask]) < 2:
            raise ReconstructionError(f"only {int(best_mask.sum())} GCPs agree within {thresh_m} m "
                                      "(need >= 3 not on one line, with the images' lines of sight)")
        H = hold.refit(Xa[best_mask], Xe[best_mask])
        new = np.linalg.norm(residual(H), axis=1) < thresh_m
        if np.array_equal(new, best_mask) or new.sum() < 3:
            break
        best_mask = new
    return best_mask


def _site_radius(H: np.ndarray, site_points: np.ndarray | None, Xe: np.ndarray) -> float:
    """How far the site reaches from the control GCPs' centre (m, horizontally): the 95th
    percentile over points of the structure through H (0 without them)."""
    if site_points is None or not len(site_points):
        return 0.0
    en = apply_affine_3d(H, np.asarray(site_points, np.float64))[:, :2] - Xe[:, :2].mean(axis=0)
    return float(np.percentile(np.hypot(en[:, 0], en[:, 1]), 95))


def _best_next(gcps: list[GcpInput], reasons: dict, N: np.ndarray, H: np.ndarray, height_m: float,
               now_m: float) -> dict | None:
    """The check point that, made a control point, would bring the expected height error down
    most (at least by a fifth): {"id", "expected_height_error_m"}, or None."""
    best = None
    for i, g in enumerate(gcps):
        if g.role != "check" or reasons[i] is not None:
            continue
        err = looseness(H, Covariance.of(N + gcp_normal(control_points(gcps, [i]), H)), height_m).expected_height_error_m
        if np.isfinite(err) and (best is None or err < best[1]):
            best = (g.id, err)
    if best is None or not (best[1] < 0.8 * now_m):
        return None
    return {"id": best[0], "expected_height_error_m": float(best[1])}


def _dropped_text(dropped: list[tuple[str, float]]) -> str:
    return ("the viewing direction of " + ", ".join(f"{im} ({deg:.1f} degrees off)" if np.isfinite(deg) else im
                                                    for im, deg in dropped)
            + f" disagrees with the other images and the control GCPs by more than {VIEW_BLUNDER_DEG:g} "
              "degrees: not used (check \"view\" in its sidecar: incidence from the vertical, not "
              "elevation; azimuth of the direction to the satellite, clockwise from north)")


def _consensus(gcps, reasons, ctrl, hold, given, dropped, min_points, thresh, iters, rng):
    """The control GCPs' consensus (RANSAC from 5 on) with the images that agree with it:
    (hold, inliers (len(ctrl),) bool, dropped views). Views left out against every control GCP
    are screened again against the consensus alone (a wrong GCP can make a good view look wrong).
    Raises ReconstructionError for a set nothing can fix."""
    held = hold is not None and len(hold.rays) >= 2 and hold.sigma_view_deg > 0
    need = min_control(True) if held else max(min_control(False), int(min_points))
    if len(ctrl) < need:
        lacking = [g.id for i, g in enumerate(gcps) if g.role == "control" and reasons[i]]
        raise ReconstructionError(
            f"only {len(ctrl)} usable control GCPs, need >= {need}"
            + ("" if held else f" ({MIN_CONTROL_HELD} when the images' viewing angles are known)")
            + (f"; without an affine position: {', '.join(lacking)}" if lacking else "")
            + "; observe more control GCPs in at least two images of this group")
    Xa = np.array([gcps[i].affine_xyz for i in ctrl], dtype=np.float64)
    Xe = np.array([gcps[i].enu for i in ctrl], dtype=np.float64)
    ids = [gcps[i].id for i in ctrl]
    _check_line(ids, Xe, Xa)
    if not held:
        _check_rank(ids, Xe, Xa)
    rng = np.random.default_rng(0) if rng is None else rng
    if len(ctrl) <= 4:
        return hold, np.ones(len(ctrl), bool), dropped
    if not held:
        return hold, fit_upgrade_ransac(Xa, Xe, thresh, iters, rng)[1], dropped
    assert hold is not None                  # held
    pts = control_points(gcps, ctrl)
    inl = fit_held_ransac(Xa, Xe, hold, thresh, iters, rng,
                          slack_u=3.0 * np.maximum(pts.sigma_h - pts.sigma_m, 0.0))
    if dropped and not inl.all():
        again, still = _screen_views(given, control_points(gcps, [i for i, ok in zip(ctrl, inl) if ok]))
        if len(again.rays) >= 2:
            hold, dropped = again, still
    return hold, inl, dropped


def upgrade(gcps: list[GcpInput], *, ransac_thresh_m: float = 2.0, min_points: int = 4,
            rng: np.random.Generator | None = None, ransac_iters: int = 1000,
            affine_height_sigma_m: float = 0.4, structure_height_m: float = 40.0,
            warn_height_error_m: float = 2.0, poor_height_error_m: float = 5.0,
            reproj_warn_px: float = 2.0, camera_rows: list[ImageRows] | None = None,
            sigma_cos: float = 0.0, hold: ImageHold | None = None,
            site_points: np.ndarray | None = None) -> UpgradeResult:
    """Fit H_A on the control GCPs (RANSAC when N >= 5) and build the full residual report.

    Check points never enter the fit. GCPs without an affine position are listed as unusable.
    With `hold` (two or more images' lines of sight: recon_core.euclidean.held), H_A is fitted
    to the GCPs, weighted by their covariances, and to the images' directions together: 3 control
    GCPs not on one line suffice, and GCPs on one plane are no longer degenerate. Without it, the
    GCPs alone (least squares); with `camera_rows` and sigma_cos > 0 the fit on the inliers also
    asks every image's tile cameras to have orthogonal rows in metres
    (recon_core.euclidean.metric_prior). Either way the report states what the fit leaves loose
    (the conditioning: the fit's own covariance).

    Raises:
        ReconstructionError: fewer usable control GCPs than needed (4, or 3 with `hold`; says
            how many and which lack an affine point), or the control set is collinear, or (without
            `hold`) exactly coplanar.
    """
    reasons = {i: _usable(g) for i, g in enumerate(gcps)}
    ctrl = [i for i, g in enumerate(gcps) if g.role == "control" and reasons[i] is None]
    given = hold if hold is not None and len(hold.rays) >= 2 and hold.sigma_view_deg > 0 else None
    dropped: list[tuple[str, float]] = []
    if given is not None:
        hold, dropped = _screen_views(given, control_points(gcps, ctrl))
    try:
        hold, inl, dropped = _consensus(gcps, reasons, ctrl, hold, given, dropped, min_points, ransac_thresh_m,
                                        ransac_iters, rng)
    except ReconstructionError as exc:
        if not dropped:
            raise
        raise ReconstructionError(f"{exc}; {_dropped_text(dropped)}") from None
    held = hold is not None and len(hold.rays) >= 2 and hold.sigma_view_deg > 0
    Xa = np.array([gcps[i].affine_xyz for i in ctrl], dtype=np.float64)
    Xe = np.array([gcps[i].enu for i in ctrl], dtype=np.float64)
    if not held and len(ctrl) > 4:
        H = _refit_inliers(Xa, Xe, inl, ransac_thresh_m)[0]
    elif not held:
        H = fit_affine_upgrade(Xa, Xe)
    used = [i for i, ok in zip(ctrl, inl) if ok]
    pts = control_points(gcps, used)
    fit = hold.fit(pts) if held and hold is not None else None
    if fit is not None:
        H = fit.H
    sigma = _combined_sigma([gcps[i] for i in used], affine_height_sigma_m)
    radius = _site_radius(H, site_points, Xe[inl])
    N_gcp = gcp_normal(pts, H)
    loose_gcp = looseness(H, Covariance.of(N_gcp), structure_height_m, radius)
    prior = None
    if camera_rows and sigma_cos > 0 and not held:
        prior = _MetricPrior(camera_rows, sigma_cos, sigma)
        H = prior.fit(Xa[inl], Xe[inl], H, structure_height_m)
    loose = looseness(H, fit.cov, structure_height_m, radius) if fit is not None else loose_gcp
    best_next = _best_next(gcps, reasons, fit.normal if fit is not None else N_gcp, H, structure_height_m,
                           loose.expected_height_error_m)
    cond = conditioning(Xe[inl], sigma, structure_height_m, warn_height_error_m, poor_height_error_m,
                        prior.ratio if prior is not None else None, loose=loose, loose_gcp=loose_gcp,
                        images=len(hold.rays) if held and hold is not None else 0, best_next=best_next)
    result = _build_result(gcps, reasons, ctrl, used, H, Xa[inl], Xe[inl], ransac_thresh_m, cond,
                           reproj_warn_px, prior, fit, hold if held else None)
    if dropped:
        result.warnings.append(_dropped_text(dropped) + ("" if held else "; the GCPs alone fix the height scale"))
    _check_point_warnings(result, gcps, reasons, ctrl, Xa, Xe, inl, H, ransac_thresh_m, held)
    return result


def _check_point_warnings(result: UpgradeResult, gcps: list[GcpInput], reasons: dict, ctrl: list[int],
                          Xa: np.ndarray, Xe: np.ndarray, inl: np.ndarray, H: np.ndarray, thresh: float,
                          held: bool) -> None:
    """What the check points say of the fit, as warnings: a RANSAC that could as well have
    rejected another control GCP (and how the check points fare either way), and check points
    off by more than the control GCPs must agree within."""
    checks = [i for i, g in enumerate(gcps) if g.role == "check" and reasons[i] is None]

    def check_rmse(Hx: np.ndarray) -> float | None:
        if not checks:
            return None
        r = np.array([apply_affine_3d(Hx, np.asarray(gcps[i].affine_xyz, float)[None])[0]
                      - np.asarray(gcps[i].enu, float) for i in checks])
        return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))
    now = check_rmse(H)
    if len(ctrl) > 4 and not inl.all() and not held:
        rivals = _rival_consensus(Xa, Xe, inl, thresh)
        if rivals:
            now_out = ", ".join(gcps[ctrl[j]].id for j in np.flatnonzero(~inl))
            alt_out = sorted({gcps[ctrl[i]].id for _, i, _ in rivals})
            text = (f"RANSAC cannot tell which control GCP is wrong: rejecting {' or '.join(alt_out)} "
                    f"instead of {now_out} fits the others as well (with {len(ctrl)} control GCPs a "
                    "blunder can look like a good point); verify them")
            if now is not None:
                alts = sorted((check_rmse(Hx), gcps[ctrl[i]].id) for _, i, Hx in rivals)
                text += (f"; the check points are off by {now:.2f} m RMS (3D) with this fit, "
                         f"{alts[0][0]:.2f} m if {alts[0][1]} is rejected instead")
            result.warnings.append(text)
    if now is not None and now > thresh:
        result.warnings.append(
            f"the check points are off by {now:.2f} m RMS (3D), more than the {thresh:g} m "
            "the control GCPs must agree within: a control GCP (or a check point) is probably wrong; "
            "see the per-point residuals")


def _rival_consensus(Xa: np.ndarray, Xe: np.ndarray, inl: np.ndarray, thresh: float
                     ) -> list[tuple[int, int, np.ndarray]]:
    """Other consensus sets RANSAC cannot tell from its own: (index of a rejected point the
    rival keeps, index of an inlier it rejects, its H), where swapping the two gives as many
    inliers and a truncated cost (MSAC, RANSAC's tie-break) within 25 % of the chosen set's.
    With 5 control GCPs and a blunder every 4 fit exactly and the costs are equal; with many
    GCPs a swap costs more and is not reported."""
    def msac(H: np.ndarray) -> float:
        r2 = np.sum((apply_affine_3d(H, Xa) - Xe) ** 2, axis=1)
        return float(np.minimum(r2, thresh ** 2).sum())

    out = []
    best = int(inl.sum())
    own = msac(fit_affine_upgrade(Xa[inl], Xe[inl]))
    Xa_w = (Xa - Xa.mean(axis=0)) @ _whitener(Xa)
    Xe_w = (Xe - Xe.mean(axis=0)) @ _whitener(Xe)
    for j in np.flatnonzero(~inl):
        for i in np.flatnonzero(inl):
            m = inl.copy()
            m[i], m[j] = False, True
            if _rank(Xa[m]) < 3 or _rank(Xe[m]) < 3 or (
                    m.sum() == 4 and _sample_degenerate(Xa_w[m], Xe_w[m], 0.05)):
                continue
            Hx = fit_affine_upgrade(Xa[m], Xe[m])
            ok = np.linalg.norm(apply_affine_3d(Hx, Xa) - Xe, axis=1) < thresh
            if ok.sum() >= best and ok[j] and not ok[i] and msac(Hx) <= 1.25 * own + 1e-9:
                out.append((int(j), int(i), Hx))
    return out


class _MetricPrior:
    """The cameras' metric constraint in the fit, and what it did (for the report)."""

    def __init__(self, rows: list[ImageRows], sigma_cos: float, sigma_m: float):
        self.rows, self.sigma_cos, self.sigma_m = rows, float(sigma_cos), float(sigma_m)
        self.report: dict[str, Any] = {}
        self.ratio: float | None = None

    def refit(self, Xa: np.ndarray, Xe: np.ndarray) -> np.ndarray:
        """H from these control points with the prior (leave-one-out refits)."""
        return fit_with_metric_prior(Xa, Xe, self.sigma_m, self.rows, self.sigma_cos)[0]

    def fit(self, Xa: np.ndarray, Xe: np.ndarray, H_gcp: np.ndarray, height_m: float) -> np.ndarray:
        H, cov = fit_with_metric_prior(Xa, Xe, self.sigma_m, self.rows, self.sigma_cos, H0=H_gcp)
        normal = _plane(Xe)[0]
        s_prior = height_sigma(H, cov, normal, height_m)
        s_gcp = height_sigma(H_gcp, gcp_only_cov(Xa, self.sigma_m), normal, height_m)
        self.ratio = min(1.0, s_prior / s_gcp) if s_gcp > 0 else None
        # the affine offset that the GCP-only fit puts height_m above the GCPs' plane, and its
        # height through the new fit
        d = np.linalg.solve(H_gcp[:3, :3], normal * height_m)
        height_change = float(H[2, :3] @ d - normal[2] * height_m)
        self.report = {
            "sigma_cos": self.sigma_cos, "sigma_gcp_m": self.sigma_m, "images": len(self.rows),
            "row_cosine_gcp_only": dict(zip((r.image for r in self.rows),
                                            row_cosines(H_gcp[:3, :3], self.rows).round(6).tolist())),
            "row_cosine": dict(zip((r.image for r in self.rows),
                                   row_cosines(H[:3, :3], self.rows).round(6).tolist())),
            "height_change_m": height_change, "at_height_m": float(height_m),
            "height_sigma_gcp_only_m": s_gcp, "height_sigma_m": s_prior,
            "what": "each image's tile cameras have orthogonal rows in metres (one equation per "
                    "image, sigma_cos on the cosine), fitted with the control GCPs; "
                    "height_change_m: how the height of a point at_height_m above the control "
                    "GCPs moved against the GCP-only fit",
        }
        return H


def _point_row(g: GcpInput, status: str, reason: str | None, r: np.ndarray | None) -> dict:
    """One report row; r: (3,) residual or None."""
    row: dict[str, Any] = {"id": g.id, "role": g.role, "status": status, "reason": reason,
                           "sigma_m": g.sigma_m, "reproj_rms_px": g.reproj_rms_px}
    if g.sigma_h_m is not None:
        row["sigma_h_m"] = g.sigma_h_m
    if r is None:
        row.update(dE=None, dN=None, dU=None, horizontal_m=None, norm3d_m=None)
    else:
        row.update(dE=float(r[0]), dN=float(r[1]), dU=float(r[2]),
                   horizontal_m=float(np.hypot(r[0], r[1])), norm3d_m=float(np.linalg.norm(r)))
    return row


def _build_result(gcps, reasons, ctrl, used, H, Xa_used, Xe_used, thresh, cond, reproj_warn_px,
                  prior: _MetricPrior | None = None, fit=None, hold: ImageHold | None = None) -> UpgradeResult:
    """Residual rows, statistics, LOO, rejections and notes for a fitted H (`fit`: the fit held
    by the images' lines of sight, when there is one)."""
    rows, rejections, res = [], [], {"control": [], "check": []}
    for i, g in enumerate(gcps):
        if reasons[i] is not None:
            rows.append(_point_row(g, "unusable", reasons[i], None))
            rejections.append({"id": g.id, "reason": reasons[i]})
            continue
        r = apply_affine_3d(H, np.asarray(g.affine_xyz, float)[None])[0] - np.asarray(g.enu, float)
        if g.role == "check":
            rows.append(_point_row(g, "check", None, r))
            res["check"].append(r)
        elif i in used:
            rows.append(_point_row(g, "used", None, r))
            res["control"].append(r)
        else:
            why = (f"RANSAC outlier: 3D residual {np.linalg.norm(r):.2f} m > {thresh} m "
                   "against the consensus of the other control GCPs")
            rows.append(_point_row(g, "rejected", why, r))
            rejections.append({"id": g.id, "reason": why})
    n = len(used)
    stats = {k: accuracy_stats(np.array(v).reshape(-1, 3)) for k, v in res.items()}
    notes, warnings = [], []
    k = len(prior.rows) if prior is not None else 0
    views = None
    if fit is not None:
        assert hold is not None              # the fit is the hold's
        k = 2 * len(hold.rays)
        views = {"images": len(hold.rays), "sigma_view_deg": fit.sigma_view_deg,
                 "sigma_view_prior_deg": hold.sigma_view_deg, "redundancy": fit.view_redundancy,
                 "residual_deg": {im: round(v, 4) for im, v in fit.view_residual_deg.items()},
                 "what": "each image's line of sight in the affine frame (its tile cameras' null vector at "
                         "the image centre) held to its direction from the metadata (\"view\" in its "
                         "sidecar), two equations per image, with the GCPs weighted by their "
                         "triangulation covariances; residual_deg: the angle left per image; "
                         "sigma_view_deg: the images' sigma estimated from those residuals"}
        _images_height_sigma(rows, gcps, fit)
        if n >= 4:
            loo = _loo_held(control_points(gcps, used), hold)
            _attach_loo(rows, [gcps[i].id for i in used], loo)
            stats["loo"] = accuracy_stats(loo[np.all(np.isfinite(loo), axis=1)])
        notes.append(f"{n} control GCPs and {len(hold.rays)} images' lines of sight: 3N - 12 + {k} = "
                     f"{3 * n - 12 + k} degrees of freedom. The control residuals are not zero: they show how "
                     "far the GCPs and the images' viewing directions disagree"
                     + ("; leave-one-out predicts each control GCP from the others and the images" if n >= 4 else "")
                     + ". Check points and each GCP's reprojection residual (reproj_rms_px) tell the rest.")
    elif n >= 5:
        loo = _loo(Xa_used, Xe_used, prior.refit if prior is not None else fit_affine_upgrade)
        _attach_loo(rows, [gcps[i].id for i in used], loo)
        stats["loo"] = accuracy_stats(loo[np.all(np.isfinite(loo), axis=1)])
    elif prior is not None:
        notes.append(f"N = 4 control GCPs and {k} images' metric constraint: 3N - 12 + {k} = {k} "
                     "degrees of freedom. The control residuals are not zero: they show how far the "
                     "GCPs and the cameras' orthogonal rows disagree. Check points and each GCP's "
                     "reprojection residual (reproj_rms_px) tell the rest.")
    else:
        notes.append("N = 4 control GCPs: no redundancy (3N - 12 = 0 degrees of freedom), so the "
                     "control residuals are zero by construction and say nothing. What still "
                     "tells: the check points and each GCP's reprojection residual "
                     "(reproj_rms_px), which catches a bad click even at N = 4.")
    warnings += _fit_warnings(rows, stats, cond, n, thresh, fit is not None, reproj_warn_px)
    if not res["check"]:
        notes.append("no check points: hold one or more GCPs out as 'check' for an independent "
                     "accuracy figure")
    return UpgradeResult(H=H, points=rows, stats=stats, dof=3 * n - 12 + k, n_control_used=n,
                         rejections=rejections, conditioning=cond, notes=notes,
                         warnings=warnings, metric_prior=prior.report if prior is not None else None,
                         views=views)


def _fit_warnings(rows: list[dict], stats: dict, cond: dict, n: int, thresh: float, held: bool,
                  reproj_warn_px: float) -> list[str]:
    """The fit's warnings: the control GCPs RANSAC rejected (and a rejection nothing is left to
    confirm), what the conditioning leaves loose beside what the check points measure, and the
    GCPs whose clicks disagree (their reprojection residuals)."""
    warnings = []
    rejected = [r for r in rows if r["status"] == "rejected"]
    n_ransac = len(rejected)
    if rejected:
        warnings.append("RANSAC rejected control GCP(s) " + ", ".join(
            f"{r['id']}" + (f" ({r['norm3d_m']:.2f} m off)" if r.get("norm3d_m") is not None else "")
            for r in rejected) + f" (threshold {thresh:g} m): not used for the upgrade; "
            "check their ground coordinates and image observations")
    if n_ransac and n == (3 if held else 4):
        warnings.append(f"RANSAC rejected {n_ransac} control GCP(s) and only {n} remain: no "
                        "redundancy is left to confirm the rejection; add control GCPs")
    if cond.get("warning"):
        chk = stats.get("check") or {}
        # the expected error is a model's figure at the structure's full height; check points,
        # where there are some, measure it: say both, so the two do not read as a contradiction
        measured = (f" (the {chk['n']} check points measure LE90 {chk['le90_m']:.2f} m, U RMSE "
                    f"{chk['rmse_U_m']:.2f} m: the expected figure is for points the structure's "
                    "full height off the GCPs' plane)") if chk.get("n") else ""
        cond["warning"] = cond["warning"].rstrip(".") + measured + "."
        warnings.append(cond["warning"])
    return warnings + _reproj_warnings(rows, reproj_warn_px)


def _images_height_sigma(rows: list[dict], gcps: list[GcpInput], fit) -> None:
    """For each GCP whose height is known worse than the horizontal (sigma_h_m): how well the
    held fit gives its height (images_height_sigma_m: the fit's covariance at its affine point
    and the point's own), so that a height taken from the images says what it is worth."""
    by_id = {g.id: g for g in gcps}
    for row in rows:
        g = by_id.get(row["id"])
        if g is None or g.sigma_h_m is None or g.affine_xyz is None or row.get("dU") is None:
            continue
        grad = np.zeros(12)
        grad[8:12] = np.r_[np.asarray(g.affine_xyz, float), 1.0]
        var = fit.cov.variance(grad)
        if g.affine_cov is not None and np.all(np.isfinite(g.affine_cov)):
            a = fit.H[2, :3]
            var += float(a @ np.asarray(g.affine_cov, float) @ a)
        row["images_height_sigma_m"] = float(np.sqrt(var)) if np.isfinite(var) else None


def _loo_held(pts: ControlPoints, hold: ImageHold) -> np.ndarray:
    """Leave-one-out residuals (n, 3) of the fit held by the images (NaN where the others lie on
    one line)."""
    n = len(pts)
    out = np.full((n, 3), np.nan)
    for i in range(n):
        keep = np.arange(n) != i
        if _rank(pts.Xe[keep]) < 2:
            continue
        H = hold.fit(pts.take(keep)).H
        out[i] = apply_affine_3d(H, pts.Xa[i:i + 1])[0] - pts.Xe[i]
    return out


def _attach_loo(rows: list[dict], ids: list[str], loo: np.ndarray) -> None:
    """Add loo_dE, loo_dN, loo_dU, loo_norm3d_m to the rows of the used control points."""
    by_id = dict(zip(ids, loo))
    for row in rows:
        r = by_id.get(row["id"]) if row["status"] == "used" else None
        if r is None:
            continue
        ok = bool(np.all(np.isfinite(r)))
        row.update(loo_dE=float(r[0]) if ok else None, loo_dN=float(r[1]) if ok else None,
                   loo_dU=float(r[2]) if ok else None,
                   loo_norm3d_m=float(np.linalg.norm(r)) if ok else None)


def _reproj_warnings(rows: list[dict], warn_px: float, ratio: float = 3.0,
                     floor_px: float = 0.75) -> list[str]:
    """Flag GCPs whose image observations disagree after triangulation (a likely bad click):
    above warn_px, or above `ratio` times the median of the others (and above floor_px), so a
    1.5 px misclick stands out among 0.1-0.4 px clicks."""
    px_all = {row["id"]: row.get("reproj_rms_px") for row in rows}
    ok = {k: v for k, v in px_all.items() if v is not None and np.isfinite(v)}
    out = []
    for row in rows:
        px = ok.get(row["id"])
        if px is None:
            continue
        others = [v for k, v in ok.items() if k != row["id"]]
        typical = float(np.median(others)) if len(others) >= 2 else None
        if px > warn_px:
            why = f"> {warn_px} px"
        elif typical is not None and px > floor_px and px > ratio * typical:
            why = f"{px / max(typical, 1e-9):.0f} x the others' median {typical:.2f} px"
        else:
            continue
        row["reproj_suspect"] = True
        out.append(f"GCP {row['id']}: reprojection residual {px:.2f} px ({why}); check its clicks "
                   "in each image")
    return out


# warnings of the affine fit that the fit with the bend replaces (upgrade.upgrade's wording)
_AFFINE_FIT_WARNINGS = ("RANSAC rejected", "RANSAC cannot tell", "the check points are off by")


def rescore_with_bend(res: UpgradeResult, H: np.ndarray, warp: EnuWarp, positions: dict, enu: dict, used: list[str],
            rejected: list[str], loo: dict, info: dict, thresh_m: float):
    """The UpgradeResult `res` with H and the warp: every GCP row with an affine position
    (positions: id -> (3,) in the frame H maps; enu: id -> surveyed (3,)) re-scored by the new
    map; the control GCPs `used` or `rejected` as the fit with the warps decided; their
    leave-one-out from that fit (loo: id -> (3,)); statistics, degrees of freedom, rejections,
    warnings and a note updated (the fit: recon_core.bend.gcp). A new object; res is unchanged."""
    rows, groups, rejections = [], {"control": [], "check": []}, []
    for row in res.points:
        row = {k: v for k, v in row.items() if not k.startswith("loo_")}
        x = positions.get(row["id"])
        if x is not None and row.get("dE") is not None:
            Y = apply_affine_3d(H, np.asarray(x, np.float64)[None])
            r = (Y + warp(Y))[0] - np.asarray(enu[row["id"]], np.float64)
            row.update(dE=float(r[0]), dN=float(r[1]), dU=float(r[2]),
                       horizontal_m=float(np.hypot(r[0], r[1])), norm3d_m=float(np.linalg.norm(r)))
            if row["id"] in used:
                row.update(status="used", reason=None)
                groups["control"].append(r)
            elif row["id"] in rejected:
                row.update(status="rejected",
                           reason=f"outlier of the fit with the bend: 3D residual {np.linalg.norm(r):.2f} m > "
                                  f"{thresh_m:g} m against the consensus of the other control GCPs")
            elif row["status"] == "check":
                groups["check"].append(r)
        if row["status"] in ("rejected", "unusable"):
            rejections.append({"id": row["id"], "reason": row["reason"]})
        rows.append(row)
    ids = list(loo)
    _attach_loo(rows, ids, np.array([loo[i] for i in ids]).reshape(-1, 3))
    stats = {k: accuracy_stats(np.array(v).reshape(-1, 3)) for k, v in groups.items()}
    stats["loo"] = accuracy_stats(np.array([loo[i] for i in ids]).reshape(-1, 3))
    k = info["warps_fitted"]
    # how well the GCPs the fit used fix the height scale (the affine fit's were fewer)
    c0 = res.conditioning or {}
    cond = conditioning(np.array([enu[i] for i in used]).reshape(-1, 3), c0.get("affine_height_sigma_m", 0.4),
                        c0.get("structure_height_m", 40.0), c0.get("warn_height_error_m", 2.0),
                        c0.get("poor_height_error_m", 5.0))
    warnings = [w for w in res.warnings if not w.startswith(_AFFINE_FIT_WARNINGS) and w != c0.get("warning")]
    if cond.get("warning"):
        warnings.append(cond["warning"])
    if rejected:
        warnings.append("the fit with the bend left out control GCP(s) " + ", ".join(rejected)
                        + f" (threshold {thresh_m:g} m): check their ground coordinates and image observations")
    c = stats["check"]
    if c.get("n") and c["rmse_3d_m"] > thresh_m:
        warnings.append(f"the check points are off by {c['rmse_3d_m']:.2f} m RMS (3D) with the bend fitted, "
                        f"more than the {thresh_m:g} m the control GCPs must agree within; see the "
                        "per-point residuals")
    what = "the views cannot see" if info["family"] == "invisible" else "of the structure (all nine)"
    note = (f"{k} quadratic warps {what} were fitted to {len(used)} control GCPs with an "
            f"affine correction of H_A (leave-one-out {info['loo_rms_bend_m']:.3f} m RMS against "
            f"{info['loo_rms_affine_m']:.3f} m for an affine map alone, on the same GCPs); the residuals "
            "are of that map")
    # the affine fit's notes on its own redundancy and metric constraint no longer hold
    notes = [t for t in res.notes if not t.startswith("N = 4 control GCPs")]
    if res.metric_prior is not None:
        note += ("; this fit uses the GCPs alone, without the cameras' metric constraint of the affine "
                 "fit (metric_prior is that fit's)")
    return replace(res, H=H, points=rows, stats=stats, dof=3 * len(used) - 12 - k,
                   n_control_used=len(used), rejections=rejections, warnings=warnings, conditioning=cond,
                   notes=notes + [note])

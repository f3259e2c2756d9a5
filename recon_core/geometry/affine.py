"""Affine camera geometry: factorisation, gauge, resection, triangulation, F_A, rectification.

Conventions (used by every function here)
-----------------------------------------
* An affine camera is a 2x4 float64 array ``P = [[m11 m12 m13 t1], [m21 m22 m23 t2]]``;
  ``x = P @ [X, Y, Z, 1]`` is the pixel (col, row) in FULL-image pixel coordinates.
  ``M = P[:, :3]`` is its 2x3 linear part and ``t = P[:, 3]`` its translation.
  A stack of cameras is (m, 2, 4); 3D points are (n, 3); image points are (n, 2).
* 2D affine maps of the image plane ("rectifying maps") are 3x3 with last row (0, 0, 1),
  acting on homogeneous (col, row, 1). 3D affine maps are 3x4 ``A`` (``X' = A[:, :3] X + A[:, 3]``)
  or 4x4 with last row (0, 0, 0, 1).
* Affine fundamental matrix: ``x2^T F x1 = 0`` with ``F = [[0,0,a],[0,0,b],[c,d,e]]``, i.e.
  ``a*x2 + b*y2 + c*x1 + d*y1 + e = 0`` (x1 in image 1, x2 in image 2). This is H&Z's
  convention (Hartley & Zisserman, 2nd ed., sec. 14.2, Algorithm 14.1, where the 4-vectors
  are ordered (x', y', x, y)) and s2p's. Normalised so that ``||(a, b, c, d)|| = 1``.

References: Hartley & Zisserman, "Multiple View Geometry", 2nd ed., ch. 14 (affine epipolar
geometry, Gold Standard F_A) and sec. 18.2 (affine reconstruction by factorisation);
Torr 1998 (GRIC model selection); s2p (de Franchis et al.) for the affine rectification.

Nothing here loops over points in Python; RANSAC evaluates hypotheses in vectorised batches.
"""

from __future__ import annotations

import math

import numpy as np

from recon_core.errors import ReconstructionError

__all__ = [
    "PARALLAX_RATIO_MIN",
    "PLANAR_CONDITIONING_MIN",
    "project",
    "normalize_points",
    "tomasi_kanade",
    "canonical_gauge",
    "measurement_singular_values",
    "parallax_ratio",
    "parallax_stats",
    "affine_map_vs_fa_gric",
    "affine_map_vs_fa_test",
    "points_conditioning",
    "resect",
    "resect_ransac",
    "triangulate_tracks",
    "reprojection_errors",
    "affine_fundamental_gold_standard",
    "affine_fundamental_from_cameras",
    "fa_residuals",
    "epipolar_distances",
    "fa_ransac",
    "apply_affine_2d",
    "rectifying_maps",
    "rectified_row_error",
    "rectified_cameras",
    "disparity_to_3d_map",
    "apply_disparity_map",
    "fit_affine_3d",
    "apply_affine_3d",
]

#: sigma3/sigma4 of the centred 4 x n measurement matrix above which a pair is taken to show
#: parallax. Pure noise (no parallax) gives a median of 1.13 and a 99.9th percentile of 1.47
#: for n = 100 points (1.07 / 1.25 for n = 300; 1.35 / 2.7 for n = 20), so 3.0 means that the
#: out-of-plane spread is about 3x the noise: a margin suited to choosing the initial pair.
PARALLAX_RATIO_MIN = 3.0

#: Smallest / largest singular value of the centred 3D points below which a resection is
#: considered nearly planar (the camera's out-of-plane column is then poorly determined).
#: 1e-3 is 1 m of RMS relief over a 1 km wide tile; a 1 km x 1 km x 50 m scene gives ~0.05.
PLANAR_CONDITIONING_MIN = 1e-3


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------
def _rng(rng) -> np.random.Generator:
    """None / int seed / Generator -> Generator."""
    if isinstance(rng, np.random.Generator):
        return rng
    return np.random.default_rng(rng)


def _as_points(x, dim: int, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != dim:
        raise ValueError(f"{name}: expected shape (n, {dim}), got {x.shape}")
    return x


def _ransac_needed(n_inliers: int, n: int, sample: int, confidence: float) -> float:
    """Number of RANSAC iterations needed for `confidence` given inlier ratio n_inliers / n."""
    w = n_inliers / max(n, 1)
    if w <= 0.0:
        return math.inf
    p_good = w**sample
    if p_good >= 1.0:
        return 0.0
    return math.log(1.0 - confidence) / math.log1p(-p_good)


class _SampleBatches:
    """Minimal samples of k indices for a batched RANSAC, (B, k) at a time, with the adaptive
    budget: iterate over it, and report each better model's inlier count with `found`."""

    def __init__(self, gen: np.random.Generator, n: int, iters: int, confidence: float,
                 k: int = 4, batch: int | None = None):
        self.gen, self.n, self.iters, self.confidence, self.k = gen, n, iters, confidence, k
        self.batch = batch or int(max(16, min(256, 4_000_000 // max(n, 1))))
        self.needed = float(iters)

    def __iter__(self):
        done = 0
        while done < min(self.iters, self.needed):
            B = int(min(self.batch, self.iters - done))
            done += B
            yield self.gen.integers(0, self.n, size=(B, self.k))

    def found(self, n_inliers: int) -> None:
        self.needed = _ransac_needed(n_inliers, self.n, self.k, self.confidence)


def project(P, X) -> np.ndarray:
    """Project 3D points with one or several affine cameras.

    P: (2, 4) or (m, 2, 4); X: (n, 3). Returns (n, 2) for one camera, (m, n, 2) for a stack:
    x = M X + t for each camera.
    """
    P = np.asarray(P, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    if P.ndim == 2:
        return X @ P[:, :3].T + P[:, 3]
    return np.einsum("mij,nj->mni", P[:, :, :3], X) + P[:, None, :, 3]


def normalize_points(x):
    """Similarity normalisation of 2D or 3D points (H&Z sec. 4.4.4).

    x: (n, d). Returns (x_normalised (n, d), T ((d+1), (d+1))) with x_n = T [x, 1]: points are
    centred on their centroid and scaled isotropically so that their RMS distance from it is
    sqrt(d) (each coordinate has unit RMS). Coincident points get scale 1.
    """
    x = np.asarray(x, dtype=np.float64)
    n, d = x.shape
    c = x.mean(axis=0)
    xc = x - c
    rms = math.sqrt(float(np.mean(np.sum(xc * xc, axis=1)))) if n else 0.0
    s = math.sqrt(d) / rms if rms > 0 else 1.0
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * c
    return xc * s, T


# ---------------------------------------------------------------------------------------------
# factorisation and gauge
# ---------------------------------------------------------------------------------------------
def tomasi_kanade(W):
    """Affine reconstruction by factorisation (H&Z Algorithm 18.1, Tomasi-Kanade).

    W: (m, n, 2) image points of n points seen in all m views (no missing data).
    The 2m x n measurement matrix (rows x_1, y_1, x_2, y_2, ...) is centred on the per-row
    centroids (the translations t_i = centroid of the image points, since the world origin is
    put at the centroid of the 3D points), then truncated to rank 3 by SVD: W~ = U S V^T,
    M = U_3 S_3^(1/2), X = S_3^(1/2) V_3^T. This is the ML affine reconstruction for isotropic
    Gaussian image noise.

    Returns (cams (m, 2, 4), X (n, 3), singular_values (min(2m, n),)) of the centred matrix;
    singular_values[3:] measure the departure from the affine rank-3 model (0 on exact data).
    The reconstruction is defined up to a 3D affine map (see `canonical_gauge`).
    """
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 3 or W.shape[2] != 2:
        raise ValueError(f"W: expected shape (m, n, 2), got {W.shape}")
    m, n, _ = W.shape
    if m < 2 or n < 4:
        raise ValueError(f"tomasi_kanade needs >= 2 views and >= 4 points, got m={m}, n={n}")
    if not np.all(np.isfinite(W)):
        raise ValueError("tomasi_kanade: W has missing (non-finite) entries")
    Wm = W.transpose(0, 2, 1).reshape(2 * m, n)  # rows x_1, y_1, x_2, y_2, ...
    t = Wm.mean(axis=1)
    U, s, Vt = np.linalg.svd(Wm - t[:, None], full_matrices=False)
    r = np.sqrt(s[:3])
    M = U[:, :3] * r
    X = (Vt[:3].T * r).copy()
    cams = np.concatenate([M.reshape(m, 2, 3), t.reshape(m, 2, 1)], axis=2)
    return cams, X, s


def canonical_gauge(cams, X):
    """Move an affine reconstruction into the canonical affine frame (H&Z sec. 14.4 / 18.2).

    cams: (m, 2, 4), m >= 2; X: (n, 3).
    Applies the 3D affine map A (4x4, last row (0,0,0,1)) with X' = A [X, 1] and
    P_i' = P_i A^-1 so that the first camera becomes [I2 | 0 | 0] = [[1,0,0,0],[0,1,0,0]] and,
    in the second camera, the row r with the larger |third-column entry| (the row with the
    larger component out of the plane of the first camera's rows) becomes [0, 0, 1 | 0].
    A is unique: A = [[P_1], [P_2[r]], [0, 0, 0, 1]], so exactly the 12 gauge dof are fixed
    and the other row of P_2 (4 numbers: the epipolar geometry) stays free.
    Projections are preserved: project(P_i', X') == project(P_i, X).

    Returns (cams' (m, 2, 4), X' (n, 3), A (4, 4)). Raises ReconstructionError if the first two
    cameras have the same viewing direction (rank-deficient A).
    """
    cams = np.asarray(cams, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    if cams.ndim != 3 or cams.shape[0] < 2 or cams.shape[1:] != (2, 4):
        raise ValueError(f"cams: expected shape (m >= 2, 2, 4), got {cams.shape}")
    P1, P2 = cams[0], cams[1]
    # Third-column entries of P2 in a frame where P1 = [I2|0|0]: with any completion, the third
    # axis is along v = null(M1) = m1_row0 x m1_row1, so the entries are proportional to P2 M v.
    v = np.cross(P1[0, :3], P1[1, :3])
    r = int(np.argmax(np.abs(P2[:, :3] @ v)))
    A = np.zeros((4, 4))
    A[:2] = P1
    A[2] = P2[r]
    A[3, 3] = 1.0
    B = A[:3, :3]
    sv = np.linalg.svd(B, compute_uv=False)
    if sv[-1] <= 1e-12 * sv[0]:
        raise ReconstructionError(
            "canonical_gauge: the first two cameras share a viewing direction (no parallax)"
        )
    Ainv = np.linalg.inv(A)
    cams_c = cams @ Ainv
    cams_c[0] = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]
    cams_c[1, r] = [0.0, 0.0, 1.0, 0.0]
    Xc = X @ B.T + A[:3, 3]
    return cams_c, Xc, A


# ---------------------------------------------------------------------------------------------
# parallax / model selection
# ---------------------------------------------------------------------------------------------
def _joint(x1, x2) -> np.ndarray:
    """(n, 4) joint-space points [x2, y2, x1, y1] (H&Z order, image 2 first)."""
    x1 = _as_points(x1, 2, "x1")
    x2 = _as_points(x2, 2, "x2")
    if len(x1) != len(x2):
        raise ValueError(f"x1 and x2 differ in length: {len(x1)} vs {len(x2)}")
    return np.concatenate([x2, x1], axis=1)


def measurement_singular_values(x1, x2) -> np.ndarray:
    """Singular values (4,) of the centred 4 x n measurement matrix [x1; y1; x2; y2] (pixels).

    Rank 3 for an affine pair with parallax (the 4th value is noise), near rank 2 when the
    views are related by a 2D affine map (flat scene, or the same viewing direction).
    """
    Z = _joint(x1, x2)
    if len(Z) < 4:
        raise ValueError("need >= 4 correspondences")
    s = np.linalg.svd(Z - Z.mean(axis=0), compute_uv=False)
    return s


def parallax_ratio(x1, x2) -> float:
    """sigma3 / sigma4 of the centred 4 x n measurement matrix (dimensionless).

    x1, x2: (n, 2) corresponding points, n >= 4. Not robust: compute it on >= 100 RANSAC
    inliers (`fa_ransac`); outliers inflate sigma4 (ratio too small) and the rare far outlier
    that lies close to the F_A hyperplane inflates sigma3 (ratio too large). For a robust
    decision use `affine_map_vs_fa_test`.
    Parallax makes the matrix rank 3 (sigma3 = parallax spread, sigma4 = noise); no parallax
    (flat scene, or the two views have the same direction) makes it rank 2, so sigma3 and
    sigma4 are both noise and the ratio is ~1: median 1.13 and 99.9th percentile 1.47 for
    n = 100 under isotropic noise. Threshold: `PARALLAX_RATIO_MIN` (3.0). Exact rank-3 data
    returns a large finite number (sigma4 floored at 1e-15 sigma1). For a ratio that does not
    depend on the noise level (sigma3/sigma2, the RMS parallax in pixels) see `parallax_stats`.
    """
    s = measurement_singular_values(x1, x2)
    return float(s[2] / max(s[3], 1e-15 * s[0], 1e-300))


def parallax_stats(x1, x2) -> dict:
    """Parallax measures of a pair from the centred 4 x n measurement matrix (x1, x2: (n, 2)).

    Returns a dict with
      singular_values: (4,) sigma1..sigma4;
      ratio_34: sigma3/sigma4 (see `parallax_ratio`; signal to noise, threshold 3.0);
      ratio_32: sigma3/sigma2 (parallax relative to the image extent covered by the matches,
        independent of the noise level: ~noise/extent (< 1e-3) when flat, ~1e-2 for a
        20-degree pair over 50 m of relief in a 1 km scene at 1 px/m);
      rms_parallax_px: sigma3/sqrt(n), RMS distance in the joint 4D space (pixels) of the points
        from the best 2D affine map between the views (includes the noise);
      rms_noise_px: sigma4/sqrt(n), RMS distance from the best F_A hyperplane (~noise std).
    """
    s = measurement_singular_values(x1, x2)
    n = len(np.asarray(x1))
    return {
        "singular_values": s,
        "ratio_34": float(s[2] / max(s[3], 1e-15 * s[0], 1e-300)),
        "ratio_32": float(s[2] / max(s[1], 1e-300)),
        "rms_parallax_px": float(s[2] / math.sqrt(n)),
        "rms_noise_px": float(s[3] / math.sqrt(n)),
        "n": n,
    }


def _plane_in_hyperplane(Y, thresh, gen, iters=500, confidence=0.999):
    """Robust (MSAC, 3-point samples) plane fit to 3D points Y (n, 3); returns signed distances.

    Refitted by total least squares on its inliers while the MSAC cost decreases.
    """
    n = len(Y)
    t2 = float(thresh) ** 2
    best_cost, best = math.inf, None
    samples = _SampleBatches(gen, n, iters, confidence, k=3, batch=128)
    for idx in samples:
        S = Y[idx]
        nrm = np.cross(S[:, 1] - S[:, 0], S[:, 2] - S[:, 0])
        ln = np.linalg.norm(nrm, axis=1)
        scale = (np.linalg.norm(S[:, 1] - S[:, 0], axis=1)
                 * np.linalg.norm(S[:, 2] - S[:, 0], axis=1))
        good = ln > 1e-6 * np.maximum(scale, 1e-300)
        if not np.any(good):
            continue
        nrm = nrm[good] / ln[good, None]
        off = -np.einsum("bi,bi->b", nrm, S[good, 0])
        r2 = (Y @ nrm.T + off) ** 2
        cost = np.minimum(r2, t2).sum(axis=0)
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            best_cost, best = float(cost[j]), (nrm[j], off[j])
            samples.found(int(np.sum(r2[:, j] < t2)))
    if best is None:  # all samples collinear: fall back to the TLS plane of everything
        c = Y.mean(axis=0)
        nv = np.linalg.svd(Y - c)[2][-1]
        return (Y - c) @ nv
    d = Y @ best[0] + best[1]
    for _ in range(5):
        inl = d**2 < t2
        if inl.sum() < 3:
            break
        c = Y[inl].mean(axis=0)
        nv = np.linalg.svd(Y[inl] - c, full_matrices=False)[2][-1]
        d_new = (Y - c) @ nv
        cost_new = float(np.minimum(d_new**2, t2).sum())
        if not cost_new < best_cost:
            break
        d, best_cost = d_new, cost_new
    return d


def _compare_models(Z, N, e, thresh, sigma, gen) -> dict:
    """F_A (hyperplane N.z + e = 0) vs the best 2D affine map inside it; Z: (n, 4) joint points."""
    n = len(Z)
    eF = Z @ N + e
    Bh = np.linalg.svd(N[None, :])[2][1:].T  # (4, 3) orthonormal basis of the hyperplane
    Y = (Z - Z.mean(axis=0)) @ Bh
    e3 = _plane_in_hyperplane(Y, thresh, gen)
    scale = float(np.sqrt(np.mean(np.sum((Z - Z.mean(axis=0)) ** 2, axis=1))))
    floor = max(1e-9 * scale, 1e-300)
    if sigma is None:
        sigma = 1.4826 * float(np.median(np.abs(eF)))
    sigma = max(float(sigma), floor)
    qF = float(np.quantile(eF**2, 0.9))
    q3 = float(np.quantile(e3**2, 0.9))
    ratio = math.sqrt(q3 / max(qF, floor**2))
    r = 4.0
    lam1, lam2, lam3 = math.log(r), math.log(r * n), 2.0
    rF = eF**2 / sigma**2
    rH = rF + e3**2 / sigma**2
    gric_f = float(np.minimum(rF, lam3 * (r - 3)).sum() + lam1 * 3 * n + lam2 * 4)
    gric_h = float(np.minimum(rH, lam3 * (r - 2)).sum() + lam1 * 2 * n + lam2 * 6)
    return {
        "n": n,
        "sigma": sigma,
        "gric_affine": gric_h,
        "gric_fa": gric_f,
        "prefers_fa": gric_f < gric_h,
        "ratio_q90": ratio,
        "q90_parallax_px": math.sqrt(q3),
        "parallax_fraction": float(np.mean(np.abs(e3) > thresh)),
    }


def affine_map_vs_fa_gric(x1, x2, sigma=None, thresh=1.0, rng=None) -> dict:
    """Compare a 2D affine map with an affine fundamental matrix on inlier matches x1, x2 (n, 2).

    Both models live in the joint 4D space z = (x2, y2, x1, y1) (r = 4): F_A is a hyperplane
    (d = 3, k = 4 parameters; Gold Standard fit), the 2D affine map a 2D affine subspace
    (d = 2, k = 6), fitted here inside the F_A hyperplane by MSAC (3-point samples, inlier
    distance `thresh` px) + total least squares, so that buildings on flat ground do not tilt
    it. Residuals: e_F = distance to F_A; e_3 = distance to the 2D map within the hyperplane;
    e_H^2 = e_F^2 + e_3^2.

    Returns a dict with
      ratio_q90: sqrt(q90(e_3^2) / q90(e_F^2)), a robust residual comparison (~1 without
        parallax, both being noise; >> 1 when at least 10 % of the points show parallax);
      q90_parallax_px: sqrt(q90(e_3^2)), pixels; parallax_fraction: share of |e_3| > thresh;
      gric_affine, gric_fa, prefers_fa: Torr's GRIC = sum min(e^2/sigma^2, 2 (r - d))
        + log(r) d n + log(r n) k with sigma = `sigma` (noise std per coordinate, px) or the
        robust 1.4826 median|e_F|. Because of GRIC's truncation it prefers F_A only when
        roughly >= 20 % of the points have parallax > 2 sigma (flat ground with a few
        buildings is called an "affine map"), and with sigma estimated from e_F (biased low)
        it has ~10 % false alarms on pure noise for n ~ 200: informative, not the decision;
      sigma, n.
    """
    Z = _joint(x1, x2)
    if len(Z) < 5:
        raise ValueError("affine_map_vs_fa_gric needs >= 5 correspondences")
    F = affine_fundamental_gold_standard(x1, x2)
    a, b, c, d, e = _F_params(F)
    return _compare_models(Z, np.array([a, b, c, d]), e, thresh, sigma, _rng(rng))


def affine_map_vs_fa_test(x1, x2, thresh=1.0, sigma=None, min_ratio=2.0, rng=None,
                          return_details=False):
    """Does the pair show parallax? Robust model comparison 2D affine map vs F_A.

    x1, x2: (n, 2) matches (outliers allowed). thresh: inlier distance in pixels (4D
    orthogonal distance to F_A, and distance to the 2D map inside the F_A hyperplane); use
    ~3x the matching noise std (1.0 px for ~0.3 px SIFT noise).
    1. `fa_ransac` (thresh) rejects outliers; fewer than 8 inliers -> False.
    2. On the inliers, `affine_map_vs_fa_gric` residuals: parallax iff
       ratio_q90 = sqrt(q90(e_3^2) / q90(e_F^2)) >= min_ratio, i.e. the 10 % of points farthest
       from the best 2D affine map are at least `min_ratio` times farther from it than the
       10 % farthest from F_A. Without parallax both residuals are noise and the ratio is
       ~1 (it stays below 1.6 in simulations with n >= 100 and 30 % outliers); the default
       2.0 asks for parallax clearly above the noise on >= 10 % of the points, which keeps
       flat ground with buildings. Outliers that survive step 1 (close to the F_A hyperplane)
       affect a 90th percentile only when they exceed ~10 % of the inliers, unlike the plain
       sigma3/sigma4 of `parallax_ratio`.
    For the initial pair ask more, e.g. `parallax_ratio` on the inliers >= PARALLAX_RATIO_MIN.
    sigma (noise std, px) only enters the GRIC values reported in the details.

    Returns bool, or (bool, details) with return_details: the `affine_map_vs_fa_gric` dict
    plus inliers (mask), n_inliers, has_parallax.
    """
    x1 = _as_points(x1, 2, "x1")
    x2 = _as_points(x2, 2, "x2")
    gen = _rng(rng)
    details: dict = {"n_inliers": 0}
    ok = False
    if len(x1) >= 8:
        try:
            F, inl = fa_ransac(x1, x2, thresh_px=thresh, rng=gen)
        except ReconstructionError:
            F, inl = None, np.zeros(len(x1), bool)
        details["inliers"] = inl
        details["n_inliers"] = int(inl.sum())
        if inl.sum() >= 8:
            a, b, c, d, e = _F_params(F)
            Z = _joint(x1[inl], x2[inl])
            details.update(_compare_models(Z, np.array([a, b, c, d]), e, thresh, sigma, gen))
            ok = bool(details["ratio_q90"] >= min_ratio)
    details["has_parallax"] = ok
    return (ok, details) if return_details else ok


# ---------------------------------------------------------------------------------------------
# resection
# ---------------------------------------------------------------------------------------------
def points_conditioning(X, weights=None) -> float:
    """Smallest / largest singular value of the centred 3D points X (n, 3) (0 if n < 2).

    ~0 for (nearly) coplanar or collinear points, for which the resected camera's
    out-of-plane column is undetermined; compare with PLANAR_CONDITIONING_MIN (1e-3).
    A 1 km x 1 km x 50 m uniformly spread scene gives ~0.05. Optional weights (n,) >= 0.
    """
    X = _as_points(X, 3, "X")
    if len(X) < 2:
        return 0.0
    if weights is None:
        Xc = X - X.mean(axis=0)
    else:
        w = np.asarray(weights, dtype=np.float64)
        Xc = (X - (w[:, None] * X).sum(0) / max(w.sum(), 1e-300)) * np.sqrt(w)[:, None]
    s = np.linalg.svd(Xc, compute_uv=False)
    return float(s[-1] / s[0]) if s[0] > 0 else 0.0


def _denormalise_camera(Q, T2, T3) -> np.ndarray:
    """Camera Q (..., 2, 4) acting on normalised coords -> pixel camera T2^-1 [Q; e4] T3."""
    T2inv = np.linalg.inv(T2)
    Qh = np.zeros(Q.shape[:-2] + (3, 4))
    Qh[..., :2, :] = Q
    Qh[..., 2, 3] = 1.0
    return (T2inv @ Qh @ T3)[..., :2, :]


def resect(X, x, weights=None) -> np.ndarray:
    """Linear least-squares affine camera from 3D-2D correspondences (H&Z sec. 7.3, affine case).

    X: (n, 3), x: (n, 2), n >= 4 non-coplanar; weights: (n,) >= 0 (squared-residual weights).
    Both point sets are similarity-normalised (`normalize_points`), the 8 parameters are solved
    row by row from x_n = [X_n, 1] q (one 4-column design shared by both rows; this is the
    Gold Standard for affine cameras, since the residual is the reprojection error), then
    de-normalised. Returns P (2, 4). Check `points_conditioning(X)` for nearly planar sets.
    """
    X = _as_points(X, 3, "X")
    x = _as_points(x, 2, "x")
    if len(X) != len(x) or len(X) < 4:
        raise ValueError(f"resect needs >= 4 matching 3D/2D points, got {len(X)}/{len(x)}")
    q, T3, T2 = _normalised_affine_lstsq(X, x, weights)
    return _denormalise_camera(q.T, T2, T3)


def _normalised_affine_lstsq(X, Y, weights=None):
    """Weighted least squares of Y ~ q^T [X, 1] on similarity-normalised data.

    X: (n, 3), Y: (n, k). Returns (q (4, k) in normalised coordinates, T_X (4, 4), T_Y (k+1,
    k+1)), the normalisations to undo. Shared by resection (k = 2) and 3D affine fits (k = 3).
    """
    Xn, TX = normalize_points(X)
    Yn, TY = normalize_points(Y)
    A = np.concatenate([Xn, np.ones((len(Xn), 1))], axis=1)
    b = Yn
    if weights is not None:
        sw = np.sqrt(np.clip(np.asarray(weights, dtype=np.float64), 0.0, None))[:, None]
        A = A * sw
        b = b * sw
    q, *_ = np.linalg.lstsq(A, b, rcond=None)
    return q, TX, TY


def resect_ransac(X, x, thresh_px=2.0, iters=500, rng=None, min_inliers=6, confidence=0.999,
                  min_sample_conditioning=None):
    """Robust affine resection: RANSAC on minimal 4-point samples + least-squares refinement.

    X: (n, 3), x: (n, 2). A sample of 4 points determines the 8 parameters exactly; samples
    whose centred 3D points have conditioning (smallest/largest singular value) below
    `min_sample_conditioning` (default max(1e-6, 0.1 * points_conditioning(X))) are rejected
    as nearly coplanar. Hypotheses are scored by the number of points with reprojection error
    < thresh_px (ties broken by the truncated squared error, MSAC), evaluated in vectorised
    batches; the number of iterations adapts to the inlier ratio (`confidence`), capped at
    `iters`. The best model is refitted by `resect` on its inliers, inliers are re-collected
    and the model refitted once more.

    Returns (P (2, 4), inlier_mask (n,) bool). Raises ReconstructionError if fewer than
    max(4, min_inliers) inliers are found.
    """
    X = _as_points(X, 3, "X")
    x = _as_points(x, 2, "x")
    n = len(X)
    if len(x) != n:
        raise ValueError("X and x differ in length")
    need = max(4, int(min_inliers))
    if n < need:
        raise ReconstructionError(f"resect_ransac: {n} correspondences, need >= {need}")
    gen = _rng(rng)
    Xn, T3 = normalize_points(X)
    xn, T2 = normalize_points(x)
    s2 = T2[0, 0]  # pixels -> normalised units
    t2 = (thresh_px * s2) ** 2
    if min_sample_conditioning is None:
        min_sample_conditioning = max(1e-6, 0.1 * points_conditioning(Xn))
    Xh = np.concatenate([Xn, np.ones((n, 1))], axis=1)  # (n, 4)

    best = (-1, math.inf)
    best_q = None
    samples = _SampleBatches(gen, n, iters, confidence)
    for idx in samples:
        S = Xn[idx]  # (B, 4, 3)
        Sc = S - S.mean(axis=1, keepdims=True)
        sv = np.linalg.svd(Sc, compute_uv=False)  # (B, 3)
        good = sv[:, 2] > min_sample_conditioning * np.maximum(sv[:, 0], 1e-300)
        if not np.any(good):
            continue
        idx = idx[good]
        A = Xh[idx]  # (b, 4, 4)
        q = np.linalg.solve(A, xn[idx])  # (b, 4, 2)
        pred = np.einsum("nk,bkj->bnj", Xh, q)  # (b, n, 2)
        r2 = np.sum((pred - xn) ** 2, axis=2)  # (b, n)
        cnt = np.sum(r2 < t2, axis=1)
        cost = np.minimum(r2, t2).sum(axis=1)
        order = np.lexsort((cost, -cnt))
        j = order[0]
        if (cnt[j], -cost[j]) > (best[0], -best[1]):
            best = (int(cnt[j]), float(cost[j]))
            best_q = q[j]
            samples.found(best[0])
    if best_q is None or best[0] < need:
        raise ReconstructionError(
            f"resect_ransac: no camera with >= {need} inliers (best {max(best[0], 0)} of {n})"
        )
    P = _denormalise_camera(best_q.T, T2, T3)
    thr2 = thresh_px**2
    inl = np.sum((project(P, X) - x) ** 2, axis=1) < thr2
    for _ in range(2):
        if inl.sum() < need:
            break
        P = resect(X[inl], x[inl])
        inl = np.sum((project(P, X) - x) ** 2, axis=1) < thr2
    if inl.sum() < need:
        raise ReconstructionError(
            f"resect_ransac: only {int(inl.sum())} inliers after refinement (need {need})"
        )
    return P, inl


# ---------------------------------------------------------------------------------------------
# triangulation
# ---------------------------------------------------------------------------------------------
def triangulate_tracks(cams, cam_idx, pt_idx, xy, n_points, weights=None, rcond=1e-8):
    """Linear multi-view affine triangulation of many tracks at once.

    cams: (m, 2, 4); observation j is pixel xy[j] (k, 2) of point pt_idx[j] (k,) in camera
    cam_idx[j] (k,); weights (k,) >= 0 optional. Each observation gives 2 linear equations
    M_c X = x - t_c; the per-point 3x3 normal equations sum_j w_j M_c^T M_c X = sum_j w_j M_c^T
    (x_j - t_c) are accumulated with np.bincount and solved batched (plus one step of iterative
    refinement). For fixed affine cameras this linear LS solution is exactly the minimum of the
    (weighted) reprojection error, so no non-linear refinement is needed.

    Returns (X (n_points, 3), ok (n_points,) bool). ok is False (and X NaN) for points with
    fewer than 2 observations or an ill-conditioned system (smallest/largest eigenvalue of the
    normal matrix < rcond, e.g. all observations from one camera or the same direction).
    """
    cams = np.asarray(cams, dtype=np.float64)
    cam_idx = np.asarray(cam_idx, dtype=np.intp).ravel()
    pt_idx = np.asarray(pt_idx, dtype=np.intp).ravel()
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    k = len(cam_idx)
    if len(pt_idx) != k or len(xy) != k:
        raise ValueError("cam_idx, pt_idx and xy must have the same length")
    n_points = int(n_points)
    w = np.ones(k) if weights is None else np.asarray(weights, dtype=np.float64).ravel()

    M = cams[:, :, :3]  # (m, 2, 3)
    G = np.einsum("mij,mil->mjl", M, M).reshape(-1, 9)  # per-camera M^T M
    Mo = M[cam_idx]  # (k, 2, 3)
    b = xy - cams[cam_idx, :, 3]  # (k, 2)
    rhs_o = np.einsum("kij,ki->kj", Mo, b) * w[:, None]  # (k, 3)
    Gw = G[cam_idx] * w[:, None]  # (k, 9)

    A = np.empty((n_points, 9))
    for c in range(9):
        A[:, c] = np.bincount(pt_idx, weights=Gw[:, c], minlength=n_points)
    A = A.reshape(n_points, 3, 3)
    rhs = np.empty((n_points, 3))
    for c in range(3):
        rhs[:, c] = np.bincount(pt_idx, weights=rhs_o[:, c], minlength=n_points)
    nobs = np.bincount(pt_idx, weights=(w > 0).astype(np.float64), minlength=n_points)

    X = np.full((n_points, 3), np.nan)
    ok = nobs >= 2
    if np.any(ok):
        # Cheap conditioning test (no eigen-decomposition: this runs on millions of dense
        # points): 27 det / trace^3 lies in [0, 1] and scales like lambda_min / lambda_max.
        Ao = A[ok]
        tr = Ao[:, 0, 0] + Ao[:, 1, 1] + Ao[:, 2, 2]
        det = (Ao[:, 0, 0] * (Ao[:, 1, 1] * Ao[:, 2, 2] - Ao[:, 1, 2] * Ao[:, 2, 1])
               - Ao[:, 0, 1] * (Ao[:, 1, 0] * Ao[:, 2, 2] - Ao[:, 1, 2] * Ao[:, 2, 0])
               + Ao[:, 0, 2] * (Ao[:, 1, 0] * Ao[:, 2, 1] - Ao[:, 1, 1] * Ao[:, 2, 0]))
        c = 27.0 * det / np.maximum(tr, 1e-300) ** 3
        good = c > rcond
        ok[np.flatnonzero(ok)[~good]] = False
    if np.any(ok):
        Ao, bo = A[ok], rhs[ok]
        Xo = solve3x3(Ao, bo)
        Xo += solve3x3(Ao, bo - np.einsum("nij,nj->ni", Ao, Xo))  # iterative refinement
        X[ok] = Xo
    return X, ok


def solve3x3(A, b) -> np.ndarray:
    """Solve many 3x3 systems A (n, 3, 3) x = b (n, 3) in closed form (adjugate / determinant).

    Several times faster than np.linalg.solve on millions of tiny systems; callers screen
    ill-conditioned systems first and may add a step of iterative refinement.
    """
    a, bb, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * c00 + bb * c01 + c * c02
    inv_det = 1.0 / det
    x0 = (c00 * b[:, 0] + (c * h - bb * i) * b[:, 1] + (bb * f - c * e) * b[:, 2]) * inv_det
    x1 = (c01 * b[:, 0] + (a * i - c * g) * b[:, 1] + (c * d - a * f) * b[:, 2]) * inv_det
    x2 = (c02 * b[:, 0] + (bb * g - a * h) * b[:, 1] + (a * e - bb * d) * b[:, 2]) * inv_det
    return np.stack([x0, x1, x2], axis=1)


def reprojection_errors(cams, cam_idx, pt_idx, xy, X) -> np.ndarray:
    """Euclidean pixel error of each observation: (k,) = ||P_cam X_pt - xy||.

    cams (m, 2, 4), cam_idx (k,), pt_idx (k,), xy (k, 2), X (n, 3).
    """
    cams = np.asarray(cams, dtype=np.float64)
    cam_idx = np.asarray(cam_idx, dtype=np.intp).ravel()
    pt_idx = np.asarray(pt_idx, dtype=np.intp).ravel()
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    X = np.asarray(X, dtype=np.float64)
    P = cams[cam_idx]
    pred = np.einsum("kij,kj->ki", P[:, :, :3], X[pt_idx]) + P[:, :, 3]
    return np.linalg.norm(pred - xy, axis=1)


# ---------------------------------------------------------------------------------------------
# affine fundamental matrix
# ---------------------------------------------------------------------------------------------
def _F_from_normal(N, e) -> np.ndarray:
    F = np.zeros((3, 3))
    F[0, 2], F[1, 2], F[2, 0], F[2, 1] = N
    F[2, 2] = e
    return F


def _F_params(F):
    F = np.asarray(F, dtype=np.float64)
    return F[0, 2], F[1, 2], F[2, 0], F[2, 1], F[2, 2]


def affine_fundamental_gold_standard(x1, x2) -> np.ndarray:
    """Gold Standard (ML) affine fundamental matrix, H&Z Algorithm 14.1.

    x1: (n, 2) points in image 1, x2: (n, 2) in image 2, n >= 4.
    Convention: x2^T F x1 = 0, F = [[0,0,a],[0,0,b],[c,d,e]], i.e.
    a*x2 + b*y2 + c*x1 + d*y1 + e = 0. The joint 4-vectors z = (x2, y2, x1, y1) are centred
    on their centroid z0; N = (a, b, c, d) is the right singular vector of the smallest singular
    value of the centred n x 4 matrix, e = -N . z0. This minimises the sum of squared
    geometric (orthogonal, 4D) distances, i.e. the reprojection error under isotropic Gaussian
    noise; pixel units are kept (no scaling, which would change the error minimised).
    Returns F (3, 3) with ||(a, b, c, d)|| = 1.
    """
    Z = _joint(x1, x2)
    if len(Z) < 4:
        raise ValueError("affine_fundamental_gold_standard needs >= 4 correspondences")
    z0 = Z.mean(axis=0)
    _, _, Vt = np.linalg.svd(Z - z0, full_matrices=False)
    N = Vt[-1]
    return _F_from_normal(N, -float(N @ z0))


def affine_fundamental_from_cameras(P1, P2) -> np.ndarray:
    """Affine fundamental matrix of two affine cameras (same convention as the Gold Standard).

    P1, P2: (2, 4). A point X projects to z = (x2, y2, x1, y1) = B X + t with the 4x3 matrix
    B = [M2; M1] and t = (t2, t1). The left null vector N of B (N^T B = 0; for rank-3 B it is
    the generalised cross product of B's columns: N_i = (-1)^i det(B without row i)) gives
    N . z = N . t for every X, so (a, b, c, d) = N and e = -N . t.
    Returns F (3, 3) with ||(a, b, c, d)|| = 1. Raises ReconstructionError if B has rank < 3
    (same viewing direction: F_A undefined).
    """
    P1 = np.asarray(P1, dtype=np.float64)
    P2 = np.asarray(P2, dtype=np.float64)
    B = np.vstack([P2[:, :3], P1[:, :3]])
    t = np.concatenate([P2[:, 3], P1[:, 3]])
    N = np.array([(-1) ** i * np.linalg.det(np.delete(B, i, axis=0)) for i in range(4)])
    nn = np.linalg.norm(N)
    if nn <= 1e-12 * np.linalg.norm(B) ** 3:
        raise ReconstructionError(
            "affine_fundamental_from_cameras: cameras share a viewing direction"
        )
    N = N / nn
    return _F_from_normal(N, -float(N @ t))


def fa_residuals(F, x1, x2) -> np.ndarray:
    """Geometric (orthogonal) distance (n,) of each correspondence to F_A in the 4D joint space.

    |a x2 + b y2 + c x1 + d y1 + e| / ||(a, b, c, d)||: the length of the smallest joint
    correction (dx1, dx2) making the pair satisfy x2^T F x1 = 0 (the Gold Standard error).
    """
    a, b, c, d, e = _F_params(F)
    x1 = _as_points(x1, 2, "x1")
    x2 = _as_points(x2, 2, "x2")
    v = a * x2[:, 0] + b * x2[:, 1] + c * x1[:, 0] + d * x1[:, 1] + e
    return np.abs(v) / math.sqrt(a * a + b * b + c * c + d * d)


def epipolar_distances(F, x1, x2):
    """Per-image epipolar distances: (d1 (n,), d2 (n,)).

    d2 = distance of x2 to its epipolar line F x1 in image 2 = |.| / ||(a, b)||;
    d1 = distance of x1 to its epipolar line F^T x2 in image 1 = |.| / ||(c, d)||.
    (Affine epipolar lines are parallel within each image.)
    """
    a, b, c, d, e = _F_params(F)
    x1 = _as_points(x1, 2, "x1")
    x2 = _as_points(x2, 2, "x2")
    v = np.abs(a * x2[:, 0] + b * x2[:, 1] + c * x1[:, 0] + d * x1[:, 1] + e)
    return v / math.hypot(c, d), v / math.hypot(a, b)


def fa_ransac(x1, x2, thresh_px=1.0, iters=1000, rng=None, confidence=0.999):
    """Robust affine fundamental matrix: MSAC on minimal 4-point samples + Gold Standard refit.

    x1, x2: (n, 2). Four joint 4D points define a hyperplane (its normal is the null vector of
    the centred 4x4 sample); samples whose centred points span fewer than 3 dimensions
    (sigma3 < 1e-6 sigma1) are rejected. A correspondence is an inlier if its 4D orthogonal
    distance (`fa_residuals`) is < thresh_px. Hypotheses (vectorised batches, iteration count
    adapted to the inlier ratio with `confidence`, capped at `iters`) are ranked by the MSAC
    cost sum(min(r^2, thresh^2)) rather than the bare inlier count: when the parallax is small
    the hyperplane can tilt cheaply, and a tilted one that swaps a couple of inliers for far,
    high-leverage outliers can have more inliers than the true one but a higher cost.
    The winner is refitted with `affine_fundamental_gold_standard` on its inliers and inliers
    re-collected, repeated while the MSAC cost decreases (at most 5 times).
    Note: without parallax (all points on a 2D affine map) every hyperplane containing that
    plane fits; check with `parallax_ratio` / `affine_map_vs_fa_test`.

    Returns (F (3, 3), inlier_mask (n,) bool). Raises ReconstructionError with < 4 inliers.
    """
    Z = _joint(x1, x2)
    x1 = Z[:, 2:]
    x2 = Z[:, :2]
    n = len(Z)
    if n < 4:
        raise ReconstructionError(f"fa_ransac: {n} correspondences, need >= 4")
    gen = _rng(rng)
    z0 = Z.mean(axis=0)
    Zc = Z - z0  # centring only (keeps pixel units: thresholds stay in pixels)
    t2 = float(thresh_px) ** 2
    best_cost = math.inf
    best_F = None
    samples = _SampleBatches(gen, n, iters, confidence)
    for idx in samples:
        S = Zc[idx]  # (B, 4, 4)
        Sm = S.mean(axis=1)
        _, sv, Vt = np.linalg.svd(S - Sm[:, None, :])
        good = sv[:, 2] > 1e-6 * np.maximum(sv[:, 0], 1e-300)
        if not np.any(good):
            continue
        N = Vt[good, 3, :]  # (b, 4) unit normals
        e = -np.einsum("bi,bi->b", N, Sm[good])
        r2 = (Zc @ N.T + e) ** 2  # (n, b)
        cost = np.minimum(r2, t2).sum(axis=0)
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            best_cost = float(cost[j])
            best_F = _F_from_normal(N[j], float(e[j] - N[j] @ z0))
            samples.found(int(np.sum(r2[:, j] < t2)))
    if best_F is None:
        raise ReconstructionError(f"fa_ransac: no non-degenerate sample among {n} matches")
    F = best_F
    r2 = fa_residuals(F, x1, x2) ** 2
    cost = float(np.minimum(r2, t2).sum())
    inl = r2 < t2
    for _ in range(5):
        if inl.sum() < 4:
            break
        F_new = affine_fundamental_gold_standard(x1[inl], x2[inl])
        r2_new = fa_residuals(F_new, x1, x2) ** 2
        cost_new = float(np.minimum(r2_new, t2).sum())
        if not cost_new < cost:
            break
        F, cost, inl = F_new, cost_new, r2_new < t2
    if inl.sum() < 4:
        raise ReconstructionError(f"fa_ransac: fewer than 4 inliers among {n} matches")
    return F, inl


# ---------------------------------------------------------------------------------------------
# rectification and disparity -> 3D
# ---------------------------------------------------------------------------------------------
def apply_affine_2d(H, x) -> np.ndarray:
    """Apply a 3x3 affine map (last row 0 0 1) to points x (n, 2) -> (n, 2)."""
    H = np.asarray(H, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    return x @ H[:2, :2].T + H[:2, 2]


def rectifying_maps(F, x1, x2, shape1=None, allow_mirror=False):
    """Affine rectification of an image pair, as s2p does it.

    F: (3, 3) affine fundamental matrix (x2^T F x1 = 0, F = [[0,0,a],[0,0,b],[c,d,e]]), from
    `affine_fundamental_from_cameras` (preferred once cameras are known) or the Gold Standard;
    x1, x2: (n, 2) inlier matches (n >= 3) used for the horizontal registration.
    shape1: optional (height, width) of image 1 (or of its tile); if given, both maps get the
    same translation so that image 1's corners map to a box starting at (0, 0).

    1. Rotations (s2p `rectifying_similarities_from_affine_fundamental_matrix`): with
       r = ||(c, d)||, s = ||(a, b)||, image 1 is rotated by R1 = [[d, -c], [c, d]] / r and image 2
       by R2 = [[-b, a], [-a, -b]] / s (both proper rotations) so that epipolar lines become
       rows; the zoom is shared: image 1 is scaled by z = sqrt(r / s), image 2 by 1/z, and a
       vertical offset +-e / (2 sqrt(r s)) makes y1' = y2' exactly on the epipolar geometry of F.
    2. Horizontal registration (s2p `register_horizontally_shear`): fit x1' ~ a' x2' + b' y2' + c'
       on the matches by least squares and fold [[a', b', c'], [0, 1, 0]] into the second map.
       This removes the tilt/shear/scale of the mean scene plane: the disparity of the matches
       is then zero on average (LS intercept) and only relief remains.
       a' > 0 for any two images of the same surface with the same handedness (the rotations
       are proper, so a' has the sign of the determinant of the inter-image affine map); a' <= 0
       means one input is mirrored (or the matches are garbage): ReconstructionError, unless
       allow_mirror is True, in which case the fold is kept and H2 mirrors image 2 (det < 0) so
       that the rectified pair still matches.

    Returns (H1, H2), each (3, 3) affine with last row (0, 0, 1): x1' = H1 [x1, 1],
    x2' = H2 [x2, 1] satisfy y1' == y2' (rows are epipolar lines).
    Disparity convention (used by `disparity_to_3d_map`): d = x2' - x1', i.e. the match of
    rectified pixel (u, v) of image 1 is (u + d, v) in rectified image 2. The sign of d versus
    height depends on the pair's geometry: convert through `disparity_to_3d_map`. OpenCV's
    StereoSGBM with left = rectified image 1 and right = rectified image 2 matches left(x) to
    right(x - D), so D = -d.
    """
    a, b, c, d, e = _F_params(F)
    r = math.hypot(c, d)
    s = math.hypot(a, b)
    if r <= 0 or s <= 0 or not (math.isfinite(r) and math.isfinite(s)):
        raise ReconstructionError("rectifying_maps: degenerate affine fundamental matrix")
    x1 = _as_points(x1, 2, "x1")
    x2 = _as_points(x2, 2, "x2")
    if len(x1) != len(x2) or len(x1) < 3:
        raise ValueError("rectifying_maps needs >= 3 matches (same length in both images)")
    z = math.sqrt(r / s)
    t = 0.5 * e / math.sqrt(r * s)
    H1 = np.eye(3)
    H1[:2, :2] = (z / r) * np.array([[d, -c], [c, d]])
    H1[1, 2] = t
    H2 = np.eye(3)
    H2[:2, :2] = (1.0 / (z * s)) * np.array([[-b, a], [-a, -b]])
    H2[1, 2] = -t

    p1 = apply_affine_2d(H1, x1)
    p2 = apply_affine_2d(H2, x2)
    A = np.column_stack([p2, np.ones(len(p2))])
    coef, *_ = np.linalg.lstsq(A, p1[:, 0], rcond=None)
    if not coef[0] > 0 and not allow_mirror:
        raise ReconstructionError(
            f"rectifying_maps: horizontal registration has a = {coef[0]:.3g} <= 0: one image is "
            "mirrored relative to the other (or the matches are wrong)"
        )
    S = np.eye(3)
    S[0] = coef
    H2 = S @ H2
    if shape1 is not None:
        h, w = shape1[:2]
        corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
        T = np.eye(3)
        T[:2, 2] = -apply_affine_2d(H1, corners).min(axis=0)
        H1 = T @ H1
        H2 = T @ H2
    return H1, H2


def rectified_row_error(H1, H2, x1, x2) -> np.ndarray:
    """Row difference y1' - y2' (n,) of matches x1, x2 (n, 2) after rectification by H1, H2."""
    return apply_affine_2d(H1, x1)[:, 1] - apply_affine_2d(H2, x2)[:, 1]


def rectified_cameras(P1, P2, H1, H2) -> np.ndarray:
    """Cameras of the rectified images: (2, 2, 4) = [A_i P_i + (h_i)], x' = H_i[:2] [P_i X, 1]."""
    out = np.empty((2, 2, 4))
    for i, (P, H) in enumerate(((P1, H1), (P2, H2))):
        P = np.asarray(P, dtype=np.float64)
        H = np.asarray(H, dtype=np.float64)
        out[i] = H[:2, :2] @ P
        out[i, :, 3] += H[:2, 2]
    return out


def disparity_to_3d_map(P1, P2, H1, H2) -> np.ndarray:
    """Affine map L (3, 4): X = L [u, v, d, 1] from rectified image-1 pixel (u, v) and disparity d.

    Convention: the match of (u, v) in rectified image 2 is (u + d, v) (d = x2' - x1', see
    `rectifying_maps`). With the rectified cameras G_i X + g_i (`rectified_cameras`) the 4
    equations G1 X = (u, v) - g1, G2 X = (u + d, v) - g2 are linear in X with a right-hand side
    C [u, v, d, 1]; X = pinv([G1; G2]) C [u, v, d, 1] (least squares; exact when H1, H2
    rectify the epipolar geometry of P1, P2, e.g. F from `affine_fundamental_from_cameras`).
    """
    R = rectified_cameras(P1, P2, H1, H2)
    G = np.vstack([R[0, :, :3], R[1, :, :3]])  # (4, 3)
    g1, g2 = R[0, :, 3], R[1, :, 3]
    C = np.array(
        [
            [1.0, 0.0, 0.0, -g1[0]],
            [0.0, 1.0, 0.0, -g1[1]],
            [1.0, 0.0, 1.0, -g2[0]],
            [0.0, 1.0, 0.0, -g2[1]],
        ]
    )
    return np.linalg.pinv(G) @ C


def apply_disparity_map(L, u, v, d) -> np.ndarray:
    """X (..., 3) = L [u, v, d, 1] for broadcastable arrays u, v, d (e.g. whole disparity maps)."""
    L = np.asarray(L, dtype=np.float64)
    u, v, d = np.broadcast_arrays(np.asarray(u, np.float64), np.asarray(v, np.float64),
                                  np.asarray(d, np.float64))
    return (u[..., None] * L[:, 0] + v[..., None] * L[:, 1] + d[..., None] * L[:, 2]
            + L[:, 3])


# ---------------------------------------------------------------------------------------------
# 3D affine maps
# ---------------------------------------------------------------------------------------------
def fit_affine_3d(X_src, X_dst, weights=None) -> np.ndarray:
    """Least-squares 3D affine map A (3, 4) with X_dst ~ A[:, :3] X_src + A[:, 3].

    X_src, X_dst: (n, 3), n >= 4 non-coplanar; weights (n,) >= 0 optional. Both sets are
    similarity-normalised for conditioning, the 12 parameters are solved (3 right-hand sides,
    one shared 4-column design), then de-normalised. Minimises the (weighted) squared
    distances in X_dst units.
    """
    Xs = _as_points(X_src, 3, "X_src")
    Xd = _as_points(X_dst, 3, "X_dst")
    if len(Xs) != len(Xd) or len(Xs) < 4:
        raise ValueError(f"fit_affine_3d needs >= 4 point pairs, got {len(Xs)}/{len(Xd)}")
    q, Ts, Td = _normalised_affine_lstsq(Xs, Xd, weights)  # q: (4, 3)
    Q = np.eye(4)
    Q[:3] = q.T
    return (np.linalg.inv(Td) @ Q @ Ts)[:3]


def apply_affine_3d(A, X) -> np.ndarray:
    """X' (n, 3) = A[:, :3] X + A[:, 3] for A (3, 4) (or (4, 4) with last row 0 0 0 1)."""
    A = np.asarray(A, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    return X @ A[:3, :3].T + A[:3, 3]


def as_4x4(A) -> np.ndarray:
    """A (3, 4) or (4, 4) affine map as a (4, 4) float64 matrix (last row 0 0 0 1)."""
    out = np.eye(4)
    out[:3] = np.asarray(A, np.float64)[:3]
    return out


def views_spread(cams) -> float:
    """How far a point triangulated by affine cameras (k, 2, >= 3) moves per pixel of image
    error along its worst-determined direction: 1 / the smallest singular value of their
    stacked 2k x 3 linear parts (inf when they do not fix a point). In one frame, sets of views
    compare by it: a small intersection angle gives a large spread, mostly in height; in a
    metric frame it is metres per pixel."""
    L = np.concatenate([np.asarray(P, np.float64)[:2, :3] for P in cams])
    s = np.linalg.svd(L, compute_uv=False)
    return float(1.0 / s[-1]) if s[-1] > 0 else float("inf")
